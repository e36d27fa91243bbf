"""The ``loss`` case of ``geco bench``: the GeCo loss core timed on random-but-valid geometry and
correspondences (the cameras given: the synthetic scenes' live in the benchmarks, which this layer
does not import)."""

from __future__ import annotations

from typing import Any

import torch
import torch.nn.functional as F
from torch import Tensor

from ..loss.geco import GeCoLossConfig, frame_pairs, geco_from_geometry
from ..types import Correspondences, SceneGeometry
from .workloads import Workload, make_step

__all__ = ["loss_workload", "smooth_field"]


def smooth_field(shape: tuple[int, ...], height: int, width: int, gen: torch.Generator) -> Tensor:
    """Seeded smooth random field ``[*shape, H, W]`` in ``[0, 1]``: a 6x8 grid upsampled bilinearly."""
    coarse = torch.rand(*shape, 6, 8, generator=gen).flatten(0, -3)[:, None]
    fine = F.interpolate(coarse, size=(height, width), mode="bilinear", align_corners=False)
    return fine.reshape(*shape, height, width)


def loss_workload(spec: dict[str, Any], device: Any, intrinsics: Tensor, extrinsics: Tensor) -> Workload:
    """The ``loss`` case of ``spec`` on ``device``: the GeCo loss core on ``intrinsics`` ``[3, 3]``
    (one camera for every frame) and camera-from-world ``extrinsics`` ``[S, 3, 4]``.

    Leaf tensors requiring grad: smooth depth in ``[3, 6]``, the cameras, smooth flow of up to
    +-4 px and covisibility in ``[0.4, 1]``. A confidence map in ``[1, 2]`` (>= 1 like VGGT's, no
    grad) exercises the confidence-percentile mask as in guidance. All maps are dense, so the cost
    does not depend on the values; nothing is rendered, which keeps the setup's memory small.
    """
    frames, height, width = spec["frames"], spec["height"], spec["width"]
    pairs = frame_pairs(frames, spec["pairs"])
    gen = torch.Generator().manual_seed(spec["seed"])
    depth = 3 + 3 * smooth_field((1, frames), height, width, gen)
    intrinsics = intrinsics.expand(1, frames, 3, 3).clone()
    extrinsics = extrinsics[None]
    flow = 8 * smooth_field((len(pairs), 2), height, width, gen) - 4
    covisibility = 0.4 + 0.6 * torch.rand(len(pairs), height, width, generator=gen)
    confidence = 1 + torch.rand(1, frames, height, width, generator=gen)
    leaves = [t.to(device).requires_grad_() for t in (depth, intrinsics, extrinsics, flow, covisibility)]
    geometry = SceneGeometry(depth=leaves[0], intrinsics=leaves[1], extrinsics=leaves[2],
                             confidence=confidence.to(device))
    correspondences = Correspondences(flow=leaves[3], covisibility=leaves[4])
    config = GeCoLossConfig(pairs=spec["pairs"])

    def scalar() -> Tensor:
        return geco_from_geometry(geometry, correspondences, pairs, config).loss

    info = {"input": f"{frames}x{height}x{width}, {len(pairs)} {spec['pairs']} pairs"}
    return Workload(make_step(spec["mode"], scalar, leaves), info)
