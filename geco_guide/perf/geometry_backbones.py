"""The geometry backbones the benchmarks can time and count: VGGT-1B, DA3-SMALL and DA3-BASE by the
names ``estimators.geometry`` gives them, their architectures (random weights) and their FLOPs at
the protocol's sizes.

:func:`geometry_flops` counts one ``estimate_geometry`` call on fake tensors
(``torch.utils.flop_counter`` formulas; no weights, no GPU, seconds on a CPU): forward, what
scoring a window costs, and forward+backward to the frames, what a guided update costs.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import torch

from ..estimators.base import FrozenEstimator
from ..estimators.da3 import DA3, network_size
from ..estimators.da3_config import DA3Config
from ..estimators.vggt import VGGT, VGGTConfig, plan_preprocess

__all__ = ["BACKBONE_ARCHITECTURES", "PROTOCOL_FRAMES", "geometry_flops", "geometry_model", "network_hw"]

#: each backbone ``estimators.geometry`` names (:data:`~geco_guide.estimators.GEOMETRY_BACKBONES`, with
#: its hub id) -> (class, full-size config, tiny config): what the benchmarks build and count
BACKBONE_ARCHITECTURES: dict[str, tuple[type[FrozenEstimator], Callable[[], Any], Callable[[], Any]]] = {
    "vggt-1b": (VGGT, VGGTConfig, VGGTConfig.tiny),
    "da3-small": (DA3, DA3Config.small, DA3Config.tiny),
    "da3-base": (DA3, DA3Config.base, DA3Config.tiny),
}
#: Frames per geometry call in the protocol: a guided update's anchors (CogVideoX-5B's 49 frames)
#: and an evaluation window (3 s sampled at 8 fps).
PROTOCOL_FRAMES = {"guided update": 4, "evaluation window": 24}


def _backbone(name: str) -> tuple[type[FrozenEstimator], Callable[[], Any], Callable[[], Any]]:
    if name not in BACKBONE_ARCHITECTURES:
        raise ValueError(f"unknown geometry backbone {name!r}; one of {', '.join(BACKBONE_ARCHITECTURES)}")
    return BACKBONE_ARCHITECTURES[name]


def geometry_model(name: str, size: str, seed: int) -> FrozenEstimator:
    """Backbone ``name`` at ``size`` (``tiny`` or ``full``) with random weights drawn from ``seed``."""
    cls, full, tiny = _backbone(name)
    return cls.random(tiny() if size == "tiny" else full(), seed=seed)


def network_hw(model: FrozenEstimator, height: int, width: int) -> tuple[int, int]:
    """The size ``model`` resizes an ``height x width`` frame to before its trunk."""
    config = model.config
    if isinstance(model, DA3):
        return network_size(height, width, config.process_res, config.patch_size)
    return plan_preprocess(height, width, config.img_size, config.patch_size).network_hw


def geometry_flops(name: str, frames: int, height: int, width: int, dtype: torch.dtype = torch.bfloat16) -> dict[str, Any]:
    """FLOPs of one ``estimate_geometry`` of backbone ``name`` (full size, trunk in ``dtype``) on
    ``[1, frames, 3, height, width]``: ``forward_tflop`` and ``forward_backward_tflop`` (the
    backward to the frames, of the sum of the outputs' means), with ``params_m`` and ``network``
    (its input size)."""
    from torch._subclasses.fake_tensor import FakeTensorMode
    from torch.utils.flop_counter import FlopCounterMode

    from .full_size import to_fake
    from .tracing import register_cpu_sdpa_flops

    cls, full, _ = _backbone(name)
    register_cpu_sdpa_flops()
    with torch.device("meta"):
        model = cls(full())
    model.trunk_to(dtype).eval()
    fake_mode = FakeTensorMode(allow_non_fake_inputs=True)
    to_fake(model, fake_mode)
    counts = {}
    with fake_mode:
        video = torch.rand(1, frames, 3, height, width).requires_grad_()
        for mode in ("forward", "forward_backward"):
            with FlopCounterMode(display=False) as counter:
                geometry = model.estimate_geometry(video)
                if mode == "forward_backward":
                    outputs = (geometry.depth, geometry.confidence, geometry.intrinsics, geometry.extrinsics)
                    sum(t.mean() for t in outputs).backward()
            counts[f"{mode}_tflop"] = counter.get_total_flops() / 1e12
    return {"backbone": name, "params_m": sum(p.numel() for p in model.parameters()) / 1e6,
            "network": "{}x{}".format(*network_hw(model, height, width)), **counts}
