"""The guidance of one call, shared by :class:`GeCoCogVideoXPipeline` and the pipeline hooks.

A :class:`GuidanceContext` holds what every guided step of a call needs: the options, the
schedule, the anchor decode, the GeCo loss and the guidance log. Its :meth:`~GuidanceContext.models`
block freezes the models and switches on the checkpointing of the call's memory plan
(:mod:`.memory_plan`), and :meth:`~GuidanceContext.guide` runs :func:`~.step.guided_step` at one
step of the loop; an out-of-memory error at the call's first update falls back to the next plan
and retries that update (same generator state, so the same video). Profilers
subclass it: :meth:`~GuidanceContext.guide` brackets the updates of a step, and
:meth:`~GuidanceContext.read_scalars` is the one host sync of an update.
"""

from __future__ import annotations

import contextlib
import gc
import logging
import time
from collections.abc import Callable, Iterable, Sequence
from typing import Any

import torch
from torch import Tensor, nn

from ..estimators.tiny_decoder import TinyDecoder
from ..loss.geco import GeCoLoss
from .config import GuidanceConfig
from .dynamic import RefreshedMasks
from .fast_decode import check_channels_last_vae, guidance_decode
from .levels import NoiseLevels
from .memory_plan import PlanChoice, explicit_plan
from .run_options import RunOptions
from .schedule import GuidanceSchedule
from .devices import decoder_replicas
from .slicing import AnchorChunk, decode_anchor_frames, decode_anchor_frames_across
from .step import GuidanceRecord, Update, guided_step, loss_terms, read_scalars

__all__ = ["AnchorDecode", "GuidanceContext", "anchor_decoder", "estimator_checkpointing", "frozen",
           "generator_states", "gradient_checkpointing", "partial_checkpointing"]

logger = logging.getLogger(__name__)


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


@contextlib.contextmanager
def estimator_checkpointing(estimators: Iterable[Any], enable: bool | None):
    """Set the estimators' ``gradient_checkpointing`` (where they have one) for the duration;
    ``None`` leaves them as they are. Restored on exit."""
    models = [m for m in estimators if enable is not None and hasattr(m, "gradient_checkpointing")]
    flags = [m.gradient_checkpointing for m in models]
    try:
        for model in models:
            model.gradient_checkpointing = enable
        yield
    finally:
        for model, flag in zip(models, flags):
            model.gradient_checkpointing = flag


@contextlib.contextmanager
def partial_checkpointing(model: Any, keep_every: int):
    """Checkpoint a denoiser's ``transformer_blocks`` one by one while differentiating, except every
    ``keep_every``-th (blocks ``0, k, 2k, ...``), whose activations are kept: a
    :class:`~.module_hooks.CheckpointedForward` hook on each, removed on exit. A model without such
    a list, or one already checkpointing, gets its own full checkpointing."""
    blocks = getattr(model, "transformer_blocks", None)
    if blocks is None or getattr(model, "is_gradient_checkpointing", False):
        with gradient_checkpointing(model, True):
            yield
        return
    # imports diffusers, which importing the package leaves out
    from .module_hooks import CHECKPOINT_HOOK, CheckpointedForward, hooked

    with contextlib.ExitStack() as stack:
        for i, block in enumerate(blocks):
            if i % keep_every:
                stack.enter_context(hooked(block, CheckpointedForward(), CHECKPOINT_HOOK))
        yield


def generator_states(generator: torch.Generator | list[torch.Generator] | None) -> list[tuple[torch.Generator, Tensor]]:
    """``(generator, state)`` of the call's generator(s), to draw the same noise again."""
    generators = generator if isinstance(generator, list) else [generator] if generator is not None else []
    return [(g, g.get_state()) for g in generators]


class AnchorDecode:
    """The chunk decode of the loss' anchor frames: ``latents [N, F, C, h, w] -> frames [N, T, 3,
    H, W]`` in ``[0, 1]`` by ``module`` (the VAE, or the tiny decoder), and :meth:`on` a replica
    of that module (another device's).

    Args:
        module: the frozen decoder.
        decode_with: ``module -> decode``: the decode by a given copy of ``module``.
    """

    def __init__(self, module: nn.Module, decode_with: Callable[[nn.Module], Callable[[Tensor], Tensor]]):
        self.module, self.decode_with = module, decode_with
        self._decode = decode_with(module)

    def __call__(self, latents: Tensor) -> Tensor:
        return self._decode(latents)

    def on(self, replica: nn.Module) -> Callable[[Tensor], Tensor]:
        """The same decode by ``replica`` (a copy of :attr:`module`, e.g. on another device)."""
        return self.decode_with(replica)


def anchor_decoder(config: GuidanceConfig, run: RunOptions, vae_decode_with: Callable[[nn.Module], Callable[[Tensor], Tensor]],
                   guidance_decoder: Any, vae: Any) -> AnchorDecode:
    """The :class:`AnchorDecode` of the loss' anchor frames: ``vae_decode_with(vae)`` with
    ``decoder="vae"`` (``vae_decode_with``: a VAE -> its chunk decode); with ``"tiny"`` the tiny
    decoder on the pipeline's latents ``[N, F, C, h, w]``, in its family's convention taken from
    ``vae``'s config (CogVideoX's divided by ``scaling_factor``, Wan's and HunyuanVideo's as they
    are). Checked at the start of a call, before any denoiser runs: ValueError (one line) for a
    missing or mismatched decoder, TypeError for ``run.decode_layout="channels_last"`` on a VAE it
    is not written for."""
    if run.decode_layout == "channels_last":
        check_channels_last_vae(vae)
    if config.decoder == "vae":
        return AnchorDecode(vae, vae_decode_with)
    if guidance_decoder is None:
        raise ValueError(
            "guidance.decoder='tiny' needs a tiny decoder: pass guidance_decoder=TinyDecoder.from_pretrained(PATH) "
            "(weights such as taecvx.pth from github.com/madebyollin/taehv; from a config: "
            "estimators.tiny_decoder=/path/to/taecvx.pth), or use guidance.decoder=vae"
        )
    vae_config = vae.config
    channels = getattr(vae_config, "latent_channels", None) or getattr(vae_config, "z_dim", None)  # CogVideoX, Wan
    if channels is not None and guidance_decoder.latent_channels != channels:
        raise ValueError(
            f"the tiny decoder ({guidance_decoder.variant.name}) takes {guidance_decoder.latent_channels} latent "
            f"channels but this VAE makes {channels}: load the tiny decoder trained for this model"
        )
    return AnchorDecode(guidance_decoder, lambda decoder: lambda latents: decoder.decode(
        decoder.pipeline_latents(latents, vae_config, layout="NTCHW")))


class GuidanceContext:
    """Guidance state of one pipeline call.

    Args:
        config: the call's resolved :class:`GuidanceConfig`.
        schedule: its :class:`GuidanceSchedule` for the call's step count.
        chunks: the anchors' causal latent chunks.
        decode_chunk: ``latents [N, F', C, h, w] -> frames [N, T, 3, H, W]`` in ``[0, 1]`` (a
            VAE's, or the pipeline adapter's).
        latent_frames: ``x0 -> [B, F, C, h, w]``: the video's latents, frames first, of the
            model's clean estimate (drops padding frames, reorders channels).
        geometry_estimator, flow_estimator: the GeCo loss' estimators.
        generator: source of the time-travel noise (the call's).
        on_record: called with each :class:`GuidanceRecord` as it is logged.
        log: the list the records are appended to as dicts (a new one by default).
        run: how the call runs (:class:`~.run_options.RunOptions`; default: the defaults): its
            decode layout and compilation, and the explicit flags ``memory_plan`` defaults to.
        memory_plan: the call's :class:`~.memory_plan.PlanChoice` (default: ``run``'s explicit
            flags, no fallback); :attr:`memory_plan` is the one in use (after a fallback, the new one).
        dynamic_masks: what moves on its own, left out of the loss
            (:func:`~.dynamic.guidance_mask_source`), or ``None`` (the paper: no masks).
        devices: the devices the anchor chunks are dealt over
            (:func:`~.devices.resolve_devices` of ``run.devices``), each with a replica of
            ``decode_chunk``'s module (an :class:`AnchorDecode`), or ``None``: one device.
    """

    def __init__(
        self,
        config: GuidanceConfig,
        schedule: GuidanceSchedule,
        chunks: Sequence[AnchorChunk],
        decode_chunk: Callable[[Tensor], Tensor],
        latent_frames: Callable[[Tensor], Tensor],
        geometry_estimator: Any,
        flow_estimator: Any,
        *,
        generator: torch.Generator | list[torch.Generator] | None = None,
        on_record: Callable[[GuidanceRecord], None] | None = None,
        log: list[dict[str, Any]] | None = None,
        run: RunOptions | None = None,
        memory_plan: PlanChoice | None = None,
        dynamic_masks: RefreshedMasks | None = None,
        devices: Sequence[torch.device] | None = None,
    ):
        self.config, self.schedule, self.chunks = config, schedule, list(chunks)
        self.devices = list(devices) if devices else None
        self._placed: list[tuple[torch.device, Callable[[Tensor], Tensor]]] | None = None
        self.dynamic_masks = dynamic_masks
        self.decode_chunk, self.latent_frames = decode_chunk, latent_frames
        self.estimators = (geometry_estimator, flow_estimator)
        self.generator, self.on_record = generator, on_record
        # No frame check: it would make each update wait for the device; a NaN decode gives NaN
        # scalars and no update instead (see guided_step).
        self.loss_fn = GeCoLoss(geometry_estimator, flow_estimator, config.loss, check_values=False)
        self.log = log if log is not None else []
        self.run = run if run is not None else RunOptions()
        self.memory_plan = memory_plan or PlanChoice(explicit_plan(self.run), "the run options' explicit flags")
        self._plan_stack: contextlib.ExitStack | None = None
        self._plan_models: tuple[list[nn.Module], Any] = ([], None)

    @contextlib.contextmanager
    def models(self, denoisers: Iterable[nn.Module], vae: Any, others: Iterable[Any] = ()):
        """Frozen ``denoisers``, ``vae``, ``others`` and estimators, with the checkpointing of the
        memory plan (the denoisers' in faithful mode, the VAE's blocks, the estimators'); all
        restored on exit."""
        denoisers, others = list(denoisers), list(others)
        tiny_decoder = next((m for m in others if isinstance(m, TinyDecoder)), None)
        with contextlib.ExitStack() as stack:
            stack.enter_context(frozen(*others, vae, *denoisers, *self.estimators))
            stack.enter_context(guidance_decode(self.run, self.config.decoder, vae, tiny_decoder))
            self._plan_models = (denoisers, vae)
            self._plan_stack = self._enter_plan()
            try:
                yield
            finally:
                self._plan_stack.close()
                self._plan_stack, self._plan_models = None, ([], None)

    def _enter_plan(self) -> contextlib.ExitStack:
        """The checkpointing switches of :attr:`memory_plan` on the models of :meth:`models`."""
        plan, (denoisers, vae) = self.memory_plan.plan, self._plan_models
        stack = contextlib.ExitStack()
        differentiated = self.config.denoiser_grad and plan.denoiser_checkpointing
        for module in denoisers:
            if differentiated and plan.denoiser_keep_every >= 2:
                stack.enter_context(partial_checkpointing(module, plan.denoiser_keep_every))
            else:
                stack.enter_context(gradient_checkpointing(module, differentiated))
        stack.enter_context(gradient_checkpointing(vae, plan.vae_block_checkpointing))
        stack.enter_context(estimator_checkpointing(self.estimators, plan.estimator_checkpointing))
        return stack

    def fall_back(self) -> None:
        """Switch to the next plan of :attr:`memory_plan`'s fallbacks after an out-of-memory
        error: free what the failed update held, re-enter the checkpointing, say so in one line."""
        choice = self.memory_plan
        failed, new = choice.plan.name, choice.fallbacks[0]
        self.memory_plan = PlanChoice(new, f"{choice.reason}; fell back from {failed!r}: out of memory at the first "
                                           "update", budget_gb=choice.budget_gb, fallbacks=choice.fallbacks[1:])
        gc.collect()
        if torch.cuda.is_available():
            torch.cuda.empty_cache()
        if self._plan_stack is not None:
            self._plan_stack.close()
            self._plan_stack = self._enter_plan()
        self._placed = None  # the replicas are copied again, with the new plan's switches
        logger.warning("guidance: out of memory at the first update with memory plan %r; retrying it with %r",
                       failed, new.name)

    def decode_anchors(self, latents: Tensor) -> Tensor:
        """The anchor frames ``[B, S, 3, H, W]`` of ``latents [B, F, C, h, w]``: on one device as the
        memory plan says, or dealt over :attr:`devices` (replicas made at the first update)."""
        checkpointed = self.memory_plan.plan.chunk_checkpointing
        if self.devices is None:
            return decode_anchor_frames(self.decode_chunk, latents, self.chunks, checkpoint_chunks=checkpointed,
                                        batch_chunks=self.memory_plan.plan.batch_chunks)
        if self._placed is None:
            replicas = decoder_replicas(self.decode_chunk.module, self.devices)
            self._placed = [(device, self.decode_chunk.on(replica)) for device, replica in zip(self.devices, replicas)]
        return decode_anchor_frames_across(self._placed, latents, self.chunks, checkpoint_chunks=checkpointed)

    def objective(self, x0: Tensor) -> tuple[Tensor, dict[str, Tensor]]:
        """GeCo loss of the anchor frames decoded from ``x0`` (differentiable), and its terms."""
        frames = self.decode_anchors(self.latent_frames(x0))
        if self.dynamic_masks is None:
            return loss_terms(self.loss_fn(frames))
        self.dynamic_masks.start_update()
        return loss_terms(self.loss_fn(frames, dynamic_masks=self.dynamic_masks))

    def read_scalars(self, values: dict[str, Tensor], device: torch.device) -> dict[str, float]:
        """The numbers of one update's record: its one device-to-host copy."""
        return read_scalars(values, device)

    def guide(self, z: Tensor, predict: Callable[[Tensor, bool], Tensor], levels: NoiseLevels, step: int,
              t: int) -> tuple[Tensor, Tensor]:
        """The ``R_t`` updates of step ``step`` (timestep ``t``): the guided ``z_t`` and the model
        output there (:func:`~.step.guided_step`), each update logged. Out of memory before the
        call's first update is logged: :meth:`fall_back` and the step again, from the same
        generator state, while the plan has fallbacks."""
        while True:
            states = generator_states(self.generator)
            try:
                return self._guide(z, predict, levels, step, t)
            except torch.cuda.OutOfMemoryError:
                if self.log or not self.memory_plan.fallbacks:
                    raise
            for generator, state in states:
                generator.set_state(state)
            self.fall_back()

    def _guide(self, z: Tensor, predict: Callable[[Tensor, bool], Tensor], levels: NoiseLevels, step: int,
               t: int) -> tuple[Tensor, Tensor]:
        config, schedule = self.config, self.schedule
        if self.dynamic_masks is not None:
            self.dynamic_masks.start_step(step)

        def on_update(update: Update) -> None:
            scalars = self.read_scalars(update.terms, z.device)
            record = GuidanceRecord(
                step=step,
                repeat=update.repeat,
                t=int(t),
                loss=scalars["loss"],
                motion=scalars.get("motion"),
                structure=scalars.get("structure"),
                fused=scalars.get("fused"),
                grad_norm=scalars["grad_norm"],
                seconds=time.perf_counter() - update.started,
                time_travel=update.time_travel,
                skipped=not scalars["finite"],
                masked_fraction=scalars.get("masked_fraction"),
                mask_source=None if self.dynamic_masks is None else self.dynamic_masks.source_name,
            )
            self.log.append(record.to_dict())
            if self.on_record is not None:
                self.on_record(record)

        return guided_step(z, predict, levels, self.objective, schedule.repeats_at(step), eta=schedule.eta,
                           time_travel=schedule.time_travel_at(step), denoiser_grad=config.denoiser_grad,
                           generator=self.generator, eps=config.grad_eps, on_update=on_update)
