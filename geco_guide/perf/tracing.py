"""Tracing a sampling call on fake tensors: FLOPs, bytes and live memory per stage, no weights, no GPU.

The real call of one step (unguided, or guided with one update) runs on fake tensors
(``FakeTensorMode``) under a :class:`CostTracker`, which counts per stage (denoiser with / without
gradients, anchor decode, VGGT, UFM, loss, final decode; forward and backward) the FLOPs
(``torch.utils.flop_counter`` formulas), bytes moved, ATen ops and the live memory
(:func:`trace_cost`). The models the GeCo pipeline guides (CogVideoX) run its own ``__call__``;
a model guided through the hooks runs its family's denoiser step
(:mod:`.denoiser_calls`) under the guidance the hooks give a stock call
(:func:`~geco_guide.sampler.pipelines.stock_call.stock_call`), then the VAE's decode of the video.
:func:`count_schedule_calls` drives the real :func:`~geco_guide.sampler.algorithm.step.guided_step` with
counting stubs over the whole schedule.
"""

from __future__ import annotations

import contextlib
import time
import weakref
from collections.abc import Callable, Iterator, Sequence
from dataclasses import replace
from typing import Any

import torch
from torch import Tensor

from ..estimators.bundle import Estimators
from ..families import VideoModel, default_anchors, model_named
from ..sampler.algorithm.config import GuidanceConfig, fused_guidance_config
from ..sampler.algorithm.levels import VPLevels
from ..sampler.algorithm.step import Update, guided_step, loss_terms
from ..sampler.running.context import GuidanceObserver
from ..sampler.running.memory_plan import model_signature
from ..sampler.running.run_options import RunOptions
from .cards import GPU_SPECS
from .full_size import CALIBRATION_MODEL, build_cost_pipeline, model_bytes, text_embed_shape
from .profile import call_marking_backward

__all__ = ["COST_STAGES", "CostTracker", "CountingObserver", "cost_guidance", "cost_run_options",
           "count_schedule_calls", "register_cpu_sdpa_flops", "settings_model", "trace_cost"]

#: Stages of the cost report; ``denoiser_cfg`` is a step's prediction without gradients (its CFG
#: calls: the unguided step, the final prediction of a guided step, fast mode's held prediction),
#: ``denoiser`` the differentiated prediction of a faithful update; ``loss`` is everything else
#: inside a guided update (GeCo loss, resizing, CFG combination, normalised update), ``other`` the
#: rest of the call.
COST_STAGES = ("denoiser_cfg", "denoiser", "anchor_decode", "vggt", "ufm", "loss", "final_decode", "other")


def register_cpu_sdpa_flops() -> None:
    """FLOP formulas for the CPU flash attention kernels (FlopCounter's registry only has the CUDA
    ones): the same counts as ``scaled_dot_product_attention`` anywhere."""
    from torch.utils import flop_counter as fc

    aten = torch.ops.aten
    if aten._scaled_dot_product_flash_attention_for_cpu in fc.flop_registry:
        return

    @fc.register_flop_formula(aten._scaled_dot_product_flash_attention_for_cpu)
    def _fwd(query_shape, key_shape, value_shape, *args, out_shape=None, **kwargs):
        return fc.sdpa_flop_count(query_shape, key_shape, value_shape)

    @fc.register_flop_formula(aten._scaled_dot_product_flash_attention_for_cpu_backward)
    def _bwd(grad_out_shape, query_shape, key_shape, value_shape, *args, out_shape=None, **kwargs):
        return fc.sdpa_backward_flop_count(grad_out_shape, query_shape, key_shape, value_shape)


def _is_attention(func: Any) -> bool:
    """Whether ATen op ``func`` is a fused attention's forward (``[B, heads, tokens, head_dim]``
    query, key and value): the SDPA kernels of every backend, not their backwards."""
    name = func._overloadpacket.__name__
    return name.startswith("_scaled_dot_product_") and "backward" not in name


def _tensor_bytes(t: Tensor) -> int:
    """Bytes of the elements of ``t`` (its view, not its storage)."""
    return t.numel() * t.element_size()


class CostTracker:
    """A ``TorchDispatchMode`` (built lazily, see :meth:`mode`) that counts, per ``(stage, kind)``
    (``kind`` = ``forward`` or ``backward``), the FLOPs of every ATen op (``torch.utils.flop_counter``
    formulas), the bytes it reads and writes (tensor arguments + outputs, views excluded) and a
    roofline time per GPU of :data:`GPU_SPECS` (``max(flops / peak, bytes / bandwidth)`` per op), and
    records the shapes of every fused attention's query and key (``attention``: what a sequence
    split over GPUs must move, :mod:`.parallel_cost`), and follows memory: every new output storage is live from its creation until a ``weakref``
    finalizer on the storage says it is freed (autograd's saved tensors keep theirs alive, so the
    graph's activations are counted); ``static`` storages (the weights) are not counted.

    Stages come from :meth:`wrap` (forward: the innermost wrapped call running; backward: from the
    first execution of an output's ``grad_fn`` to the gradient w.r.t. an input, as
    :func:`~.profile.call_marking_backward`); ops of the autograd engine run in ``backward``
    (``torch._C._current_graph_task_id() != -1``), including checkpoint recomputation.
    """

    def __init__(self, static: Sequence[Tensor] = ()) -> None:
        self.stack: list[str] = []
        self.bwd_stage: str | None = None
        self.in_update = 0
        self.flops: dict[tuple[str, str], int] = {}
        self.bytes: dict[tuple[str, str], int] = {}
        self.roofline_s: dict[str, dict[tuple[str, str], float]] = {gpu: {} for gpu in GPU_SPECS}
        self.ops: dict[tuple[str, str], int] = {}
        self.calls: dict[str, int] = {}
        self.static = {t.untyped_storage()._cdata for t in static}
        self.live: dict[int, int] = {}
        self.current = 0
        self.peak = 0
        self.peak_key: tuple[str, str] | None = None
        self.stage_peak: dict[tuple[str, str], int] = {}
        self.attention: dict[tuple[str, str], dict[tuple, int]] = {}

    def key(self) -> tuple[str, str]:
        backward = torch._C._current_graph_task_id() != -1
        if self.stack:
            stage = self.stack[-1]
        elif backward and self.bwd_stage is not None:
            stage = self.bwd_stage
        else:
            stage = "loss" if self.in_update else "other"
        return stage, "backward" if backward else "forward"

    def _free(self, key: int) -> None:
        self.current -= self.live.pop(key, 0)

    def record(self, func: Any, args: tuple, kwargs: dict, out: Any) -> None:
        from torch.utils import flop_counter as fc
        from torch.utils._pytree import tree_flatten

        key = self.key()
        formula = fc.flop_registry.get(func._overloadpacket)
        flops = int(formula(*args, **kwargs, out_val=out)) if formula is not None else 0
        outputs = [t for t in tree_flatten(out)[0] if isinstance(t, Tensor)]
        moved = 0
        if not func.is_view:
            inputs = [t for t in tree_flatten((args, kwargs))[0] if isinstance(t, Tensor)]
            moved = sum(_tensor_bytes(t) for t in inputs + outputs)
        self.flops[key] = self.flops.get(key, 0) + flops
        self.bytes[key] = self.bytes.get(key, 0) + moved
        self.ops[key] = self.ops.get(key, 0) + 1
        for gpu, spec in GPU_SPECS.items():
            seconds = max(flops / spec["bf16_flops_per_s"], moved / spec["bytes_per_s"])
            self.roofline_s[gpu][key] = self.roofline_s[gpu].get(key, 0.0) + seconds
        for t in outputs:
            storage = t.untyped_storage()
            sid = storage._cdata
            if sid in self.static or sid in self.live:
                continue
            self.live[sid] = storage.nbytes()
            self.current += self.live[sid]
            weakref.finalize(storage, self._free, sid)
        if _is_attention(func):
            shapes = (tuple(args[0].shape), tuple(args[1].shape), args[0].element_size())
            calls = self.attention.setdefault(key, {})
            calls[shapes] = calls.get(shapes, 0) + 1
        if self.current > self.peak:
            self.peak, self.peak_key = self.current, key
        self.stage_peak[key] = max(self.stage_peak.get(key, 0), self.current)

    def mode(self) -> Any:
        """The dispatch mode to enter (inside a ``FakeTensorMode``, or on real tensors)."""
        from torch.utils._python_dispatch import TorchDispatchMode

        tracker = self

        class _Mode(TorchDispatchMode):
            def __torch_dispatch__(self, func, types, args=(), kwargs=None):
                kwargs = kwargs or {}
                out = func(*args, **kwargs)
                tracker.record(func, args, kwargs, out)
                return out

        return _Mode()

    def wrap(self, obj: Any, name: str, stage: str | Callable[[], str]) -> None:
        """Label the ops of ``obj.name`` (an instance attribute replaces the method) as ``stage``
        (or ``stage()``, evaluated per call), forward and backward."""
        original = getattr(obj, name)

        def wrapper(*args: Any, **kwargs: Any) -> Any:
            label = stage() if callable(stage) else stage

            def start() -> None:
                self.bwd_stage = label

            def end() -> None:
                if self.bwd_stage == label:
                    self.bwd_stage = None

            def labelled(*args: Any, **kwargs: Any) -> Any:
                # a call: not a checkpoint's recomputation (backward), not nested in a call of the same stage
                new_call = torch._C._current_graph_task_id() == -1 and not (self.stack and self.stack[-1] == label)
                self.calls[label] = self.calls.get(label, 0) + new_call
                self.stack.append(label)
                try:
                    return original(*args, **kwargs)
                finally:
                    self.stack.pop()

            return call_marking_backward(labelled, args, kwargs, start, end)

        setattr(obj, name, wrapper)

    def summary(self) -> dict[str, Any]:
        """Per-stage FLOPs, bytes, op counts, roofline seconds and peak memory (bytes)."""
        stages: dict[str, Any] = {}
        for stage, kind in sorted(self.flops):
            entry = stages.setdefault(stage, {"calls": self.calls.get(stage, 0)})
            k = (stage, kind)
            entry[kind] = {"flops": self.flops[k], "bytes": self.bytes[k], "ops": self.ops[k],
                           "peak_live_bytes": self.stage_peak[k],
                           "roofline_s": {gpu: self.roofline_s[gpu][k] for gpu in GPU_SPECS}}
        attention = {"/".join(key): [{"query": list(q), "key": list(k), "element_bytes": size, "calls": n}
                                     for (q, k, size), n in calls.items()] for key, calls in self.attention.items()}
        return {"stages": stages, "peak_live_bytes": self.peak,
                "peak_at": "/".join(self.peak_key) if self.peak_key else None, "attention": attention}


def settings_model(settings: dict[str, Any]) -> VideoModel:
    """The registry model a cost trace's ``settings`` trace (the tiny preset: the CogVideoX
    family's stand-in, compressed as CogVideoX-5B)."""
    return model_named(CALIBRATION_MODEL if settings["preset"] == "tiny" else settings["model"])


def cost_guidance(settings: dict[str, Any], mode: str, repeats: str, time_travel: list[int] | None) -> GuidanceConfig | bool:
    """The guidance of a cost trace or count: the preset's config with the run's settings."""
    if mode == "unguided":
        return False
    from ..tiny import tiny_guidance_config  # the tiny models pull in transformers: only when asked for

    # the fused loss (gradients through VGGT too): the costlier of the two presets, what was measured
    base = tiny_guidance_config() if settings["preset"] == "tiny" else fused_guidance_config()
    chunk_latents = settings.get("chunk_latents")
    anchors = default_anchors(settings["frames"], settings_model(settings).temporal_compression)
    return replace(base, anchors=anchors, repeats=repeats, time_travel=time_travel,
                   denoiser_grad=mode == "faithful", decoder=settings.get("decoder", "vae"),
                   chunk_latents=base.chunk_latents if chunk_latents is None else chunk_latents)


def cost_run_options(settings: dict[str, Any]) -> RunOptions:
    """How the guidance of a cost trace runs: a named plan sets every checkpointing flag, the
    estimators' too; else the preset's flags with the run's changes, as given."""
    from ..tiny import tiny_run_options  # the tiny models pull in transformers: only when asked for

    base = tiny_run_options() if settings["preset"] == "tiny" else RunOptions()
    changes = {k: settings[k] for k in ("vae_checkpointing", "vae_block_checkpointing", "denoiser_checkpointing")
               if settings.get(k) is not None}
    return replace(base, memory_plan=settings.get("plan") or "explicit",
                   vae_checkpointing=changes.get("vae_checkpointing", base.vae_checkpointing),
                   vae_block_checkpointing=changes.get("vae_block_checkpointing", base.vae_block_checkpointing),
                   gradient_checkpointing=changes.get("denoiser_checkpointing", base.gradient_checkpointing))


class CountingObserver(GuidanceObserver):
    """Watches the updates of a call traced on fake tensors: the ops inside the updates of a step
    count as ``loss`` unless a wrapped stage claims them (:attr:`CostTracker.in_update`)."""

    def __init__(self, tracker: CostTracker) -> None:
        self.tracker = tracker

    @contextlib.contextmanager
    def step(self, step: int, t: int) -> Iterator[None]:
        self.tracker.in_update += 1
        try:
            yield
        finally:
            self.tracker.in_update -= 1


def _traced_models(pipe: Any, estimators: Estimators) -> dict[str, Any]:
    """The models of a traced call by the names the reports give their weights."""
    return {"transformer": pipe.transformer, "transformer_2": getattr(pipe, "transformer_2", None), "vae": pipe.vae,
            "geometry_estimator": estimators.geometry, "flow_estimator": estimators.flow,
            "text_encoder": getattr(pipe, "text_encoder", None), "guidance_decoder": estimators.tiny_decoder}


def trace_cost(settings: dict[str, Any], mode: str) -> dict[str, Any]:
    """One pipeline call of 1 step on fake tensors, counted by a :class:`CostTracker`: unguided (one
    step's prediction and the final decode) or guided with ``R = 1`` (one update of ``mode``, the
    step's final prediction, the final decode); see the module docstring for what runs."""
    from torch._subclasses.fake_tensor import FakeTensorMode

    register_cpu_sdpa_flops()
    fake_mode = FakeTensorMode(allow_non_fake_inputs=True)
    pipe, call, estimators = build_cost_pipeline(settings, fake_mode)
    models = _traced_models(pipe, estimators)
    weights = [t for m in models.values() if isinstance(m, torch.nn.Module) for t in [*m.parameters(), *m.buffers()]]
    tracker = CostTracker(static=weights)
    tracker.wrap(pipe.vae, "decode", lambda: "final_decode" if "final_decode" in tracker.stack else "anchor_decode")
    if estimators.tiny_decoder is not None:
        tracker.wrap(estimators.tiny_decoder, "decode", "anchor_decode")
    if mode != "unguided":
        tracker.wrap(estimators.geometry, "estimate_geometry", "vggt")
        tracker.wrap(estimators.flow, "estimate_flow", "ufm")
    guidance = cost_guidance(settings, mode, "1", None)
    stock = settings["preset"] != "tiny" and model_named(settings["model"]).guided_by != "pipeline"
    trace = _trace_stock_step if stock else _trace_pipeline_call
    start = time.perf_counter()
    frames_shape = trace(settings, pipe, call, estimators, tracker, fake_mode, guidance)
    summary = tracker.summary()
    summary.update(trace_s=time.perf_counter() - start, output_shape=frames_shape,
                   weights_bytes={name: model_bytes(m) for name, m in models.items()},
                   signature=model_signature(pipe.transformer.config,
                                             experts=2 if models["transformer_2"] is not None else 1),
                   guided_updates=1 if guidance is not False else 0)
    return summary


def _trace_pipeline_call(settings: dict[str, Any], pipe: Any, call: dict[str, Any], estimators: Estimators,
                         tracker: CostTracker, fake_mode: Any, guidance: GuidanceConfig | bool) -> list[int]:
    """The real ``GeCoCogVideoXPipeline.__call__`` of one step on fake tensors; its output's shape.
    Fake tensors have no values, so the scheduler's timestep table is built outside the fake mode
    and ``scheduler.step`` gets the real timestep."""
    from torch._subclasses.fake_tensor import unset_fake_temporarily

    tracker.wrap(pipe.transformer, "forward", lambda: "denoiser" if torch.is_grad_enabled() else "denoiser_cfg")
    tracker.wrap(pipe, "decode_latents", "final_decode")
    scheduler, table = pipe.scheduler, {"timesteps": [], "i": 0}
    set_timesteps, step = scheduler.set_timesteps, scheduler.step

    def set_timesteps_real(*args: Any, **kwargs: Any) -> Any:
        with unset_fake_temporarily():
            out = set_timesteps(*args, **kwargs)
        table.update(timesteps=scheduler.timesteps.tolist(), i=0)
        return out

    def step_real(model_output: Tensor, timestep: Any, *args: Any, **kwargs: Any) -> Any:
        t = table["timesteps"][table["i"]]
        table["i"] += 1
        return step(model_output, t, *args, **kwargs)

    scheduler.set_timesteps, scheduler.step = set_timesteps_real, step_real
    with fake_mode, tracker.mode():
        if settings["preset"] != "tiny":
            dtype = getattr(torch, settings["dtype"])
            shape = text_embed_shape(settings["model"])
            call["prompt_embeds"], call["negative_prompt_embeds"] = (torch.empty(shape, dtype=dtype) for _ in range(2))
        out = pipe(**call, num_inference_steps=1, guidance=guidance, run_options=cost_run_options(settings),
                   guidance_scale=settings["guidance_scale"], estimators=estimators if guidance is not False else None,
                   observer=CountingObserver(tracker))
        frames_shape = list(out.frames.shape)
        del out
    return frames_shape


class _Step:
    """The traced step's prediction and final decode, as methods the tracker labels."""

    def __init__(self, predict: Callable[[Tensor, bool], Tensor], decode: Callable[[Tensor], Tensor]):
        self.predict, self.final_decode = predict, decode


def _trace_stock_step(settings: dict[str, Any], pipe: Any, call: dict[str, Any], estimators: Estimators,
                      tracker: CostTracker, fake_mode: Any, guidance: GuidanceConfig | bool) -> list[int]:
    """One step of a stock pipeline on fake tensors (:func:`~.denoiser_calls.denoiser_step`): its
    prediction, or with ``guidance`` the update the hooks make at a guided step
    (:func:`~geco_guide.sampler.pipelines.stock_call.stock_call`'s context, the models frozen and the memory
    plan's checkpointing on, as :func:`~geco_guide.sampler.pipelines.stock_call.guide_stock_step` runs it)
    and the prediction there; then the VAE's decode of the video through the family's adapter, as
    the pipeline decodes it. The scheduler's own step is left out (a few element-wise ops). Returns
    the decoded video's shape."""
    from ..sampler.pipelines.adapters import adapter_for
    from ..sampler.pipelines.stock_call import stock_call
    from .denoiser_calls import denoiser_step

    model = model_named(settings["model"])
    adapter = adapter_for(pipe)
    dtype = getattr(torch, settings["dtype"])
    # the pipeline's call runs without gradients; guidance turns them on where it differentiates
    with fake_mode, tracker.mode(), torch.no_grad():
        step = denoiser_step(pipe, model, settings["frames"], settings["height"], settings["width"], dtype)

        def decode(z: Tensor) -> Tensor:
            return adapter.decode(pipe, adapter.frames_first(pipe, z, step.geometry))

        labelled = _Step(step.predict, decode)
        tracker.wrap(labelled, "predict", lambda: "denoiser" if torch.is_grad_enabled() else "denoiser_cfg")
        tracker.wrap(labelled, "final_decode", "final_decode")
        z = step.sample
        if guidance is False:
            labelled.predict(z, False)
        else:
            stock = stock_call(pipe, adapter, step.geometry, guidance, cost_run_options(settings), estimators)
            context = stock.context(1, generator=torch.Generator(), observer=CountingObserver(tracker))
            with context.models(adapter.denoisers(pipe), pipe.vae, adapter.frozen_modules(pipe)):
                z, _ = context.guide(z, labelled.predict, step.levels, 0, 999)
        frames_shape = list(labelled.final_decode(z.detach()).shape)
    return frames_shape


def count_schedule_calls(mode: str, settings: dict[str, Any]) -> dict[str, int]:
    """How often each unit of work runs in a whole sampling call (``settings["steps"]`` steps, the
    guidance schedule of the preset with the run's time travel, scaled to the steps by
    :meth:`GuidanceConfig.schedule`): the real :func:`guided_step` driven by counting stubs
    (R_t = 0 steps make the pipeline's single CFG call). Returns ``steps``, ``updates``,
    ``denoiser_cfg`` (calls without gradients), ``denoiser_grad`` and ``time_travel_updates``."""
    steps = settings["steps"]
    counts = {"steps": steps, "updates": 0, "denoiser_cfg": 0, "denoiser_grad": 0, "time_travel_updates": 0}
    if mode == "unguided":
        counts["denoiser_cfg"] = steps
        return counts
    config = cost_guidance(settings, mode, settings["repeats"], settings["time_travel"])
    schedule = config.schedule(steps)

    def predict(z: Tensor, differentiate: bool) -> Tensor:
        counts["denoiser_grad" if differentiate and torch.is_grad_enabled() else "denoiser_cfg"] += 1
        return z * 0.5

    def on_update(update: Update) -> None:
        counts["updates"] += 1
        counts["time_travel_updates"] += update.time_travel

    for i in range(steps):
        repeats = schedule.repeats_at(i)
        if repeats == 0:
            counts["denoiser_cfg"] += 1
            continue
        guided_step(torch.ones(1, 4), predict, VPLevels(0.5, 0.6), lambda x0: loss_terms((x0**2).sum()), repeats,
                    step_size=config.step_size, time_travel=schedule.time_travel_at(i), denoiser_grad=config.denoiser_grad,
                    on_update=on_update)
    return counts


