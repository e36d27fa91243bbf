"""Temporally smooth thin-plate-spline warps of any clip (the GeCo paper's WarpBench).

The supplement's recipe ("Details on Thin-plate-spline for WarpBench"), step by step:

1. ``K`` control points ``c_i`` in the foreground mask, by farthest-point sampling
   (:func:`sample_controls`);
2. their displacements ``u_{i,t}`` over time (:func:`control_displacements`: independent Gaussian
   draws per frame, smoothed in step 4);
3. per frame the TPS ``f_t`` (affine + ``r^2 log r`` basis) mapping ``c_i`` to ``c_i + u_{i,t}``,
   whose displacement ``U_t(p) = f_t(p) - p`` is the TPS interpolant of the ``u_{i,t}``
   (:func:`thin_plate_spline`; the affine part reproduces the identity exactly);
4. ``Ũ_t = w U_t`` with a feathered weight map ``w`` (:func:`feather_weights`) and the EMA
   ``Ū_t = β Ū_{t-1} + (1 - β) Ũ_t`` (:func:`warp_fields`);
5. backward sampling ``I_def(p) = I(p + Ū_t(p))`` (:func:`backward_warp`).

:func:`warp_clip` warps every frame; :func:`warp_one_frame` replaces one random frame with its
warped version (Task 1). The ground truth is ``Ū_t`` and its magnitude; the artifact mask is
``|Ū_t| > mask_threshold`` pixels. Everything is deterministic from the seed.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch
from torch import Tensor

from ..geometry import pixel_grid, sample_bilinear

__all__ = ["WarpParams", "WarpResult", "backward_warp", "central_mask", "control_displacements",
           "farthest_point_sampling", "feather_weights", "raised_cosine", "thin_plate_spline", "warp_clip",
           "warp_fields", "warp_one_frame"]


@dataclass(frozen=True)
class WarpParams:
    """Options of a WarpBench-style warp.

    Attributes:
        num_controls: ``K`` TPS control points (>= 3, so the affine part is determined).
        amplitude: standard deviation of the control displacements, in pixels.
        beta: EMA factor over time, in ``[0, 1)`` (0: independent frames).
        feather_px: width of the weight map's ramp inside the mask, in pixels; ``None``: a
            quarter of the mask's largest inscribed radius.
        mask_threshold: ground-truth artifact pixels move more than this, in pixels.
        seed: seeds the control points, the displacements and the anomalous frame.
    """

    num_controls: int = 12
    amplitude: float = 4.0
    beta: float = 0.5
    feather_px: float | None = None
    mask_threshold: float = 0.1
    seed: int = 0

    def __post_init__(self) -> None:
        if self.num_controls < 3:
            raise ValueError(f"num_controls must be >= 3, got {self.num_controls}")
        if not (math.isfinite(self.amplitude) and self.amplitude > 0):
            raise ValueError(f"amplitude must be a finite number > 0, got {self.amplitude}")
        if not 0.0 <= self.beta < 1.0:
            raise ValueError(f"beta must be in [0, 1), got {self.beta}")
        if self.feather_px is not None and not (math.isfinite(self.feather_px) and self.feather_px > 0):
            raise ValueError(f"feather_px must be a finite number > 0 or None, got {self.feather_px}")
        if not (math.isfinite(self.mask_threshold) and self.mask_threshold >= 0):
            raise ValueError(f"mask_threshold must be a finite number >= 0, got {self.mask_threshold}")


@dataclass
class WarpResult:
    """A warped clip and its ground truth.

    Attributes:
        frames: ``[S, 3, H, W]`` the warped clip.
        displacement: ``[S, H, W, 2]`` ``Ū_t``: frame ``t`` at ``p`` shows the source frame at
            ``p + Ū_t(p)`` (zeros for frames left alone).
        mask: ``[S, H, W]`` bool, ``|Ū_t| > mask_threshold``.
        controls: ``[K, 2]`` control points ``(u, v)``.
        anomalous_frame: the replaced frame (:func:`warp_one_frame`), ``None`` for a warped clip.
    """

    frames: Tensor
    displacement: Tensor
    mask: Tensor
    controls: Tensor
    anomalous_frame: int | None = None

    @property
    def magnitude(self) -> Tensor:
        """``[S, H, W]`` ``M_t = |Ū_t|`` in pixels."""
        return self.displacement.norm(dim=-1)


def central_mask(height: int, width: int, fraction: float = 0.5) -> Tensor:
    """``[H, W]`` bool ellipse centred in the image, ``fraction`` of its height and width across."""
    grid = pixel_grid(height, width, dtype=torch.float64)
    centre = grid.new_tensor([(width - 1) / 2, (height - 1) / 2])
    semi_axes = grid.new_tensor([fraction * width / 2, fraction * height / 2])
    return ((grid - centre) / semi_axes).square().sum(-1) <= 1.0


def raised_cosine(inset: Tensor, width: float) -> Tensor:
    """Weight rising smoothly from 0 at ``inset <= 0`` to 1 at ``inset >= width`` (same shape)."""
    t = (inset / width).clamp(0.0, 1.0)
    return 0.5 - 0.5 * torch.cos(math.pi * t)


def distance_to_outside(mask: Tensor, chunk: int = 4096) -> Tensor:
    """Euclidean distance ``[H, W]`` of each mask pixel to the nearest pixel outside the mask
    (0 outside; ``inf`` if every pixel is inside). The image border does not count as outside:
    a mask touching it is cut by the frame, not by the object."""
    height, width = mask.shape
    grid = pixel_grid(height, width, dtype=torch.float64)
    inside, outside = grid[mask], grid[~mask]
    result = torch.zeros(height, width, dtype=torch.float64)
    if outside.numel() == 0:
        return torch.full_like(result, math.inf)
    if inside.numel() == 0:
        return result
    # Only outside pixels next to the mask can be nearest: a 3x3 dilation of the mask finds them.
    near = torch.nn.functional.max_pool2d(mask[None, None].double(), 3, stride=1, padding=1)[0, 0] > 0
    boundary = grid[near & ~mask]
    result[mask] = torch.cat([torch.cdist(part, boundary).amin(-1) for part in inside.split(chunk)])
    return result


def feather_weights(mask: Tensor, feather_px: float | None = None) -> Tensor:
    """Feathered weight map ``[..., H, W]`` in ``[0, 1]`` of masks ``[..., H, W]``: 0 outside,
    a raised cosine over ``feather_px`` pixels inside the rim (default: a quarter of the largest
    inscribed radius of each mask), so the warp fades out without a seam."""
    flat = mask.reshape(-1, *mask.shape[-2:])
    weights = []
    for m in flat:
        inset = distance_to_outside(m)
        finite = inset[torch.isfinite(inset)]
        width = feather_px if feather_px is not None else max(float(finite.max()) / 4 if finite.numel() else 1.0, 1.0)
        weights.append(torch.where(torch.isinf(inset), torch.ones_like(inset), raised_cosine(inset, width)))
    return torch.stack(weights).reshape(mask.shape)


def farthest_point_sampling(points: Tensor, k: int, generator: torch.Generator) -> Tensor:
    """Indices ``[k]`` of ``k`` well-spread points of ``points [N, 2]``: a random first point, then
    each time the point farthest from those chosen."""
    if not 0 < k <= points.shape[0]:
        raise ValueError(f"cannot sample {k} points from {points.shape[0]}")
    chosen = [int(torch.randint(points.shape[0], (1,), generator=generator))]
    nearest = (points - points[chosen[0]]).norm(dim=-1)
    for _ in range(k - 1):
        chosen.append(int(nearest.argmax()))
        nearest = torch.minimum(nearest, (points - points[chosen[-1]]).norm(dim=-1))
    return torch.tensor(chosen)


def sample_controls(mask: Tensor, k: int, generator: torch.Generator) -> Tensor:
    """``k`` control points ``[k, 2]`` ``(u, v)`` float64 spread over the True pixels of ``mask [H, W]``."""
    points = pixel_grid(*mask.shape, dtype=torch.float64)[mask]
    if points.shape[0] < k:
        raise ValueError(f"the mask has {points.shape[0]} pixels, fewer than the {k} control points")
    return points[farthest_point_sampling(points, k, generator)]


def control_displacements(num_controls: int, num_frames: int, amplitude: float, generator: torch.Generator) -> Tensor:
    """``[S, K, 2]`` float64 displacements: independent ``N(0, amplitude^2)`` draws per frame
    (the EMA of :func:`warp_fields` makes them temporally smooth). Drawn frame by frame so a
    clip's first frames do not depend on its length."""
    return torch.stack(
        [amplitude * torch.randn(num_controls, 2, generator=generator, dtype=torch.float64) for _ in range(num_frames)]
    )


def _tps_kernel(r2: Tensor) -> Tensor:
    """``U(r) = r^2 log r`` written in terms of ``r^2`` (0 at the origin)."""
    return torch.where(r2 > 0, 0.5 * r2 * torch.log(r2.clamp_min(1e-30)), torch.zeros_like(r2))


def thin_plate_spline(controls: Tensor, values: Tensor, points: Tensor) -> Tensor:
    """Interpolate ``values [C, D]`` given at ``controls [C, 2]`` to ``points [N, 2]`` -> ``[N, D]``.

    Solves the standard thin-plate system (kernel ``r^2 log r`` plus an affine part) exactly;
    the system is linear in the values, so ``D`` may stack many frames' displacements.
    """
    n = controls.shape[0]
    kernel = _tps_kernel(torch.cdist(controls, controls).square())
    affine = torch.cat((torch.ones(n, 1, dtype=controls.dtype), controls), dim=1)
    system = torch.zeros(n + 3, n + 3, dtype=controls.dtype)
    system[:n, :n] = kernel
    system[:n, n:] = affine
    system[n:, :n] = affine.T
    rhs = torch.cat((values, torch.zeros(3, values.shape[1], dtype=values.dtype)))
    coeffs = torch.linalg.solve(system, rhs)
    basis = _tps_kernel(torch.cdist(points, controls).square())
    points_affine = torch.cat((torch.ones(points.shape[0], 1, dtype=points.dtype), points), dim=1)
    return basis @ coeffs[:n] + points_affine @ coeffs[n:]


def warp_fields(controls: Tensor, displacements: Tensor, weights: Tensor, height: int, width: int, beta: float) -> Tensor:
    """The smoothed displacement fields ``Ū_t`` ``[S, H, W, 2]`` float64.

    Args:
        controls: ``[K, 2]`` control points ``(u, v)``.
        displacements: ``[S, K, 2]`` their displacements ``u_{i,t}``.
        weights: ``[H, W]`` or ``[S, H, W]`` feathered weight map(s) ``w``.
        beta: EMA factor; ``Ū_{-1} = 0``.
    """
    num_frames, num_controls, _ = displacements.shape
    grid = pixel_grid(height, width, dtype=torch.float64).reshape(-1, 2)
    values = displacements.permute(1, 0, 2).reshape(num_controls, 2 * num_frames).double()
    fields = thin_plate_spline(controls.double(), values, grid).reshape(height, width, num_frames, 2).permute(2, 0, 1, 3)
    weighted = fields * weights.double().expand(num_frames, height, width)[..., None]
    state = torch.zeros(height, width, 2, dtype=torch.float64)
    smoothed = []
    for frame in weighted:
        state = beta * state + (1 - beta) * frame
        smoothed.append(state)
    return torch.stack(smoothed)


def backward_warp(frames: Tensor, displacement: Tensor) -> Tensor:
    """``I_def(p) = I(p + Ū(p))``: frames ``[S, C, H, W]``, displacement ``[S, H, W, 2]`` -> ``[S, C, H, W]``
    (bilinear; the border value outside the image), in the frames' dtype."""
    height, width = frames.shape[-2:]
    coords = pixel_grid(height, width, dtype=displacement.dtype)[None] + displacement
    return sample_bilinear(frames.to(displacement.dtype), coords).to(frames.dtype)


def _clip_fields(frames: Tensor, mask: Tensor | None, params: WarpParams, generator: torch.Generator) -> tuple[Tensor, Tensor]:
    """Control points ``[K, 2]`` and fields ``Ū_t`` ``[S, H, W, 2]`` of the whole clip."""
    num_frames, _, height, width = frames.shape
    mask = central_mask(height, width) if mask is None else mask.bool()
    if mask.shape[-2:] != (height, width) or mask.ndim not in (2, 3) or (mask.ndim == 3 and mask.shape[0] != num_frames):
        raise ValueError(f"mask must be [H, W] or [S, H, W] = [{num_frames}, {height}, {width}], got {list(mask.shape)}")
    # Per-frame masks (a moving object): the controls cover every frame's foreground, and each
    # frame's weight map keeps the warp on that frame's object.
    controls = sample_controls(mask if mask.ndim == 2 else mask.any(0), params.num_controls, generator)
    displacements = control_displacements(params.num_controls, num_frames, params.amplitude, generator)
    weights = feather_weights(mask, params.feather_px)
    return controls, warp_fields(controls, displacements, weights, height, width, params.beta)


def _check_clip(frames: Tensor) -> None:
    if frames.ndim != 4 or frames.shape[1] != 3 or not frames.is_floating_point():
        raise ValueError(f"frames must be a float [S, 3, H, W] tensor, got {list(frames.shape)} {frames.dtype}")
    if frames.shape[0] < 2:
        raise ValueError(f"a clip needs at least 2 frames, got {frames.shape[0]}")


def warp_clip(frames: Tensor, mask: Tensor | None = None, params: WarpParams = WarpParams()) -> WarpResult:
    """Warp every frame of ``frames [S, 3, H, W]`` inside ``mask`` (``[H, W]`` or ``[S, H, W]``,
    default :func:`central_mask`)."""
    _check_clip(frames)
    generator = torch.Generator().manual_seed(params.seed)
    controls, fields = _clip_fields(frames, mask, params, generator)
    return WarpResult(backward_warp(frames, fields), fields, fields.norm(dim=-1) > params.mask_threshold, controls)


def warp_one_frame(frames: Tensor, mask: Tensor | None = None, params: WarpParams = WarpParams()) -> WarpResult:
    """Replace one random frame of ``frames [S, 3, H, W]`` by its warped version (the frame of
    :func:`warp_clip`'s clip); the other frames and their fields stay untouched (Task 1)."""
    _check_clip(frames)
    generator = torch.Generator().manual_seed(params.seed)
    controls, fields = _clip_fields(frames, mask, params, generator)
    anomalous = int(torch.randint(frames.shape[0], (1,), generator=generator))
    keep = torch.zeros_like(fields)
    keep[anomalous] = fields[anomalous]
    warped = frames.clone()
    warped[anomalous] = backward_warp(frames[anomalous][None], keep[anomalous][None])[0]
    return WarpResult(warped, keep, keep.norm(dim=-1) > params.mask_threshold, controls, anomalous)
