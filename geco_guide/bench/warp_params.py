"""The options of a WarpBench-style warp (:mod:`geco_guide.bench.warp` does the warping). Imports
no torch, so that the command's parser shows their defaults at once."""

from __future__ import annotations

import math
from dataclasses import dataclass

__all__ = ["WarpParams"]


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
