"""The guidance of one call of a stock diffusers pipeline, through its family's adapter.

Two front doors guide pipelines whose code is diffusers' own: the hooks of :mod:`.hooks` (a
``DiffusionPipeline`` of a family of the registry) and the loop of :mod:`.modular` (a Modular
Diffusers pipeline of Wan's). Both set a call up and take a guided step the same way, here:

* :func:`stock_call`: the checks of a call before its first denoising step (anchors, loss, run
  options, denoiser caches, scheduler, decoder, devices, masks, memory plan), and
  :meth:`StockCall.context`, the :class:`~.context.GuidanceContext` that guides it once the step
  count is known. The one place where the :class:`~geco_guide.estimators.bundle.Estimators` of a
  guided stock call are taken apart.
* :func:`guide_stock_step`: the ``R_t`` updates of one step, and the sample and model output the
  pipeline's scheduler then steps with (a multistep scheduler told to keep the update).
* :meth:`StockCall.particle_batch` and :meth:`StockCall.searcher`: a particle search of the call
  (:mod:`.search`), which decodes and scores the same anchors as guidance.

How each door predicts the model output at new latents differs (the hooks replay the captured
denoiser calls, the loop re-runs its own denoiser block), and so does where it keeps a call's
state; what a prediction is used for does not.
"""

from __future__ import annotations

import functools
from collections.abc import Callable, Iterable, Sequence
from dataclasses import dataclass
from typing import Any

import torch
from torch import Tensor, nn

from ...estimators.bundle import Estimators
from ...io.devices import planning_memory_gb, resolve_devices
from ...loss.geco import GeCoLoss
from ..algorithm.config import GuidanceConfig
from ..algorithm.dynamic import RefreshedMasks, guidance_mask_source
from ..algorithm.levels import keep_update
from ..algorithm.slicing import AnchorChunk
from ..diffusers_private import execution_device, offloads_models
from ..running.anchor_decode import AnchorDecode, anchor_decoder, plan_anchor_decode
from ..running.context import GuidanceContext, GuidanceObserver
from ..running.context_parallel import start_context_parallel
from ..running.memory_plan import SAFE_PLAN, PlanChoice, choose_plan, model_signature
from ..running.run_options import RunOptions, check_call_options
from ..search.particle_search import ParticleBatch, ParticleScorer, ParticleSearch, SearchConfig, choose_particle_batch
from .adapters import (
    CallGeometry,
    PipelineAdapter,
    check_no_denoiser_cache,
    check_scheduler,
    noise_levels,
)

__all__ = ["StockCall", "denoiser_signature", "guide_stock_step", "stock_call"]


class _WithVae:
    """A pipeline seen with another VAE (a replica on another device), for an adapter's decode."""

    def __init__(self, pipe: Any, vae: nn.Module):
        self._pipe, self.vae = pipe, vae

    def __getattr__(self, name: str) -> Any:
        return getattr(self._pipe, name)


def _vae_decode_with(pipe: Any, adapter: PipelineAdapter, vae: nn.Module) -> Callable[[Tensor], Tensor]:
    """The adapter's chunk decode by ``vae``: the pipeline's own, or a replica of it on another
    device (``run.devices``), seen as the pipeline's VAE."""
    return functools.partial(adapter.decode, pipe if vae is pipe.vae else _WithVae(pipe, vae))


@dataclass(frozen=True)
class StockCall:
    """What one guided call of a stock pipeline decided before its first denoising step
    (:func:`stock_call`), and the :class:`~.context.GuidanceContext` that guides it
    (:meth:`context`, once the call's step count is known).

    Attributes:
        pipe, adapter, geometry, config, run, estimators: as given to :func:`stock_call`.
        chunks: the anchors' causal latent chunks.
        decode_chunk: their decode (the adapter's by the VAE, or the tiny decoder's).
        masks: the dynamic masks of ``config.dynamic``, or ``None``.
        devices: ``run.devices`` resolved, or ``None`` for one device.
        device_gb: the memory (GiB) a plan budgets for on them
            (:func:`~geco_guide.io.devices.planning_memory_gb`), ``None`` where unknown.
        memory_plan: the plan chosen for the call (a fallback is the context's); ``None`` for a
            call that only searches (no guidance).
    """

    pipe: Any
    adapter: PipelineAdapter
    geometry: CallGeometry
    config: GuidanceConfig
    run: RunOptions
    estimators: Estimators
    chunks: list[AnchorChunk]
    decode_chunk: AnchorDecode
    masks: RefreshedMasks | None
    devices: list[torch.device] | None
    device_gb: float | None
    memory_plan: PlanChoice | None

    def context(self, num_steps: int, generator: torch.Generator | list[torch.Generator] | None = None,
                log: list[dict[str, Any]] | None = None, observer: GuidanceObserver | None = None) -> GuidanceContext:
        """The guidance of the call's ``num_steps`` steps (its ``R_t`` schedule is made for them);
        ``generator``: the call's, the source of the time-travel noise; ``log``: the list the
        records are appended to; ``observer``: watches the updates."""
        config, pipe = self.config, self.pipe
        return GuidanceContext(
            config, config.schedule(num_steps), self.chunks, decode_chunk=self.decode_chunk,
            latent_frames=functools.partial(self.adapter.frames_first, pipe, geometry=self.geometry),
            estimators=self.estimators, generator=generator, log=log, run=self.run, memory_plan=self.memory_plan,
            dynamic_masks=self.masks, devices=self.devices, observer=observer,
        )

    def particle_batch(self, particles: int) -> ParticleBatch:
        """The particle batch of a search of ``particles`` particles in this call
        (:func:`~.search.choose_particle_batch`)."""
        pipe, geometry = self.pipe, self.geometry
        scale = self.adapter.spatial_compression(pipe)
        return choose_particle_batch(
            self.config, self.run, particles, self.memory_plan,
            signature=denoiser_signature(self.adapter.denoisers(pipe)), frames=geometry.num_frames,
            height=geometry.latent_height * scale, width=geometry.latent_width * scale,
            device_gb=self.device_gb, offload=offloads_models(pipe),
            devices=len(self.devices) if self.devices else 1)

    def searcher(self, search: SearchConfig, num_steps: int, context: GuidanceContext | None, batch: int,
                 generator: torch.Generator | list[torch.Generator] | None,
                 search_generator: torch.Generator) -> ParticleSearch:
        """The :class:`~.search.ParticleSearch` of the call's ``num_steps`` steps: its particles
        scored on the anchors guidance decodes (``context``'s decode, or the plan-free one of a
        call without guidance), ``batch`` at a time; ``generator``: the particles' own;
        ``search_generator``: the resamplings'."""
        decode = context.anchor_objective.decode if context is not None else plan_anchor_decode(
            SAFE_PLAN, self.decode_chunk, self.chunks, self.devices, processes=self.run.context_parallel or 1)
        latent_frames = functools.partial(self.adapter.frames_first, self.pipe, geometry=self.geometry)
        scorer = ParticleScorer(decode, latent_frames, GeCoLoss(self.estimators, self.config.loss, check_values=False),
                                self.masks, batch)
        return ParticleSearch(search, num_steps, scorer, generator=search_generator, noise=generator, batch=batch,
                              masks=self.masks if context is not None else None)


def denoiser_signature(denoisers: Sequence[nn.Module]) -> dict[str, Any]:
    """The signature the memory plan's estimates know a stock pipeline by: its first denoiser's
    config and how many denoisers take turns (Wan 2.2 A14B's two experts)."""
    return model_signature(denoisers[0].config, experts=len(denoisers))


def stock_call(pipe: Any, adapter: PipelineAdapter, geometry: CallGeometry, config: GuidanceConfig, run: RunOptions,
               estimators: Estimators) -> StockCall:
    """One guided call of ``pipe``, checked before its first denoising step.

    Args:
        pipe: the pipeline (or a Modular pipeline's components): its ``scheduler``, ``vae``,
            execution device and the denoisers ``adapter`` finds on it.
        adapter: its family's :class:`~.adapters.PipelineAdapter`.
        geometry: the call's frame geometry (:meth:`~.adapters.PipelineAdapter.call_geometry`).
        config, run: what guidance computes and how it runs (``config.enabled``).
        estimators: the GeCo loss' models; for ``config.dynamic`` naming subjects, its
            segmenter makes their masks (:meth:`Estimators.masks_for`); its tiny decoder decodes
            the anchors with ``config.decoder="tiny"``.

    Raises:
        ValueError: (one line) anchors the video cannot contain, a loss without an update, run
            options the config cannot use, a denoiser cache, an unknown scheduler, a missing or
            mismatched tiny decoder, subjects without a segmenter, a memory plan that cannot fit.
    """
    adapter.check(pipe, geometry)
    config.check_loss()
    check_call_options(config, run)
    # the split of the denoisers (run.context_parallel), once: the hooks made it on attaching
    start_context_parallel(pipe, adapter, run, differentiates=config.enabled and config.denoiser_grad)
    denoisers = adapter.denoisers(pipe)
    check_no_denoiser_cache(denoisers)
    chunks = config.anchor_chunks(geometry.num_frames, geometry.temporal_compression)
    check_scheduler(pipe.scheduler)
    decode_chunk = anchor_decoder(config, run, functools.partial(_vae_decode_with, pipe, adapter),
                                  estimators.tiny_decoder, pipe.vae)
    home = execution_device(pipe)
    masks = guidance_mask_source(config, estimators, home)
    scale = adapter.spatial_compression(pipe)
    devices = resolve_devices(run.devices)
    device_gb = planning_memory_gb(home, devices)
    memory_plan = choose_plan(
        config, run, signature=denoiser_signature(denoisers), frames=geometry.num_frames,
        height=geometry.latent_height * scale, width=geometry.latent_width * scale, device_gb=device_gb,
        offload=offloads_models(pipe)
    ) if config.enabled else None
    return StockCall(pipe, adapter, geometry, config, run, estimators, chunks, decode_chunk, masks, devices,
                     device_gb, memory_plan)


def guide_stock_step(
    context: GuidanceContext,
    pipe: Any,
    adapter: PipelineAdapter,
    denoisers: Iterable[nn.Module],
    step: int,
    timestep: Tensor | float,
    sample: Tensor,
    model_output: Tensor,
    predict: Callable[[Tensor, bool], Tensor],
    *,
    batches: Sequence[Sequence[int]] | None = None,
    predict_rows: Callable[[Tensor, Sequence[int], bool], Tensor] | None = None,
) -> tuple[Tensor, Tensor]:
    """The ``R_t`` updates of loop step ``step`` (:meth:`GuidanceContext.guide`), with the models
    frozen and the memory plan's checkpointing on ``denoisers`` (those ``predict`` runs).

    Args:
        sample: ``z_t``, the latents the pipeline's scheduler is about to step, in its layout
            (``[B, C, F, h, w]`` for Wan, ``[B, F, C, h, w]`` for CogVideoX, tokens ``[B, S, C]`` for LTX).
        model_output: the pipeline's own (CFG-combined) model output at ``sample``, of its shape.
        predict: ``(z, differentiate) -> model output at z`` (:func:`~.step.guided_step`).
        batches, predict_rows: a search's particle sub-batches, each guided on its own
            (:meth:`GuidanceContext.guide <.context.GuidanceContext.guide>`).

    Returns:
        ``(sample, model_output)`` for ``pipe.scheduler.step``: the guided latents in fp32 (fp64
        for an fp64 pipeline: a low-precision copy would round the update away) and the model
        output there in ``model_output``'s dtype, both on ``sample``'s device. A multistep
        scheduler's history has been told to keep the update (:func:`~geco_guide.sampler.algorithm.levels.keep_update`).
    """
    scheduler = pipe.scheduler
    with context.models(denoisers, pipe.vae, adapter.frozen_modules(pipe)):
        z, out = context.guide(sample, predict, noise_levels(scheduler, timestep, step), step, int(timestep),
                               batches=batches, predict_rows=predict_rows)
    z = z.to(sample.device)
    keep_update(scheduler, sample, z)
    return (z.double() if sample.dtype == torch.float64 else z), out.to(device=sample.device, dtype=model_output.dtype)
