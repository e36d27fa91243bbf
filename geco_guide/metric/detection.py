"""Per-frame detection maps: where a video breaks, frame by frame (the paper code's detection demo;
the command is :mod:`geco_guide.cli.detection`).

:func:`geco_guide.metric.evaluate.evaluate_video` scores the protocol's windows; here every frame gets
its own window of ``W`` frames (default 20) with the frame at its start, centre or end (clamped
at the clip's ends), GeCo runs on the pairs ``frame -> each other frame of the window``, and the
frame's motion / structure / fused maps are the means over those pairs. The structure cue checks
occlusion in both directions (the supplement's "Occlusion Handling": a source pixel also needs
the target pixel it lands on to see it back), unless ``two_way=False``.

Output per video: ``<out>/<stem>.detection.mp4`` / ``.gif`` and/or ``<out>/<stem>.detection/
NNNNN.png``: source | motion | structure | fused on the fixed colour scale of
:data:`geco_guide.metric.render.MAP_RANGE` with a legend and the frame's scores; and
``<out>/<stem>.detection.json`` with the per-frame scores. Written atomically.
"""

from __future__ import annotations

import io
from dataclasses import fields, replace
from pathlib import Path
from typing import Any

import numpy as np
import torch
from PIL import Image
from torch import Tensor

from ..estimators.bundle import Estimators
from ..estimators.dynamic_masks import GivenMasks, mask_source
from ..geometry import relative_pose, sample_at_projection
from ..io.files import write_bytes_atomic
from ..io.masks import fit_masks
from ..io.video import check_fps, write_video
from ..loss.cues import CUES, MAP_ORDER, fuse_cues, masked_mean, structure_residual
from ..loss.geco import MIN_UNMASKED_FRACTION, GeCoLossConfig, GeCoMaps
from ..types import SceneGeometry, check_estimator_bundle, check_frame_values
from .evaluate import MASKED_FRAME_NOTE, EvaluationMaps, score_frames
from .render import colorize, hatch, map_frames, text_scale

__all__ = ["ANCHORS", "FORMATS", "detection_maps", "frame_scores", "render_detection", "window_indices",
           "write_detection", "write_pngs"]

#: Where a frame sits in its window.
ANCHORS = ("start", "center", "end")
#: What the maps are written as: an mp4, a gif, a folder of PNG frames.
FORMATS = ("mp4", "gif", "png")



def window_indices(num_frames: int, frame: int, size: int, anchor: str) -> list[int]:
    """``[frame, *its neighbours]``: the ``size`` frames around ``frame`` (it first, then the
    others in time order). ``anchor``: ``start`` looks ahead, ``end`` back, ``center`` both ways;
    a window that would leave the clip is shifted back inside it."""
    if anchor not in ANCHORS:
        raise ValueError(f"anchor must be one of {ANCHORS}, got {anchor!r}")
    if size < 2:
        raise ValueError(f"the window needs at least 2 frames, got {size}")
    start = {"start": frame, "center": frame - size // 2, "end": frame + 1 - size}[anchor]
    start = max(0, min(start, num_frames - size))
    return [frame] + [k for k in range(start, min(start + size, num_frames)) if k != frame]


def seen_back(geometry: SceneGeometry, pairs: list[tuple[int, int]], config: GeCoLossConfig) -> Tensor:
    """The reverse occlusion check ``[1, P, H, W]`` bool: for each pair ``(s, t)`` and source
    pixel ``p``, the target pixel at ``p``'s projection passes the structure test towards ``s``
    (it is not hidden from ``s``), i.e. the two frames see the same surface there."""
    depth, K, extrinsics = geometry.depth[0], geometry.intrinsics[0], geometry.extrinsics[0]
    src = [s for s, _ in pairs]
    tgt = [t for _, t in pairs]
    tgt_to_src = relative_pose(extrinsics[tgt], extrinsics[src])
    _, reverse_valid = structure_residual(depth[tgt], depth[src], K[tgt], K[src], tgt_to_src,
                                          tau=config.occlusion_tau, edge_tau=config.depth_edge_tau)
    src_to_tgt = relative_pose(extrinsics[src], extrinsics[tgt])
    _, back, _ = sample_at_projection(depth[src], K[src], K[tgt], src_to_tgt, reverse_valid[:, None].to(depth.dtype))
    return (back[:, 0] > 0.5)[None]


def frame_maps(frames: Tensor, window: list[int], estimators: Estimators, config: GeCoLossConfig,
               two_way: bool = True, flow_batch_size: int = 16, dynamic_masks: Any = None) -> GeCoMaps:
    """Maps ``[1, H, W]`` of frame ``window[0]`` of ``frames [S, 3, H, W]`` against the other
    frames of ``window``: the pixel-wise mean over the pairs ``window[0] -> window[k]``
    (``dynamic_masks``: ``[S, H, W]`` bool of the whole clip, at the frames' size)."""
    pairs = [(0, k) for k in range(1, len(window))]
    if isinstance(dynamic_masks, Tensor):
        dynamic_masks = dynamic_masks[window]
    scene, result = score_frames(frames[window], estimators, config, pairs, flow_batch_size, dynamic_masks)
    maps = result.pair_maps
    if two_way:
        structure_valid = maps.structure_valid & seen_back(scene, pairs, config)
        fused, fused_valid = fuse_cues(maps.motion, maps.motion_valid, maps.structure, structure_valid)
        maps = replace(maps, structure_valid=structure_valid, fused=fused, fused_valid=fused_valid)
    averaged = []
    for name in MAP_ORDER:
        values, valid = maps.cue(name)
        averaged += [masked_mean(values, valid, dims=(1,)).cpu().float(), valid.any(1).cpu()]
    return GeCoMaps(*averaged)


@torch.no_grad()
def detection_maps(frames: Tensor, estimators: Estimators, config: GeCoLossConfig | None = None, *,
                   window: int = 20, anchor: str = "center", two_way: bool = True,
                   flow_batch_size: int = 16, dynamic_masks: Any = None) -> EvaluationMaps:
    """Every frame's own maps: ``frames [S, 3, H, W]`` in ``[0, 1]`` -> :class:`EvaluationMaps`
    ``[S, H, W]`` with the ``estimators`` (:class:`~geco_guide.estimators.Estimators`; ``window``
    is capped at the clip's length). ``dynamic_masks``: given masks of
    the clip, ``[S, H, W]`` (any size of the frames' aspect ratio) or a mask file; the maps then
    carry them, drawn striped by :func:`render_detection`. (Automatic and text masks differ per
    window here; score with ``evaluate_video`` for them.)"""
    if frames.ndim != 4 or frames.shape[1] != 3 or frames.shape[0] < 2:
        raise ValueError(f"frames must be [S >= 2, 3, H, W], got {list(frames.shape)}")
    check_frame_values(frames)  # as evaluate_video: a NaN frame is an error, not maps of None
    config = config or GeCoLossConfig()
    masks = None
    if dynamic_masks is not None:  # the whole clip's masks, checked before any window
        source = mask_source(dynamic_masks)
        if not isinstance(source, GivenMasks):
            raise ValueError("detection maps take given dynamic masks (a tensor or a mask file); "
                             "automatic and text masks: use evaluate_video")
        masks = fit_masks(source.masks, frames.shape[0], tuple(frames.shape[-2:]), source.name)
    size = min(window, frames.shape[0])
    windows = [window_indices(frames.shape[0], t, size, anchor) for t in range(frames.shape[0])]
    check_estimator_bundle(estimators, "detection_maps")
    per_frame = [frame_maps(frames, w, estimators, config, two_way, flow_batch_size, masks) for w in windows]
    stacked = [torch.cat([getattr(m, f.name) for m in per_frame]) for f in fields(GeCoMaps)]
    return EvaluationMaps(*stacked, frames=frames.detach().float().cpu(), dynamic_masks=masks)


def frame_scores(maps: EvaluationMaps) -> list[dict[str, float | None]]:
    """Per frame, each cue's mean over its valid pixels: ``None`` without a valid pixel, or, with
    dynamic masks, where fewer than :data:`~geco_guide.loss.geco.MIN_UNMASKED_FRACTION` of the
    frame's pixels stay valid (as ``evaluate_video`` counts frames), with a ``note`` saying so."""
    rows = []
    least = MIN_UNMASKED_FRACTION if maps.dynamic_masks is not None else 0.0
    for k in range(len(maps)):
        row: dict[str, Any] = {}
        for name in MAP_ORDER:
            values, valid = maps.cue(name)
            counts = bool(valid[k].any()) and float(valid[k].float().mean()) >= least
            row[name] = float(values[k][valid[k]].mean()) if counts else None
            if not counts and least:
                row["note"] = MASKED_FRAME_NOTE
        rows.append(row)
    return rows


def render_detection(maps: EvaluationMaps, scores: list[dict[str, float | None]]) -> Tensor:
    """``[S, 3, H', W']``: labelled panels source | motion | structure | fused (enlarged to a
    readable size: :func:`~.render.map_frames`), the legend, and a line with the frame's index and
    scores."""
    scale = text_scale(maps.frames.shape[-2])
    heat = [colorize(*maps.cue(name)) for name in MAP_ORDER]
    if maps.dynamic_masks is not None:  # left out as moving on its own: striped, not "consistent"
        heat = [hatch(panel, maps.dynamic_masks, scale) for panel in heat]

    def text(value: float | None) -> str:
        return "N/A" if value is None else f"{value:.3f}"

    captions = [f"frame {k}   " + "   ".join(f"{n} {text(row[n])}" for n in CUES)
                for k, row in enumerate(scores)]
    return map_frames(maps.frames, heat, ["SOURCE", *(name.upper() for name in MAP_ORDER)], captions)


def _uint8(frames: Tensor) -> np.ndarray:
    return (frames.clamp(0, 1).permute(0, 2, 3, 1).numpy() * 255.0 + 0.5).astype(np.uint8)


def write_pngs(folder: Path, frames: Tensor) -> Path:
    """One PNG per frame, ``folder/NNNNN.png``, each written atomically."""
    for k, frame in enumerate(_uint8(frames)):
        buffer = io.BytesIO()
        Image.fromarray(frame).save(buffer, format="PNG")
        write_bytes_atomic(folder / f"{k:05d}.png", buffer.getvalue())
    return folder


def write_detection(rendered: Tensor, stem: Path, formats: list[str], fps: float) -> list[Path]:
    """Write ``rendered [S, 3, H, W]`` as ``stem.detection.{mp4,gif}`` / ``stem.detection/*.png``.
    A frame rate outside the :data:`~geco_guide.io.video.FPS_RANGE` of a video format asked for
    is refused before any of them is written."""
    for f in formats:
        if f != "png":
            check_fps(fps, f".{f}")
    writers = {
        "mp4": lambda: write_video(stem.with_name(f"{stem.name}.detection.mp4"), rendered, fps=fps),
        "gif": lambda: write_video(stem.with_name(f"{stem.name}.detection.gif"), rendered, fps=fps),
        "png": lambda: write_pngs(stem.with_name(f"{stem.name}.detection"), rendered),
    }
    return [writers[f]() for f in formats]
