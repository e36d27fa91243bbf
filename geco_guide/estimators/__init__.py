"""Frozen GeCo backbones, and the one function that builds them from a config.

:func:`load_estimators` is shared by ``python -m geco_guide.generate`` and
``python -m geco_guide.evaluate``: hub ids, local folders, or ``tiny-random`` for the tiny,
randomly initialised offline models of :func:`tiny_estimators`. This module stays light (no
model code is imported until an estimator is built), because every ``geco_guide.estimators.*``
import runs it.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import torch

from ..io.devices import resolve_device

TINY_RANDOM = "tiny-random"


@dataclass
class EstimatorsConfig:
    """The frozen GeCo backbones: hub ids or local folders, or ``tiny-random``.

    ``dtype`` is the storage dtype of their ViT trunks (``trunk_to``): bfloat16 halves their
    memory and speeds them up on a GPU; the heads, outputs and the GeCo loss stay float32.
    ``gradient_checkpointing`` recomputes their trunks' blocks in the guidance backward: less
    activation memory (about 6 GiB at 480x720 in the cost model) for one more trunk forward.
    """

    geometry: str = "facebook/VGGT-1B"
    flow: str = "infinity1096/UFM-Base"
    dtype: str = "bfloat16"
    gradient_checkpointing: bool = False
    init_seed: int = 0


def estimator_id(estimator: Any) -> str:
    """What produced an estimator's numbers: the id it was loaded from, else its class name."""
    return getattr(estimator, "geco_estimator_id", None) or type(estimator).__name__


def tiny_estimators(seed: int = 0) -> tuple[Any, Any]:
    """Tiny random ``(VGGT, UFM)`` estimators (geometry, flow) of the real architectures, seeded:
    what the ``tiny-random`` ids load (offline, CPU, seconds)."""
    from .ufm import UFM, UFMConfig
    from .vggt import VGGT, VGGTConfig

    return VGGT.random(VGGTConfig.tiny(), seed=seed), UFM.random(UFMConfig.tiny(), seed=seed)


def load_estimators(estimators_cfg: EstimatorsConfig, device: str | torch.device = "auto") -> tuple[Any, Any]:
    """``(geometry, flow)`` of ``estimators_cfg``: frozen, in eval mode, on ``device``.

    Args:
        estimators_cfg: :class:`~geco_guide.config.EstimatorsConfig` (``geometry`` / ``flow``: a
            hub id, a local folder or ``tiny-random``; ``dtype`` of their trunks, the heads and
            outputs stay float32; ``gradient_checkpointing`` of their trunks; ``init_seed`` of
            tiny models).
        device: a torch device or ``"auto"``.

    Each estimator gets a ``geco_estimator_id`` attribute (the id it came from) so results can
    name their estimators (:func:`estimator_id`).

    Raises:
        WeightsNotFoundError: one line naming the repo id, when the weights are unavailable.
    """
    dtype = getattr(torch, estimators_cfg.dtype)
    device = resolve_device(device)
    tiny = None
    if TINY_RANDOM in (estimators_cfg.geometry, estimators_cfg.flow):
        tiny = tiny_estimators(estimators_cfg.init_seed)
    if estimators_cfg.geometry == TINY_RANDOM:
        geometry = tiny[0].to(device).trunk_to(dtype)
    else:
        from .vggt import VGGT

        geometry = VGGT.from_pretrained(estimators_cfg.geometry, dtype=dtype, device=device)
    if estimators_cfg.flow == TINY_RANDOM:
        flow = tiny[1].to(device).trunk_to(dtype)
    else:
        from .ufm import UFM

        flow = UFM.from_pretrained(estimators_cfg.flow, dtype=dtype, device=device)
    for model, name in ((geometry, estimators_cfg.geometry), (flow, estimators_cfg.flow)):
        model.eval().requires_grad_(False)
        model.gradient_checkpointing = estimators_cfg.gradient_checkpointing
        suffix = f"(seed={estimators_cfg.init_seed})" if name == TINY_RANDOM else ""
        model.geco_estimator_id = f"{name}{suffix}"
    return geometry, flow
