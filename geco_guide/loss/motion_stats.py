"""How much a video moves: Total Motion and Mean Motion (GeCo paper, supplement).

A geometric-consistency score is only meaningful next to the amount of motion: a still video is
trivially consistent. For consecutive frames ``t -> t+1``,
``m_t = mean over valid pixels of |flow_t| / image diagonal``; Total Motion ``TM = sum_t m_t``
(reported in %), Mean Motion ``MM = TM / S`` (% per second), where ``S`` is the clip's duration in
seconds (supplement, "Motion magnitude").
"""

from __future__ import annotations

import math
from dataclasses import dataclass

from torch import Tensor

from ..geometry import check_tensor
from .cues import masked_mean, safe_norm

__all__ = ["MotionStats", "motion_statistics"]


@dataclass
class MotionStats:
    """Per-step motion ``[T]`` (fraction of the diagonal), Total Motion (%) and Mean Motion (%/s)."""

    per_step: Tensor
    total_motion: float
    mean_motion: float


def motion_statistics(flow: Tensor, valid: Tensor | None, duration_s: float) -> MotionStats:
    """Total and Mean Motion of a clip from the flow of its consecutive frame pairs.

    Args:
        flow: ``[T, 2, H, W]`` flow from frame ``t`` to ``t+1`` (``T = S - 1`` pairs), pixels.
        valid: ``[T, H, W]`` bool pixels to average over (e.g. co-visible), or ``None`` for all.
        duration_s: the clip's duration ``S`` in seconds (frames / native frame rate).

    Returns:
        :class:`MotionStats`.
    """
    check_tensor(flow, "flow", (None, 2, None, None))
    if not (duration_s > 0 and math.isfinite(duration_s)):
        raise ValueError(f"duration_s must be a finite number > 0, got {duration_s}")
    steps, _, height, width = flow.shape
    if steps == 0:
        raise ValueError("flow must hold at least one frame pair")
    magnitude = safe_norm(flow, dim=1) / math.hypot(height, width)
    if valid is None:
        per_step = magnitude.mean(dim=(-2, -1))
    else:
        per_step = masked_mean(magnitude, valid, dims=(-2, -1))
    total = 100.0 * float(per_step.sum())
    return MotionStats(per_step=per_step, total_motion=total, mean_motion=total / duration_s)
