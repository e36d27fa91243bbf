"""Detection statistics that judge whether a map localises an artifact (the paper's Tasks 1-3).

* :func:`average_precision`: ranking AP of a score map against a ground-truth mask
  (threshold-free: the mean precision at the rank of each true pixel).
* :func:`best_threshold_iou_f1`: IoU and F1 of ``score >= threshold`` at the per-image best
  threshold (every distinct score is tried; ties never split).
* :func:`spearman`: Spearman's rank correlation, ties getting their average rank.

All take flattened-compatible tensors and return plain floats; NaN where undefined (no positive
pixel, a constant sample).
"""

from __future__ import annotations

import math

import torch
from torch import Tensor

__all__ = ["average_precision", "best_threshold_iou_f1", "spearman"]


def _ranked_hits(scores: Tensor, labels: Tensor) -> tuple[Tensor, Tensor]:
    """Labels sorted by descending score (stable) ``[N]`` float64, and ``[N]`` bool marking the
    last position of each run of equal scores: a threshold can only cut after such a position."""
    values = scores.detach().flatten().double()
    order = torch.argsort(values, descending=True, stable=True)
    hits = labels.detach().flatten()[order].double()
    sorted_values = values[order]
    group_end = torch.ones_like(hits, dtype=torch.bool)
    group_end[:-1] = sorted_values[1:] != sorted_values[:-1]
    return hits, group_end


def _check_pair(scores: Tensor, labels: Tensor) -> None:
    if scores.numel() != labels.numel():
        raise ValueError(f"scores and labels must have as many elements, got {list(scores.shape)} and {list(labels.shape)}")
    if scores.numel() == 0:
        raise ValueError("scores must not be empty")


def average_precision(scores: Tensor, labels: Tensor) -> float:
    """Area under the precision-recall curve of ``scores`` ranking the True ``labels`` first.

    Ties are broken by position (stable sort); in GeCo maps they are the invalid pixels set to 0,
    which rank below every positive score anyway. NaN when ``labels`` has no True entry.
    """
    _check_pair(scores, labels)
    hits, _ = _ranked_hits(scores, labels)
    if hits.sum() == 0:
        return math.nan
    precision = hits.cumsum(0) / torch.arange(1, hits.numel() + 1, dtype=torch.float64)
    return float((precision * hits).sum() / hits.sum())


def best_threshold_iou_f1(scores: Tensor, labels: Tensor) -> tuple[float, float]:
    """``(IoU, F1)`` of the mask ``scores >= t`` at the best threshold ``t`` of this image.

    Every distinct score value is a candidate threshold (the top-k pixels for each k at a tie
    boundary); IoU and F1 are both monotone in the same quantity, so one threshold maximises both.
    NaN when ``labels`` has no True entry.
    """
    _check_pair(scores, labels)
    hits, group_end = _ranked_hits(scores, labels)
    positives = hits.sum()
    if positives == 0:
        return math.nan, math.nan
    true_pos = hits.cumsum(0)[group_end]
    predicted = torch.arange(1, hits.numel() + 1, dtype=torch.float64)[group_end]
    iou = true_pos / (predicted + positives - true_pos)
    f1 = 2 * true_pos / (predicted + positives)
    return float(iou.max()), float(f1.max())


def average_ranks(x: Tensor) -> Tensor:
    """``[N]`` -> ranks 1..N ``[N]`` float64, tied values sharing their mean rank."""
    values = x.detach().flatten().double()
    order = torch.argsort(values, stable=True)
    sorted_values = values[order]
    _, inverse, counts = torch.unique_consecutive(sorted_values, return_inverse=True, return_counts=True)
    ends = counts.cumsum(0).double()
    mean_rank = ends - (counts.double() - 1) / 2  # mean of the positions start+1 .. end
    ranks = torch.empty_like(values)
    ranks[order] = mean_rank[inverse]
    return ranks


def spearman(a: Tensor, b: Tensor) -> float:
    """Spearman rank correlation of two samples of equal size (Pearson of average ranks).

    NaN for fewer than 2 values or a constant sample.
    """
    if a.numel() != b.numel():
        raise ValueError(f"samples must have as many elements, got {a.numel()} and {b.numel()}")
    if a.numel() < 2:
        return math.nan
    ra, rb = average_ranks(a), average_ranks(b)
    ra, rb = ra - ra.mean(), rb - rb.mean()
    denom = (ra.square().sum() * rb.square().sum()).sqrt()
    return float((ra * rb).sum() / denom) if denom > 0 else math.nan
