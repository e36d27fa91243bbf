"""Occlusion inconsistencies composited into any clip (the GeCo paper's OccluBench).

A region of the clip is (i) visible and empty, (ii) hidden by an occluder that slides over it,
and (iii) re-revealed with an object that was not there before: no single static world
explains both the empty and the filled region. The object comes from a second image (or a frame
of a second clip) or, by default, a seeded procedural texture.

:func:`composite_occlusion` composites the two layers in image space and returns, besides the
frames, a label map per frame (which layer each pixel shows) and each layer's per-frame
translation, so the exact correspondences of the edited clip are known
(:func:`geco_guide.bench.synthetic.with_overlay` gives them to a synthetic scene's oracle). The
ground-truth artifact mask is the object in the re-revealed frames.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch
import torch.nn.functional as F
from torch import Tensor

from ..geometry import pixel_grid

__all__ = ["OBJECT", "OCCLUDER", "OcclusionParams", "OcclusionResult", "check_region", "composite_occlusion",
           "default_region", "occlusion_phases"]

SCENE, OCCLUDER, OBJECT = 0, 1, 2  # layer labels, back to front


@dataclass(frozen=True)
class OcclusionParams:
    """Options of an OccluBench-style edit.

    Attributes:
        region: ``(left, top, right, bottom)`` of the object's box in pixels (right/bottom
            exclusive); ``None``: a central box of ``region_fraction`` of the height and width.
        region_fraction: size of the default region.
        occluded_from, revealed_from: the first occluded and the first re-revealed frame as
            fractions of the clip (at least one frame per phase).
        seed: seeds the procedural textures.
    """

    region: tuple[int, int, int, int] | None = None
    region_fraction: float = 0.35
    occluded_from: float = 0.25
    revealed_from: float = 0.5
    seed: int = 0

    def __post_init__(self) -> None:
        if not 0.0 < self.region_fraction <= 1.0:
            raise ValueError(f"region_fraction must be in (0, 1], got {self.region_fraction}")
        if not 0.0 < self.occluded_from < self.revealed_from < 1.0:
            raise ValueError(
                f"need 0 < occluded_from < revealed_from < 1, got {self.occluded_from} and {self.revealed_from}"
            )


@dataclass
class OcclusionResult:
    """An edited clip and its ground truth.

    Attributes:
        frames: ``[S, 3, H, W]`` the edited clip.
        labels: ``[S, H, W]`` int64, the layer each pixel shows (:data:`SCENE`, :data:`OCCLUDER`,
            :data:`OBJECT`).
        offsets: ``[3, S, 2]`` float64, each layer's translation ``(du, dv)`` in frame ``t``
            (a layer's content at ``p`` in frame ``s`` is at ``p + offsets[l, t] - offsets[l, s]``
            in frame ``t``; row :data:`SCENE` is unused: the scene moves as the scene moves).
        mask: ``[S, H, W]`` bool, the object in re-revealed frames: the artifact.
        region: the object's box ``(left, top, right, bottom)``.
        phases: ``(occluded_from, revealed_from)`` frame indices.
    """

    frames: Tensor
    labels: Tensor
    offsets: Tensor
    mask: Tensor
    region: tuple[int, int, int, int]
    phases: tuple[int, int]


def occlusion_phases(num_frames: int, params: OcclusionParams = OcclusionParams()) -> tuple[int, int]:
    """``(a, b)``: frames ``[0, a)`` see the empty region, ``[a, b)`` the occluder, ``[b, S)`` the object."""
    if num_frames < 3:
        raise ValueError(f"an occlusion edit needs at least 3 frames (one per phase), got {num_frames}")
    a = min(max(1, round(params.occluded_from * num_frames)), num_frames - 2)
    b = min(max(a + 1, round(params.revealed_from * num_frames)), num_frames - 1)
    return a, b


def default_region(height: int, width: int, fraction: float) -> tuple[int, int, int, int]:
    """A central box ``(left, top, right, bottom)`` of ``fraction`` of the image's sides (>= 2 px)."""
    h, w = max(2, round(fraction * height)), max(2, round(fraction * width))
    top, left = (height - h) // 2, (width - w) // 2
    return left, top, left + w, top + h


def check_region(region: tuple[int, int, int, int], height: int, width: int) -> tuple[int, int, int, int]:
    """``region`` ``(left, top, right, bottom)`` if it is a non-empty box inside the
    ``width`` x ``height`` image (right/bottom exclusive); else a one-line ValueError. Checked
    before anything reads the image at the region (its scene track, its object)."""
    left, top, right, bottom = region
    if not (0 <= left < right <= width and 0 <= top < bottom <= height):
        raise ValueError(f"region {tuple(region)} (left, top, right, bottom) must be a non-empty box inside the "
                         f"{width}x{height} image")
    return left, top, right, bottom


def procedural_texture(height: int, width: int, seed: int) -> Tensor:
    """A smooth colourful texture ``[3, H, W]`` in ``[0, 1]``, seeded (random frequencies and phases)."""
    generator = torch.Generator().manual_seed(seed)
    grid = pixel_grid(height, width, dtype=torch.float64) / max(height, width)
    colour = 0.25 + 0.6 * torch.rand(3, generator=generator, dtype=torch.float64)
    pattern = torch.zeros(height, width, dtype=torch.float64)
    for _ in range(3):
        frequency = 4.0 + 10.0 * torch.rand(2, generator=generator, dtype=torch.float64)
        phase = 2 * math.pi * float(torch.rand(1, generator=generator, dtype=torch.float64))
        pattern = pattern + torch.sin(grid @ frequency + phase) / 3
    return (colour[:, None, None] * (0.7 + 0.3 * pattern)).clamp(0, 1)


def fit_image(image: Tensor, height: int, width: int) -> Tensor:
    """``image [C, h, w]`` resized (bilinear) to ``[C, height, width]``."""
    return F.interpolate(image[None].double(), size=(height, width), mode="bilinear", align_corners=False)[0]


def occluder_track(phases: tuple[int, int], region: tuple[int, int, int, int], width: int) -> tuple[int, dict[int, int]]:
    """Width and left edge, per occluded frame, of a full-height bar that slides left to right
    over the region and hides all of it (plus a margin) in every occluded frame.

    The bar is in view in the occluded frames only (it passes close to the camera between
    frames): a moving occluder is itself inconsistent with a static scene, and it must not sit
    beside the object in the re-revealed frames, where only the object is the artifact.
    """
    left, _, right, _ = region
    occluded_from, revealed_from = phases
    margin = max(1, (right - left) // 4)
    step = max(1, (right - left) // 4)
    bar = (right - left) + 2 * margin + step * (revealed_from - occluded_from - 1)
    start = left - margin - step * (revealed_from - occluded_from - 1)
    return min(bar, 2 * width), {t: start + step * (t - occluded_from) for t in range(occluded_from, revealed_from)}


def composite_occlusion(
    frames: Tensor,
    params: OcclusionParams = OcclusionParams(),
    object_image: Tensor | None = None,
    object_alpha: Tensor | None = None,
    region_track: Tensor | None = None,
) -> OcclusionResult:
    """Composite an occluder and a re-revealed object into ``frames [S, 3, H, W]``.

    Args:
        frames: a static-scene clip in ``[0, 1]``.
        params: region, phases and seed.
        object_image: ``[3, h, w]`` the object (resized to the region); default a procedural texture.
        object_alpha: ``[h, w]`` where the object is (resized to the region, > 0.5 counts);
            default an ellipse filling the region.
        region_track: ``[S, 2]`` the region's translation ``(du, dv)`` per frame, rounded to whole
            pixels: the occluder follows it and the object is pasted there (e.g. the scene's flow
            at the region, so the object stays on the surface it replaces); default zeros: fixed
            in the image.

    Returns:
        :class:`OcclusionResult`.
    """
    if frames.ndim != 4 or frames.shape[1] != 3 or not frames.is_floating_point():
        raise ValueError(f"frames must be a float [S, 3, H, W] tensor, got {list(frames.shape)} {frames.dtype}")
    num_frames, _, height, width = frames.shape
    phases = occlusion_phases(num_frames, params)
    region = params.region or default_region(height, width, params.region_fraction)
    left, top, right, bottom = check_region(region, height, width)
    box_h, box_w = bottom - top, right - left
    image = procedural_texture(box_h, box_w, params.seed) if object_image is None else fit_image(object_image, box_h, box_w)
    if object_alpha is None:
        v, u = torch.meshgrid(torch.linspace(-1, 1, box_h, dtype=torch.float64), torch.linspace(-1, 1, box_w, dtype=torch.float64), indexing="ij")
        alpha = u.square() + v.square() <= 1.0
    else:
        alpha = fit_image(object_alpha[None].double(), box_h, box_w)[0] > 0.5
    if not alpha.any():
        raise ValueError("the object's alpha mask is empty")

    track = torch.zeros(num_frames, 2, dtype=torch.int64) if region_track is None else region_track.round().long()
    if track.shape != (num_frames, 2):
        raise ValueError(f"region_track must be [S, 2] = [{num_frames}, 2], got {list(track.shape)}")
    labels = torch.full((num_frames, height, width), SCENE, dtype=torch.int64)
    out = frames.clone()
    for t in range(phases[1], num_frames):
        du, dv = track[t].tolist()
        x0, y0, x1, y1 = max(left + du, 0), max(top + dv, 0), min(right + du, width), min(bottom + dv, height)
        if x0 < x1 and y0 < y1:  # the object may leave the image
            box = (slice(y0 - top - dv, y1 - top - dv), slice(x0 - left - du, x1 - left - du))
            labels[t, y0:y1, x0:x1] = torch.where(alpha[box], OBJECT, SCENE)
            out[t, :, y0:y1, x0:x1] = torch.where(alpha[box], image[(slice(None), *box)].to(frames.dtype), out[t, :, y0:y1, x0:x1])
    bar, lefts = occluder_track(phases, region, width)
    bar_texture = procedural_texture(height, bar, params.seed + 1) * 0.6  # darker than most scenes
    lefts = {t: x + int(track[t, 0]) for t, x in lefts.items()}
    for t, x in lefts.items():
        lo, hi = max(x, 0), min(x + bar, width)
        if lo < hi:
            labels[t, :, lo:hi] = OCCLUDER
            out[t, :, :, lo:hi] = bar_texture[:, :, lo - x : hi - x].to(frames.dtype)
    offsets = torch.zeros(3, num_frames, 2, dtype=torch.float64)
    offsets[OBJECT] = track.double()
    for t, x in lefts.items():
        offsets[OCCLUDER, t, 0] = x
    return OcclusionResult(out, labels, offsets, labels == OBJECT, region, phases)
