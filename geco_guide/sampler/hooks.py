"""Attach GeCo guidance to stock diffusers video pipelines, without copying their code.

``attach_geco_guidance(pipe, config, geometry_estimator=..., flow_estimator=...)`` installs three
things on the pipeline *instance* and returns a handle whose ``detach()`` (or the end of its
``with`` block) removes them again, leaving the pipeline exactly as it was:

1. ``pipe.prepare_latents`` is wrapped (an instance attribute over the class method): every call
   of the pipeline goes through it before its first denoising step. The hook reads the frame
   geometry of the call from its arguments (and the caller's ``generator``, the source of the
   time-travel noise), checks the anchors against the video the call will make, and the latents
   the caller passed (finite, and of the call's shape where the adapter knows it), and resets its
   per-call state. Anchors the video cannot contain and unusable latents raise ValueError here, up
   front.
2. Forward hooks on the denoiser(s) (``register_forward_pre_hook``/``register_forward_hook``
   with kwargs) capture each call's arguments and output: latent model input, timestep, text
   states, CFG batch layout. They also validate the ``R_t`` schedule against the scheduler's
   timestep table before the first denoiser call.
3. ``pipe.scheduler.step`` is wrapped (an instance attribute). At a step with ``R_t > 0`` the
   wrapper runs the shared guidance (:class:`~geco_guide.sampler.context.GuidanceContext`) on the
   ``sample`` the pipeline is about to step: it predicts ``x0`` from the captured model output (fast mode) or by
   re-running the captured denoiser calls with gradients, both CFG branches (faithful mode),
   decodes the anchor chunks, and updates ``z_t`` (time travel included). It then hands the
   original ``step`` the guided sample and the model output re-computed there, after telling a
   multistep scheduler's history to keep the update (:func:`.adapters.keep_update`). Steps with
   ``R_t = 0`` call the original ``step`` untouched.

The model output of a step is rebuilt from the outputs of its denoiser calls with weights fitted
on the captured outputs (CFG in one batched call or two calls, dynamic CFG, no CFG; an adapter
may override the combination, as LTX does for ``guidance_rescale``) and checked against the
output the pipeline passed: an output the calls cannot reproduce fails loudly instead of guiding
with a wrong prediction.

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

import functools
import inspect
import types
from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Any

import torch
from torch import Tensor, nn

from ..estimators.bundle import Estimators
from ..types import DynamicMaskSource, FlowEstimator, GeometryEstimator, missing_estimators, one_of_names
from .adapters import (
    CallGeometry,
    PipelineAdapter,
    adapter_for,
    check_no_denoiser_cache,
    check_scheduler,
    fit_combination,
    keep_update,
    noise_levels,
)
from .anchor_decode import anchor_decoder
from .config import GuidanceConfig, check_call_options, resolve_call_options
from .context import GuidanceContext
from .multi_device import resolve_devices
from .dynamic import RefreshedMasks, guidance_mask_source
from .memory_plan import PlanChoice, choose_plan, model_signature, planning_memory_gb
from .run_options import RunOptions
from .pipeline_cogvideox import GeCoCogVideoXPipeline
from .slicing import AnchorChunk, check_latents
from .step import LatentsWatch

__all__ = ["GeCoGuidanceHandle", "attach_geco_guidance"]

_MISSING = object()


@dataclass
class _Call:
    module: nn.Module
    args: tuple
    kwargs: dict
    output: Tensor


@dataclass
class _CallState:
    geometry: CallGeometry
    chunks: list[AnchorChunk]
    decode_chunk: Any  # the anchor chunks' decode (the VAE's or the tiny decoder's)
    generator: Any
    config: GuidanceConfig
    run: RunOptions
    memory_plan: PlanChoice
    dynamic_masks: RefreshedMasks | None = None
    devices: list[torch.device] | None = None  # run.devices, resolved
    context: GuidanceContext | None = None  # from the first denoiser call on (it fixes the schedule)
    counter: int = 0
    calls: list[_Call] = field(default_factory=list)
    watch: LatentsWatch | None = None  # from the first scheduler step on


class _WithVae:
    """A pipeline seen with another VAE (a replica on another device), for an adapter's decode."""

    def __init__(self, pipe: Any, vae: nn.Module):
        self._pipe, self.vae = pipe, vae

    def __getattr__(self, name: str) -> Any:
        return getattr(self._pipe, name)


def _output_tensor(output: Any) -> Tensor:
    if isinstance(output, Tensor):
        return output
    if isinstance(output, (tuple, list)):
        return output[0]
    return output.sample


def _hidden_states(args: tuple, kwargs: dict) -> tuple[Tensor, str | int]:
    if "hidden_states" in kwargs:
        return kwargs["hidden_states"], "hidden_states"
    if args and isinstance(args[0], Tensor):
        return args[0], 0
    raise ValueError("could not find the denoiser's hidden_states argument")


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
            out = _output_tensor(call.output)
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
                out = _output_tensor(call.module(*args, **kwargs))
                parts.extend(out.split(self.batch))
            return self.adapter.combine(self.pipe, parts, self.weights, sample=z, step=self.step)


class GeCoGuidanceHandle:
    """GeCo guidance attached to one pipeline; see :func:`attach_geco_guidance`.

    Attributes:
        pipe: the guided pipeline.
        adapter: its family's :class:`~geco_guide.sampler.adapters.PipelineAdapter`.
        config: the :class:`GuidanceConfig` used by the next call (may be replaced between calls).
        run_options: how the next call's guidance runs (a :class:`~.run_options.RunOptions`;
            may be replaced between calls).
        geometry_estimator, flow_estimator: the GeCo loss' estimators.
        dynamic_masks: the :class:`~geco_guide.types.DynamicMaskSource` of ``config.dynamic``
            (``None``: the automatic detector for ``"auto"``, nothing without ``config.dynamic``).
        log: one dict per guided update of the last call (``step, repeat, t, loss, motion,
            structure, fused, grad_norm, seconds, time_travel, skipped``).
        geometry: the :class:`~geco_guide.sampler.adapters.CallGeometry` of the last call.
    """

    def __init__(self, pipe, adapter: PipelineAdapter, config: GuidanceConfig, geometry_estimator, flow_estimator,
                 decoder=None, dynamic_masks=None, run_options: RunOptions | None = None):
        self.pipe = pipe
        self.run_options = run_options if run_options is not None else RunOptions()
        self.dynamic_masks = dynamic_masks
        self.decoder = decoder
        self.adapter = adapter
        self.config = config
        self.geometry_estimator = geometry_estimator
        self.flow_estimator = flow_estimator
        self.log: list[dict[str, Any]] = []
        self.geometry: CallGeometry | None = None
        self._state: _CallState | None = None
        self._replaying = False
        self._attached = False
        self._hook_handles: list[Any] = []
        self._saved_prepare = _MISSING
        self._schedulers: list[tuple[Any, Any]] = []  # (scheduler, previous instance 'step' or _MISSING)

    # ------------------------------------------------------------------------------------------
    # install / remove

    @property
    def attached(self) -> bool:
        return self._attached

    def _attach(self) -> None:
        pipe = self.pipe
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
            self._hook_handles.append(module.register_forward_pre_hook(self._pre_hook, with_kwargs=True))
            self._hook_handles.append(module.register_forward_hook(self._post_hook, with_kwargs=True))
        self._patch_scheduler(pipe.scheduler)
        self._attached = True

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
        for handle in self._hook_handles:
            handle.remove()
        self._hook_handles.clear()
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
        self._state = None
        self._attached = False

    def __enter__(self) -> "GeCoGuidanceHandle":
        return self

    def __exit__(self, *exc) -> None:
        self.detach()

    @property
    def devices(self) -> list[str] | None:
        """The devices the last guided call dealt its anchor chunks over (``run.devices``),
        ``None`` for one device or before a call."""
        state = self._state
        return [str(device) for device in state.devices] if state is not None and state.devices else None

    @property
    def memory_plan(self) -> dict[str, Any] | None:
        """The memory plan of the last guided call (:meth:`PlanChoice.to_dict
        <geco_guide.sampler.memory_plan.PlanChoice.to_dict>`, after any fallback), ``None`` before one."""
        state = self._state
        if state is None:
            return None
        return (state.context.memory_plan if state.context is not None else state.memory_plan).to_dict()

    # ------------------------------------------------------------------------------------------
    # per call

    def _begin_call(self, args: dict[str, Any], latents: Tensor) -> None:
        config, run = self.config, self.run_options
        geometry = self.adapter.call_geometry(self.pipe, args, latents)
        self.geometry = geometry
        self.log = []
        self._state = None
        if not config.enabled:
            return
        check_latents(args.get("latents"), self.adapter.latents_shape(self.pipe, args),
                      f"this {type(self.pipe).__name__} call")
        self.adapter.check(self.pipe, geometry)
        config.check_loss()
        check_call_options(config, run)
        check_no_denoiser_cache(self.adapter.denoisers(self.pipe))
        chunks = config.anchor_chunks(geometry.num_frames, geometry.temporal_compression)
        check_scheduler(self.pipe.scheduler)
        decode_chunk = anchor_decoder(config, run, self._vae_decode_with, self.decoder, self.pipe.vae)
        devices = resolve_devices(run.devices)
        masks = guidance_mask_source(config, self.dynamic_masks, self.pipe._execution_device)
        # the estimates know CogVideoX-5B, whose VAE is 8x spatially; other models get the safe plan
        scale = getattr(self.pipe, "vae_scale_factor_spatial", 8)
        memory_plan = choose_plan(
            config, run, signature=model_signature(self.adapter.denoisers(self.pipe)[0].config), frames=geometry.num_frames,
            height=geometry.latent_height * scale, width=geometry.latent_width * scale,
            device_gb=planning_memory_gb(self.pipe._execution_device, devices), offload=bool(getattr(self.pipe, "_all_hooks", None)))
        self._state = _CallState(geometry, chunks, decode_chunk, args.get("generator"), config, run, memory_plan,
                                 masks, devices)

    def _vae_decode_with(self, vae: nn.Module) -> Any:
        """The adapter's chunk decode by ``vae``: the pipeline's own, or a replica of it on another
        device (``run.devices``), seen as the pipeline's VAE."""
        return functools.partial(self.adapter.decode, self.pipe if vae is self.pipe.vae else _WithVae(self.pipe, vae))

    def _pre_hook(self, module, args, kwargs):
        state = self._state
        if state is None or self._replaying:
            return None
        if state.context is None:  # first denoiser call of this pipeline call
            pipe, adapter = self.pipe, self.adapter
            self._patch_scheduler(pipe.scheduler)
            check_scheduler(pipe.scheduler)
            state.context = GuidanceContext(
                state.config, state.config.schedule(len(pipe.scheduler.timesteps)), state.chunks,
                decode_chunk=state.decode_chunk,
                latent_frames=functools.partial(adapter.frames_first, pipe, geometry=state.geometry),
                geometry_estimator=self.geometry_estimator, flow_estimator=self.flow_estimator,
                generator=state.generator, log=self.log, run=state.run, memory_plan=state.memory_plan,
                dynamic_masks=state.dynamic_masks, devices=state.devices,
            )
        return None

    def _post_hook(self, module, args, kwargs, output):
        state = self._state
        if state is None or self._replaying:
            return None
        state.calls.append(_Call(module, tuple(args), dict(kwargs), _output_tensor(output).detach()))
        return None

    def _step(self, scheduler, original, signature, args, kwargs):
        state = self._state
        if state is None or self._replaying or scheduler is not self.pipe.scheduler:
            return original(*args, **kwargs)
        bound = signature.bind(*args, **kwargs)
        i = state.counter
        state.counter += 1
        calls, state.calls = state.calls, []
        schedule = state.context.schedule if state.context is not None else None
        repeats = schedule.repeats_at(i) if schedule is not None and i < schedule.num_steps else 0
        if repeats == 0:
            result = original(*args, **kwargs)
        else:
            model_output = bound.arguments["model_output"]
            sample = bound.arguments["sample"]
            timestep = bound.arguments["timestep"]
            self._watch_latents(state, sample, i, check=True)  # a callback may have set them since the last step
            new_sample, new_output = self._guide(scheduler, state.context, i, timestep, sample, model_output, calls)
            keep_update(scheduler, sample, new_sample)
            bound.arguments["model_output"] = new_output.to(model_output.dtype)
            # fp32 (or the pipeline's fp64): a low-precision copy would round the update away
            bound.arguments["sample"] = new_sample.double() if sample.dtype == torch.float64 else new_sample
            result = original(*bound.args, **bound.kwargs)
        # NaN latents are refused at a guided step (its log already waited for the device) and at
        # the last step, before the pipeline decodes NaN frames
        latents = result[0] if isinstance(result, tuple) else getattr(result, "prev_sample", None)
        self._watch_latents(state, latents, i, check=repeats > 0 or schedule is None or i >= schedule.num_steps - 1)
        return result

    @staticmethod
    def _watch_latents(state: _CallState, latents: Any, i: int, check: bool) -> None:
        """Note the latents of step ``i`` in the call's :class:`LatentsWatch`; with ``check``, raise
        NonFiniteLatentsError if any seen so far held NaN or inf."""
        if not isinstance(latents, Tensor):
            return
        if state.watch is None:
            state.watch = LatentsWatch(state.context.schedule.num_steps if state.context is not None else i + 1)
        state.watch.see(latents, i)
        if check:
            state.watch.check()

    def _guide(self, scheduler, context: GuidanceContext, i: int, timestep, sample, model_output, calls):
        pipe, adapter = self.pipe, self.adapter
        replay = _Replay(pipe, adapter, calls, sample, model_output, i)
        start = sample.detach().float()

        def predict(z: Tensor, differentiate: bool) -> Tensor:
            if not differentiate and torch.equal(z, start):
                return model_output.float()  # the pipeline's own prediction at this very sample
            self._replaying = True
            try:
                return replay(z, differentiate)
            finally:
                self._replaying = False

        denoisers = {id(c.module): c.module for c in calls}.values()
        with context.models(denoisers, pipe.vae, [*adapter.frozen_modules(pipe), self.decoder]):
            z, out = context.guide(sample, predict, noise_levels(scheduler, timestep, i), i, int(timestep))
        return z.to(sample.device), out.to(sample.device)


def attach_geco_guidance(
    pipe,
    config: GuidanceConfig | Mapping[str, Any] | None = None,
    *,
    run_options: RunOptions | Mapping[str, Any] | None = None,
    geometry_estimator: GeometryEstimator | None = None,
    flow_estimator: FlowEstimator | None = None,
    geometry: GeometryEstimator | None = None,
    flow: FlowEstimator | None = None,
    decoder: Any = None,
    dynamic_masks: DynamicMaskSource | None = None,
    estimators: Estimators | None = None,
) -> GeCoGuidanceHandle:
    """Guide every following call of a stock diffusers video pipeline with GeCo.

    Args:
        pipe: a ``CogVideoXPipeline`` (1.0, or 1.5 with ``patch_size_t=2``),
            ``CogVideoXImageToVideoPipeline``, ``WanPipeline``, ``LTXPipeline`` or
            ``HunyuanVideoPipeline`` (or a subclass, or a class registered with
            :func:`geco_guide.sampler.adapters.register_adapter`).
        config: a :class:`GuidanceConfig` or a dict of fields over the default one. Its
            ``repeats`` schedule must cover the call's ``num_inference_steps``; its anchors are
            pixel frames of the output video.
        run_options: how the guidance runs on this machine (a
            :class:`~geco_guide.sampler.run_options.RunOptions` or a dict of its fields: memory
            plan, decode layout, devices).
        geometry_estimator, flow_estimator: the GeCo loss' estimators (e.g. ``VGGT``, ``UFM``), as
            the components of ``GeCoCogVideoXPipeline`` are named; ``geometry=`` / ``flow=`` are
            the same arguments under their earlier names.
        estimators: the same two as one :class:`~geco_guide.estimators.Estimators` (e.g. of
            :func:`~geco_guide.estimators.load_estimators`), instead of ``geometry_estimator`` /
            ``flow_estimator``.
        decoder: the tiny decoder of ``config.decoder="tiny"``
            (:class:`~geco_guide.estimators.tiny_decoder.TinyDecoder` of the pipeline's family):
            it decodes the loss' anchor frames; the video is always the VAE's.
        dynamic_masks: what moves on its own, for ``config.dynamic``: a
            :class:`~geco_guide.types.DynamicMaskSource`, e.g.
            :func:`~geco_guide.estimators.segmenters.text_segmenter` of the subjects (``"auto"``
            needs none); see docs/guidance.md, Moving subjects.

    Returns:
        A :class:`GeCoGuidanceHandle`; ``handle.detach()`` (or leaving ``with handle:``)
        restores the pipeline exactly. ``handle.log`` holds the last call's guidance log.

    Raises:
        ValueError: an unsupported pipeline (naming the supported ones and how to register an
            adapter), missing estimators (or one given under both names), or a pipeline that
            already has GeCo guidance attached.
    """
    if isinstance(pipe, GeCoCogVideoXPipeline):
        raise ValueError(
            "GeCoCogVideoXPipeline guides itself: pass guidance=... to its call instead of attaching a hook"
        )
    geometry_estimator = one_of_names(geometry_estimator, geometry, "geometry_estimator", "geometry")
    flow_estimator = one_of_names(flow_estimator, flow, "flow_estimator", "flow")
    if estimators is not None:
        if geometry_estimator is not None or flow_estimator is not None:
            raise ValueError("pass estimators= or geometry_estimator= / flow_estimator=, not both")
        geometry_estimator, flow_estimator = estimators.geometry, estimators.flow
    adapter = adapter_for(pipe)
    config, run_options = resolve_call_options(None, config, None, run_options)
    missing = missing_estimators(geometry_estimator, flow_estimator)
    if missing:
        raise ValueError(
            f"GeCo guidance needs the {' and '.join(missing)} estimator(s): "
            "attach_geco_guidance(pipe, geometry_estimator=..., flow_estimator=...)"
        )
    current = pipe.__dict__.get("prepare_latents")
    if getattr(current, "_geco_handle", None) is not None:
        raise ValueError("this pipeline already has GeCo guidance attached; detach() it first")
    handle = GeCoGuidanceHandle(pipe, adapter, config, geometry_estimator, flow_estimator, decoder, dynamic_masks,
                                run_options)
    handle._attach()
    return handle
