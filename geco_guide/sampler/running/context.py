"""The guidance of one call, shared by :class:`GeCoCogVideoXPipeline` and the pipeline hooks.

A :class:`GuidanceContext` composes three parts that each do one job:

* the objective of an update (:class:`~.objective.AnchorObjective`: decode the anchor frames
  with the memory plan's strategy of :mod:`.anchor_decode`, then score them with the GeCo loss);
* the execution (:class:`GuidanceExecution`): the models frozen and the checkpointing of the
  call's memory plan (:mod:`.memory_plan`) switched on in its :meth:`~GuidanceExecution.models`
  block, and, after an out-of-memory error at the call's first update, the next plan and that
  update again (same generator state, so the same video), decided once for every device;
* the log (:class:`GuidanceLog`): one :class:`~.step.GuidanceRecord` per update.

:meth:`GuidanceContext.guide` runs :func:`~.step.guided_step` at one step of the loop with them,
and :meth:`GuidanceContext.report` says what the call decided (:class:`GuidanceReport`: the log,
the memory plan, the devices, the decoder, the masks), which the pipeline returns in its output
and the hooks' handle keeps as ``handle.last``. Profilers watch a call through one public seam, a
:class:`GuidanceObserver` passed to the call: what the updates score, the updates of each step,
each update's record.
"""

from __future__ import annotations

import contextlib
import gc
import logging
import math
import time
from collections.abc import Callable, Iterable, Iterator, Sequence
from dataclasses import asdict, dataclass, field
from typing import Any, TypeVar

import torch
from torch import Tensor, nn

from ...estimators.bundle import Estimators
from ...estimators.tiny_decoder import TinyDecoder
from ...loss.cues import CUES
from ...loss.geco import GeCoLoss
from ..algorithm.config import GuidanceConfig
from ..algorithm.dynamic import RefreshedMasks
from ..algorithm.levels import NoiseLevels
from ..algorithm.objective import AnchorObjective
from ..algorithm.schedule import GuidanceSchedule
from ..algorithm.slicing import AnchorChunk
from ..algorithm.step import GuidanceRecord, Objective, Update, guided_step, read_scalars
from ..diffusers_private import supports_gradient_checkpointing
from .anchor_decode import AnchorDecode, plan_anchor_decode
from .fast_decode import guidance_decode
from .memory_plan import MemoryPlan, PlanChoice, explicit_plan
from .run_options import RunOptions

__all__ = ["GuidanceContext", "GuidanceExecution", "GuidanceLog", "GuidanceObserver", "GuidanceReport",
           "decoder_note", "estimator_checkpointing", "frozen", "generator_states", "gradient_checkpointing",
           "partial_checkpointing"]

logger = logging.getLogger(__name__)

T = TypeVar("T")


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
    if not enable or not supports_gradient_checkpointing(model) or model.is_gradient_checkpointing:
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


class GuidanceObserver:
    """Watches the updates of a guided call without changing them: the one seam of profilers and
    measurements (pass one to the pipeline's call, ``observer=``, or set ``handle.observer`` of the
    hooks). Each method does nothing by default; override the ones you need.
    """

    def objective(self, anchor_objective: AnchorObjective, plan: MemoryPlan) -> Objective:
        """What the updates score: by default ``anchor_objective`` itself (decode the anchors of
        ``x0``, then the GeCo loss). Called when the memory plan is chosen, and again with the new
        plan after an out-of-memory fallback; a wrapper must return what it wraps returns."""
        return anchor_objective

    @contextlib.contextmanager
    def step(self, step: int, t: int) -> Iterator[None]:
        """Around the ``R_t`` updates of denoising step ``step`` (timestep ``t``), their backward
        passes included."""
        yield

    def on_update(self, record: GuidanceRecord) -> None:
        """After each update, with its record (read from the device once, see :func:`~.step.read_scalars`)."""


def decoder_note(decoder: str, estimators: Estimators) -> str:
    """What decoded the loss' anchor frames, for the record: the VAE, or the estimators' tiny
    decoder of its variant and the file it came from (else its id in the bundle, ``tiny-random``
    for the stand-in)."""
    tiny_decoder = estimators.tiny_decoder
    if decoder != "tiny" or tiny_decoder is None:
        return "vae (the model's own)"
    origin = tiny_decoder.checkpoint_file or estimators.sources.get("tiny_decoder") or "random"
    return f"TinyDecoder({tiny_decoder.variant.name}) from {origin}"


@dataclass
class GuidanceReport:
    """What one guided call decided: the pipeline's output carries it (``output.report``), the
    hooks' handle keeps the last (``handle.last``), and a sidecar is written from it.

    Attributes:
        guidance: the resolved :class:`GuidanceConfig` of the call (a dict), ``None`` without guidance.
        log: one dict per guided update (``step, repeat, t, loss, motion, structure, fused,
            grad_norm, seconds, time_travel, skipped, valid_fraction``; with dynamic masks ``masked_fraction`` and
            ``mask_source``).
        memory_plan: the memory plan the call ran with (:meth:`PlanChoice.to_dict
            <geco_guide.sampler.running.memory_plan.PlanChoice.to_dict>`, after any fallback).
        devices: the devices its anchor decode was dealt over (``run.devices``), ``None`` for one.
        scheduler: the class of the scheduler that stepped.
        decoder: what decoded the loss' anchor frames (:func:`decoder_note`).
        mask_source: where the dynamic masks came from, ``None`` without.
        masked_fraction: the mean fraction of the anchor frames' pixels masked over the updates,
            ``None`` without masks.
        search: what a particle search did (:meth:`ParticleSearch.report
            <geco_guide.sampler.search.particle_search.ParticleSearch.report>`), ``None`` without one.
    """

    guidance: dict[str, Any] | None = None
    log: list[dict[str, Any]] = field(default_factory=list)
    memory_plan: dict[str, Any] | None = None
    devices: list[str] | None = None
    scheduler: str | None = None
    decoder: str | None = None
    mask_source: str | None = None
    masked_fraction: float | None = None
    search: dict[str, Any] | None = None

    def to_dict(self) -> dict[str, Any]:
        return asdict(self)


class GuidanceLog:
    """The guidance log of a call: one :class:`~.step.GuidanceRecord` per update, appended to
    :attr:`records` as a dict and passed to :attr:`on_record`.

    Args:
        records: the list the records are appended to (a new one by default).
        on_record: called with each record as it is logged.
        observer: told of each record after ``on_record`` (:meth:`GuidanceObserver.on_update`).
    """

    def __init__(self, records: list[dict[str, Any]] | None = None,
                 on_record: Callable[[GuidanceRecord], None] | None = None,
                 observer: GuidanceObserver | None = None):
        self.records = records if records is not None else []
        self.on_record, self.observer = on_record, observer or GuidanceObserver()

    def recorder(self, step: int, t: int, device: torch.device, mask_source: str | None = None,
                 particles: Sequence[int] | None = None) -> Callable[[Update], None]:
        """The ``on_update`` of :func:`~.step.guided_step` at step ``step`` (timestep ``t``): each
        update's numbers read to ``device``'s host and logged; ``mask_source``: the dynamic masks'
        source, ``None`` without masks; ``particles``: the search's particles it guides, ``None``
        outside a search."""

        def on_update(update: Update) -> None:
            scalars = read_scalars(update.terms, device)
            record = GuidanceRecord(
                step=step,
                repeat=update.repeat,
                t=int(t),
                loss=scalars["loss"],
                **{cue: scalars.get(cue) for cue in CUES},
                grad_norm=scalars["grad_norm"],
                seconds=time.perf_counter() - update.started,
                time_travel=update.time_travel,
                skipped=not scalars["finite"],
                valid_fraction=scalars.get("valid_fraction"),
                masked_fraction=scalars.get("masked_fraction"),
                mask_source=mask_source,
                particles=None if particles is None else [particles[0], particles[-1]],
            )
            self.records.append(record.to_dict())
            if self.on_record is not None:
                self.on_record(record)
            self.observer.on_update(record)

        return on_update


class GuidanceExecution:
    """How the guidance of one call runs: the models frozen, the guidance decode's layout, the
    checkpointing switches of the memory plan, and the fallback to the plan's next one after an
    out-of-memory error at the call's first update. One decision for the call on every device:
    the decoder replicas of other devices are copied with the switches on.

    Args:
        config: the call's :class:`GuidanceConfig` (which decoder; whether the denoiser is
            differentiated).
        run: how the call runs (:class:`~.run_options.RunOptions`; default: the defaults): its
            decode layout and compilation, and the explicit flags ``memory_plan`` defaults to.
        memory_plan: the call's :class:`~.memory_plan.PlanChoice` (default: ``run``'s explicit
            flags, no fallback); :attr:`memory_plan` is the one in use (after a fallback, the new one).
        estimators: the loss' estimators: frozen, their checkpointing switched.
        on_plan: called with the new :class:`~.memory_plan.MemoryPlan` after a fallback, with its
            switches on (the anchor decode is picked again there).
    """

    def __init__(self, config: GuidanceConfig, run: RunOptions | None = None, memory_plan: PlanChoice | None = None,
                 estimators: Sequence[Any] = (), on_plan: Callable[[MemoryPlan], None] | None = None):
        self.config, self.estimators, self.on_plan = config, tuple(estimators), on_plan
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
        error: free what the failed update held, re-enter the checkpointing, tell ``on_plan``,
        say so in one line."""
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
        if self.on_plan is not None:
            self.on_plan(new)
        logger.warning("guidance: out of memory at the first update with memory plan %r; retrying it with %r",
                       failed, new.name)

    def retrying(self, attempt: Callable[[], T], generator: torch.Generator | list[torch.Generator] | None,
                 started: Callable[[], bool]) -> T:
        """``attempt()``; out of memory while not ``started()`` (no update of the call logged yet)
        and while the plan has fallbacks: :meth:`fall_back` and ``attempt()`` again, from the same
        state of ``generator`` (the call's)."""
        while True:
            states = generator_states(generator)
            try:
                return attempt()
            except torch.cuda.OutOfMemoryError:
                if started() or not self.memory_plan.fallbacks:
                    raise
            for g, state in states:
                g.set_state(state)
            self.fall_back()


class GuidanceContext:
    """The guidance of one pipeline call: its objective, execution and log, composed.

    Args:
        config: the call's resolved :class:`GuidanceConfig`.
        schedule: its :class:`GuidanceSchedule` for the call's step count.
        chunks: the anchors' causal latent chunks.
        decode_chunk: the :class:`~.anchor_decode.AnchorDecode` of the chunks (the VAE's, or the
            tiny decoder's; :func:`~.anchor_decode.anchor_decoder`).
        latent_frames: ``x0 -> [B, F, C, h, w]``: the video's latents, frames first, of the
            model's clean estimate (drops padding frames, reorders channels).
        estimators: the GeCo loss' models (:class:`~geco_guide.estimators.Estimators`).
        generator: source of the time-travel noise (the call's).
        on_record: called with each :class:`GuidanceRecord` as it is logged.
        log: the list the records are appended to as dicts (a new one by default).
        run, memory_plan: of the :class:`GuidanceExecution`; :attr:`memory_plan` is the plan in
            use (after a fallback, the new one).
        dynamic_masks: what moves on its own, left out of the loss
            (:func:`~.dynamic.guidance_mask_source`), or ``None`` (the paper: no masks).
        devices: the devices the anchor chunks are dealt over
            (:func:`~geco_guide.io.devices.resolve_devices` of ``run.devices``), each with a replica of
            ``decode_chunk``'s module, or ``None``: one device.
        observer: watches the updates (:class:`GuidanceObserver`), or ``None``.
    """

    def __init__(
        self,
        config: GuidanceConfig,
        schedule: GuidanceSchedule,
        chunks: Sequence[AnchorChunk],
        decode_chunk: AnchorDecode,
        latent_frames: Callable[[Tensor], Tensor],
        estimators: Estimators,
        *,
        generator: torch.Generator | list[torch.Generator] | None = None,
        on_record: Callable[[GuidanceRecord], None] | None = None,
        log: list[dict[str, Any]] | None = None,
        run: RunOptions | None = None,
        memory_plan: PlanChoice | None = None,
        dynamic_masks: RefreshedMasks | None = None,
        devices: Sequence[torch.device] | None = None,
        observer: GuidanceObserver | None = None,
    ):
        self.config, self.schedule, self.generator, self.dynamic_masks = config, schedule, generator, dynamic_masks
        self.estimators = estimators
        self.observer = observer or GuidanceObserver()
        self.guidance_log = GuidanceLog(log, on_record, self.observer)
        self.execution = GuidanceExecution(config, run, memory_plan, (estimators.geometry, estimators.flow),
                                           on_plan=self._use_plan)
        self._decode_chunk, self._chunks = decode_chunk, list(chunks)
        self._devices = list(devices) if devices else None
        # No frame check: it would make each update wait for the device; a NaN decode gives NaN
        # scalars and no update instead (see guided_step).
        loss_fn = GeCoLoss(estimators, config.loss, check_values=False)
        self.anchor_objective = AnchorObjective(self._anchor_decode(self.memory_plan.plan), latent_frames, loss_fn,
                                                dynamic_masks)
        self.update_objective = self.observer.objective(self.anchor_objective, self.memory_plan.plan)

    @property
    def log(self) -> list[dict[str, Any]]:
        """The guidance log: one dict per update (:meth:`GuidanceRecord.to_dict`)."""
        return self.guidance_log.records

    @property
    def on_record(self) -> Callable[[GuidanceRecord], None] | None:
        """Called with each :class:`GuidanceRecord` as it is logged (settable)."""
        return self.guidance_log.on_record

    @on_record.setter
    def on_record(self, on_record: Callable[[GuidanceRecord], None] | None) -> None:
        self.guidance_log.on_record = on_record

    @property
    def memory_plan(self) -> PlanChoice:
        """The memory plan in use (after a fallback, the new one)."""
        return self.execution.memory_plan

    def models(self, denoisers: Iterable[nn.Module], vae: Any,
               others: Iterable[Any] = ()) -> contextlib.AbstractContextManager[None]:
        """The execution's :meth:`GuidanceExecution.models` block: the models frozen (the
        estimators' tiny decoder and segmenter among them), the memory plan's checkpointing on;
        all restored on exit."""
        extra = [m for m in (self.estimators.tiny_decoder, self.estimators.segmenter) if isinstance(m, nn.Module)]
        return self.execution.models(denoisers, vae, [*others, *extra])

    def _anchor_decode(self, plan: MemoryPlan) -> Callable[[Tensor], Tensor]:
        return plan_anchor_decode(plan, self._decode_chunk, self._chunks, self._devices,
                                  processes=self.execution.run.context_parallel or 1)

    def _use_plan(self, plan: MemoryPlan) -> None:
        """After a fallback: the new plan's anchor decode (the replicas copied again, with its switches)."""
        self.anchor_objective = self.anchor_objective.with_decode(self._anchor_decode(plan))
        self.update_objective = self.observer.objective(self.anchor_objective, plan)

    def objective(self, x0: Tensor) -> tuple[Tensor, dict[str, Tensor]]:
        """What an update scores at ``x0`` (differentiable): :attr:`update_objective`, by default the
        GeCo loss of the anchor frames decoded from ``x0``; the loss and its terms."""
        return self.update_objective(x0)

    def guide(self, z: Tensor, predict: Callable[[Tensor, bool], Tensor], levels: NoiseLevels, step: int,
              t: int, *, batches: Sequence[Sequence[int]] | None = None,
              predict_rows: Callable[[Tensor, Sequence[int], bool], Tensor] | None = None) -> tuple[Tensor, Tensor]:
        """The ``R_t`` updates of step ``step`` (timestep ``t``): the guided ``z_t`` and the model
        output there (:func:`~.step.guided_step`), each update logged. Out of memory before the
        call's first update is logged: the execution's fallback and the step again
        (:meth:`GuidanceExecution.retrying`).

        A search's particles are guided in sub-batches: ``batches`` (lists of particles covering
        ``z``'s batch in order, :func:`~.particles.particle_batches`), each guided on its own as
        a call of those particles alone, its model outputs from ``predict_rows(z_rows, rows,
        differentiate)``, its time-travel noise from their generators (the call's ``k``-th for
        particle ``k``), its updates logged with their particles. The norm of an update is each
        video's, so a particle's update is its own whatever the sub-batch.
        """
        with self.observer.step(step, int(t)):
            if batches is None:
                return self.execution.retrying(lambda: self._guide(z, predict, levels, step, t, self.generator),
                                               self.generator, started=lambda: bool(self.log))
            guided, outputs = [], []
            for rows in batches:
                index = torch.as_tensor(rows, device=z.device)
                generator = [self.generator[k] for k in rows] if isinstance(self.generator, list) else self.generator
                z_rows = z[index]

                def predict_these(z_in: Tensor, differentiate: bool, rows: Sequence[int] = rows) -> Tensor:
                    return predict_rows(z_in, rows, differentiate)

                z_new, output = self.execution.retrying(
                    lambda: self._guide(z_rows, predict_these, levels, step, t, generator, rows), generator,
                    started=lambda: bool(self.log))
                guided.append(z_new)
                outputs.append(output)
            return torch.cat(guided), torch.cat(outputs)

    def _guide(self, z: Tensor, predict: Callable[[Tensor, bool], Tensor], levels: NoiseLevels, step: int, t: int,
               generator: torch.Generator | list[torch.Generator] | None,
               particles: Sequence[int] | None = None) -> tuple[Tensor, Tensor]:
        config, schedule = self.config, self.schedule
        if self.dynamic_masks is not None:
            self.dynamic_masks.start_step(step, particles[0] if particles else 0)
        on_update = self.guidance_log.recorder(
            step, t, z.device, None if self.dynamic_masks is None else self.dynamic_masks.source_name, particles)
        return guided_step(z, predict, levels, self.objective, schedule.repeats_at(step), step_size=schedule.step_size,
                           time_travel=schedule.time_travel_at(step), denoiser_grad=config.denoiser_grad,
                           generator=generator, eps=config.grad_eps, on_update=on_update)

    def report(self, scheduler: Any) -> GuidanceReport:
        """What the call decided (:class:`GuidanceReport`), once its loop is done."""
        fractions = [r["masked_fraction"] for r in self.log
                     if r.get("masked_fraction") is not None and math.isfinite(r["masked_fraction"])]
        return GuidanceReport(
            guidance=asdict(self.config),
            log=self.log,
            memory_plan=self.memory_plan.to_dict(),
            devices=[str(device) for device in self._devices] if self._devices else None,
            scheduler=type(scheduler).__name__,
            decoder=decoder_note(self.config.decoder, self.estimators),
            mask_source=None if self.dynamic_masks is None else self.dynamic_masks.source_name,
            masked_fraction=sum(fractions) / len(fractions) if fractions else None,
        )
