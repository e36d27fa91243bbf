"""The model-agnostic guided step: ``R_t`` GeCo updates of the latents of one denoising step.

    for r in range(R_t):
        out = predict(z_t)                          # through the denoiser (faithful), or held constant (fast)
        x0  = levels.to_x0(z_t, out)
        L   = objective(x0)                         # anchor frames decoded from x0, GeCo loss
        g   = dL/dz_t
        z_t <- z_t - step_size * g / (||g|| + eps)        # fp32, norm per video (the paper's eta)
        (time travel: z_t <- renoise(DDIM(z_t, x0) - step_size * g / (||g|| + eps)) back to t)
    return z_t, predict(z_t)                        # the guided latents and the model output there

The caller's scheduler then takes the step from the guided latents with that model output. The
model enters only through ``predict``, ``objective`` and the step's :class:`~.levels.NoiseLevels`;
this module imports torch only.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Sequence
from dataclasses import asdict, dataclass
from typing import Any

import torch
from torch import Tensor

from ...loss.cues import MAP_ORDER
from .levels import NoiseLevels, randn_like

__all__ = ["GuidanceRecord", "LatentsWatch", "NonFiniteLatentsError", "Objective", "Update", "guided_step",
           "loss_terms", "normalized_update", "read_scalars", "score_anchor_frames"]

Objective = Callable[[Tensor], "tuple[Tensor, dict[str, Tensor]]"]


def normalized_update(z: Tensor, grad: Tensor, step_size: float, eps: float = 1e-8) -> tuple[Tensor, Tensor]:
    """``z - step_size * g / (||g|| + eps)`` in fp32, with the norm taken per video. Returns (z, ||g||)."""
    grad = grad.float()
    norm = grad.flatten(1).norm(dim=1).view(-1, *([1] * (grad.ndim - 1)))
    return z.float() - step_size * grad / (norm + eps), norm.flatten()


@dataclass
class Update:
    """One update as :func:`guided_step` made it, its numbers still on the device.

    Attributes:
        repeat: index of the update within the step.
        terms: 0-dim tensors: the objective's (``loss``; ``motion``, ``structure``, ``fused`` for a
            GeCo result), ``grad_norm`` (``||g||``, the batch mean) and ``finite`` (False: the
            loss or the gradient was not finite and the update was skipped).
        started: ``time.perf_counter()`` at its start.
        time_travel: whether it was a time-travel update.
    """

    repeat: int
    terms: dict[str, Tensor]
    started: float
    time_travel: bool


@dataclass
class GuidanceRecord:
    """One guided update of the guidance log: step index, timestep, loss and cues before the
    update, ``||g||``, seconds, the fraction of the anchor frames' pixels the loss measured
    (``valid_fraction``: 0 when everything was masked or invalid; ``None`` for a loss that is a
    bare tensor); with dynamic masks also the mean fraction of the anchor frames' pixels masked and
    the masks' source (absent from :meth:`to_dict` without masks); in a search
    whose particles are guided in sub-batches, the first and last particle of the update's
    sub-batch (absent without a search)."""

    step: int
    repeat: int
    t: int
    loss: float
    motion: float | None
    structure: float | None
    fused: float | None
    grad_norm: float
    seconds: float
    time_travel: bool
    skipped: bool = False
    valid_fraction: float | None = None
    masked_fraction: float | None = None
    mask_source: str | None = None
    particles: list[int] | None = None

    def to_dict(self) -> dict[str, Any]:
        record = asdict(self)
        if self.mask_source is None:
            del record["masked_fraction"], record["mask_source"]
        if self.particles is None:
            del record["particles"]
        return record


def loss_terms(result: Any) -> tuple[Tensor, dict[str, Tensor]]:
    """The loss to differentiate and the scalars to record of a loss result (a ``GeCoResult`` or a
    scalar tensor), as tensors: reading them is a host sync. A ``GeCoResult`` adds
    ``valid_fraction`` (the fraction of the anchors' pixels its loss measured: 0 moves nothing) and,
    with dynamic masks, ``masked_fraction``, the mean over clips and frames."""
    if isinstance(result, Tensor):
        return result, {"loss": result}
    terms = {name: getattr(result, name) for name in ("loss", *MAP_ORDER)}
    terms["valid_fraction"] = result.valid_fraction()
    if getattr(result, "masked_fraction", None) is not None:
        terms["masked_fraction"] = result.masked_fraction.mean()
    return result.loss, terms


def read_scalars(values: dict[str, Tensor], device: torch.device) -> dict[str, float]:
    """Plain floats of ``values`` (0-dim tensors) with one device-to-host copy for all of them.
    Fake tensors (the cost model's trace of a call) have no values: zeros, and ``finite`` true."""
    from torch._subclasses.fake_tensor import is_fake

    stacked = torch.stack([v.detach().to(device=device, dtype=torch.float32).reshape(()) for v in values.values()])
    if is_fake(stacked):
        return {**dict.fromkeys(values, 0.0), "finite": 1.0}
    return dict(zip(values, stacked.tolist()))


def guided_step(
    z: Tensor,
    predict: Callable[[Tensor, bool], Tensor],
    levels: NoiseLevels,
    objective: Objective,
    repeats: int,
    *,
    step_size: float,
    time_travel: bool = False,
    denoiser_grad: bool = True,
    generator: torch.Generator | list[torch.Generator] | None = None,
    eps: float = 1e-8,
    on_update: Callable[[Update], None] | None = None,
) -> tuple[Tensor, Tensor]:
    """``repeats`` GeCo updates of ``z_t`` (see the module docstring).

    Args:
        z: ``z_t [B, ...]`` (any float dtype; the updates run in fp32).
        predict: ``(z, differentiate) -> model output`` (CFG-combined) at ``z``. Called with True
            for each update in faithful mode, and with False under ``torch.no_grad`` for the
            output returned and, in fast mode, for the one output the step's updates share.
        levels: the step's noise levels; ``x0 = levels.to_x0(z, output)``.
        objective: ``x0 -> (loss, terms)``: a scalar to differentiate and the 0-dim tensors to
            record (:func:`loss_terms` of a loss result).
        repeats: ``R_t``; 0 returns ``z`` and the model output there.
        step_size: normalised step size (the paper's eta).
        time_travel: take the DDIM step with the update, then re-noise back to ``t``.
        denoiser_grad: differentiate through the denoiser at every update (the paper), or hold its
            output constant through the step (fast: ``dx0/dz_t = sqrt(a_t)`` for v-prediction);
            the denoiser then runs once per step as without guidance, plus once after each
            time-travel re-noising.
        generator: source of the time-travel noise.
        eps: of the normalised update.
        on_update: called with each :class:`Update` once it is queued.

    Returns:
        ``(z, output)``: the guided ``z_t`` (fp32) and the model output at it.
    """
    z = z.detach().float()
    held: tuple[Tensor, Tensor] | None = None  # fast mode: (z, output) of the last prediction, until time travel moves z
    for r in range(repeats):
        started = time.perf_counter()
        with torch.enable_grad():
            z_in = z.detach().requires_grad_(True)
            if denoiser_grad:
                x0 = levels.to_x0(z_in, predict(z_in, True).float())
            else:
                if held is None:
                    with torch.no_grad():
                        held = (z, predict(z, False).float())
                # With the output held, x0 is linear in z: its value at the held latents plus the
                # move since, so every update of the step rounds x0 as the first one does.
                x0 = levels.to_x0(*held) + levels.to_x0(z_in - held[0], torch.zeros_like(held[1]))
            loss, terms = objective(x0)
            (grad,) = torch.autograd.grad(loss, z_in, allow_unused=True)
        grad = torch.zeros_like(z) if grad is None else grad
        # A NaN gradient must never reach the latents, nor a finite one of a NaN loss (a garbage
        # objective); torch.where keeps the check on the device.
        finite = torch.isfinite(grad).all() & torch.isfinite(loss.detach()).all()
        grad = torch.where(finite, grad, torch.zeros_like(grad))
        z_new, norm = normalized_update(z, grad, step_size, eps)
        if time_travel:
            z = levels.renoise(levels.step(z, x0.detach()) + (z_new - z), randn_like(z, generator))
            held = None
        else:
            z = z_new
        if on_update is not None:
            on_update(Update(r, {**terms, "grad_norm": norm.mean(), "finite": finite}, started, time_travel))
    if held is None:
        with torch.no_grad():
            return z, predict(z, False)
    return z, held[1]


def score_anchor_frames(video: Tensor, anchors: Sequence[int], loss_fn: Callable[[Tensor], Any]) -> dict[str, float]:
    """GeCo scalars (``motion``, ``structure``, ``fused``, ``loss``) of the anchor frames of a
    decoded ``video [B, F, 3, H, W]`` in ``[0, 1]``, without gradients: a cue over no valid pixel
    is NaN, and ``nan_reason`` says why (``GeCoResult.scalars``); with dynamic masks also
    ``masked_fraction``."""
    from ...loss.geco import no_valid_pixels_reason

    if video.ndim != 5:
        raise ValueError(f"video must be [B, F, 3, H, W], got shape {list(video.shape)}")
    bad = [a for a in anchors if not 0 <= a < video.shape[1]]
    if bad:
        raise ValueError(f"anchors {bad} out of range for a {video.shape[1]}-frame video")
    with torch.no_grad():
        result = loss_fn(video[:, list(anchors)].float())
    if isinstance(result, Tensor):
        return {"loss": float(result)}
    scores: dict[str, Any] = result.scalars()
    if result.masked_fraction is not None:
        scores["masked_fraction"] = float(result.masked_fraction.mean())
    if result.empty_cues():
        scores["nan_reason"] = no_valid_pixels_reason(result.dynamic_masks is not None)
    return scores


class NonFiniteLatentsError(ValueError):
    """The latents of a sampling call turned NaN or inf: the video would be NaN frames."""


class LatentsWatch:
    """The first denoising step after which a call's latents hold NaN or inf, kept on the
    latents' device: :meth:`see` queues the test without waiting for it (no host sync per step),
    :meth:`check` reads it (one device-to-host copy) and refuses."""

    def __init__(self, num_steps: int) -> None:
        self.num_steps = num_steps
        self._first: Tensor | None = None  # -1 while every latent seen is finite

    def see(self, latents: Tensor, step: int) -> None:
        """Note the latents of denoising step ``step`` (0-based): what it made, or what it starts from."""
        from torch._subclasses.fake_tensor import is_fake

        if is_fake(latents):  # the cost model's trace: no values to check, and no ops to add to its count
            return
        if self._first is None:
            self._first = torch.full((), -1, dtype=torch.long, device=latents.device)
        turned = (self._first < 0) & ~torch.isfinite(latents).all().to(self._first.device)
        self._first = self._first.masked_fill(turned, step)

    def check(self) -> None:
        """Raises:
            NonFiniteLatentsError: one line naming the first step whose latents hold NaN or inf.
        """
        step = -1 if self._first is None else int(self._first)
        if step >= 0:
            raise NonFiniteLatentsError(
                f"the latents hold NaN or inf from denoising step {step} on (0-based, of {self.num_steps}); the "
                "video would be NaN frames, so the call stops (lower guidance.step_size or the guidance scale, or check "
                "latents set by a callback)"
            )
