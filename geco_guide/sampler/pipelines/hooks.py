"""Attach GeCo guidance to stock diffusers video pipelines, without copying their code.

``attach_geco_guidance(pipe, config, estimators)`` installs three things on the pipeline
*instance* and returns a handle whose ``detach()`` (or the end of its ``with`` block) removes them
again, leaving the pipeline exactly as it was:

1. ``pipe.prepare_latents`` is wrapped (an instance attribute over the class method): every call
   of the pipeline goes through it before its first denoising step. The hook reads the frame
   geometry of the call from its arguments (and the caller's ``generator``, the source of the
   time-travel noise), checks the anchors against the video the call will make, and the latents
   the caller passed (finite, and of the call's shape where the adapter knows it), and resets its
   per-call state (one :class:`GuidanceCallState`, as diffusers' stateful hooks keep theirs). Anchors the video cannot contain and unusable latents raise ValueError here, up
   front.
2. A ``ModelHook`` in each denoiser's diffusers ``HookRegistry`` (:class:`DenoiserCapture`)
   captures each call's arguments and output: latent model input, timestep, text states, CFG
   batch layout. At the first denoiser call it validates the ``R_t`` schedule against the
   scheduler's timestep table. Registered in the registry, it composes with diffusers' own hooks
   (offloading, layerwise casting, context parallelism) as docs/architecture.md describes.
3. ``pipe.scheduler.step`` is wrapped (an instance attribute). At a step with ``R_t > 0`` the
   wrapper runs the shared guidance (:class:`~geco_guide.sampler.running.context.GuidanceContext`) on the
   ``sample`` the pipeline is about to step: it predicts ``x0`` from the captured model output (fast mode) or by
   re-running the captured denoiser calls with gradients, both CFG branches (faithful mode),
   decodes the anchor chunks, and updates ``z_t`` (time travel included). It then hands the
   original ``step`` the guided sample and the model output re-computed there, after telling a
   multistep scheduler's history to keep the update (:func:`~geco_guide.sampler.algorithm.levels.keep_update`). Steps with
   ``R_t = 0`` call the original ``step`` untouched.

The model output of a step is rebuilt from the outputs of its denoiser calls with weights fitted
on the captured outputs (CFG in one batched call or two calls, dynamic CFG, no CFG; an adapter
may override the combination, as LTX does for ``guidance_rescale``) and checked against the
output the pipeline passed: an output the calls cannot reproduce fails loudly instead of guiding
with a wrong prediction.

With a particle search (``handle.enable_search``, :mod:`.search`), a fourth piece: a ``ModelHook`` under the
capture (:class:`ParticleSplit`) runs the pipeline's own denoiser calls of the ``K`` particles in
sub-batches (dealt over ``run.devices``), the wrapped ``step`` guides the particles sub-batch by
sub-batch (the replay cut to their rows) and, at a resampling step, scores and resamples them and
carries the scheduler's per-particle state and the step's other per-particle arguments
(CogVideoX-DPM's ``old_pred_original_sample``); the VAE decodes one video at a time during the
call (its ``use_slicing``, as it was before on the next call and on detach), so that each
particle's frames are its own decode. Call the pipeline with one prompt,
``num_videos_per_prompt=K`` and a generator per particle.

Compared with ``GeCoCogVideoXPipeline``: the same guided step, schedule, time travel, fast and
faithful modes, anchors and loss, and in both the pipeline's own scheduler takes the step from
the guided sample. The difference: the latents between steps are whatever the pipeline keeps
(stock CogVideoX rounds them to the model dtype after every step, which adds rounding noise to an
update, measured in docs/guidance.md; ``GeCoCogVideoXPipeline`` keeps fp32 latents while guiding;
Wan, HunyuanVideo and LTX keep fp32 latents). The guided sample reaches the scheduler in fp32.
Denoiser caches (FirstBlockCache, FasterCache, ...) are refused while guiding, with one line
naming the cache, before any denoising step. The wrapped ``step`` shows the original signature,
so pipelines still pass ``eta`` and ``generator`` to it.
"""

from __future__ import annotations

import copy
import functools
import inspect
import types
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field, fields
from typing import Any

import torch
from diffusers.hooks import ModelHook
from diffusers.hooks.hooks import BaseState
from torch import Tensor, nn

from ...estimators.bundle import Estimators
from ...types import check_estimator_bundle, refuses_earlier_keywords
from ..algorithm.config import GuidanceConfig
from ..algorithm.slicing import check_latents
from ..algorithm.step import LatentsWatch
from ..diffusers_private import hook_registry
from ..running.context import GuidanceContext, GuidanceObserver, GuidanceReport
from ..running.context_parallel import start_context_parallel
from ..running.module_hooks import register_hook
from ..running.multi_device import module_replicas
from ..running.run_options import RunOptions, resolve_call_options
from ..search.particle_search import ParticleBatch, ParticleSearch, SearchConfig, check_search_call, resolve_search_config
from ..search.particles import (
    ParticleBatches,
    call_rows,
    deal_final_decode,
    hidden_states_of,
    output_tensor,
    particle_batches,
    particle_rows,
)
from .adapters import CallGeometry, PipelineAdapter, adapter_for, check_scheduler, fit_combination, noise_levels
from .pipeline_cogvideox import GeCoCogVideoXPipeline
from .stock_call import StockCall, guide_stock_step, stock_call

__all__ = ["CAPTURE_HOOK", "PARTICLE_HOOK", "DenoiserCapture", "GeCoGuidanceHandle", "GuidanceCallState",
           "ParticleSplit", "attach_geco_guidance"]

_MISSING = object()
#: The name of :class:`DenoiserCapture` in a denoiser's hook registry.
CAPTURE_HOOK = "geco_denoiser_capture"
#: The name of :class:`ParticleSplit` in a denoiser's hook registry (under the capture).
PARTICLE_HOOK = "geco_particle_split"


@dataclass
class _Call:
    module: nn.Module
    args: tuple
    kwargs: dict
    output: Tensor


@dataclass
class GuidanceCallState(BaseState):
    """What the hooks keep of one pipeline call, in one object (as diffusers' stateful hooks keep
    theirs in a ``BaseState``): :meth:`reset` when the call prepares its latents, filled in by
    its denoiser calls and scheduler steps, :meth:`close` on detach.

    Attributes:
        log: one dict per guided update of the call (``handle.log``; a new list each call, so the
            last call's report keeps its own).
        report: what the call decided (``handle.last``), once its denoising loop ends.
        geometry: the call's :class:`~.adapters.CallGeometry` (``handle.geometry``).
        call: the guided (or searched) call set up before its first step, ``None`` while the
            hooks have nothing to do (no call yet, guidance off without a search, detached).
        generator: the call's generator, the source of the time-travel noise.
        context: its guidance, from the first denoiser call on (it fixes the schedule).
        num_steps: the call's step count, from the first denoiser call on.
        counter: the scheduler steps taken so far.
        calls: the denoiser calls captured since the last scheduler step.
        watch: the latents seen, from the first scheduler step on.
        search_config, particle_batch, search: the call's particle search (``search`` from the
            first denoiser call on), ``None`` without.
        places: per denoiser (by id), the devices and replicas a search's particle sub-batches
            run on (:class:`ParticleSplit`).
        replaying: a guided step is re-running the captured denoiser calls (not the pipeline's own).
        vae_slicing: a search call's VAE and its ``use_slicing`` before the call.
        restore_decode: puts back a search's dealt final decode.
    """

    log: list[dict[str, Any]] = field(default_factory=list)
    report: GuidanceReport | None = None
    geometry: CallGeometry | None = None
    call: StockCall | None = None
    generator: Any = None
    context: GuidanceContext | None = None
    num_steps: int | None = None
    counter: int = 0
    calls: list[_Call] = field(default_factory=list)
    watch: LatentsWatch | None = None
    search_config: SearchConfig | None = None
    particle_batch: ParticleBatch | None = None
    search: ParticleSearch | None = None
    places: dict[int, list[tuple[torch.device | None, Any]]] = field(default_factory=dict)
    replaying: bool = False
    vae_slicing: tuple[Any, bool] | None = None
    restore_decode: Callable[[], None] | None = None

    @property
    def guiding(self) -> bool:
        """Whether the hooks act on the pipeline's denoiser calls and steps now: a call is set up
        and its own calls run (not a replay)."""
        return self.call is not None and not self.replaying

    @property
    def batches(self) -> list[list[int]] | None:
        """A search's sub-batches of particles (guided one after the other), ``None`` without."""
        if self.search_config is None:
            return None
        return particle_batches(self.search_config.particles, self.particle_batch.size)

    def close(self) -> None:
        """End the call: what a search changed on the VAE put back (its ``use_slicing``, its
        ``decode``), nothing more to act on; the report, log and geometry stay readable."""
        if self.vae_slicing is not None:
            vae, previous = self.vae_slicing
            vae.use_slicing, self.vae_slicing = previous, None
        if self.restore_decode is not None:
            self.restore_decode()
            self.restore_decode = None
        self.call = None

    def reset(self) -> None:
        """Before a new call: the last one closed, every field back to its default."""
        self.close()
        for item in fields(self):
            setattr(self, item.name, getattr(GuidanceCallState(), item.name))


def _hidden_states(args: tuple, kwargs: dict) -> tuple[Tensor, str | int]:
    return hidden_states_of(args, kwargs), "hidden_states" if "hidden_states" in kwargs else 0


class _Replay:
    """Re-run one step's captured denoiser calls at new latents and combine them as the pipeline did."""

    def __init__(self, pipe, adapter: PipelineAdapter, calls: list[_Call], sample: Tensor, model_output: Tensor,
                 step: int):
        if not calls:
            raise ValueError(
                "GeCo guidance saw no denoiser call before scheduler.step; the pipeline computes its model output "
                "in a way this hook does not know"
            )
        self.pipe, self.adapter, self.batch, self.step = pipe, adapter, sample.shape[0], step
        self.items = []
        parts: list[Tensor] = []
        for call in calls:
            hidden, key = _hidden_states(call.args, call.kwargs)
            rep, dim = self._locate(hidden, sample)
            self.items.append((call, key, hidden, rep, dim, sample.shape[dim] if dim is not None else None))
            out = output_tensor(call.output)
            if out.shape[0] != hidden.shape[0] or out.shape[1:] != sample.shape[1:]:
                raise ValueError(
                    f"denoiser output {list(out.shape)} does not match the latents {list(sample.shape)} "
                    f"(x {rep} CFG branches): register an adapter for this pipeline"
                )
            parts.extend(out.split(self.batch))
        self.weights, _ = fit_combination(parts, model_output)
        combined = adapter.combine(pipe, parts, self.weights, sample=sample, step=step)
        residual = float((combined - model_output.float()).norm() / model_output.float().norm().clamp_min(1e-30))
        low_precision = any(p.dtype not in (torch.float32, torch.float64) for p in parts) or model_output.dtype not in (
            torch.float32,
            torch.float64,
        )
        if residual > (3e-2 if low_precision else 1e-4):
            raise ValueError(
                f"GeCo guidance cannot rebuild the model output from the {len(calls)} denoiser call(s) of this step "
                f"(relative residual {residual:.2e}): the {type(pipe).__name__} combines them in a way its adapter "
                "does not know (e.g. a non-linear CFG rescale); register an adapter with its own combine()"
            )

    @staticmethod
    def _locate(hidden: Tensor, sample: Tensor) -> tuple[int, int | None]:
        batch = sample.shape[0]
        layout = f"denoiser input {list(hidden.shape)} is not laid out like the latents {list(sample.shape)}"
        if hidden.ndim != sample.ndim or hidden.shape[0] % batch:
            raise ValueError(layout)
        rep = hidden.shape[0] // batch
        diff = [d for d in range(1, sample.ndim) if hidden.shape[d] != sample.shape[d]]
        if len(diff) > 1 or (diff and hidden.shape[diff[0]] < sample.shape[diff[0]]):
            raise ValueError(layout)
        dim = diff[0] if diff else None
        latent_part = hidden if dim is None else hidden.narrow(dim, 0, sample.shape[dim])
        expected = sample.to(hidden.dtype)
        expected = torch.cat([expected] * rep) if rep > 1 else expected
        if not torch.equal(latent_part, expected.to(latent_part.device)):
            raise ValueError(
                "the denoiser input does not contain the latents the scheduler steps (a scaled or transformed "
                "model input?): register an adapter for this pipeline"
            )
        return rep, dim

    def rows(self, chosen: list[int]) -> _Replay:
        """The same replay for particles ``chosen`` of the step's batch alone: each call cut to
        their rows (:func:`~.particles.particle_rows`), ``z`` of ``len(chosen)`` videos."""
        sub = copy.copy(self)
        sub.batch, sub.items = len(chosen), []
        for call, key, hidden, rep, dim, channels in self.items:
            rows = particle_rows(self.batch, hidden.shape[0], chosen)
            args, kwargs = call_rows(call.args, call.kwargs, rows, hidden.shape[0])
            sub.items.append((_Call(call.module, args, kwargs, call.output), key, hidden[rows], rep, dim, channels))
        return sub

    def __call__(self, z: Tensor, differentiate: bool) -> Tensor:
        parts: list[Tensor] = []
        with torch.set_grad_enabled(differentiate and torch.is_grad_enabled()):
            for call, key, hidden, rep, dim, channels in self.items:
                z_in = z.to(device=hidden.device, dtype=hidden.dtype)
                z_in = torch.cat([z_in] * rep) if rep > 1 else z_in
                if dim is not None:
                    z_in = torch.cat([z_in, hidden.narrow(dim, channels, hidden.shape[dim] - channels)], dim=dim)
                args, kwargs = list(call.args), dict(call.kwargs)
                if key == "hidden_states":
                    kwargs["hidden_states"] = z_in
                else:
                    args[key] = z_in
                out = output_tensor(call.module(*args, **kwargs))
                parts.extend(out.split(self.batch))
            return self.adapter.combine(self.pipe, parts, self.weights, sample=z, step=self.step)


class DenoiserCapture(ModelHook):
    """The ``ModelHook`` that hands each call of a denoiser to the guidance ``handle``: told of the
    call before it runs (the first call of a pipeline call fixes the schedule), then given its
    arguments and output."""

    def __init__(self, handle: GeCoGuidanceHandle):
        super().__init__()
        self.handle = handle

    def new_forward(self, module: nn.Module, *args: Any, **kwargs: Any) -> Any:
        self.handle._before_denoiser_call()
        output = self.fn_ref.original_forward(*args, **kwargs)
        self.handle._after_denoiser_call(module, args, kwargs, output)
        return output


class ParticleSplit(ModelHook):
    """The ``ModelHook`` under :class:`DenoiserCapture` that runs a search's denoiser calls in
    sub-batches of particles (:class:`~.particles.ParticleBatches`, dealt over ``run.devices``):
    the capture sees, and replays, the pipeline's call as one. Calls run as they are outside a
    search, during a replay (the guidance's and the search's calls, of a sub-batch already) and
    where the call's batch holds no whole blocks of the particles."""

    def __init__(self, handle: GeCoGuidanceHandle):
        super().__init__()
        self.handle = handle

    def new_forward(self, module: nn.Module, *args: Any, **kwargs: Any) -> Any:
        state, forward = self.handle.state, self.fn_ref.original_forward
        call_places = state.places.get(id(module))  # the devices and replicas of this call's search
        if call_places is None or not state.guiding or state.search_config is None:
            return forward(*args, **kwargs)
        particles = state.search_config.particles
        if hidden_states_of(args, kwargs).shape[0] % particles:
            return forward(*args, **kwargs)
        places = [(device, forward if runner is None else runner) for device, runner in call_places]
        return ParticleBatches(particles, state.particle_batch.size, places)(*args, **kwargs)


class GeCoGuidanceHandle:
    """GeCo guidance attached to one pipeline; see :func:`attach_geco_guidance`.

    Attributes:
        pipe: the guided pipeline.
        adapter: its family's :class:`~geco_guide.sampler.pipelines.adapters.PipelineAdapter`.
        config: the :class:`GuidanceConfig` used by the next call (may be replaced between calls).
        run_options: how the next call's guidance runs (a :class:`~.run_options.RunOptions`;
            may be replaced between calls).
        estimators: the GeCo loss' models (:class:`~geco_guide.estimators.Estimators`: the
            geometry and flow estimators, and the segmenter of ``config.dynamic``'s subjects and
            the tiny decoder of ``config.decoder="tiny"`` where they are used).
        observer: a :class:`~geco_guide.sampler.running.context.GuidanceObserver` watching the next
            calls' updates, or ``None``.
        search: the particle search of the next calls (a
            :class:`~geco_guide.sampler.search.particle_search.SearchConfig`; ``None``: none), set by
            :meth:`enable_search`.
        search_generator: the generator of the search's resampling draws, set with ``search``.
        state: the current or last call's :class:`GuidanceCallState` (``last``, ``log`` and
            ``geometry`` read it).
    """

    def __init__(self, pipe, adapter: PipelineAdapter, config: GuidanceConfig, estimators: Estimators,
                 run_options: RunOptions | None = None):
        self.pipe = pipe
        self.search: SearchConfig | None = None
        self.search_generator: torch.Generator | None = None
        self.run_options = run_options if run_options is not None else RunOptions()
        self.adapter = adapter
        self.config = config
        self.estimators = estimators
        self.observer: GuidanceObserver | None = None
        self.state = GuidanceCallState()
        # per denoiser (by id): the module and its hooks' removers
        self._hooked: dict[int, tuple[nn.Module, list[Any]]] = {}
        self._schedulers: list[tuple[Any, Any]] = []
        self._saved_prepare: Any = _MISSING
        self._attached = False

    def enable_search(self, search: SearchConfig | Mapping[str, Any], generator: torch.Generator) -> None:
        """Make every following call a particle search (:mod:`.search`), guided or not
        (``config.enabled``): call the pipeline with one prompt,
        ``num_videos_per_prompt=search.particles`` and a generator per particle; ``last.search``
        says what it did.

        Args:
            search: a :class:`~geco_guide.sampler.search.particle_search.SearchConfig` or a dict of its fields.
            generator: the generator of the resamplings' draws, apart from the particles' own.

        Raises:
            ValueError: a detached handle (no call it could act on), a search without particles, or a
                ``generator`` that is no ``torch.Generator``.
        """
        if not self._attached:
            raise ValueError("this guidance handle is detached (detach() or the end of its with block): a search "
                             "would act on no call; attach_geco_guidance(pipe, ...) again and enable it on that handle")
        resolved = resolve_search_config(search)
        if resolved is None:
            raise ValueError("enable_search needs search.particles (a number of particles); "
                             "disable_search() samples without one")
        if not isinstance(generator, torch.Generator):
            raise ValueError("a search draws its resamplings from a generator of its own: pass a torch.Generator, "
                             f"got {type(generator).__name__}")
        self.search, self.search_generator = resolved, generator

    def disable_search(self) -> None:
        """Sample the following calls without a particle search."""
        self.search, self.search_generator = None, None

    @property
    def log(self) -> list[dict[str, Any]]:
        """One dict per guided update of the current or last call (``step, repeat, t, loss, motion,
        structure, fused, grad_norm, seconds, time_travel, skipped``); ``last.log`` once it ends."""
        return self.state.log

    @property
    def last(self) -> GuidanceReport | None:
        """What the last call decided (:class:`~geco_guide.sampler.running.context.GuidanceReport`),
        ``None`` before one; set when its denoising loop ends."""
        return self.state.report

    @property
    def geometry(self) -> CallGeometry | None:
        """The :class:`~geco_guide.sampler.pipelines.adapters.CallGeometry` of the last call."""
        return self.state.geometry

    # ------------------------------------------------------------------------------------------
    # install / remove

    @property
    def attached(self) -> bool:
        return self._attached

    def _attach(self) -> None:
        pipe = self.pipe
        # the split first (run.context_parallel), so that the hooks registered below wrap it
        start_context_parallel(pipe, self.adapter, self.run_options,
                               differentiates=self.config.enabled and self.config.denoiser_grad)
        self._saved_prepare = pipe.__dict__.get("prepare_latents", _MISSING)
        original_prepare = pipe.prepare_latents
        signature = inspect.signature(original_prepare)

        def prepare_latents(*args, **kwargs):
            bound = signature.bind(*args, **kwargs)
            bound.apply_defaults()
            result = original_prepare(*args, **kwargs)
            latents = result[0] if isinstance(result, tuple) else result
            self._begin_call(dict(bound.arguments), latents)
            return result

        prepare_latents._geco_handle = self  # type: ignore[attr-defined]
        pipe.prepare_latents = prepare_latents
        for module in self.adapter.denoisers(pipe):
            self._register_hooks(module)
        self._patch_scheduler(pipe.scheduler)
        self._attached = True

    def _register_hooks(self, module: nn.Module) -> None:
        """The particle split (inner) and the capture (outer) in ``module``'s hook registry."""
        removers = [register_hook(module, ParticleSplit(self), PARTICLE_HOOK)]
        removers.append(register_hook(module, DenoiserCapture(self), CAPTURE_HOOK))
        self._hooked[id(module)] = (module, removers)

    def _remove_hooks(self, module: nn.Module) -> None:
        _, removers = self._hooked.pop(id(module))
        for remove in reversed(removers):
            remove()

    def _replicas(self, module: nn.Module, devices: list[torch.device]) -> list[nn.Module]:
        """Copies of ``module`` on ``devices`` (the module itself where it lives), made without our
        hooks (a copied registry would still call the original's forward)."""
        self._remove_hooks(module)
        try:
            if "forward" in module.__dict__ or hook_registry(module) is not None:
                raise ValueError(f"run.devices deals a search's particles over copies of the {type(module).__name__}, "
                                 "which cannot carry the hooks it has (offloading, caches, ...): remove them, or leave "
                                 "run.devices unset")
            return module_replicas(module, devices)
        finally:
            self._register_hooks(module)

    def _patch_scheduler(self, scheduler) -> None:
        if any(s is scheduler for s, _ in self._schedulers):
            return
        previous = scheduler.__dict__.get("step", _MISSING)
        original = scheduler.step
        signature = inspect.signature(original)

        @functools.wraps(original)
        def step(stepped, *args, **kwargs):
            if stepped is not scheduler:  # a deep copy (LTX-2's audio scheduler): it steps itself, unguided
                return type(stepped).step(stepped, *args, **kwargs)
            return self._step(scheduler, original, signature, args, kwargs)

        # functools.wraps keeps the name and docstring; the explicit signature keeps what pipelines
        # inspect to decide which extra arguments to pass (``prepare_extra_step_kwargs``: ``eta``,
        # ``generator``): a bare (*args, **kwargs) would make them silently drop both.
        step.__signature__ = signature.replace(  # type: ignore[attr-defined]
            parameters=[inspect.Parameter("stepped", inspect.Parameter.POSITIONAL_ONLY), *signature.parameters.values()])
        step._geco_handle = self  # type: ignore[attr-defined]
        # bound to the scheduler, so that a deep copy of it (copy.deepcopy rebinds methods to the
        # copy) calls the wrapper with the copy instead of stepping this scheduler twice
        scheduler.step = types.MethodType(step, scheduler)
        self._schedulers.append((scheduler, previous))

    def detach(self) -> None:
        """Remove every hook and wrapper; the pipeline is exactly as before :func:`attach_geco_guidance`."""
        if not self._attached:
            return
        for module, _ in list(self._hooked.values()):
            self._remove_hooks(module)
        if self._saved_prepare is _MISSING:
            del self.pipe.__dict__["prepare_latents"]
        else:
            self.pipe.__dict__["prepare_latents"] = self._saved_prepare
        for scheduler, previous in self._schedulers:
            if previous is _MISSING:
                del scheduler.__dict__["step"]
            else:
                scheduler.__dict__["step"] = previous
        self._schedulers.clear()
        self.state.close()
        self._attached = False

    def __enter__(self) -> "GeCoGuidanceHandle":
        return self

    def __exit__(self, *exc) -> None:
        self.detach()

    # ------------------------------------------------------------------------------------------
    # per call

    def _begin_call(self, args: dict[str, Any], latents: Tensor) -> None:
        config, run = self.config, self.run_options
        geometry = self.adapter.call_geometry(self.pipe, args, latents)
        state = self.state
        state.reset()
        state.geometry = geometry
        search = resolve_search_config(self.search)
        if not config.enabled and search is None:
            state.report = GuidanceReport(scheduler=type(self.pipe.scheduler).__name__)
            return
        check_latents(args.get("latents"), self.adapter.latents_shape(self.pipe, args),
                      f"this {type(self.pipe).__name__} call")
        check_hook_run_options(run)
        generator = args.get("generator")
        if search is not None:
            check_search_call(search, run, generator, self.search_generator)
            if latents.shape[0] != search.particles:
                raise ValueError(f"search.particles={search.particles}: call the {type(self.pipe).__name__} with one "
                                 f"prompt and num_videos_per_prompt={search.particles} (its batch is the particles), "
                                 f"got a batch of {latents.shape[0]}")
        call = stock_call(self.pipe, self.adapter, geometry, config, run, self.estimators)
        state.generator, state.search_config = generator, search
        if search is not None:
            state.particle_batch = call.particle_batch(search.particles)
            vae = getattr(self.pipe, "vae", None)
            if hasattr(vae, "use_slicing"):  # the final videos one at a time: each particle's frames its own
                state.vae_slicing = (vae, vae.use_slicing)
                vae.use_slicing = True
            for module, _ in list(self._hooked.values()):
                places: list[tuple[Any, Any]] = [(None, None)]  # the call's own device and forward
                if call.devices:
                    replicas = self._replicas(module, call.devices)
                    places = [(device, None if replica is module else replica)
                              for device, replica in zip(call.devices, replicas)]
                state.places[id(module)] = places
        state.call = call  # last: a call that failed its checks leaves the hooks nothing to act on

    def _before_denoiser_call(self) -> None:
        state = self.state
        if not state.guiding:
            return
        if state.context is None and state.search is None:  # first denoiser call of this pipeline call
            pipe = self.pipe
            self._patch_scheduler(pipe.scheduler)
            check_scheduler(pipe.scheduler)
            num_steps = state.num_steps = len(pipe.scheduler.timesteps)
            if state.call.config.enabled:
                state.context = state.call.context(num_steps, state.generator, state.log, self.observer)
            if state.search_config is not None:
                state.search = state.call.searcher(state.search_config, num_steps, state.context,
                                                   state.particle_batch.size, state.generator, self.search_generator)

    def _after_denoiser_call(self, module: nn.Module, args: tuple, kwargs: dict, output: Any) -> None:
        state = self.state
        if not state.guiding:
            return
        state.calls.append(_Call(module, tuple(args), dict(kwargs), output_tensor(output).detach()))

    def _step(self, scheduler, original, signature, args, kwargs):
        state = self.state
        if not state.guiding or scheduler is not self.pipe.scheduler:
            return original(*args, **kwargs)
        bound = signature.bind(*args, **kwargs)
        i = state.counter
        state.counter += 1
        calls, state.calls = state.calls, []
        schedule = state.context.schedule if state.context is not None else None
        repeats = schedule.repeats_at(i) if schedule is not None and i < schedule.num_steps else 0
        searching = state.search is not None and state.search.resamples_at(i)
        if repeats == 0 and not searching:
            result = original(*args, **kwargs)
        else:
            model_output = bound.arguments["model_output"]
            sample = bound.arguments["sample"]
            timestep = bound.arguments["timestep"]
            self._watch_latents(state, sample, i, check=True)  # a callback may have set them since the last step
            replay = _Replay(self.pipe, self.adapter, calls, sample, model_output, i)
            predict_rows = self._predict_rows(replay, sample, model_output)
            if repeats:
                sample, model_output = self._guide(state, i, timestep, sample, model_output, replay, predict_rows)
            if searching:  # the step's other per-particle arguments (CogVideoX-DPM's old_pred_original_sample)
                others = [name for name, value in bound.arguments.items() if name not in ("model_output", "sample")
                          and isinstance(value, Tensor) and value.shape == sample.shape]
                sample, model_output, carried = state.search.step(
                    i, timestep, sample, model_output, noise_levels(scheduler, timestep, i), predict_rows, scheduler,
                    [bound.arguments[name] for name in others])
                bound.arguments.update(zip(others, carried))
            bound.arguments["sample"], bound.arguments["model_output"] = sample, model_output
            result = original(*bound.args, **bound.kwargs)
        # NaN latents are refused at a guided or searched step (its log already waited for the
        # device) and at the last step, before the pipeline decodes NaN frames
        latents = result[0] if isinstance(result, tuple) else getattr(result, "prev_sample", None)
        last_step = state.num_steps is None or i >= state.num_steps - 1
        self._watch_latents(state, latents, i, check=repeats > 0 or searching or last_step)
        if last_step and (state.context is not None or state.search is not None):
            report = (state.context.report(scheduler) if state.context is not None
                      else GuidanceReport(scheduler=type(scheduler).__name__))
            if state.search is not None:
                masks = state.call.masks
                report.mask_source = None if masks is None else masks.source_name  # what its scores left out
                report.search = {**state.search.report(state.search_config.particles),
                                 "particle_batch": state.particle_batch.to_dict()}
                vae = getattr(self.pipe, "vae", None)
                if state.call.devices and vae is not None:
                    state.restore_decode = deal_final_decode(vae, state.call.devices)
                    report.search["final_decode_devices"] = [str(device) for device in state.call.devices]
            state.report = report
        return result

    @staticmethod
    def _watch_latents(state: GuidanceCallState, latents: Any, i: int, check: bool) -> None:
        """Note the latents of step ``i`` in the call's :class:`LatentsWatch`; with ``check``, raise
        NonFiniteLatentsError if any seen so far held NaN or inf."""
        if not isinstance(latents, Tensor):
            return
        if state.watch is None:
            state.watch = LatentsWatch(state.num_steps if state.num_steps is not None else i + 1)
        state.watch.see(latents, i)
        if check:
            state.watch.check()

    def _predict_rows(self, replay: _Replay, sample: Tensor, model_output: Tensor):
        """``(z, rows, differentiate) -> model output`` of particles ``rows`` at ``z``: the step's
        denoiser calls replayed for them alone (the pipeline's own output where ``z`` is the
        sample it stepped from and no gradient is asked for)."""
        start = sample.detach().float()

        def predict_rows(z: Tensor, rows: list[int], differentiate: bool) -> Tensor:
            index = torch.as_tensor(rows, device=start.device)
            if not differentiate and torch.equal(z.to(start.device), start[index]):
                return model_output[index.to(model_output.device)].float()
            self.state.replaying = True
            try:
                return replay.rows(rows)(z, differentiate)
            finally:
                self.state.replaying = False

        return predict_rows

    def _guide(self, state: GuidanceCallState, i: int, timestep, sample, model_output, replay: _Replay, predict_rows):
        pipe, adapter = self.pipe, self.adapter
        start = sample.detach().float()

        def predict(z: Tensor, differentiate: bool) -> Tensor:
            if not differentiate and torch.equal(z, start):
                return model_output.float()  # the pipeline's own prediction at this very sample
            self.state.replaying = True
            try:
                return replay(z, differentiate)
            finally:
                self.state.replaying = False

        denoisers = {id(item[0].module): item[0].module for item in replay.items}.values()
        return guide_stock_step(state.context, pipe, adapter, denoisers, i, timestep, sample, model_output, predict,
                                batches=state.batches, predict_rows=predict_rows)


def check_hook_run_options(run: RunOptions) -> None:
    """ValueError (one line) for run options the hooks cannot act on: ``run.split_cfg`` splits the
    denoiser calls of ``GeCoCogVideoXPipeline``, and the hooks leave a pipeline's own calls as they
    are (the option would do nothing)."""
    if run.split_cfg:
        raise ValueError("run.split_cfg splits the denoiser calls of GeCoCogVideoXPipeline; the hooks leave a "
                         "pipeline's own denoiser calls as they are: use run.split_cfg=false here")


@refuses_earlier_keywords(
    "attach_geco_guidance",
    decoder="the tiny decoder is Estimators(..., tiny_decoder=...)",
    dynamic_masks="the segmenter is Estimators(..., segmenter=...); what moves is config.dynamic",
    search="a search is handle.enable_search(SearchConfig(...), generator) on the handle this returns")
def attach_geco_guidance(
    pipe,
    config: GuidanceConfig | Mapping[str, Any] | None = None,
    estimators: Estimators | None = None,
    run_options: RunOptions | Mapping[str, Any] | None = None,
) -> GeCoGuidanceHandle:
    """Guide every following call of a stock diffusers video pipeline with GeCo.

    Args:
        pipe: a pipeline of a class the model registry names (:mod:`geco_guide.families`, each
            entry's ``pipeline``; :func:`geco_guide.sampler.pipelines.adapters.supported_pipelines`), a
            subclass, or a class registered with :func:`geco_guide.sampler.pipelines.adapters.register_adapter`.
        config: a :class:`GuidanceConfig` or a dict of fields over the default one. Its
            ``repeats`` schedule must cover the call's ``num_inference_steps``; its anchors are
            pixel frames of the output video.
        estimators: the GeCo loss' models as one :class:`~geco_guide.estimators.Estimators`
            (e.g. of :func:`~geco_guide.estimators.load_estimators`): the geometry and flow
            estimators, the text segmenter of the subjects ``config.dynamic`` names (``"auto"``
            needs none; docs/guidance.md, Moving subjects) and the tiny decoder of
            ``config.decoder="tiny"`` (a :class:`~geco_guide.estimators.tiny_decoder.TinyDecoder`
            of the pipeline's family, which decodes the loss' anchor frames; the video is always
            the VAE's).
        run_options: how the guidance runs on this machine (a
            :class:`~geco_guide.sampler.running.run_options.RunOptions` or a dict of its fields: memory
            plan, decode layout, devices).

    Returns:
        A :class:`GeCoGuidanceHandle`; ``handle.detach()`` (or leaving ``with handle:``)
        restores the pipeline exactly. ``handle.log`` holds the current or last call's guidance
        log, ``handle.last`` what the last call decided. ``handle.enable_search(...)`` makes the
        following calls a particle search, with or without guidance.

    Raises:
        ValueError: an unsupported pipeline (naming the supported ones and how to register an
            adapter), estimators that lack a method, run options the hooks cannot act on, or a
            pipeline that already has GeCo guidance attached.
        TypeError: estimators that are no bundle, or passed by an earlier keyword (``geometry=``,
            ``flow_estimator=``, ``decoder=``, ``dynamic_masks=``).
    """
    if isinstance(pipe, GeCoCogVideoXPipeline):
        raise ValueError(
            "GeCoCogVideoXPipeline guides itself: pass guidance=... to its call instead of attaching a hook"
        )
    adapter = adapter_for(pipe)
    config, run_options = resolve_call_options(None, config, None, run_options)
    check_estimator_bundle(estimators, "attach_geco_guidance", argument="estimators")
    check_hook_run_options(run_options)
    current = pipe.__dict__.get("prepare_latents")
    if getattr(current, "_geco_handle", None) is not None:
        raise ValueError("this pipeline already has GeCo guidance attached; detach() it first")
    handle = GeCoGuidanceHandle(pipe, adapter, config, estimators, run_options)
    handle._attach()
    return handle
