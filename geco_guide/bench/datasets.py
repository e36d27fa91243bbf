"""Build WarpBench- and OccluBench-style benchmarks from any static-scene clip (the command is
:mod:`geco_guide.cli.benchmarks`).

Each clip becomes a folder ``<out>/<name>-s<seed>/`` holding

* ``frames/00000.png ...``: the edited clip (lossless);
* ``truth.npz``: ``mask [S, H, W]`` (the artifact), and for a warp ``displacement [S, H, W, 2]``
  (``Ū_t``: frame ``t`` at ``p`` shows the source at ``p + Ū_t(p)``) and ``magnitude [S, H, W]``;
  for an occlusion edit ``labels [S, H, W]`` and ``offsets [3, S, 2]`` (see
  :class:`~geco_guide.bench.occlusion.OcclusionResult`);
* ``meta.json`` (written last: a folder without it is incomplete): the kind, mode, anomalous
  frame, phases, every parameter, the seed and the source.

``synthetic`` renders :func:`geco_guide.bench.synthetic.rigid_clip` instead of reading a video, and
``synthetic-3d`` is :func:`geco_guide.bench.synthetic.occlusion_swap_clip` (an occlusion edit made in
3D: the re-revealed box is a real surface the flow can follow); such folders record it, and :func:`oracle_clip` rebuilds their exact depth, cameras and flow, so
``geco validate --oracle`` can score them with ground-truth estimators.
Everything is deterministic from the seed and written atomically.
"""

from __future__ import annotations

import argparse
import io
import json
import zipfile
from dataclasses import asdict, dataclass, replace
from pathlib import Path
from typing import Any

import numpy as np
import torch
from PIL import Image
from torch import Tensor

from ..io.files import write_bytes_atomic, write_json_atomic
from ..io.video import VIDEO_SUFFIXES, input_stem, read_frames
from .occlusion import (
    OcclusionParams,
    OcclusionResult,
    check_region,
    composite_occlusion,
    default_region,
)
from .synthetic import (
    SyntheticClip,
    occlusion_swap_clip,
    rigid_clip,
    with_overlay,
    with_warp,
)
from .warp import WarpParams, WarpResult, warp_clip, warp_one_frame

__all__ = ["KINDS", "SYNTHETIC", "SYNTHETIC_3D", "Benchmark", "build_one", "check_synthetic_size",
           "evenly_spaced", "find_benchmarks", "load_benchmark", "load_clip", "oracle_clip", "output_stem",
           "scene_track", "write_benchmark"]

KINDS = ("warp", "occlusion")
SYNTHETIC = "synthetic"  # the gallery scene (rigid_clip): any edit
SYNTHETIC_3D = "synthetic-3d"  # occlusion_swap_clip: an occlusion inconsistency built in 3D


@dataclass
class Benchmark:
    """One built clip, loaded.

    Attributes:
        path: its folder.
        meta: ``meta.json``.
        frames: ``[S, 3, H, W]`` float32 in ``[0, 1]``.
        truth: ``truth.npz`` as tensors (``mask`` bool ``[S, H, W]``, ...).
    """

    path: Path
    meta: dict[str, Any]
    frames: Tensor
    truth: dict[str, Tensor]

    @property
    def kind(self) -> str:
        return self.meta["kind"]


# --------------------------------------------------------------------------------------------
# inputs


def read_image(path: str | Path) -> Tensor:
    """An image file -> ``[3, H, W]`` float32 in ``[0, 1]`` (one-line error if unreadable)."""
    try:
        with Image.open(path) as image:
            array = np.asarray(image.convert("RGB"), dtype=np.float32) / 255.0
    except (OSError, ValueError) as err:
        raise ValueError(f"cannot read image {str(path)!r}: {err}") from None
    return torch.from_numpy(array).permute(2, 0, 1).contiguous()


def read_object(path: str | Path) -> Tensor:
    """The object to paste, ``[3, H, W]``: an image, or the middle frame of a video / frame folder
    (an object that changes over time would be a second artifact)."""
    path = Path(path)
    if path.is_dir() or path.suffix.lower() in VIDEO_SUFFIXES:
        frames = read_frames(path).frames
        return frames[frames.shape[0] // 2]
    return read_image(path)


def read_mask(path: str | Path, num_frames: int, height: int, width: int) -> Tensor:
    """A mask image (``[H, W]``) or a folder / video of per-frame masks (``[S, H, W]``), bool,
    resized (nearest) to the clip; white (> 0.5) is foreground."""
    path = Path(path)
    if path.is_dir() or path.suffix.lower() in VIDEO_SUFFIXES:
        masks = read_frames(path).frames.mean(1, keepdim=True)
        if masks.shape[0] != num_frames:
            raise ValueError(f"mask {str(path)!r} has {masks.shape[0]} frames, the clip {num_frames}")
    else:
        masks = read_image(path).mean(0, keepdim=True)[None]
    masks = torch.nn.functional.interpolate(masks, size=(height, width), mode="nearest")[:, 0] > 0.5
    if not masks.flatten(1).any(1).all():
        raise ValueError(f"mask {str(path)!r} is empty (in at least one frame)")
    return masks[0] if masks.shape[0] == 1 else masks


def output_stem(source: str) -> str:
    """The folder-name stem of an input: ``synthetic`` / ``synthetic-3d`` as they are, a file's
    stem, a folder's own name (:func:`~geco_guide.io.video.input_stem`)."""
    return source if source in (SYNTHETIC, SYNTHETIC_3D) else input_stem(source)


def load_clip(source: str, max_frames: int, synthetic_size: tuple[int, int, int]) -> tuple[Tensor, SyntheticClip | None]:
    """Frames ``[S, 3, H, W]`` of ``source`` (at most ``max_frames``, evenly spaced), and the
    synthetic clip when ``source`` is ``synthetic`` / ``synthetic-3d`` (``synthetic_size``:
    frames, height, width)."""
    if source in (SYNTHETIC, SYNTHETIC_3D):
        check_synthetic_size(synthetic_size)
        clip = (rigid_clip if source == SYNTHETIC else occlusion_swap_clip)(*synthetic_size)
        return clip.frames.float(), clip
    return read_frames(source, select=lambda count, fps: evenly_spaced(count, max_frames), min_frames=3).frames, None


def evenly_spaced(count: int, keep: int) -> list[int]:
    """``min(count, keep)`` indices of ``range(count)`` spread over the whole clip, its first and
    last frame included (17 frames, keep 20 -> all 17; 8 frames, keep 4 -> 0, 2, 5, 7)."""
    kept = min(count, keep)
    return sorted({round(k * (count - 1) / max(kept - 1, 1)) for k in range(kept)})


#: The smallest synthetic scene: an occlusion edit needs a frame per phase, a warp a few pixels.
MIN_SYNTHETIC_SIZE = (3, 8, 8)


def check_synthetic_size(size: tuple[int, int, int], option: str = "--synthetic-size") -> None:
    """One-line ValueError naming ``option`` unless ``size`` (frames, height, width) is at least
    :data:`MIN_SYNTHETIC_SIZE`."""
    if len(size) != 3 or any(v < low for v, low in zip(size, MIN_SYNTHETIC_SIZE)):
        frames, height, width = MIN_SYNTHETIC_SIZE
        raise ValueError(f"{option} (frames, height, width) must be at least {frames} frames of {height}x{width}, "
                         f"got {' '.join(map(str, size))}")


# --------------------------------------------------------------------------------------------
# folders


def _png(frame: Tensor) -> bytes:
    array = (frame.detach().float().clamp(0, 1).permute(1, 2, 0).numpy() * 255.0 + 0.5).astype(np.uint8)
    buffer = io.BytesIO()
    Image.fromarray(array).save(buffer, format="PNG")
    return buffer.getvalue()


def _npz(arrays: dict[str, Tensor]) -> bytes:
    buffer = io.BytesIO()
    np.savez_compressed(buffer, **{k: v.detach().cpu().numpy() for k, v in arrays.items()})
    return buffer.getvalue()


def write_benchmark(folder: Path, frames: Tensor, truth: dict[str, Tensor], meta: dict[str, Any]) -> Path:
    """Write one clip's folder (frames, ``truth.npz``, then ``meta.json``), atomically per file."""
    if (folder / "meta.json").exists():
        (folder / "meta.json").unlink()  # rebuilding: incomplete until the new meta lands
    names = [f"{k:05d}.png" for k in range(frames.shape[0])]
    for name, frame in zip(names, frames):
        write_bytes_atomic(folder / "frames" / name, _png(frame))
    for stale in {p.name for p in (folder / "frames").glob("*.png")} - set(names):  # a longer earlier build
        (folder / "frames" / stale).unlink()
    write_bytes_atomic(folder / "truth.npz", _npz(truth))
    return write_json_atomic(folder / "meta.json", meta)


def load_benchmark(folder: str | Path) -> Benchmark:
    """Read a folder written by :func:`write_benchmark` (one-line error if incomplete)."""
    folder = Path(folder)
    meta_path = folder / "meta.json"
    if not meta_path.is_file():
        raise ValueError(f"{str(folder)!r} is not a built benchmark clip (no meta.json)")
    try:
        meta = json.loads(meta_path.read_text())
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as err:
        raise ValueError(f"{str(meta_path)!r}: cannot read it as JSON ({err})") from None
    if not isinstance(meta, dict):
        raise ValueError(f"{str(meta_path)!r} must hold a JSON object, got {type(meta).__name__}")  # noqa: TRY004 (a damaged file)
    if meta.get("kind") not in KINDS:
        raise ValueError(f"{str(meta_path)!r}: kind must be one of {KINDS}, got {meta.get('kind')!r}")
    try:
        with np.load(folder / "truth.npz") as data:
            truth = {key: torch.from_numpy(data[key]) for key in data.files}
    except (OSError, ValueError, zipfile.BadZipFile) as err:
        raise ValueError(f"{str(folder)!r}: cannot read truth.npz ({err})") from None
    frames = read_frames(folder / "frames").frames
    truth["mask"] = checked_mask(truth, folder, frames.shape)
    check_meta(meta, meta_path, frames.shape[0])
    return Benchmark(folder, meta, frames, truth)


def checked_mask(truth: dict[str, Tensor], folder: Path, frames_shape: torch.Size) -> Tensor:
    """The truth's ``mask`` as bool ``[S, H, W]``, checked against the frames ``[S, 3, H, W]``: a
    mask that is not 0/1 (NaN, grey levels) is refused, not read as artifact pixels."""
    mask = truth.get("mask")
    if mask is None:
        raise ValueError(f"{str(folder)!r}: truth.npz holds no mask")
    if mask.ndim != 3 or tuple(mask.shape) != (frames_shape[0], *frames_shape[-2:]):
        raise ValueError(f"{str(folder)!r}: frames {list(frames_shape)} do not match the truth {list(mask.shape)}")
    if mask.dtype != torch.bool:
        values = mask.double()
        if not bool(((values == 0) | (values == 1)).all()):
            bad = values[(values != 0) & (values != 1)]
            raise ValueError(f"{str(folder)!r}: truth.npz mask must be 0/1, it holds {int(bad.numel())} other value(s) "
                             f"(e.g. {float(bad[0]):g})")
        mask = values == 1
    return mask


def check_meta(meta: dict[str, Any], meta_path: Path, num_frames: int) -> None:
    """One-line ValueError when ``meta.json`` contradicts the clip: an ``anomalous_frame`` that is
    not one of its ``num_frames`` frames, a ``synthetic`` spec without its scene and size."""
    frame = meta.get("anomalous_frame")
    if frame is not None and (isinstance(frame, bool) or not isinstance(frame, int) or not 0 <= frame < num_frames):
        raise ValueError(f"{str(meta_path)!r}: anomalous_frame must be a frame of the clip in [0, {num_frames}), got {frame!r}")
    spec = meta.get("synthetic")
    if spec is not None:
        keys = ("scene", "num_frames", "height", "width")
        if not isinstance(spec, dict) or any(key not in spec for key in keys) or \
                not all(isinstance(spec[key], int) and spec[key] > 0 for key in keys[1:]):
            raise ValueError(f"{str(meta_path)!r}: synthetic must be an object with {keys[0]} and positive integer {', '.join(keys[1:])}, got {spec!r}")


def truth_field(bench: Benchmark, key: str) -> Tensor:
    """``truth.npz``'s array ``key``, or a one-line ValueError naming the clip."""
    if key not in bench.truth:
        raise ValueError(f"{str(bench.path)!r}: truth.npz holds no {key!r}, which a {bench.kind} clip needs")
    return bench.truth[key]


def meta_field(bench: Benchmark, key: str) -> Any:
    """``meta.json``'s entry ``key``, or a one-line ValueError naming the clip."""
    if key not in bench.meta:
        raise ValueError(f"{str(bench.path / 'meta.json')!r} holds no {key!r}, which a {bench.kind} clip needs")
    return bench.meta[key]


def find_benchmarks(root: str | Path) -> list[Path]:
    """``root`` itself if it is a clip folder, else its clip sub-folders (sorted); error if none."""
    root = Path(root)
    if not root.exists():
        raise FileNotFoundError(f"benchmark folder {str(root)!r} does not exist")
    if (root / "meta.json").is_file():
        return [root]
    found = sorted(p for p in root.iterdir() if (p / "meta.json").is_file()) if root.is_dir() else []
    if not found:
        raise ValueError(f"{str(root)!r} holds no built benchmark clip (folders with meta.json)")
    return found


def oracle_clip(bench: Benchmark) -> SyntheticClip:
    """The exact ground truth of a clip built from ``synthetic``: the rendered scene with the
    recorded edit applied (error for clips built from real footage)."""
    spec = bench.meta.get("synthetic")
    if spec is None:
        raise ValueError(f"{str(bench.path)!r} was built from {bench.meta.get('source')!r}, not a synthetic scene: "
                         "oracle estimators need its ground truth")
    if spec["scene"] == SYNTHETIC_3D:
        return replace(occlusion_swap_clip(spec["num_frames"], spec["height"], spec["width"]), frames=bench.frames)
    clip = rigid_clip(spec["num_frames"], spec["height"], spec["width"])
    if bench.kind == "warp":
        edit = WarpResult(bench.frames, truth_field(bench, "displacement").double(), bench.truth["mask"], torch.empty(0, 2))
        return with_warp(clip, edit)
    edit = OcclusionResult(bench.frames, truth_field(bench, "labels").long(), truth_field(bench, "offsets").double(),
                           bench.truth["mask"], tuple(meta_field(bench, "region")), tuple(meta_field(bench, "phases")))
    return with_overlay(clip, edit)


# --------------------------------------------------------------------------------------------
# builders


def scene_track(clip: SyntheticClip, region: tuple[int, int, int, int]) -> Tensor:
    """``[S, 2]`` the scene's motion at the region's centre since frame 0 (its true flow), so an
    object pasted there stays on the surface it replaces."""
    left, top, right, bottom = region
    u, v = (left + right - 1) // 2, (top + bottom - 1) // 2
    rows = [torch.zeros(2, dtype=torch.float64)]
    rows += [clip.rigid_correspondences(0, t)[0][:, v, u].double() for t in range(1, clip.num_frames)]
    return torch.stack(rows)


def build_warp(frames: Tensor, mask: Tensor | None, params: WarpParams, mode: str) -> tuple[WarpResult, dict[str, Tensor]]:
    """The warp of ``mode`` (``clip``: every frame, ``frame``: one random frame) and its truth arrays."""
    result = (warp_clip if mode == "clip" else warp_one_frame)(frames, mask, params)
    truth = {"mask": result.mask, "displacement": result.displacement.float(), "magnitude": result.magnitude.float()}
    return result, truth


def build_one(kind: str, source: str, frames: Tensor, synthetic: SyntheticClip | None, seed: int,
              args: argparse.Namespace) -> tuple[Tensor, dict[str, Tensor], dict[str, Any]]:
    """Edit one clip: ``(frames, truth, meta)``."""
    num_frames, _, height, width = frames.shape
    meta: dict[str, Any] = {"kind": kind, "source": source, "seed": seed, "num_frames": num_frames,
                            "height": height, "width": width}
    if synthetic is not None:
        meta["synthetic"] = {"scene": source, "num_frames": num_frames, "height": height, "width": width}
    if source == SYNTHETIC_3D:  # the edit is part of the scene: only the ground truth to write
        if kind != "occlusion":
            raise ValueError(f"{SYNTHETIC_3D} is an occlusion scene; warp the gallery scene '{SYNTHETIC}' instead")
        meta.update(mode="clip", anomalous_frame=None, params={}, scene="synthetic.occlusion_swap_clip")
        return frames, {"mask": synthetic.mask}, meta
    if kind == "warp":
        mask = read_mask(args.mask, num_frames, height, width) if args.mask else None
        given = {"num_controls": args.controls, "amplitude": args.amplitude, "beta": args.beta,
                 "feather_px": args.feather, "mask_threshold": args.mask_threshold}
        params = WarpParams(**{key: value for key, value in given.items() if value is not None}, seed=seed)
        result, truth = build_warp(frames, mask, params, args.mode)
        meta.update(mode=args.mode, anomalous_frame=result.anomalous_frame, params=asdict(params),
                    mask=args.mask or "central ellipse", controls=result.controls.tolist())
        return result.frames, truth, meta
    params = OcclusionParams(region=tuple(args.region) if args.region else None, seed=seed)
    region = check_region(params.region or default_region(height, width, params.region_fraction), height, width)
    image = read_object(args.object) if args.object else None
    alpha = read_image(args.object_mask).mean(0) if args.object_mask else None
    track = scene_track(synthetic, region) if synthetic is not None else None
    result = composite_occlusion(frames, params, image, alpha, track)
    truth = {"mask": result.mask, "labels": result.labels.to(torch.int16), "offsets": result.offsets}
    meta.update(mode="clip", anomalous_frame=None, params=asdict(params), region=list(result.region),
                phases=list(result.phases), object=args.object or "procedural", object_mask=args.object_mask or "ellipse",
                region_track="scene flow" if track is not None else "fixed in the image")
    return result.frames, truth, meta
