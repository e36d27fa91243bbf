"""Ranking statistics used to judge whether a map localises an artifact."""

import torch
from torch import Tensor


def average_precision(scores: Tensor, labels: Tensor) -> float:
    """Area under the precision-recall curve of ``scores`` ranking the True ``labels`` first."""
    order = torch.argsort(scores.flatten().double(), descending=True, stable=True)
    hits = labels.flatten()[order].double()
    precision = hits.cumsum(0) / torch.arange(1, hits.numel() + 1, dtype=torch.float64)
    return float((precision * hits).sum() / hits.sum())


def spearman(a: Tensor, b: Tensor) -> float:
    """Spearman rank correlation of two 1-D samples."""
    ranks = torch.stack([x.flatten().double().argsort().argsort().double() for x in (a, b)])
    return float(torch.corrcoef(ranks)[0, 1])
