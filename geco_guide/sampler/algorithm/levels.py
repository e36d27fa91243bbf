"""Noise-level arithmetic of one denoising step (what the guided step needs of a scheduler).

Both supported parametrisations write a noisy latent as ``z = a x0 + b eps``:

- variance preserving (CogVideoX, v-prediction): ``a = sqrt(alpha_bar)``, ``b = sqrt(1 - alpha_bar)``,
  cumulative alphas taken from the scheduler's table at its timestep entries (:class:`VPLevels`);
- rectified flow (Wan, HunyuanVideo, LTX-Video): ``a = 1 - sigma``, ``b = sigma``, the model
  predicts ``v = eps - x0`` so ``x0 = z - sigma v`` (:class:`FlowLevels`).

"DDIM" is the deterministic step that keeps the implied noise ``eps = (z - a_t x0) / b_t``:
``z_prev = a_prev x0 + b_prev eps`` (for rectified flow this is exactly the Euler step
``z + (sigma_prev - sigma_t) v``). Time travel re-noises with the forward transition of the
process from the ``prev`` level back to ``t``: ``z_t = (a_t / a_prev) z_prev + sqrt(b_t^2 -
(a_t b_prev / a_prev)^2) n``. Coefficients are computed in the precision of the scheduler's table
and applied to fp32 latents, as diffusers' DDIM step does.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import torch
from torch import Tensor

from ..diffusers_private import sigma_to_alpha_sigma_t

__all__ = ["FlowLevels", "NoiseLevels", "VPLevels", "ddim_step", "flow_renoise", "flow_step", "flow_to_x0",
           "keep_update", "randn_like", "renoise", "v_to_x0"]


def v_to_x0(z: Tensor, v: Tensor, alpha_t: Tensor | float) -> Tensor:
    """Clean-sample estimate of v-prediction: ``x0 = sqrt(a_t) z_t - sqrt(1 - a_t) v``."""
    return (alpha_t**0.5) * z - ((1 - alpha_t) ** 0.5) * v


def ddim_step(z: Tensor, x0: Tensor, alpha_t: Tensor | float, alpha_prev: Tensor | float) -> Tensor:
    """Deterministic DDIM ``z_prev = A z_t + B x0`` with ``A = sqrt((1-a_prev)/(1-a_t))``."""
    a = ((1 - alpha_prev) / (1 - alpha_t)) ** 0.5
    b = alpha_prev**0.5 - alpha_t**0.5 * a
    return a * z + b * x0


def randn_like(z: Tensor, generator: torch.Generator | list[torch.Generator] | None) -> Tensor:
    """Standard normal noise shaped like ``z`` (fp32) drawn from ``generator`` (list: one per video)."""
    if isinstance(generator, (list, tuple)):
        if len(generator) != z.shape[0]:
            raise ValueError(f"got {len(generator)} generators for a batch of {z.shape[0]}")
        return torch.cat([randn_like(z[i : i + 1], g) for i, g in enumerate(generator)])
    device = generator.device if generator is not None else z.device
    noise = torch.randn(z.shape, generator=generator, device=device, dtype=torch.float32)
    return noise.to(z.device)


def renoise(z_prev: Tensor, alpha_t: Tensor | float, alpha_prev: Tensor | float, noise: Tensor) -> Tensor:
    """Forward-diffuse ``z_prev`` (level ``alpha_prev``) back to level ``alpha_t``."""
    ratio = alpha_t / alpha_prev
    return (ratio**0.5) * z_prev + ((1 - ratio) ** 0.5) * noise


def flow_to_x0(z: Tensor, v: Tensor, sigma_t: Tensor | float) -> Tensor:
    """Clean-sample estimate of rectified flow (``z = (1-s) x0 + s eps``, ``v = eps - x0``): ``x0 = z - s v``."""
    return z - sigma_t * v


def flow_step(z: Tensor, x0: Tensor, sigma_t: Tensor | float, sigma_prev: Tensor | float) -> Tensor:
    """Deterministic flow step to ``sigma_prev`` with the velocity implied by ``x0``: the Euler step
    ``z + (s_prev - s_t) (z - x0) / s_t`` (identical to DDIM in the flow parametrisation)."""
    return z + (sigma_prev - sigma_t) * ((z - x0) / sigma_t)


def flow_renoise(z_prev: Tensor, sigma_t: Tensor | float, sigma_prev: Tensor | float, noise: Tensor) -> Tensor:
    """Forward transition of rectified flow from ``sigma_prev`` back to ``sigma_t >= sigma_prev``.

    With ``z_prev = (1-s_p) x0 + s_p e1``: ``a = (1-s_t)/(1-s_p)`` gives ``a z_prev = (1-s_t) x0 +
    a s_p e1``, and independent noise of std ``sqrt(s_t^2 - (a s_p)^2)`` completes ``s_t eps``.
    """
    sigma_t = torch.as_tensor(sigma_t, dtype=torch.float64)
    sigma_prev = torch.as_tensor(sigma_prev, dtype=torch.float64)
    a = (1 - sigma_t) / (1 - sigma_prev)
    std = (sigma_t**2 - (a * sigma_prev) ** 2).clamp_min(0) ** 0.5
    return float(a) * z_prev + float(std) * noise


class NoiseLevels:
    """The two noise levels of one step and the arithmetic :func:`~geco_guide.sampler.algorithm.step.guided_step` needs between them."""

    def to_x0(self, z: Tensor, out: Tensor) -> Tensor:  # pragma: no cover - interface
        """Clean estimate from the latents and the (CFG-combined) model output."""
        raise NotImplementedError

    def step(self, z: Tensor, x0: Tensor) -> Tensor:  # pragma: no cover - interface
        """Deterministic DDIM step to the ``prev`` level."""
        raise NotImplementedError

    def renoise(self, z_prev: Tensor, noise: Tensor) -> Tensor:  # pragma: no cover - interface
        """Forward-diffuse from the ``prev`` level back to ``t``."""
        raise NotImplementedError


@dataclass(frozen=True)
class VPLevels(NoiseLevels):
    """Variance-preserving v-prediction (CogVideoX): cumulative alphas of this and the next table entry."""

    alpha_t: Any
    alpha_prev: Any

    def to_x0(self, z: Tensor, out: Tensor) -> Tensor:
        return v_to_x0(z, out, self.alpha_t)

    def step(self, z: Tensor, x0: Tensor) -> Tensor:
        return ddim_step(z, x0, self.alpha_t, self.alpha_prev)

    def renoise(self, z_prev: Tensor, noise: Tensor) -> Tensor:
        return renoise(z_prev, self.alpha_t, self.alpha_prev, noise)


@dataclass(frozen=True)
class FlowLevels(NoiseLevels):
    """Rectified flow with velocity prediction (Wan, HunyuanVideo, LTX-Video): ``sigma`` of this and
    the next entry of the scheduler's ``sigmas`` (the last entry is the final ``sigma``, usually 0)."""

    sigma_t: Any
    sigma_prev: Any

    def to_x0(self, z: Tensor, out: Tensor) -> Tensor:
        return flow_to_x0(z, out, self.sigma_t)

    def step(self, z: Tensor, x0: Tensor) -> Tensor:
        return flow_step(z, x0, self.sigma_t, self.sigma_prev)

    def renoise(self, z_prev: Tensor, noise: Tensor) -> Tensor:
        return flow_renoise(z_prev, self.sigma_t, self.sigma_prev, noise)


def keep_update(scheduler, old_sample: Tensor, new_sample: Tensor) -> None:
    """Make a multistep scheduler's history keep a change of the sample about to be stepped.

    UniPC's corrector rebuilds the current sample from ``last_sample`` (the previous step's
    input) and the model outputs, ignoring the sample it is handed: a guided change would be
    discarded. Its result is affine in ``last_sample`` with the coefficient ``c = sigma_t /
    sigma_s0`` (data prediction; ``alpha_t / alpha_s0`` otherwise), so shifting ``last_sample`` by
    ``delta / c`` makes the corrected sample move by exactly ``delta = new - old``. Other supported
    schedulers step from the sample they are given (nothing to do).
    """
    from diffusers import UniPCMultistepScheduler

    if not isinstance(scheduler, UniPCMultistepScheduler):
        return
    idx = scheduler.step_index
    if idx is None or idx == 0 or scheduler.last_sample is None or (idx - 1) in scheduler.disable_corrector:
        return  # no corrector at this step
    alpha_t, sigma_t = sigma_to_alpha_sigma_t(scheduler, scheduler.sigmas[idx])
    alpha_s0, sigma_s0 = sigma_to_alpha_sigma_t(scheduler, scheduler.sigmas[idx - 1])
    coeff = float(sigma_t / sigma_s0) if scheduler.predict_x0 else float(alpha_t / alpha_s0)
    last = scheduler.last_sample
    delta = new_sample.float() - old_sample.float()
    scheduler.last_sample = (last.float() + delta.to(last.device) / coeff).to(last.dtype)
