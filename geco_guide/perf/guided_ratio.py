"""The compute an A/B run's best-of arm is matched to (``geco ab --best-of matched``): the guided /
unguided sampling time ratio the cost model predicts for a run's config on a card, and the card the
local GPU is."""

from __future__ import annotations

import torch

from ..config import GeCoConfig
from ..estimators import TINY_RANDOM
from ..io.devices import resolve_device
from .cards import GPU_SPECS
from .cost import cost_report, cost_settings
from .plans import KNOWN_MODELS, card_plan

__all__ = ["local_card", "predicted_ratio"]


def local_card(cfg: GeCoConfig) -> str | None:
    """The card of :data:`~geco_guide.perf.cards.GPU_SPECS` that ``model.device`` is, or None (a CPU,
    or a GPU the cost model does not know)."""
    device = resolve_device(cfg.model.device)
    if device.type != "cuda":
        return None
    name = torch.cuda.get_device_name(device).replace(" ", "").upper()
    # the longest first: an "L40S" is no "L4"
    return next((card for card in sorted(GPU_SPECS, key=len, reverse=True) if card.upper() in name), None)


def predicted_ratio(cfg: GeCoConfig, gpu: str) -> float:
    """The guided / unguided sampling time ratio the cost model predicts for ``cfg``'s model, video
    size, steps, schedule, mode and anchor decoder on ``gpu``, under the memory plan
    ``memory_plan=auto`` picks for the card (as ``geco bench cost --gpu``). The model is the
    registry's ``model.name`` (whatever folder holds its weights), or the tiny models."""
    key = "tiny" if cfg.model.id == TINY_RANDOM and cfg.model.name == KNOWN_MODELS["tiny"]["family"] else cfg.model.name
    if key not in KNOWN_MODELS:
        traced = ", ".join(name for name in KNOWN_MODELS if name != "tiny")
        raise ValueError(f"--best-of matched: the cost model does not trace {cfg.model.name!r} (it traces {traced} "
                         "and the tiny models); pass an integer --best-of N")
    known, s, guidance = KNOWN_MODELS[key], cfg.sampling, cfg.guidance
    mode = "faithful" if guidance.denoiser_grad else "fast"
    card = card_plan(gpu, mode, guidance.decoder, s.num_frames, s.height, s.width, model=key)
    if card["plan"] is None:
        raise ValueError(f"--best-of matched: no guided run of this config fits the {gpu}: {card['reason']}")
    settings = cost_settings(preset=known["preset"], model=known["model"] or known["family"],
                             steps=s.num_inference_steps, frames=s.num_frames, height=s.height, width=s.width,
                             dtype=None, decoder=guidance.decoder, plan=card["plan"])
    settings.update(repeats=guidance.repeats, time_travel=list(guidance.time_travel or []) or None)
    return float(cost_report(settings, mode)["roofline"]["ratio_guided_over_unguided"][gpu])
