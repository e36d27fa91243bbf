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
import time
from collections.abc import Callable
from dataclasses import asdict, dataclass, field, fields, replace
from pathlib import Path
from typing import Any

import torch
from torch import Tensor

from ..estimators import Estimators, EstimatorsConfig, load_estimators
from ..estimators.dynamic_masks import AUTO, GivenMasks, looks_like_path, mask_source
from ..io.masks import MaskReadError, fit_masks, read_masks
from ..io.video import (
    VideoFrames,
    read_frames,
    write_video,
)
from ..loss.cues import MAP_ORDER
from ..loss.geco import (
    CUES,
    MIN_UNMASKED_FRACTION,
    GeCoLoss,
    GeCoLossConfig,
    GeCoMaps,
    GeCoResult,
    check_movers,
    frame_pairs,
    geco_from_geometry,
    no_valid_pixels_reason,
    resolve_dynamic_masks,
)
from ..loss.motion_stats import motion_statistics
from ..types import (Correspondences, SceneGeometry, check_estimator_bundle, check_frame_values, plural,
                     refuses_earlier_keywords)
from .protocol import (
    EvaluationConfig,
    Window,
    evaluation_windows,
    motion_grid,
    sampled_rate,
    scoring_plan,
)
from .render import colorize, hatch, map_frames, outline, text_scale

__all__ = ["MAP_PANELS", "MASKED_FRAME_NOTE", "PAPER_NAMES", "EvaluationMaps", "EvaluationResult", "clip_mask_source",
           "cue_scores", "evaluate_video", "finite_or_none", "map_caption", "mean_or_nan", "render_maps", "score_frames",
           "write_maps_video"]

MAP_PANELS = ("source", *MAP_ORDER)
#: Why a frame's score is ``None`` with dynamic masks.
MASKED_FRAME_NOTE = (f"scores are None where fewer than {MIN_UNMASKED_FRACTION:.0%} of the frame's pixels stay valid "
                     "outside the dynamic mask")
PAPER_NAMES = {
    **{name: CUES[name].symbol for name in MAP_ORDER},
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
        dynamic_masks: ``[N, H, W]`` bool, the pixels left out as moving on their own, or ``None``.
        movers: with ``movers="rigid"``, ``[N, H, W]`` int64, the mover each pixel belongs to (ids
            distinct over the windows; 0 none), for the outlines; ``None`` otherwise.

    ``maps[k]`` is a dict of frame ``k``'s ``frame [3, H, W]`` and maps ``[H, W]``.
    """

    frames: Tensor
    dynamic_masks: Tensor | None = None
    movers: Tensor | None = None

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
            consecutive frames of the clip's time grid (:func:`geco_guide.metric.protocol.motion_grid`).
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
        dynamic_masks: with dynamic masks, ``{source, masked_fraction, min_unmasked_fraction}``
            (the mean masked fraction of the evaluated frames; each frame row then has its own
            ``masked_fraction`` and, where a score is ``None`` because of the mask, a ``note``),
            plus ``nan_reason`` when no frame kept enough unmasked pixels; ``None`` without.
        movers: with ``evaluation.loss.movers="rigid"``, ``{mode, rigid, non_rigid, share, movers}``:
            per mover (of each window) its ``window``, ``id``, ``frames`` (source indices),
            ``pixels``, ``inlier_fraction``, ``residual``, ``verdict`` (rigid / non-rigid) and
            ``share`` of the clip's fused score; ``rigid`` / ``non_rigid`` count them and ``share``
            adds the shares up; ``None`` with ``drop``.
        nan_reason: why a score is NaN (no frame with valid pixels), ``None`` when all are finite.
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
    dynamic_masks: dict[str, Any] | None = None
    movers: dict[str, Any] | None = None
    nan_reason: str | None = None

    def to_dict(self) -> dict[str, Any]:
        """JSON-ready (no tensors; NaN scores become ``None``)."""
        data = {name: finite_or_none(getattr(self, name)) for name in (*MAP_ORDER, "total_motion", "mean_motion")}
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
            **({} if self.dynamic_masks is None else {"dynamic_masks": self.dynamic_masks}),
            **({} if self.movers is None else {"movers": self.movers}),
            **({} if self.nan_reason is None else {"nan_reason": self.nan_reason}),
        }


def finite_or_none(value: float) -> float | None:
    """``value``, or None (JSON ``null``) where it is not finite."""
    return value if math.isfinite(value) else None


def cue_scores(result: EvaluationResult | None) -> dict[str, float | None]:
    """The clip's score of each cue (:data:`~geco_guide.loss.geco.CUES`), None where it is not
    finite, all None where there is no ``result`` (a clip that could not be scored)."""
    return {name: None if result is None else finite_or_none(getattr(result, name)) for name in CUES}


def mean_or_nan(values: list[float]) -> float:
    """The mean, NaN for no values."""
    return sum(values) / len(values) if values else math.nan


def estimator_device(*models: Any) -> torch.device:
    """Where the estimator models' weights live (frames go there); CPU for weightless ones (oracles)."""
    for model in models:
        if isinstance(model, torch.nn.Module):
            for tensor in model.parameters():
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
def score_frames(frames: Tensor, estimators: Estimators, config: GeCoLossConfig,
                 pairs: list[tuple[int, int]] | None = None, flow_batch_size: int = 16,
                 dynamic_masks: Any = None) -> tuple[SceneGeometry, GeCoResult]:
    """GeCo of one clip ``frames [S, 3, H, W]`` in ``[0, 1]`` (a batch of 1) over ``pairs``
    (default: ``config.pairs``) with ``estimators``: one geometry call, the flow
    ``flow_batch_size`` pairs per call; ``dynamic_masks`` (``[S, H, W]``, a mask file or a mask
    source: see :func:`~geco_guide.loss.geco.resolve_dynamic_masks`) leave moving content out.
    Returns the estimated geometry and the :class:`GeCoResult`."""
    device = estimator_device(estimators.geometry, estimators.flow)
    pairs = pairs if pairs is not None else frame_pairs(frames.shape[0], config.pairs)
    scene = estimators.geometry.estimate_geometry(frames[None].to(device))
    correspondences = pair_correspondences(GeCoLoss(estimators, config), frames, pairs, flow_batch_size, device)
    masks, source = resolve_dynamic_masks(dynamic_masks, frames[None].to(device), scene, correspondences, pairs)
    return scene, geco_from_geometry(scene, correspondences, pairs, config, masks, source)


def clip_mask_source(dynamic_masks: Any, clip: VideoFrames, source_frames: int | None = None) -> Any:
    """The dynamic-mask source of a read clip: given masks (a path, a tensor or
    :class:`GivenMasks`) are checked against the video's frame count and size and cut to the
    protocol's frames (``clip.indices``), so windows and subsampling pick the same frames from
    masks and video; ``"auto"``, text and mask sources pass through
    :func:`~geco_guide.estimators.dynamic_masks.mask_source`.

    ``source_frames``: the frames of the whole video when the clip stops earlier
    (``evaluation.max_frames``; ``clip.num_frames`` counts the clip's): masks of the whole video
    are cut as the frames are, and masks of the clip alone are taken too.
    """
    counts = sorted({clip.num_frames, source_frames or clip.num_frames})
    read = isinstance(dynamic_masks, (str, os.PathLike)) and looks_like_path(os.fspath(dynamic_masks))
    if read:
        masks, count = read_masks(dynamic_masks, clip.indices)  # the protocol's frames only
        source = GivenMasks(masks, f"given: {os.fspath(dynamic_masks)}", dynamic_masks)
    else:
        source = mask_source(dynamic_masks)
        if not isinstance(source, GivenMasks):
            return source
        count = source.masks.shape[0]
    if count not in counts:
        scored = "" if len(counts) == 1 else f" (its first {clip.num_frames} scored: evaluation.max_frames)"
        holds = "hold" if source.path is None else "holds"  # masks, or a mask file
        raise MaskReadError(f"{source.name} {holds} {count} frame(s), the video {counts[-1]}{scored}: "
                            "give one mask per frame")
    if not read:
        source = GivenMasks(source.masks[list(clip.indices)], source.source_name, source.path)
    # a size that cannot fit fails now, not after the models load
    fit_masks(source.masks[:1], 1, tuple(clip.frames.shape[-2:]), source.name)
    return source


def _mask_notes(rows: list[dict[str, Any]], result: GeCoResult) -> None:
    """Add each frame's masked fraction, and why a score is missing where the mask took it."""
    for k, row in enumerate(rows):
        row["masked_fraction"] = float(result.masked_fraction[0, k])
        if any(row[name] is None for name in CUES):
            row["note"] = MASKED_FRAME_NOTE


def _is_subject_text(spec: Any) -> bool:
    """Whether ``dynamic_masks`` names subjects for a text segmenter (not a path, ``"auto"``, a
    tensor or a source)."""
    return isinstance(spec, str) and spec.strip() not in ("", AUTO) and not looks_like_path(spec)


def _protocol_frames(cfg: EvaluationConfig) -> Callable[[int, float], list[int]]:
    """The frame selector of the protocol: every window's frames and the motion grid."""

    def select(num_frames: int, fps: float) -> list[int]:
        num_frames = min(num_frames, cfg.max_frames or num_frames)
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


def _load_frames(video: str | os.PathLike | Tensor, fps: float | None,
                 cfg: EvaluationConfig) -> tuple[VideoFrames, str | None, int]:
    """The protocol's frames of ``video``, its path (``None`` for a tensor) and the frame count of
    the whole video; the clip ends at ``evaluation.max_frames``: its ``num_frames``, windows and
    motion grid are those of its first frames."""
    select = _protocol_frames(cfg)
    if isinstance(video, Tensor):
        if video.ndim != 4 or video.shape[1] != 3 or not video.is_floating_point():
            raise ValueError(f"video must be a float [S, 3, H, W] tensor in [0, 1], got {list(video.shape)} {video.dtype}")
        if fps is None:
            raise ValueError("fps (> 0) is required when video is a tensor")
        if video.shape[0] < 2:
            raise ValueError(f"video must hold at least 2 frames, got {video.shape[0]}")
        total = video.shape[0]
        video = video[: cfg.max_frames]
        indices = select(video.shape[0], fps)
        return VideoFrames(video.detach()[indices].float().cpu(), indices, float(fps), video.shape[0]), None, total
    clip = read_frames(video, fps=fps, default_fps=cfg.default_fps, select=select, min_frames=2)
    return replace(clip, num_frames=min(clip.num_frames, cfg.max_frames or clip.num_frames)), str(video), clip.num_frames


def plan_text(plan: dict[str, int], num_frames: int, fps: float) -> str:
    """One line saying what scoring a clip takes (:func:`~.protocol.scoring_plan`), before it starts."""
    return (f"{num_frames} frames at {fps:g} fps ({num_frames / fps:.1f} s): {plural(plan['windows'], 'window')} of "
            f"up to {plan['window_frames']} frames, motion statistics over {plan['motion_frames']} frames; "
            f"{plan['flow_pairs']} flow-estimator pairs in all (evaluation.max_frames bounds a long clip)")


def estimate_text(plan: dict[str, int], first_window_s: float, first_window_frames: int, pairs: str) -> str:
    """The time left, estimated after the first window: its seconds per flow pair (the geometry
    estimator's call included) times the pairs still to come. Rough: the motion statistics' pairs
    have no geometry call, so it errs long."""
    done = len(frame_pairs(first_window_frames, pairs))
    left = (plan["flow_pairs"] - done) * first_window_s / done
    return f"the first window took {first_window_s:.1f} s: about {left:.0f} s to go (estimated)"


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


@refuses_earlier_keywords("evaluate_video")
@torch.no_grad()
def evaluate_video(
    video: str | os.PathLike | Tensor,
    estimators: Estimators | EstimatorsConfig | None = None,
    config: EvaluationConfig | None = None,
    *,
    fps: float | None = None,
    model: str | None = None,
    maps: bool = False,
    progress: Callable[[str], None] | None = None,
    dynamic_masks: Any = None,
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
        estimators: the models as one :class:`~geco_guide.estimators.Estimators` (pass them to
            score many videos with one load; its segmenter, when it has one, masks the subjects
            that text ``dynamic_masks`` name), or an :class:`EstimatorsConfig` to load them from
            (``None``: its defaults, VGGT-1B + UFM-Base), on ``config.device``.
        config: the protocol, an :class:`EvaluationConfig` (``None``: the paper's).
        fps: the source frame rate, overriding everything else.
        model: a model name of ``config.model_fps`` (e.g. ``cogvideox-5b``): its native frame
            rate replaces the file's (the paper's protocol); ``fps`` still wins.
        maps: keep the per-frame maps (:class:`EvaluationMaps`) for :func:`write_maps_video`.
        progress: called with one line before each window and before the motion statistics
            (a long clip takes a while per window).
        dynamic_masks: content that moves on its own, left out of the scores: ``None`` (the
            paper's metric), masks of the whole video (a mask video, PNG folder or ``.npz`` path,
            or a ``[S, H, W]`` tensor; cut to the protocol's frames, and to
            ``evaluation.max_frames`` as the video is), ``"auto"``, text for a
            segmenter, or a :class:`~geco_guide.types.DynamicMaskSource` (asked per window). A
            frame with fewer than :data:`~geco_guide.loss.geco.MIN_UNMASKED_FRACTION` of its
            pixels valid outside the mask scores ``None`` with a note; Total / Mean Motion stay
            unmasked (they describe the camera and the content alike).

    Raises:
        VideoReadError: unreadable input or fewer than 2 frames (a ValueError).
        ValueError: evaluated frames with NaN/inf values or outside ``[0, 1]``, naming them; an
            unknown ``model``; ``dynamic_masks`` that is an empty string (not the working folder).
        TypeError: estimators that are not a bundle, or passed by an earlier keyword
            (``geometry=``, ``flow_estimator=``, ...).
    """
    cfg = _evaluation_config(estimators, config)
    if isinstance(estimators, Estimators) and estimators.segmenter is not None and _is_subject_text(dynamic_masks):
        dynamic_masks = estimators.masks_for(dynamic_masks)
    rate, fps_source = protocol_fps(fps, model, cfg)
    clip, source, source_frames = _load_frames(video, rate, cfg)
    if rate is None:
        fps_source = clip.fps_source  # the file's rate, or default_fps for inputs without one
    # NaN pixels would score NaN (or 0.0 once masked), 0-255 frames garbage: refuse them, by index.
    check_frame_values(clip.frames, "video" if source is None else source, indices=clip.indices)
    loss_config = cfg.loss
    check_movers(loss_config, dynamic_masks is not None)
    masks = clip_mask_source(dynamic_masks, clip, source_frames)
    if not isinstance(estimators, Estimators):
        estimators = load_estimators(estimators or EstimatorsConfig(), cfg.device)
    metric = GeCoLoss(estimators, loss_config)
    scored = _score_windows(clip, estimators, cfg, loss_config, masks, maps=maps, progress=progress)
    stats = _motion_statistics(clip, metric, cfg, progress)
    scores = {name: _clip_score(scored.windows, name) for name in CUES}
    nan_reason = None if all(map(math.isfinite, scores.values())) else no_valid_pixels_reason(masks is not None)
    return EvaluationResult(
        **scores, total_motion=stats.total_motion, mean_motion=stats.mean_motion, frame_scores=scored.frame_scores,
        windows=scored.windows, num_frames=clip.num_frames, fps=clip.fps, fps_source=fps_source,
        sampled_fps=sampled_rate(clip.fps, cfg.max_fps), estimators=estimators.ids("geometry", "flow"),
        config=asdict(cfg), source=source, maps=None if scored.maps is None else scored.maps.stacked(),
        dynamic_masks=_mask_record(masks, scored.frame_scores, nan_reason),
        movers=None if loss_config.movers == "drop" else _movers_record(scored.movers, scored.windows, scores["fused"]),
        nan_reason=nan_reason,
    )


def _evaluation_config(estimators: object, config: EvaluationConfig | None) -> EvaluationConfig:
    """The protocol of a call (``config``, or the paper's for ``None``) once its ``estimators`` and
    ``config`` are of the types :func:`evaluate_video` takes (TypeError, one line, otherwise)."""
    if isinstance(estimators, Estimators) or not (estimators is None or isinstance(estimators, EstimatorsConfig)):
        check_estimator_bundle(estimators, "evaluate_video")
    if config is not None and not isinstance(config, EvaluationConfig):
        raise TypeError(f"evaluate_video: config must be an EvaluationConfig (a config's evaluation section), "
                        f"got {type(config).__name__}")
    return config if config is not None else EvaluationConfig()


def _positions(clip: VideoFrames, indices: list[int]) -> list[int]:
    """Where the source frames ``indices`` lie among the clip's read frames (``clip.indices``)."""
    position = {index: k for k, index in enumerate(clip.indices)}
    return [position[i] for i in indices]


@dataclass
class _KeptMaps:
    """The windows' maps kept for :class:`EvaluationMaps`, window after window, on the CPU: each
    window's frame maps ``[S, H, W]``, frames ``[S, 3, H, W]``, dropped masks ``[S, H, W]`` and
    mover labels ``[S, H, W]`` (made distinct over the windows)."""

    maps: list[list[Tensor]] = field(default_factory=list)
    frames: list[Tensor] = field(default_factory=list)
    masks: list[Tensor] = field(default_factory=list)
    movers: list[Tensor] = field(default_factory=list)

    def add(self, result: GeCoResult, frames: Tensor, masked: bool) -> None:
        """Keep a window's ``result`` and ``frames``; ``masked``: the clip has dynamic masks."""
        self.maps.append([getattr(result.frame_maps, name)[0].cpu() for name in _MAP_FIELDS])
        self.frames.append(frames)
        if result.movers is not None:  # the pixels a mover leaves out, and its labels after the earlier windows'
            self.masks.append(result.movers.dropped[0].cpu())
            offset = max((int(m.max()) for m in self.movers), default=0)
            labels = result.movers.fit.labels[0].cpu()
            self.movers.append(torch.where(labels > 0, labels + offset, labels))
        elif masked:
            self.masks.append(result.dynamic_masks[0].cpu())

    def stacked(self) -> EvaluationMaps:
        """Every kept window's maps as one :class:`EvaluationMaps`, in window order."""
        stacked = [torch.cat(parts) if parts[0].dtype == torch.bool else torch.cat(parts).float() for parts in zip(*self.maps)]
        return EvaluationMaps(*stacked, frames=torch.cat(self.frames),
                              dynamic_masks=torch.cat(self.masks) if self.masks else None,
                              movers=torch.cat(self.movers) if self.movers else None)


@dataclass
class _ScoredWindows:
    """What scoring a clip's windows gives: every frame's row (window after window), every
    window's record, the movers' rows (with ``evaluation.loss.movers="rigid"``) and, when asked for,
    the maps."""

    frame_scores: list[dict[str, Any]] = field(default_factory=list)
    windows: list[dict[str, Any]] = field(default_factory=list)
    movers: list[dict[str, Any]] = field(default_factory=list)
    maps: _KeptMaps | None = None


def _score_windows(clip: VideoFrames, estimators: Estimators, cfg: EvaluationConfig, loss_config: GeCoLossConfig,
                   masks: Any, *, maps: bool, progress: Callable[[str], None] | None) -> _ScoredWindows:
    """GeCo (``loss_config``) on each window of the protocol (:func:`~.protocol.evaluation_windows`)
    of ``clip``, with the clip's dynamic-mask source ``masks`` (cut to each window where given); ``progress``
    is told the plan, each window and, after the first, the time left."""
    scored = _ScoredWindows(maps=_KeptMaps() if maps else None)
    planned = evaluation_windows(clip.num_frames, clip.fps, cfg.window_seconds, cfg.max_windows, cfg.max_fps)
    plan = scoring_plan(clip.num_frames, clip.fps, cfg)
    if progress is not None:  # before the work: a long clip's motion statistics alone take long
        progress(plan_text(plan, clip.num_frames, clip.fps))
    started = time.perf_counter()
    for w, window in enumerate(planned):
        if progress is not None and w == 1:
            progress(estimate_text(plan, time.perf_counter() - started, len(planned[0].indices), cfg.loss.pairs))
        if progress is not None:
            progress(f"window {w + 1}/{len(planned)}: {len(window.indices)} frames from "
                     f"{window.indices[0] / clip.fps:.2f} s to {window.indices[-1] / clip.fps:.2f} s")
        window_frames = clip.frames[_positions(clip, window.indices)]
        _, result = score_frames(window_frames, estimators, loss_config, flow_batch_size=cfg.flow_batch_size,
                                 dynamic_masks=_window_masks(masks, clip, window.indices))
        rows = _frame_rows(result, window, w, clip.fps)
        if masks is not None:
            _mask_notes(rows, result)
        scored.frame_scores.extend(rows)
        scored.windows.append(_window_record(window, rows))
        scored.movers.extend(_window_movers(result, window, w))
        if scored.maps is not None:
            scored.maps.add(result, window_frames, masks is not None)
    return scored


def _window_masks(masks: Any, clip: VideoFrames, indices: list[int]) -> Any:
    """A window's dynamic-mask source: given masks cut to its frames ``indices``, any other
    source (or ``None``) as it is."""
    if not isinstance(masks, GivenMasks):
        return masks
    return GivenMasks(masks.masks[_positions(clip, indices)], masks.source_name, masks.path)


def _frame_rows(result: GeCoResult, window: Window, w: int, fps: float) -> list[dict[str, Any]]:
    """The rows of window ``w``'s frames: source index, time and each cue's score (``None`` where
    the frame has no valid pixel)."""
    rows = []
    for k, index in enumerate(window.indices):
        scores = {
            name: float(result.frame_scores[name][0, k]) if bool(result.frame_has_valid[name][0, k]) else None
            for name in CUES
        }
        rows.append({"index": index, "time_s": index / fps, "window": w, **scores})
    return rows


def _window_movers(result: GeCoResult, window: Window, w: int) -> list[dict[str, Any]]:
    """The movers of window ``w`` (none without ``movers="rigid"``), each with its contribution to
    the window's fused score."""
    if result.movers is None:
        return []
    return [{"window": w, **record, "contribution": float(result.movers.contribution[0, record["id"] - 1])}
            for record in result.movers.records(0, window.indices)]


def _motion_statistics(clip: VideoFrames, metric: GeCoLoss, cfg: EvaluationConfig,
                       progress: Callable[[str], None] | None) -> Any:
    """Total / Mean Motion of ``clip``: the flow between consecutive frames of its time grid
    (:func:`~.protocol.motion_grid`), unmasked."""
    if progress is not None:
        progress("motion statistics (consecutive frames)")
    grid = motion_grid(clip.num_frames, clip.fps, cfg.max_fps)
    steps = [(k, k + 1) for k in range(len(grid) - 1)]
    device = estimator_device(metric.geometry_estimator, metric.flow_estimator)
    consecutive = pair_correspondences(metric, clip.frames[_positions(clip, grid)], steps, cfg.flow_batch_size, device)
    return motion_statistics(
        consecutive.flow.float(), consecutive.covisibility > cfg.loss.covisibility_threshold,
        duration_s=clip.num_frames / clip.fps,
    )


def _mask_record(masks: Any, frame_scores: list[dict[str, Any]], nan_reason: str | None) -> dict[str, Any] | None:
    """The report's ``dynamic_masks``: the masks' source and the evaluated frames' mean masked
    fraction (with the ``nan_reason`` of a clip the masks left unscored); ``None`` without masks."""
    if masks is None:
        return None
    record = {"source": masks.source_name, "masked_fraction": mean_or_nan([row["masked_fraction"] for row in frame_scores]),
              "min_unmasked_fraction": MIN_UNMASKED_FRACTION}
    if nan_reason is not None:
        record["nan_reason"] = nan_reason
    return record


def _movers_record(movers: list[dict[str, Any]], windows: list[dict[str, Any]], fused: float) -> dict[str, Any]:
    """The report's ``movers``: each window's movers with their share of the clip's fused score
    (a window's part weighted by its frames, as :func:`_clip_score` weighs the windows), counted."""
    scored = sum(len(w["frames"]) for w in windows if w["fused"] is not None)
    rows = []
    for mover in movers:
        row = dict(mover)
        part = row.pop("contribution") * len(windows[row["window"]]["frames"]) / scored if scored else math.nan
        row["share"] = finite_or_none(part / fused) if math.isfinite(fused) and fused > 0 else None
        rows.append(row)
    return {"mode": "rigid", "rigid": sum(r["verdict"] == "rigid" for r in rows),
            "non_rigid": sum(r["verdict"] == "non-rigid" for r in rows),
            "share": sum(r["share"] or 0.0 for r in rows), "movers": rows}


# --------------------------------------------------------------------------------------------
# maps video


def _score_text(value: float | None) -> str:
    return "N/A" if value is None else f"{value:.3f}"


def render_maps(result: EvaluationResult) -> Tensor:
    """The frames of the maps video: ``[N, 3, H', W']``.

    Rows: labelled panels source | motion | structure | fused (:func:`map_frames`: enlarged to a
    readable size, viridis on
    the fixed :data:`~geco_guide.metric.render.MAP_RANGE`, grey = no valid pixel, grey-and-white stripes
    = left out by the dynamic mask, a white outline = a mover scored against its own motion), the legend
    (:func:`colorbar`), and a line with the frame's time and scores.
    """
    if result.maps is None:
        raise ValueError("the result holds no maps: evaluate with maps=True")
    m = result.maps
    scale = text_scale(m.frames.shape[-2])
    heat = [colorize(getattr(m, name), getattr(m, f"{name}_valid")) for name in MAP_PANELS[1:]]
    if m.dynamic_masks is not None:  # left out as moving on its own: striped, not "consistent"
        heat = [hatch(panel, m.dynamic_masks, scale) for panel in heat]
    if m.movers is not None:  # scored against their own motion, on the static part's colour scale
        heat = [outline(panel, m.movers) for panel in heat]
    captions = [map_caption(row) for row in result.frame_scores]
    return map_frames(m.frames, heat, [name.upper() for name in MAP_PANELS], captions)


def map_caption(row: dict[str, Any]) -> str:
    """The line under a frame of the maps video: its time and scores (a frame row of
    :attr:`EvaluationResult.frame_scores`), in lower case: ``t = 0.62 s   fused 0.051 ...``."""
    return (f"t = {row['time_s']:.2f} s   fused {_score_text(row['fused'])}   motion {_score_text(row['motion'])}   "
            f"structure {_score_text(row['structure'])}")


def write_maps_video(result: EvaluationResult, path: str | os.PathLike) -> Path:
    """Render :func:`render_maps` as an mp4 at the evaluated frame rate, atomically."""
    return write_video(path, render_maps(result), fps=result.sampled_fps)
