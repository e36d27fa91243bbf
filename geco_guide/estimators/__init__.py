"""Frozen GeCo backbones, and the one function that builds them from a config.

:func:`load_estimators` is shared by ``python -m geco_guide.generate`` and
``python -m geco_guide evaluate``: hub ids, local folders, or ``tiny-random`` for the tiny,
randomly initialised offline models of :func:`tiny_estimators`. This module stays light (no
model code is imported until an estimator is built), because every ``geco_guide.estimators.*``
import runs it.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Optional

import torch

from ..io.devices import resolve_device
from .loading import WeightsNotFoundError

__all__ = ["TINY_RANDOM", "EstimatorsConfig", "estimator_id", "load_estimators", "tiny_estimators",
           "tiny_random_decoder", "with_config_key"]

TINY_RANDOM = "tiny-random"


@dataclass
class EstimatorsConfig:
    """The frozen GeCo backbones: hub ids or local folders, or ``tiny-random``.

    ``dtype`` is the storage dtype of their ViT trunks (``trunk_to``): bfloat16 halves their
    memory and speeds them up on a GPU; the heads, outputs and the GeCo loss stay float32.
    ``gradient_checkpointing`` recomputes their trunks' blocks in the guidance backward: less
    activation memory (how much: docs/performance.md) for one more trunk forward.
    ``tiny_decoder`` is the weights of the tiny decoder that ``guidance.decoder=tiny`` decodes the
    anchor frames with: a ``.pth`` / ``.safetensors`` file (``taecvx.pth`` for CogVideoX, from
    :data:`~geco_guide.estimators.tiny_decoder.WEIGHTS_URL`), a folder holding it, a hub id, or
    ``tiny-random``; unused (and not loaded) with ``guidance.decoder=vae``.
    ``segmenter`` is the weights of the text segmenter that masks the subjects named by
    ``guidance.dynamic`` (:mod:`~geco_guide.estimators.segmenters`, SAM 3 video): a hub id, a
    local folder or ``tiny-random``; unused (and not loaded) unless ``guidance.dynamic`` names
    subjects.
    """

    geometry: str = "facebook/VGGT-1B"
    flow: str = "infinity1096/UFM-Base"
    dtype: str = "bfloat16"
    gradient_checkpointing: bool = False
    init_seed: int = 0
    tiny_decoder: Optional[str] = None
    segmenter: str = "facebook/sam3"


def estimator_id(estimator: Any) -> str:
    """What produced an estimator's numbers: the id it was loaded from, else its class name."""
    return getattr(estimator, "geco_estimator_id", None) or type(estimator).__name__


def tiny_estimators(seed: int = 0) -> tuple[Any, Any]:
    """Tiny random ``(VGGT, UFM)`` estimators (geometry, flow) of the real architectures, seeded:
    what the ``tiny-random`` ids load (offline, CPU, seconds)."""
    from .ufm import UFM, UFMConfig
    from .vggt import VGGT, VGGTConfig

    return VGGT.random(VGGTConfig.tiny(), seed=seed), UFM.random(UFMConfig.tiny(), seed=seed)


def tiny_random_decoder(variant: str = "cogvideox", seed: int = 0, latent_channels: int | None = None) -> Any:
    """A tiny random :class:`~.tiny_decoder.TinyDecoder` of ``variant`` (frozen, float32): what
    ``estimators.tiny_decoder=tiny-random`` loads. ``latent_channels``: the latents it takes when
    they are not the variant's (the tiny models' VAE makes 4; the published variants take 16 or
    more)."""
    from dataclasses import replace

    from .tiny_decoder import TinyDecoder, resolve_variant

    spec = resolve_variant(variant)
    if latent_channels is not None:
        spec = replace(spec, latent_channels=latent_channels)
    return TinyDecoder.tiny(spec, seed)


def with_config_key(err: Exception, key: str, example: str) -> WeightsNotFoundError:
    """``err``'s one line, ending with the config key that points at local weights instead."""
    return WeightsNotFoundError(f"{err} (config: {key}={example})")


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
        WeightsNotFoundError: one line naming the repo id and the config key to point at a local
            folder instead, when the weights are unavailable.
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

        try:
            geometry = VGGT.from_pretrained(estimators_cfg.geometry, dtype=dtype, device=device)
        except WeightsNotFoundError as err:
            raise with_config_key(err, "estimators.geometry", "/path/to/VGGT-1B") from None
    if estimators_cfg.flow == TINY_RANDOM:
        flow = tiny[1].to(device).trunk_to(dtype)
    else:
        from .ufm import UFM

        try:
            flow = UFM.from_pretrained(estimators_cfg.flow, dtype=dtype, device=device)
        except WeightsNotFoundError as err:
            raise with_config_key(err, "estimators.flow", "/path/to/UFM-Base") from None
    for model, name in ((geometry, estimators_cfg.geometry), (flow, estimators_cfg.flow)):
        model.eval().requires_grad_(False)
        model.gradient_checkpointing = estimators_cfg.gradient_checkpointing
        suffix = f"(seed={estimators_cfg.init_seed})" if name == TINY_RANDOM else ""
        model.geco_estimator_id = f"{name}{suffix}"
    return geometry, flow
