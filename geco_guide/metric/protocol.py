"""The GeCo-Eval protocol as pure functions: overlapping windows of ``window_seconds`` covering the
clip (:func:`evaluation_windows`, at most ``max_windows``), each sampled on a time grid at
``min(max_fps, fps)`` (:func:`time_grid_indices`), the frames of Total / Mean Motion
(:func:`motion_grid`), the native frame rate of each model (:data:`PAPER_MODEL_FPS`), and
:class:`EvaluationConfig`, the options of scoring a video."""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import ClassVar, Optional

from ..families import paper_fps
from ..loss.geco import GeCoLossConfig, frame_pairs
from ..loss.presets import evaluation_loss
from ..types import OptionError, refuse_renamed_arguments

__all__ = ["PAPER_MODEL_FPS", "EvaluationConfig", "Window", "evaluation_windows", "motion_grid",
           "sampled_rate", "scoring_plan", "time_grid_indices"]

#: model -> its native frame rate (fps), the table GeCo-Eval times its windows with (the registry's)
PAPER_MODEL_FPS = paper_fps()


def sampled_rate(fps: float, max_fps: float) -> float:
    """The evaluation rate of a clip of ``fps``: ``min(max_fps, fps)`` (never upsampled)."""
    if not fps > 0 or not max_fps > 0:
        raise ValueError(f"fps and max_fps must be > 0, got {fps}, {max_fps}")
    return min(float(max_fps), float(fps))


def time_grid_indices(num_frames: int, fps: float, start_s: float, length_s: float, rate: float) -> list[int]:
    """Source frames nearest to the times ``start_s + k / rate``, ``k < max(2, floor(length_s * rate))``.

    The GeCo-Eval script's sampling: times are clamped to the clip (the last frame starts at
    ``num_frames / fps - 1 / fps``), rounded to the nearest frame (half to even) and de-duplicated;
    fewer than 2 distinct frames fall back to the frames nearest the interval's two ends, and
    when those are one frame (a window past the clip's last frame), to it and the one before.

    Returns:
        Increasing 0-based source indices (at least 2 when ``num_frames >= 2``).
    """
    if num_frames < 2:
        raise ValueError(f"a clip needs at least 2 frames, got {num_frames}")
    if not fps > 0 or not rate > 0 or not length_s > 0:
        raise ValueError(f"fps, rate and length_s must be > 0, got {fps}, {rate}, {length_s}")
    count = max(2, math.floor(length_s * rate + 1e-9))  # 3 s x 8 fps is 24 samples, not 23.999...
    last_time = num_frames / fps - 1.0 / fps
    indices = sorted({
        min(num_frames - 1, max(0, round(min(max(start_s + k / rate, 0.0), last_time) * fps))) for k in range(count)
    })
    if len(indices) < 2:
        ends = (round(start_s * fps), round((start_s + length_s) * fps))
        indices = sorted({min(num_frames - 1, max(0, i)) for i in ends})
    if len(indices) < 2:  # both ends past the clip's last frame (a very low fps): it and the one before
        indices = [max(0, indices[0] - 1), max(1, indices[0])]
    return indices


@dataclass(frozen=True)
class Window:
    """One evaluation window: its start and length in seconds and its sampled source frames."""

    start_s: float
    length_s: float
    indices: list[int]


def evaluation_windows(num_frames: int, fps: float, window_seconds: float, max_windows: int,
                       max_fps: float) -> list[Window]:
    """The GeCo-Eval windows of a clip of ``num_frames`` frames at ``fps``.

    The clip (duration ``T = num_frames / fps``) is covered by ``n = ceil(T / window_seconds)``
    windows of ``window_seconds``, their starts evenly spaced from 0 to ``T - window_seconds``
    (so they overlap unless ``T`` is a multiple of the length); a clip shorter than one window is
    one window of ``T``; when ``n > max_windows``, exactly ``max_windows`` windows of
    ``T / max_windows`` tile the clip. Each window samples its frames with
    :func:`time_grid_indices` at ``min(max_fps, fps)``.

    Examples: 49 frames at 16 fps (3.06 s) -> 2 windows starting at 0 and 0.0625 s, 24 frames
    each; 10 s at 30 fps -> 4 windows of 3 s; 20 s -> 4 windows of 5 s.
    """
    if max_windows < 1:
        raise ValueError(f"max_windows must be >= 1, got {max_windows}")
    if not window_seconds > 0:
        raise ValueError(f"window_seconds must be > 0, got {window_seconds}")
    rate = sampled_rate(fps, max_fps)
    duration = num_frames / fps
    needed = math.ceil(duration / window_seconds - 1e-9)
    if needed <= 1:
        starts, length = [0.0], min(window_seconds, duration)
    else:
        count, length = (needed, window_seconds) if needed <= max_windows else (max_windows, duration / max_windows)
        starts = [(duration - length) * k / (count - 1) for k in range(count)] if count > 1 else [0.0]
    return [Window(start, length, time_grid_indices(num_frames, fps, start, length, rate)) for start in starts]


def motion_grid(num_frames: int, fps: float, max_fps: float) -> list[int]:
    """The frames Total / Mean Motion are measured on: the whole clip on the windows' time grid
    (:func:`time_grid_indices` from 0 over the clip's duration at ``min(max_fps, fps)``)."""
    return time_grid_indices(num_frames, fps, 0.0, num_frames / fps, sampled_rate(fps, max_fps))


@refuse_renamed_arguments
@dataclass
class EvaluationConfig:
    """How a video is scored: the GeCo-Eval protocol (paper, section "Evaluation protocol", and
    its published evaluation script).

    Attributes:
        window_seconds: length of an evaluation window; ``ceil(duration / window_seconds)``
            windows of this length cover the clip, overlapping (:func:`geco_guide.metric.protocol.evaluation_windows`).
        max_windows: more windows than this are replaced by exactly ``max_windows`` equal windows
            tiling the clip (the script's ``max_windows=4``).
        max_fps: frames are sampled inside each window on a time grid at ``min(max_fps, fps)``.
        default_fps: frame rate of inputs that carry none (frame folders, gifs without timing).
        model_fps: native frame rate per model name (``--model NAME``): it replaces the file's
            rate, as the paper evaluates every model at its native rate.
        flow_batch_size: frame pairs per flow-estimator call (bounds memory; any value gives the
            same numbers).
        device: where the estimators run (``auto`` = cuda if available, else cpu).
        loss: the metric's :class:`GeCoLossConfig`: frame pairs within a window (``all``, the
            script's; ``center``; ``adjacent``), covisibility threshold, occlusion tau,
            confidence percentile, ``loss.movers`` (what dynamic masks do to what they cover), ...;
            full-resolution flow input (``flow_downscale=1.0``).
        max_frames: score only the first ``max_frames`` frames of a clip (``None``: all, the
            protocol). Total / Mean Motion cover the whole clip, so a long clip costs time in
            proportion to its length (:func:`scoring_plan`); this bounds it.
    """

    #: Earlier spellings, refused in one line naming the new one: ``movers`` is the loss' own
    #: option, spelt once (``evaluation.loss.movers``).
    RENAMED: ClassVar[dict[str, tuple[str, str]]] = {
        "movers": ("evaluation.loss.movers", "EvaluationConfig(loss=GeCoLossConfig(movers=...))"),
    }

    window_seconds: float = 3.0
    max_windows: int = 4
    max_fps: float = 8.0
    default_fps: float = 8.0
    model_fps: dict[str, float] = field(default_factory=lambda: dict(PAPER_MODEL_FPS))
    flow_batch_size: int = 16
    device: str = "auto"
    loss: GeCoLossConfig = field(default_factory=evaluation_loss)
    max_frames: Optional[int] = None

    def __post_init__(self) -> None:
        if self.max_frames is not None and self.max_frames < 2:
            raise OptionError("max_frames", f"must be >= 2 (GeCo compares frames), got {self.max_frames}")
        if not self.window_seconds > 0:
            raise OptionError("window_seconds", f"must be > 0, got {self.window_seconds}")
        if self.max_windows < 1:
            raise OptionError("max_windows", f"must be >= 1, got {self.max_windows}")
        if not self.max_fps > 0:
            raise OptionError("max_fps", f"must be > 0, got {self.max_fps}")
        if not self.default_fps > 0:
            raise OptionError("default_fps", f"must be > 0, got {self.default_fps}")
        bad = {name: fps for name, fps in self.model_fps.items() if not (fps > 0 and math.isfinite(fps))}
        if bad:
            raise OptionError("model_fps", f"must map model names to finite rates > 0, got {bad}")
        if self.flow_batch_size < 1:
            raise OptionError("flow_batch_size", f"must be >= 1, got {self.flow_batch_size}")
        if not (self.device in ("auto", "cpu", "mps") or self.device.startswith("cuda")):
            raise OptionError("device", f"must be auto, cpu, mps or cuda[:N], got {self.device!r}")

    def fps_of_model(self, name: str) -> float:
        """The native frame rate of model ``name``; ValueError listing the known names."""
        if name not in self.model_fps:
            raise ValueError(f"unknown model {name!r} for its frame rate; known: {sorted(self.model_fps)} "
                             "(add one with evaluation.model_fps.NAME=FPS, or pass --fps)")
        return float(self.model_fps[name])


def scoring_plan(num_frames: int, fps: float, cfg: EvaluationConfig) -> dict[str, int]:
    """What scoring a clip of ``num_frames`` at ``fps`` takes under ``cfg``: ``windows``,
    ``window_frames`` (the largest window's), ``flow_pairs`` (the windows' frame pairs, the
    geometry estimator running once per window, and the motion statistics' consecutive pairs: what
    the time grows with) and ``motion_frames``. Cheap: no frame is read."""
    windows = evaluation_windows(num_frames, fps, cfg.window_seconds, cfg.max_windows, cfg.max_fps)
    motion = motion_grid(num_frames, fps, cfg.max_fps)
    window_pairs = sum(len(frame_pairs(len(w.indices), cfg.loss.pairs)) for w in windows)
    return {"windows": len(windows), "window_frames": max(len(w.indices) for w in windows),
            "flow_pairs": window_pairs + len(motion) - 1, "motion_frames": len(motion)}
