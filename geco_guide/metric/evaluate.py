"""Score any video with GeCo: :func:`evaluate_video` (the command is :mod:`geco_guide.cli.evaluate`).

The GeCo-Eval protocol (:class:`~geco_guide.config.EvaluationConfig`, the paper and its published
evaluation script): the clip, timed at the model's native frame rate (``--model``), ``--fps`` or
the file's, is covered by ``ceil(T / 3 s)`` overlapping windows of 3 s (more than 4 -> exactly 4
equal windows), each sampled on a time grid at ``min(8, fps)`` fps; GeCo runs on each window with
every ordered frame pair. A frame's map is the pixel-wise mean over its pairs, its score the mean
over valid pixels, a window's score the mean over its frames, and the clip's the windows'
frame-weighted mean. Total Motion / Mean Motion come from the flow between consecutive frames of
the whole clip's time grid.

The maps video of a result: :func:`render_maps` / :func:`write_maps_video`.
"""

from __future__ import annotations

import math
import os
from collections.abc import Callable
from dataclasses import asdict, dataclass, field, fields
from pathlib import Path
from typing import Any

import torch
from torch import Tensor

from ..estimators import EstimatorsConfig, estimator_id, load_estimators
from ..io.video import (
    VideoFrames,
    read_frames,
    write_video,
)
from ..loss.geco import (
    CUES,
    GeCoLoss,
    GeCoLossConfig,
    GeCoMaps,
    GeCoResult,
    frame_pairs,
    geco_from_geometry,
)
from ..loss.motion_stats import motion_statistics
from ..types import Correspondences, SceneGeometry, check_frame_values, one_of_names
from .protocol import (
    EvaluationConfig,
    Window,
    evaluation_windows,
    motion_grid,
    sampled_rate,
)
from .render import colorbar, colorize, side_by_side, text_scale, text_strip

MAP_PANELS = ("source", "motion", "structure", "fused")
PAPER_NAMES = {
    "motion": "M_motion",
    "structure": "M_struct",
    "fused": "M_geo",
    "total_motion": "Total Motion (%)",
    "mean_motion": "Mean Motion (%/s)",
}


@dataclass
class EvaluationMaps(GeCoMaps):
    """The frame maps of every evaluated frame (``N`` of them, in time order), on the CPU.

    Attributes:
        motion, structure, fused: ``[N, H, W]`` the frame maps (mean over the frame's pairs),
            with their ``*_valid`` masks, as in :class:`~geco_guide.loss.geco.GeCoMaps`.
        frames: ``[N, 3, H, W]`` the evaluated frames.

    ``maps[k]`` is a dict of frame ``k``'s ``frame [3, H, W]`` and maps ``[H, W]``.
    """

    frames: Tensor

    def __len__(self) -> int:
        return self.frames.shape[0]

    def __getitem__(self, k: int) -> dict[str, Tensor]:
        return {"frame": self.frames[k], **{name: getattr(self, name)[k] for name in _MAP_FIELDS}}


_MAP_FIELDS = tuple(f.name for f in fields(GeCoMaps))


@dataclass
class EvaluationResult:
    """GeCo scores of one video.

    Attributes:
        motion, structure, fused: M_motion, M_struct, M_geo: means of the frame scores over
            evaluated frames with valid pixels (frame-weighted over windows); NaN if none.
        total_motion: Total Motion (%): the flow magnitude over the image diagonal, summed over
            consecutive frames of the clip's time grid (:func:`geco_guide.video.motion_grid`).
        mean_motion: Mean Motion (%/s): Total Motion over the clip's duration.
        frame_scores: per evaluated frame and window ``{index, time_s, window, motion, structure,
            fused}`` (source frame index; a score is ``None`` when the frame has no valid pixel;
            overlapping windows score a frame once each).
        windows: per window ``{start_s, length_s, frames, motion, structure, fused}`` (``frames``:
            source indices).
        num_frames: frames in the source video.
        fps: the frame rate the protocol used; fps_source: where it came from (``--fps``,
            ``model <name>``, ``file``, ``default``); sampled_fps: the windows' sampling rate.
        estimators: ``{geometry, flow}`` ids.
        config: the :class:`EvaluationConfig` used, as a dict.
        source: the input path, ``None`` for a tensor.
        maps: :class:`EvaluationMaps` when asked for (``maps=True``).
    """

    motion: float
    structure: float
    fused: float
    total_motion: float
    mean_motion: float
    frame_scores: list[dict[str, Any]]
    windows: list[dict[str, Any]]
    num_frames: int
    fps: float
    fps_source: str
    sampled_fps: float
    estimators: dict[str, str]
    config: dict[str, Any]
    source: str | None = None
    maps: EvaluationMaps | None = field(default=None, repr=False)

    def to_dict(self) -> dict[str, Any]:
        """JSON-ready (no tensors; NaN scores become ``None``)."""
        data = {name: finite_or_none(getattr(self, name)) for name in ("motion", "structure", "fused", "total_motion", "mean_motion")}
        return {
            "source": self.source,
            **data,
            "paper_names": PAPER_NAMES,
            "num_frames": self.num_frames,
            "num_evaluated_frames": len(self.frame_scores),
            "fps": self.fps,
            "fps_source": self.fps_source,
            "duration_s": self.num_frames / self.fps,
            "sampled_fps": self.sampled_fps,
            "windows": self.windows,
            "frame_scores": self.frame_scores,
            "estimators": self.estimators,
            "config": self.config,
        }


def finite_or_none(value: float) -> float | None:
    """``value``, or None (JSON ``null``) where it is not finite."""
    return value if math.isfinite(value) else None


def mean_or_nan(values: list[float]) -> float:
    """The mean, NaN for no values."""
    return sum(values) / len(values) if values else math.nan


def estimator_device(*estimators: Any) -> torch.device:
    """Where the estimators' weights live (frames go there); CPU for weightless ones (oracles)."""
    for estimator in estimators:
        if isinstance(estimator, torch.nn.Module):
            for tensor in estimator.parameters():
                return tensor.device
    return torch.device("cpu")


def pair_correspondences(metric: GeCoLoss, frames: Tensor, pairs: list[tuple[int, int]], batch_size: int, device: torch.device) -> Correspondences:
    """Flow + covisibility of ``pairs`` of ``frames [S, 3, H, W]``, ``batch_size`` pairs per
    estimator call; only the frames a batch uses are moved to ``device``.
    Returns flow ``[P, 2, H, W]`` and covisibility ``[P, H, W]`` on ``device``."""
    flows, covis = [], []
    for start in range(0, len(pairs), batch_size):
        chunk = pairs[start : start + batch_size]
        used = sorted({k for pair in chunk for k in pair})
        local = {k: n for n, k in enumerate(used)}
        subset = frames[used][None].to(device)
        result = metric.estimate_correspondences(subset, [(local[i], local[j]) for i, j in chunk])
        flows.append(result.flow)
        covis.append(result.covisibility)
    return Correspondences(flow=torch.cat(flows), covisibility=torch.cat(covis))


@torch.no_grad()
def score_frames(frames: Tensor, geometry: Any, flow: Any, config: GeCoLossConfig,
                 pairs: list[tuple[int, int]] | None = None, flow_batch_size: int = 16) -> tuple[SceneGeometry, GeCoResult]:
    """GeCo of one clip ``frames [S, 3, H, W]`` in ``[0, 1]`` (a batch of 1) over ``pairs``
    (default: ``config.pairs``): one geometry call, the flow ``flow_batch_size`` pairs per call.
    Returns the estimated geometry and the :class:`GeCoResult`."""
    device = estimator_device(geometry, flow)
    pairs = pairs if pairs is not None else frame_pairs(frames.shape[0], config.pairs)
    scene = geometry.estimate_geometry(frames[None].to(device))
    correspondences = pair_correspondences(GeCoLoss(geometry, flow, config), frames, pairs, flow_batch_size, device)
    return scene, geco_from_geometry(scene, correspondences, pairs, config)


def _split_config(config: Any) -> tuple[EvaluationConfig, EstimatorsConfig]:
    if config is None:
        return EvaluationConfig(), EstimatorsConfig()
    if isinstance(config, EvaluationConfig):
        return config, EstimatorsConfig()
    # a whole GeCoConfig, by its sections: the config module sits above the metric
    if isinstance(getattr(config, "evaluation", None), EvaluationConfig) and hasattr(config, "estimators"):
        return config.evaluation, config.estimators
    raise ValueError(f"config must be an EvaluationConfig or a GeCoConfig, got {type(config).__name__}")


def _protocol_frames(cfg: EvaluationConfig) -> Callable[[int, float], list[int]]:
    """The frame selector of the protocol: every window's frames and the motion grid."""

    def select(num_frames: int, fps: float) -> list[int]:
        if num_frames < 2:
            return list(range(num_frames))
        windows = evaluation_windows(num_frames, fps, cfg.window_seconds, cfg.max_windows, cfg.max_fps)
        return sorted({i for w in windows for i in w.indices} | set(motion_grid(num_frames, fps, cfg.max_fps)))

    return select


def protocol_fps(fps: float | None, model: str | None, cfg: EvaluationConfig) -> tuple[float | None, str]:
    """The frame rate the protocol uses and why: ``fps`` (``--fps``) over the model's native rate
    (``--model``, :attr:`EvaluationConfig.model_fps`) over the file's (``None`` here: read later)."""
    if fps is not None:
        if not (fps > 0 and math.isfinite(fps)):
            raise ValueError(f"fps must be a finite number > 0, got {fps}")
        return float(fps), "--fps"
    if model is not None:
        return cfg.fps_of_model(model), f"model {model}"
    return None, "file"  # replaced by the reader's answer: file or default


def _load_frames(video: str | os.PathLike | Tensor, fps: float | None, cfg: EvaluationConfig) -> tuple[VideoFrames, str | None]:
    select = _protocol_frames(cfg)
    if isinstance(video, Tensor):
        if video.ndim != 4 or video.shape[1] != 3 or not video.is_floating_point():
            raise ValueError(f"video must be a float [S, 3, H, W] tensor in [0, 1], got {list(video.shape)} {video.dtype}")
        if fps is None:
            raise ValueError("fps (> 0) is required when video is a tensor")
        if video.shape[0] < 2:
            raise ValueError(f"video must hold at least 2 frames, got {video.shape[0]}")
        indices = select(video.shape[0], fps)
        return VideoFrames(video.detach()[indices].float().cpu(), indices, float(fps), video.shape[0]), None
    clip = read_frames(video, fps=fps, default_fps=cfg.default_fps, select=select, min_frames=2)
    return clip, str(video)


def _window_record(window: Window, rows: list[dict[str, Any]]) -> dict[str, Any]:
    """A window's scores: the mean over its frames with valid pixels, per cue."""
    return {
        "start_s": window.start_s,
        "length_s": window.length_s,
        "frames": list(window.indices),
        **{name: finite_or_none(mean_or_nan([r[name] for r in rows if r[name] is not None])) for name in CUES},
    }


def _clip_score(windows: list[dict[str, Any]], name: str) -> float:
    """Windows' scores of cue ``name`` averaged with their frame counts as weights (the script's
    frame-weighted mean), over windows with a score."""
    scored = [(w[name], len(w["frames"])) for w in windows if w[name] is not None]
    total = sum(weight for _, weight in scored)
    return sum(value * weight for value, weight in scored) / total if total else math.nan


@torch.no_grad()
def evaluate_video(
    video: str | os.PathLike | Tensor,
    *,
    geometry_estimator: Any = None,
    flow_estimator: Any = None,
    config: Any = None,
    fps: float | None = None,
    model: str | None = None,
    maps: bool = False,
    progress: Callable[[str], None] | None = None,
    geometry: Any = None,
    flow: Any = None,
) -> EvaluationResult:
    """GeCo scores of a video under the GeCo-Eval protocol (:class:`EvaluationConfig`).

    The clip is covered by overlapping windows of ~3 s (at most 4), each sampled at
    ``min(8, fps)`` fps; GeCo runs on each window (all ordered pairs by default, the published
    evaluation script's, where ``GeCoLoss()`` uses the guidance loss' adjacent pairs: see
    :mod:`geco_guide.loss.presets`); a frame's score
    is the mean of its map over valid pixels, a window's the mean over its frames, the clip's the
    windows' frame-weighted mean. Total / Mean Motion come from consecutive frames of the clip's
    time grid.

    Args:
        video: a path (mp4 or another ffmpeg format, gif, folder of png/jpg frames) or frames
            ``[S, 3, H, W]`` in ``[0, 1]`` (then ``fps`` or ``model`` is required).
        geometry_estimator, flow_estimator: a :class:`GeometryEstimator` / :class:`FlowEstimator`;
            built from the config's estimators when ``None`` (pass them to score many videos
            with one load). ``geometry=`` / ``flow=`` are the same arguments under their
            earlier names.
        config: an :class:`EvaluationConfig`, or a whole :class:`GeCoConfig` (its ``evaluation``
            and ``estimators``); ``None``: defaults (VGGT-1B + UFM-Base).
        fps: the source frame rate, overriding everything else.
        model: a model name of ``config.model_fps`` (e.g. ``cogvideox-5b``): its native frame
            rate replaces the file's (the paper's protocol); ``fps`` still wins.
        maps: keep the per-frame maps (:class:`EvaluationMaps`) for :func:`write_maps_video`.
        progress: called with one line before each window and before the motion statistics
            (a long clip takes a while per window).

    Raises:
        VideoReadError: unreadable input or fewer than 2 frames (a ValueError).
        ValueError: evaluated frames with NaN/inf values or outside ``[0, 1]``, naming them; an
            unknown ``model``.
    """
    geometry = one_of_names(geometry_estimator, geometry, "geometry_estimator", "geometry")
    flow = one_of_names(flow_estimator, flow, "flow_estimator", "flow")
    cfg, estimators_cfg = _split_config(config)
    rate, fps_source = protocol_fps(fps, model, cfg)
    clip, source = _load_frames(video, rate, cfg)
    if rate is None:
        fps_source = clip.fps_source  # the file's rate, or default_fps for inputs without one
    # NaN pixels would score NaN (or 0.0 once masked), 0-255 frames garbage: refuse them, by index.
    check_frame_values(clip.frames, "video" if source is None else source, indices=clip.indices)
    if geometry is None or flow is None:
        loaded = load_estimators(estimators_cfg, cfg.device)
        geometry = geometry if geometry is not None else loaded[0]
        flow = flow if flow is not None else loaded[1]
    device = estimator_device(geometry, flow)
    metric = GeCoLoss(geometry, flow, cfg.loss)
    position = {index: k for k, index in enumerate(clip.indices)}

    def frames_of(indices: list[int]) -> Tensor:
        return clip.frames[[position[i] for i in indices]]

    frame_scores: list[dict[str, Any]] = []
    windows: list[dict[str, Any]] = []
    kept_maps: list[list[Tensor]] = []
    kept_frames: list[Tensor] = []
    planned = evaluation_windows(clip.num_frames, clip.fps, cfg.window_seconds, cfg.max_windows, cfg.max_fps)
    for w, window in enumerate(planned):
        if progress is not None:
            progress(f"window {w + 1}/{len(planned)}: {len(window.indices)} frames from "
                     f"{window.indices[0] / clip.fps:.2f} s to {window.indices[-1] / clip.fps:.2f} s")
        window_frames = frames_of(window.indices)
        _, result = score_frames(window_frames, geometry, flow, cfg.loss, flow_batch_size=cfg.flow_batch_size)
        rows = []
        for k, index in enumerate(window.indices):
            scores = {
                name: float(result.frame_scores[name][0, k]) if bool(result.frame_has_valid[name][0, k]) else None
                for name in CUES
            }
            rows.append({"index": index, "time_s": index / clip.fps, "window": w, **scores})
        frame_scores.extend(rows)
        windows.append(_window_record(window, rows))
        if maps:
            kept_maps.append([getattr(result.frame_maps, name)[0].cpu() for name in _MAP_FIELDS])
            kept_frames.append(window_frames)

    if progress is not None:
        progress("motion statistics (consecutive frames)")
    grid = motion_grid(clip.num_frames, clip.fps, cfg.max_fps)
    steps = [(k, k + 1) for k in range(len(grid) - 1)]
    consecutive = pair_correspondences(metric, frames_of(grid), steps, cfg.flow_batch_size, device)
    stats = motion_statistics(
        consecutive.flow.float(), consecutive.covisibility > cfg.loss.covisibility_threshold,
        duration_s=clip.num_frames / clip.fps,
    )
    evaluation_maps = None
    if maps:
        stacked = [torch.cat(parts) if parts[0].dtype == torch.bool else torch.cat(parts).float() for parts in zip(*kept_maps)]
        evaluation_maps = EvaluationMaps(*stacked, frames=torch.cat(kept_frames))
    return EvaluationResult(
        **{name: _clip_score(windows, name) for name in CUES},
        total_motion=stats.total_motion,
        mean_motion=stats.mean_motion,
        frame_scores=frame_scores,
        windows=windows,
        num_frames=clip.num_frames,
        fps=clip.fps,
        fps_source=fps_source,
        sampled_fps=sampled_rate(clip.fps, cfg.max_fps),
        estimators={"geometry": estimator_id(geometry), "flow": estimator_id(flow)},
        config=asdict(cfg),
        source=source,
        maps=evaluation_maps,
    )


# --------------------------------------------------------------------------------------------
# maps video


def _score_text(value: float | None) -> str:
    return "N/A" if value is None else f"{value:.3f}"


def render_maps(result: EvaluationResult) -> Tensor:
    """The frames of the maps video: ``[N, 3, H', W']``.

    Rows: labelled panels source | motion | structure | fused (:func:`side_by_side`, viridis on
    the fixed :data:`~geco_guide.video.MAP_RANGE`, grey = no valid pixel), the legend
    (:func:`colorbar`), and a line with the frame's time and scores.
    """
    if result.maps is None:
        raise ValueError("the result holds no maps: evaluate with maps=True")
    m = result.maps
    heat = [colorize(getattr(m, name), getattr(m, f"{name}_valid")) for name in MAP_PANELS[1:]]
    grid = side_by_side([m.frames, *heat], [name.upper() for name in MAP_PANELS])
    num, _, _, width = grid.shape
    scale = text_scale(m.frames.shape[-2])
    legend = colorbar(width, scale)[None].expand(num, -1, -1, -1)
    lines = []
    for row in result.frame_scores:
        text = (
            f"T={row['time_s']:.2f}S FUSED {_score_text(row['fused'])} MOTION {_score_text(row['motion'])} "
            f"STRUCTURE {_score_text(row['structure'])}"
        )
        lines.append(text_strip(text, width, scale))
    return torch.cat((grid, legend, torch.stack(lines)), dim=-2)


def write_maps_video(result: EvaluationResult, path: str | os.PathLike) -> Path:
    """Render :func:`render_maps` as an mp4 at the evaluated frame rate, atomically."""
    return write_video(path, render_maps(result), fps=result.sampled_fps)
