"""The two small protocols GeCo needs from its frozen backbones, and their outputs.

A :class:`GeometryEstimator` turns a clip into per-frame depth, intrinsics, extrinsics and
(optionally) a confidence map; a :class:`FlowEstimator` turns batched image pairs into dense
flow and a covisibility probability. Both work at the resolution of the frames they are given
and follow the conventions of ``geco_guide.loss.geometry`` (integer pixel centres, OpenCV
camera axes, camera-from-world extrinsics, z-depth).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Protocol, runtime_checkable

import torch
from torch import Tensor


@dataclass
class SceneGeometry:
    """Per-frame geometry of a clip.

    Attributes:
        depth: ``[B, S, H, W]`` z-depth, > 0 where valid.
        intrinsics: ``[B, S, 3, 3]`` pinhole K in pixels of the ``H x W`` frames.
        extrinsics: ``[B, S, 3, 4]`` camera-from-world ``[R | t]``.
        confidence: ``[B, S, H, W]`` larger = more reliable, or ``None`` when unavailable.
    """

    depth: Tensor
    intrinsics: Tensor
    extrinsics: Tensor
    confidence: Tensor | None = None


@dataclass
class Correspondences:
    """Dense correspondences from source to target images.

    Attributes:
        flow: ``[N, 2, H, W]`` displacement (du, dv) in pixels, ``target = source + flow``.
        covisibility: ``[N, H, W]`` probability in ``[0, 1]`` that a source pixel is visible
            in the target.
    """

    flow: Tensor
    covisibility: Tensor


@runtime_checkable
class GeometryEstimator(Protocol):
    """Anything that maps frames ``[B, S, 3, H, W]`` in ``[0, 1]`` to :class:`SceneGeometry`."""

    def estimate_geometry(self, frames: Tensor) -> SceneGeometry:
        ...


@runtime_checkable
class FlowEstimator(Protocol):
    """Anything that maps image pairs ``[N, 3, H, W]`` in ``[0, 1]`` to :class:`Correspondences`."""

    def estimate_flow(self, source: Tensor, target: Tensor) -> Correspondences:
        ...


def check_frames(frames: Tensor, name: str = "frames") -> None:
    """Raise a ValueError naming ``name`` unless it is a floating ``[B, S, 3, H, W]`` tensor."""
    if not isinstance(frames, torch.Tensor):
        raise ValueError(f"{name} must be a torch.Tensor, got {type(frames).__name__}")
    if frames.ndim != 5 or frames.shape[2] != 3:
        raise ValueError(f"{name} must have shape [B, S, 3, H, W], got {list(frames.shape)}")
    if not frames.is_floating_point():
        raise ValueError(f"{name} must be a floating tensor in [0, 1], got dtype {frames.dtype}")
