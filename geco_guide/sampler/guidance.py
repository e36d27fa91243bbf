"""The model-agnostic guided step, shared by GeCoCogVideoXPipeline and the pipeline hooks.

One denoising step ``t -> t_prev`` with GeCo guidance, for any latent video model:

    for r in range(R_t):
        x0 = predict_x0(z_t)                        # through the denoiser, or with its output held constant
        L  = loss(decode_anchors(x0))               # frozen VAE on short causal chunks, GeCo loss
        g  = dL/dz_t
        z_t <- z_t - eta * g / (||g|| + eps)        # fp32, norm per video
        (time travel: z_t <- renoise(DDIM(z_t, x0) - eta * g / (||g|| + eps)) back to t)
    x0 = predict_x0(z_t) without gradients          # the last, gradient-free prediction
    z_prev = DDIM(z_t, x0)                          # deterministic; optional (the hooks let the
                                                    # pipeline's own scheduler take the step)

The model only enters through three callables (``predict_x0``, ``decode_anchors``, ``loss_fn``)
and the two noise levels of the step, :class:`NoiseLevels`. Both supported parametrisations
write a noisy latent as ``z = a x0 + b eps``:

- variance preserving (CogVideoX, v-prediction): ``a = sqrt(alpha_bar)``, ``b = sqrt(1 - alpha_bar)``,
  cumulative alphas taken from the scheduler's table at its timestep entries (:class:`VPLevels`);
- rectified flow (Wan, HunyuanVideo, LTX-Video): ``a = 1 - sigma``, ``b = sigma``, the model
  predicts ``v = eps - x0`` so ``x0 = z - sigma v`` (:class:`FlowLevels`).

"DDIM" is the deterministic step that keeps the implied noise ``eps = (z - a_t x0) / b_t``:
``z_prev = a_prev x0 + b_prev eps`` (for rectified flow this is exactly the Euler step
``z + (sigma_prev - sigma_t) v``). Time travel re-noises with the forward transition of the
process from the ``prev`` level back to ``t``: ``z_t = (a_t / a_prev) z_prev + sqrt(b_t^2 -
(a_t b_prev / a_prev)^2) n``. This module imports torch only.
"""

from __future__ import annotations

import contextlib
import time
from collections.abc import Callable, Mapping, Sequence
from dataclasses import asdict, dataclass, field, replace
from typing import Any, Optional

import torch
from torch import Tensor, nn

from ..loss.geco import GeCoLossConfig
from ..types import OptionError, merge_dataclass, non_finite_fields
from .schedule import (
    PAPER_ETA,
    PAPER_REPEATS,
    PAPER_TIME_TRAVEL,
    GuidanceSchedule,
    scale_schedule,
)
from .slicing import AnchorChunk, anchor_latent_chunks

PAPER_ANCHORS = (12, 24, 36, 48)
# An update of eta moves the latents by eta in L2 norm; 1000 is about the norm of the whole latent
# video at 480x720 (the paper: 3). Larger values only overflow the latents to NaN/inf after
# minutes of sampling (a black video), so they are refused at once.
MAX_ETA = 1000.0


def _guidance_loss_default() -> GeCoLossConfig:
    # The paper runs the flow estimator on frames downscaled by 0.5 during guidance.
    return GeCoLossConfig(flow_downscale=0.5)


@dataclass
class GuidanceConfig:
    """GeCo guidance options (defaults: the paper's schedule for 50 DDIM steps of a 49-frame video,
    with the method section's fused loss; :func:`paper_guidance_config` is the paper's experiment,
    the residual motion cue without gradients through the geometry estimator).

    Attributes:
        enabled: ``False`` samples without guidance (plain deterministic DDIM).
        anchors: 0-based pixel frames decoded and scored during guidance.
        chunk_latents: latents per causal chunk decoded for each anchor (ending at its latent).
        repeats: ``R_t`` per step, as runs ``"RxN,..."`` (see :mod:`.schedule`). Runs written for
            another step count are scaled to the sampler's, phases in proportion (with a
            warning); an explicit per-step list must match exactly.
        eta: normalised step size of each update (>= 0).
        time_travel: inclusive ``[first, last]`` step window of time travel; empty/None disables.
            Scaled with the runs of ``repeats``.
        denoiser_grad: ``True`` backpropagates through the denoiser at every update (paper);
            ``False`` is the fast mode that holds the model output constant through the step
            (``dx0/dz_t = sqrt(a_t)``), so the denoiser runs once per step as without guidance
            (plus once after each time-travel re-noising).
        gradient_checkpointing: checkpoint the denoiser's blocks while differentiating it.
        vae_checkpointing: decode the anchor chunks one at a time in checkpointed regions, with
            the VAE's own block checkpointing inside (where the VAE supports it): the backward
            then holds one chunk's decode instead of all of them, for extra forward decodes.
            The CogVideoX-5B VAE needs it at 480x720 (docs/benchmarks.md); ``False`` batches the
            chunks in one decode and keeps everything (fastest, for small videos).
        grad_eps: ``eps`` of the normalised update.
        loss: the GeCo loss options; the structure cue only gives gradients with
            ``loss.geometry_grad=True`` (default), since it depends on the frames only through
            the geometry estimator: ``cue="structure"`` with ``geometry_grad=False`` is refused
            before any denoising step.
    """

    enabled: bool = True
    anchors: list[int] = field(default_factory=lambda: list(PAPER_ANCHORS))
    chunk_latents: int = 3
    repeats: str = PAPER_REPEATS
    eta: float = PAPER_ETA
    time_travel: Optional[list[int]] = field(default_factory=lambda: list(PAPER_TIME_TRAVEL))
    denoiser_grad: bool = True
    gradient_checkpointing: bool = True
    vae_checkpointing: bool = True
    grad_eps: float = 1e-8
    loss: GeCoLossConfig = field(default_factory=_guidance_loss_default)

    def __post_init__(self) -> None:
        for key, value in non_finite_fields(self):  # the first one
            raise OptionError(key, f"must be a finite number, got {value}")
        if not 0 <= self.eta <= MAX_ETA:
            raise OptionError("eta", f"must be in [0, {MAX_ETA:g}], got {self.eta}")
        if not self.grad_eps > 0:
            raise OptionError("grad_eps", f"must be > 0, got {self.grad_eps}")
        if self.chunk_latents < 2:
            raise OptionError("chunk_latents", f"must be >= 2, got {self.chunk_latents}")

    def schedule(self, num_steps: int) -> GuidanceSchedule:
        """The validated :class:`GuidanceSchedule` for ``num_steps`` steps (runs scaled, see
        :func:`~geco_guide.sampler.schedule.scale_schedule`)."""
        repeats, time_travel = scale_schedule(self.repeats, self.time_travel, num_steps)
        return GuidanceSchedule.build(repeats, num_steps, self.eta, time_travel)

    def check_loss(self) -> None:
        """ValueError (one line) for a loss that cannot give an update."""
        loss = self.loss
        if self.enabled and getattr(loss, "cue", None) == "structure" and not getattr(loss, "geometry_grad", True):
            raise ValueError(
                "guidance.loss.cue='structure' needs guidance.loss.geometry_grad=true: the structure cue reaches the "
                "frames only through the geometry estimator, so without its gradient there is no update "
                "(use cue=motion or fused, or geometry_grad=true)"
            )

    def anchor_chunks(self, num_frames: int, temporal_compression: int) -> list[AnchorChunk]:
        """The causal latent chunk of each anchor of a ``num_frames`` video (ValueError for anchors
        the video cannot contain)."""
        return anchor_latent_chunks(self.anchors, num_frames, temporal_compression, self.chunk_latents)

    def validate(self, num_steps: int, num_frames: int,
                 temporal_compression: int) -> tuple[GuidanceSchedule, list[AnchorChunk]]:
        """Check everything against a run; ValueError naming the problem. Returns the schedule
        and the anchors' chunks."""
        self.check_loss()
        chunks = self.anchor_chunks(num_frames, temporal_compression)
        return self.schedule(num_steps), chunks


def paper_guidance_config() -> GuidanceConfig:
    """The paper's guidance experiment (supplement; the published code's ``residual_motion`` loss):
    the residual motion cue on adjacent pairs of the anchors, flow input x0.5, depth and cameras
    constants of the update (``geometry_grad=False``: the update reaches the frames through the flow
    estimator only). ``GuidanceConfig()`` differs only in the loss: the method section's fused
    ``M_geo`` with gradients through the geometry estimator too."""
    return GuidanceConfig(loss=GeCoLossConfig(cue="motion", pairs="adjacent", flow_downscale=0.5, geometry_grad=False))


def resolve_guidance_config(
    base: GuidanceConfig | None, override: GuidanceConfig | Mapping[str, Any] | bool | None
) -> GuidanceConfig:
    """The guidance config of one call: ``override`` (config, dict of changes, or bool) over ``base``.

    ``False`` disables guidance, ``True``/``None`` keeps ``base``; a dict changes only the keys it
    names (``{"loss": {"cue": "motion"}}`` works). Unknown keys raise ValueError naming them.
    """
    base = base if base is not None else GuidanceConfig()
    if override is None or override is True:
        return base
    if override is False:
        return replace(base, enabled=False)
    if isinstance(override, GuidanceConfig):
        return override
    if hasattr(override, "keys"):  # dict or omegaconf DictConfig
        return merge_dataclass(base, override, "guidance")
    raise ValueError(f"guidance must be a GuidanceConfig, a dict, True/False or None, got {type(override).__name__}")


# --------------------------------------------------------------------------------------------
# DDIM arithmetic (v-prediction). Coefficients are computed in the precision of the scheduler's
# alphas_cumprod table and applied to fp32 latents, exactly as diffusers' DDIM step does.


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


def normalized_update(z: Tensor, grad: Tensor, eta: float, eps: float = 1e-8) -> tuple[Tensor, Tensor]:
    """``z - eta * g / (||g|| + eps)`` in fp32, with the norm taken per video. Returns (z, ||g||)."""
    grad = grad.float()
    norm = grad.flatten(1).norm(dim=1).view(-1, *([1] * (grad.ndim - 1)))
    return z.float() - eta * grad / (norm + eps), norm.flatten()


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
    """The two noise levels of one step and the arithmetic ``guided_step`` needs between them."""

    def to_x0(self, z: Tensor, out: Tensor) -> Tensor:  # pragma: no cover - interface
        """Clean estimate from the latents and the (CFG-combined) model output."""
        raise NotImplementedError

    def step(self, z: Tensor, x0: Tensor) -> Tensor:  # pragma: no cover - interface
        """Deterministic DDIM step to the ``prev`` level."""
        raise NotImplementedError

    def renoise(self, z_prev: Tensor, noise: Tensor) -> Tensor:  # pragma: no cover - interface
        """Forward-diffuse from the ``prev`` level back to ``t``."""
        raise NotImplementedError

    def shift_x0(self, x0: Tensor, dz: Tensor) -> Tensor:  # pragma: no cover - interface
        """Clean estimate after the latents moved by ``dz`` with the model output held constant."""
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

    def shift_x0(self, x0: Tensor, dz: Tensor) -> Tensor:
        return x0 + (self.alpha_t**0.5) * dz


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

    def shift_x0(self, x0: Tensor, dz: Tensor) -> Tensor:
        return x0 + dz


@contextlib.contextmanager
def frozen(*modules: Any):
    """Disable ``requires_grad`` of every parameter of the given modules; restore on exit."""
    params = [p for m in modules if isinstance(m, nn.Module) for p in m.parameters()]
    flags = [p.requires_grad for p in params]
    try:
        for p in params:
            p.requires_grad_(False)
        yield
    finally:
        for p, flag in zip(params, flags):
            p.requires_grad_(flag)


@contextlib.contextmanager
def gradient_checkpointing(model: Any, enable: bool):
    """Turn on the model's diffusers gradient checkpointing for the duration; restore on exit."""
    if not enable or not getattr(model, "_supports_gradient_checkpointing", False) or model.is_gradient_checkpointing:
        yield
        return
    model.enable_gradient_checkpointing()
    try:
        yield
    finally:
        model.disable_gradient_checkpointing()


# --------------------------------------------------------------------------------------------


@dataclass
class GuidanceRecord:
    """One guided update: step index, timestep, loss and cues before the update, ||g||, seconds."""

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

    def to_dict(self) -> dict[str, Any]:
        return asdict(self)


def _loss_terms(result: Any) -> tuple[Tensor, dict[str, Tensor]]:
    """The loss to differentiate and the scalars to record, as tensors (reading them is a host sync)."""
    if isinstance(result, Tensor):
        return result, {"loss": result}
    return result.loss, {name: getattr(result, name) for name in ("loss", "motion", "structure", "fused")}


def _read_scalars(values: dict[str, Tensor], device: torch.device) -> dict[str, float]:
    """Plain floats of ``values`` (0-dim tensors) with one device-to-host copy for all of them."""
    stacked = torch.stack([v.detach().to(device=device, dtype=torch.float32).reshape(()) for v in values.values()])
    return dict(zip(values, stacked.tolist()))


def guided_step(
    z: Tensor,
    *,
    predict_x0: Callable[[Tensor, bool], Tensor],
    decode_anchors: Callable[[Tensor], Tensor],
    loss_fn: Callable[[Tensor], Any],
    levels: NoiseLevels,
    repeats: int = 0,
    eta: float = PAPER_ETA,
    time_travel: bool = False,
    denoiser_grad: bool = True,
    generator: torch.Generator | list[torch.Generator] | None = None,
    eps: float = 1e-8,
    step: int = 0,
    t: int = 0,
    on_record: Callable[[GuidanceRecord], None] | None = None,
    take_step: bool = True,
) -> tuple[Tensor, Tensor, list[GuidanceRecord]]:
    """One denoising step with ``repeats`` GeCo updates of ``z`` (see the module docstring).

    Args:
        z: ``z_t`` (any float dtype; the update runs in fp32).
        predict_x0: ``(z, differentiate_denoiser) -> x0`` in fp32. It is called with True for
            each update in faithful mode, and with False under ``torch.no_grad`` for the final
            prediction and, in fast mode, for the one prediction the step's updates share.
        decode_anchors: ``x0 -> frames [B, S, 3, H, W]`` in ``[0, 1]`` (differentiable).
        loss_fn: ``frames -> GeCoResult`` (``.loss``, ``.motion``, ``.structure``, ``.fused``)
            or a scalar tensor.
        levels: the step's :class:`NoiseLevels` (:class:`VPLevels` or :class:`FlowLevels`);
            ``predict_x0`` must agree with it (``x0 = levels.to_x0(z, model_output)``).
        repeats: ``R_t``; 0 makes this a plain DDIM step.
        eta: normalised step size.
        time_travel: take the DDIM step with the update, then re-noise back to ``t``.
        denoiser_grad: differentiate through the denoiser at every update (paper), or hold its
            output constant through the step (fast): ``x0`` then moves with ``z`` as
            ``levels.shift_x0`` says (``sqrt(a_t)`` for v-prediction), and the denoiser runs once
            per step as without guidance, plus once after each time-travel re-noising.
        generator: source of the time-travel noise.
        eps: of the normalised update.
        step, t: step index and timestep, for the records.
        on_record: called with each :class:`GuidanceRecord` as soon as it exists.
        take_step: ``False`` returns the guided ``z_t`` instead of taking the final DDIM step
            (the pipeline hooks hand it to the pipeline's own scheduler).

    Returns:
        ``(z_prev, x0, records)``: the latents at the next level (fp32; the guided ``z_t`` when
        ``take_step=False``), the final clean estimate and one record per update.
    """
    z = z.detach().float()
    records: list[GuidanceRecord] = []
    # Fast mode holds the model output constant, so one prediction serves every update of the step
    # and the final DDIM step: (z, x0) of the last denoiser call, until time travel re-noises z.
    held: tuple[Tensor, Tensor] | None = None
    for r in range(repeats):
        start = time.perf_counter()
        with torch.enable_grad():
            z_in = z.detach().requires_grad_(True)
            if denoiser_grad:
                x0 = predict_x0(z_in, True)
            else:
                if held is None:
                    with torch.no_grad():
                        held = (z, predict_x0(z, False).float())
                x0 = levels.shift_x0(held[1], z_in - held[0])
            loss, terms = _loss_terms(loss_fn(decode_anchors(x0)))
            (grad,) = torch.autograd.grad(loss, z_in, allow_unused=True)
        if grad is None:
            grad = torch.zeros_like(z)
        # A NaN gradient must never reach the latents; torch.where keeps the check on the device.
        finite = torch.isfinite(grad).all()
        grad = torch.where(finite, grad, torch.zeros_like(grad))
        x0 = x0.detach().float()
        z_new, norm = normalized_update(z, grad, eta, eps)
        if time_travel:
            z_prev = levels.step(z, x0) + (z_new - z)
            z = levels.renoise(z_prev, randn_like(z, generator))
            held = None
        else:
            z = z_new
        # The update's only host sync: the record's numbers, read once the update is queued.
        scalars = _read_scalars({**terms, "grad_norm": norm.mean(), "finite": finite}, z.device)
        record = GuidanceRecord(
            step=step,
            repeat=r,
            t=int(t),
            loss=scalars["loss"],
            motion=scalars.get("motion"),
            structure=scalars.get("structure"),
            fused=scalars.get("fused"),
            grad_norm=scalars["grad_norm"],
            seconds=time.perf_counter() - start,
            time_travel=time_travel,
            skipped=not scalars["finite"],
        )
        records.append(record)
        if on_record is not None:
            on_record(record)
    with torch.no_grad():
        x0 = predict_x0(z, False).float() if held is None else levels.shift_x0(held[1], z - held[0])
        if not take_step:
            return z, x0, records
        z_prev = levels.step(z, x0)
    return z_prev, x0, records


def score_anchor_frames(video: Tensor, anchors: Sequence[int], loss_fn: Callable[[Tensor], Any]) -> dict[str, float]:
    """GeCo scalars (``motion``, ``structure``, ``fused``, ``loss``) of the anchor frames of a
    decoded ``video [B, F, 3, H, W]`` in ``[0, 1]``, without gradients."""
    if video.ndim != 5:
        raise ValueError(f"video must be [B, F, 3, H, W], got shape {list(video.shape)}")
    bad = [a for a in anchors if not 0 <= a < video.shape[1]]
    if bad:
        raise ValueError(f"anchors {bad} out of range for a {video.shape[1]}-frame video")
    with torch.no_grad():
        _, terms = _loss_terms(loss_fn(video[:, list(anchors)].float()))
    return _read_scalars(terms, video.device)
