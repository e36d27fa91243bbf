"""The cost model of a sampling call: FLOPs, bytes, memory and a roofline time, on fake tensors.

The real pipeline call of one step (unguided, or guided with one update) runs on fake tensors
(``FakeTensorMode``: no weights, no GPU) under a :class:`CostTracker`, which counts per stage
(denoiser with / without gradients, anchor decode, VGGT, UFM, loss, final decode; forward and
backward) the FLOPs (``torch.utils.flop_counter`` formulas), bytes moved, ATen ops and the live
memory. :func:`count_schedule_calls` drives the real :func:`~geco_guide.sampler.step.guided_step`
with counting stubs over the schedule; :func:`whole_run_costs` combines units and counts, and
:func:`cost_report` adds a roofline time on the cards of :data:`GPU_SPECS` with one efficiency
calibrated on the measured unguided H200 step (always at the size that was measured, so that a
smaller video predicts less time). :func:`compare_with_measured` sets it against a
``sampling`` report.
"""

from __future__ import annotations

import contextlib
import functools
import json
import time
import weakref
from collections.abc import Callable, Iterator, Sequence
from dataclasses import replace
from pathlib import Path
from typing import Any

import torch
from torch import Tensor

from ..sampler.config import GuidanceConfig, fused_guidance_config
from ..sampler.context import GuidanceObserver
from ..sampler.levels import VPLevels
from ..sampler.memory_plan import model_signature
from ..sampler.run_options import RunOptions
from ..sampler.schedule import PAPER_REPEATS, PAPER_TIME_TRAVEL
from ..families import default_anchors, model_named
from ..sampler.step import Update, guided_step, loss_terms
from .measure import GIB, environment_info
from .full_size import FULL_SIZE_VIDEO, TEXT_EMBED_SHAPE, build_cost_pipeline, model_bytes
from .profile import call_marking_backward

__all__ = ["AUTO_MASK_REFRESH_S", "GPU_SPECS", "H200_UNGUIDED_STEP_S", "INTERCONNECT_BYTES_PER_S",
           "NOMINAL_STEPS", "CostTracker", "at_calibration_size", "calibration_call_roofline_s",
           "compare_with_measured", "cost_report", "cost_settings", "cost_table", "count_schedule_calls",
           "CountingObserver", "dynamic_mask_costs", "dynamic_masks_table", "load_measured",
           "sam3_refresh_cost", "several_gpus", "several_gpus_table", "trace_cost"]

NOMINAL_STEPS = 50

#: The cards the cost model predicts for: memory (GB = 1e9 bytes), dense (no sparsity) bf16
#: tensor-core peak with fp32 accumulation, and memory bandwidth, from the vendor's data sheets:
#: NVIDIA H200 SXM (141 GB, 989.4 TFLOP/s, 4.8 TB/s), NVIDIA H100 SXM (80 GB, 989.4, 3.35 TB/s),
#: NVIDIA L40S (48 GB, 362.05, 864 GB/s), NVIDIA RTX A6000 (48 GB, 154.8, 768 GB/s), NVIDIA
#: GeForce RTX 4090 (24 GB, 165.2 with fp32 accumulation per the Ada Lovelace architecture
#: whitepaper, 1008 GB/s), NVIDIA L4 (24 GB, 121, 300 GB/s).
GPU_SPECS: dict[str, dict[str, float]] = {
    "H200": {"bf16_flops_per_s": 989.4e12, "bytes_per_s": 4.8e12, "memory_gb": 141},
    "H100": {"bf16_flops_per_s": 989.4e12, "bytes_per_s": 3.35e12, "memory_gb": 80},
    "L40S": {"bf16_flops_per_s": 362.05e12, "bytes_per_s": 864e9, "memory_gb": 48},
    "A6000": {"bf16_flops_per_s": 154.8e12, "bytes_per_s": 768e9, "memory_gb": 48},
    "RTX4090": {"bf16_flops_per_s": 165.2e12, "bytes_per_s": 1008e9, "memory_gb": 24},
    "L4": {"bf16_flops_per_s": 121e12, "bytes_per_s": 300e9, "memory_gb": 24},
}
#: Measured on the H200 (docs/benchmarks/sampling_full_h200_*.json): one unguided CFG step of the
#: CogVideoX-5B transformer at 49x480x720, steady state (steps 2-4 of the three unguided arms).
H200_UNGUIDED_STEP_S = 1.78
#: The settings of that measurement: the efficiency is the roofline time of one CFG call at this size
#: over the measured step, whatever size a report traces (a report of another size reuses it).
CALIBRATION_SETTINGS = {"preset": "full", **FULL_SIZE_VIDEO, "dtype": "bfloat16"}
#: Stages of the cost report; ``denoiser_cfg`` is a CFG call without gradients (the unguided step,
#: the final prediction of a guided step, fast mode's held prediction), ``denoiser`` the
#: differentiated call of a faithful update; ``loss`` is everything else inside a guided update
#: (GeCo loss, resizing, CFG combination, normalised update), ``other`` the rest of the call.
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


def _tensor_bytes(t: Tensor) -> int:
    """Bytes of the elements of ``t`` (its view, not its storage)."""
    return t.numel() * t.element_size()


class CostTracker:
    """A ``TorchDispatchMode`` (built lazily, see :meth:`mode`) that counts, per ``(stage, kind)``
    (``kind`` = ``forward`` or ``backward``), the FLOPs of every ATen op (``torch.utils.flop_counter``
    formulas), the bytes it reads and writes (tensor arguments + outputs, views excluded) and a
    roofline time per GPU of :data:`GPU_SPECS` (``max(flops / peak, bytes / bandwidth)`` per op), and
    follows memory: every new output storage is live from its creation until a ``weakref``
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
        return {"stages": stages, "peak_live_bytes": self.peak,
                "peak_at": "/".join(self.peak_key) if self.peak_key else None}


def cost_guidance(settings: dict[str, Any], mode: str, repeats: str, time_travel: list[int] | None) -> GuidanceConfig | bool:
    """The guidance of a cost trace or count: the preset's config with the run's settings."""
    if mode == "unguided":
        return False
    from ..tiny import tiny_guidance_config  # the tiny models pull in transformers: only when asked for

    # the fused loss (gradients through VGGT too): the costlier of the two presets, what was measured
    base = tiny_guidance_config() if settings["preset"] == "tiny" else fused_guidance_config()
    chunk_latents = settings.get("chunk_latents")
    anchors = default_anchors(settings["frames"], model_named("cogvideox-5b").temporal_compression)
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


def trace_cost(settings: dict[str, Any], mode: str) -> dict[str, Any]:
    """One pipeline call of 1 step on fake tensors, counted by a :class:`CostTracker`: unguided (one
    CFG step and the final decode) or guided with ``R = 1`` (one update of ``mode``, the step's final
    prediction, the final decode). The call is the real ``GeCoCogVideoXPipeline.__call__``; fake
    tensors have no values, so the scheduler's timestep table is built outside the fake mode,
    ``scheduler.step`` gets the real timestep, and the guidance context
    (:func:`counting_context_class`) reads no scalars."""
    from torch._subclasses.fake_tensor import FakeTensorMode, unset_fake_temporarily

    register_cpu_sdpa_flops()
    fake_mode = FakeTensorMode(allow_non_fake_inputs=True)
    pipe, call, estimators = build_cost_pipeline(settings, fake_mode)
    models = {"transformer": pipe.transformer, "vae": pipe.vae, "geometry_estimator": estimators.geometry,
              "flow_estimator": estimators.flow, "text_encoder": pipe.text_encoder,
              "guidance_decoder": estimators.tiny_decoder}
    weights = [t for m in models.values() if isinstance(m, torch.nn.Module) for t in [*m.parameters(), *m.buffers()]]
    tracker = CostTracker(static=weights)

    tracker.wrap(pipe.transformer, "forward", lambda: "denoiser" if torch.is_grad_enabled() else "denoiser_cfg")
    tracker.wrap(pipe.vae, "decode", lambda: "final_decode" if "final_decode" in tracker.stack else "anchor_decode")
    tracker.wrap(pipe, "decode_latents", "final_decode")
    if estimators.tiny_decoder is not None:
        tracker.wrap(estimators.tiny_decoder, "decode", "anchor_decode")
    if mode != "unguided":
        tracker.wrap(estimators.geometry, "estimate_geometry", "vggt")
        tracker.wrap(estimators.flow, "estimate_flow", "ufm")

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
    guidance = cost_guidance(settings, mode, "1", None)
    start = time.perf_counter()
    with fake_mode, tracker.mode():
        if settings["preset"] != "tiny":
            dtype = getattr(torch, settings["dtype"])
            call["prompt_embeds"], call["negative_prompt_embeds"] = (
                torch.empty(TEXT_EMBED_SHAPE, dtype=dtype) for _ in range(2))
        out = pipe(**call, num_inference_steps=1, guidance=guidance, run_options=cost_run_options(settings),
                   guidance_scale=6.0, estimators=estimators if mode != "unguided" else None,
                   observer=CountingObserver(tracker))
        frames_shape = list(out.frames.shape)
        del out
    summary = tracker.summary()
    summary.update(trace_s=time.perf_counter() - start, output_shape=frames_shape,
                   weights_bytes={name: model_bytes(m) for name, m in models.items()},
                   signature=model_signature(pipe.transformer.config),
                   guided_updates=1 if mode != "unguided" else 0)
    return summary


def at_calibration_size(settings: dict[str, Any]) -> bool:
    """Whether ``settings`` trace the model, size and dtype of the measured step (:data:`CALIBRATION_SETTINGS`)."""
    return all(settings.get(key) == value for key, value in CALIBRATION_SETTINGS.items())


@functools.cache
def calibration_call_roofline_s() -> float:
    """H200 roofline seconds of one CFG call of the full-size denoiser at :data:`CALIBRATION_SETTINGS`
    (one unguided call traced on fake tensors, a few seconds, once per process)."""
    settings = cost_settings(preset="full", steps=1, frames=None, height=None, width=None, dtype=None)
    cfg = trace_cost(settings, "unguided")["stages"]["denoiser_cfg"]
    return _roofline(cfg, "H200") / cfg["calls"]


def sam3_refresh_cost(num_frames: int = 4, dtype: torch.dtype = torch.bfloat16) -> dict[str, Any]:
    """Predicted cost of one refresh of ``guidance.dynamic`` subject masks by SAM 3 (the default
    segmenter): its vision encoder on the ``num_frames`` anchor frames at its input size,
    traced on fake tensors (the default ``Sam3VideoConfig``, weights in ``dtype``), seconds per
    card with the cost model's one efficiency (:func:`calibration_call_roofline_s`).

    A lower bound: the text encoder, the DETR heads and the tracker's propagation (per subject,
    per frame) make data-dependent calls that fake tensors cannot trace, and are not counted; the
    vision encoder is the bulk of a frame's work (the encoder runs once per frame,
    whatever the subjects).
    """
    from torch._subclasses.fake_tensor import FakeTensorMode
    from transformers import Sam3VideoConfig, Sam3VideoModel

    from .full_size import to_fake

    config = Sam3VideoConfig()
    with torch.device("meta"):
        model = Sam3VideoModel(config).to(dtype).eval()
    fake_mode = FakeTensorMode(allow_non_fake_inputs=True)
    to_fake(model.detector_model.vision_encoder, fake_mode)
    tracker = CostTracker()
    size = config.image_size
    with fake_mode, torch.no_grad(), tracker.mode():
        model.detector_model.vision_encoder(torch.zeros(num_frames, 3, size, size, dtype=dtype))
    stage = tracker.summary()["stages"]["other"]
    efficiency = calibration_call_roofline_s() / H200_UNGUIDED_STEP_S
    return {"frames": num_frames, "input_size": size, "flops": stage["forward"]["flops"],
            "time_s": {gpu: stage["forward"]["roofline_s"][gpu] / efficiency for gpu in GPU_SPECS},
            "counted": "SAM 3's vision encoder on the anchor frames (a lower bound; see sam3_refresh_cost)"}


#: Measured: one refresh of the automatic masks (``guidance.dynamic=auto``,
#: :class:`~geco_guide.estimators.motion_masks.MotionMasks`) on 4 anchor frames of 480x720, with
#: exact depth and flow, on one thread of this project's 2-core CPU machine (median of 3; 0.76-0.80 s
#: on 2 threads). It runs on what GeCo already estimated: no model of its own.
AUTO_MASK_REFRESH_S = 0.68


def dynamic_mask_costs(num_steps: int = NOMINAL_STEPS, refresh: int = 1) -> dict[str, Any]:
    """The predicted overhead of ``guidance.dynamic`` on the paper's schedule of ``num_steps``
    steps with masks refreshed every ``refresh``-th guided step: per refresh, per whole run and
    per update, for SAM 3 (:func:`sam3_refresh_cost`, per card) and the automatic masks
    (:data:`AUTO_MASK_REFRESH_S`, on the CPU whatever the card)."""
    from ..sampler.schedule import GuidanceSchedule, scale_schedule

    repeats, time_travel = scale_schedule(PAPER_REPEATS, PAPER_TIME_TRAVEL, num_steps)
    per_step = GuidanceSchedule.build(repeats, num_steps, time_travel=time_travel).repeats
    guided_steps = [step for step, r in enumerate(per_step) if r > 0]
    refreshes, updates = len(guided_steps[::refresh]), sum(per_step)
    sam3 = sam3_refresh_cost()

    def overhead(seconds: float) -> dict[str, float]:
        return {"refresh_s": seconds, "run_s": seconds * refreshes, "per_update_s": seconds * refreshes / updates}

    return {"steps": num_steps, "refreshes": refreshes, "updates": updates,
            "sam3": {"counted": sam3["counted"], **{gpu: overhead(t) for gpu, t in sam3["time_s"].items()}},
            "auto": {"counted": "measured on one CPU thread (AUTO_MASK_REFRESH_S)", **overhead(AUTO_MASK_REFRESH_S)}}


def dynamic_masks_table(costs: dict[str, Any]) -> str:
    """Markdown: :func:`dynamic_mask_costs` per card (SAM 3) and for the automatic masks."""
    rows = [f"dynamic masks: {costs['refreshes']} refreshes, {costs['updates']} updates ({costs['steps']} steps)",
            "| masks | card | per refresh (s) | per run (s) | per update (s) |", "|---|---|---|---|---|"]
    rows += [f"| SAM 3 (predicted, lower bound) | {gpu} | {c['refresh_s']:.3f} | {c['run_s']:.1f} | {c['per_update_s']:.3f} |"
             for gpu, c in costs["sam3"].items() if gpu != "counted"]
    auto = costs["auto"]
    rows.append(f"| auto (measured, one CPU thread) | any | {auto['refresh_s']:.2f} | {auto['run_s']:.1f} | "
                f"{auto['per_update_s']:.3f} |")
    return "\n".join(rows)


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


def _flops(stage: dict[str, Any], kind: str | None = None) -> int:
    kinds = (kind,) if kind else ("forward", "backward")
    return sum(stage.get(k, {}).get("flops", 0) for k in kinds)


def _ops(stage: dict[str, Any]) -> int:
    return sum(stage.get(k, {}).get("ops", 0) for k in ("forward", "backward"))


def _roofline(stage: dict[str, Any], gpu: str) -> float:
    return sum(stage.get(k, {}).get("roofline_s", {}).get(gpu, 0.0) for k in ("forward", "backward"))


def whole_run_costs(unguided: dict[str, Any], guided: dict[str, Any] | None, counts: dict[str, int],
                    counts_unguided: dict[str, int]) -> dict[str, Any]:
    """Whole-run totals from the traced units and the schedule counts.

    Units: a CFG call without gradients (``denoiser_cfg``, per call, from the unguided trace), one
    guided update (every stage of the guided trace's update except its ``denoiser_cfg`` calls: the
    differentiated denoiser call, anchor decode, VGGT, UFM, loss, forward and backward), and per
    call once: ``final_decode`` and ``other`` (latents, rotary tables, scheduler step; tiny).
    """
    cfg = unguided["stages"]["denoiser_cfg"]
    cfg_calls = cfg["calls"]
    per_call = {"flops": _flops(cfg) / cfg_calls, "ops": _ops(cfg) / cfg_calls,
                "roofline_s": {gpu: _roofline(cfg, gpu) / cfg_calls for gpu in GPU_SPECS}}
    once = {s: unguided["stages"].get(s, {}) for s in ("final_decode", "other")}

    def totals(trace: dict[str, Any] | None, c: dict[str, int]) -> dict[str, Any]:
        stages: dict[str, dict[str, Any]] = {}
        stages["denoiser_cfg"] = {"count": c["denoiser_cfg"], "flops_forward": c["denoiser_cfg"] * per_call["flops"],
                                  "flops_backward": 0, "ops": c["denoiser_cfg"] * per_call["ops"],
                                  "roofline_s": {g: c["denoiser_cfg"] * per_call["roofline_s"][g] for g in GPU_SPECS}}
        if trace is not None:
            for name in ("denoiser", "anchor_decode", "vggt", "ufm", "loss"):
                s = trace["stages"].get(name, {})
                stages[name] = {"count": c["updates"], "flops_forward": c["updates"] * _flops(s, "forward"),
                                "flops_backward": c["updates"] * _flops(s, "backward"), "ops": c["updates"] * _ops(s),
                                "roofline_s": {g: c["updates"] * _roofline(s, g) for g in GPU_SPECS}}
        for name, s in once.items():
            stages[name] = {"count": 1, "flops_forward": _flops(s, "forward"), "flops_backward": _flops(s, "backward"),
                            "ops": _ops(s),
                            "roofline_s": {g: _roofline(s, g) for g in GPU_SPECS}}
        total = sum(s["flops_forward"] + s["flops_backward"] for s in stages.values())
        return {"stages": stages, "flops": total, "ops": sum(s["ops"] for s in stages.values()),
                "roofline_s": {g: sum(s["roofline_s"][g] for s in stages.values()) for g in GPU_SPECS}}

    return {"unguided": totals(None, counts_unguided), "guided": totals(guided, counts) if guided else None,
            "cfg_call": per_call}


def cost_settings(*, preset: str, steps: int | None, frames: int | None, height: int | None, width: int | None,
                  dtype: str | None, no_time_travel: bool = False, paper_schedule: bool = False, seed: int = 0,
                  chunk_latents: int | None = None, vae_checkpointing: bool | None = None,
                  vae_block_checkpointing: bool | None = None,
                  denoiser_checkpointing: bool | None = None, estimator_checkpointing: bool = False,
                  vae_tiling: bool = False, calibration_step_s: float = H200_UNGUIDED_STEP_S,
                  decoder: str = "vae", plan: str | None = None) -> dict[str, Any]:
    """The settings of a cost report, the presets' defaults filled in (``None``: the preset's).
    ``decoder`` decodes the anchor frames (``guidance.decoder``): the VAE, or ``tiny``: the TAEHV
    tiny decoder of the published widths (random weights on fake tensors, like every model here).
    ``plan``: a named memory plan (:data:`~geco_guide.sampler.memory_plan.PLANS`), which sets every
    checkpointing flag (the estimators' too) over the flags given; ``None``: the flags as given.

    Full size: 49x480x720 bfloat16, the paper's 50-step schedule. Tiny: 17x32x48 float32 and the
    tiny preset's 4-step schedule, or the paper's 50-step one with ``paper_schedule``.
    """
    if preset == "tiny":
        from ..tiny import TINY_HEIGHT, TINY_NUM_FRAMES, TINY_WIDTH, tiny_guidance_config

        video = {"frames": TINY_NUM_FRAMES, "height": TINY_HEIGHT, "width": TINY_WIDTH}
        base = tiny_guidance_config()
        repeats, time_travel, dtype = base.repeats, base.time_travel, dtype or "float32"
        default_steps = 4
        if paper_schedule:
            repeats, time_travel, default_steps = PAPER_REPEATS, list(PAPER_TIME_TRAVEL), NOMINAL_STEPS
    else:
        video = dict(FULL_SIZE_VIDEO)
        repeats, time_travel, default_steps = PAPER_REPEATS, list(PAPER_TIME_TRAVEL), NOMINAL_STEPS
        dtype = dtype or "bfloat16"
    video.update({k: v for k, v in (("frames", frames), ("height", height), ("width", width)) if v is not None})
    return {"preset": preset, **video, "dtype": dtype, "steps": default_steps if steps is None else steps,
            "repeats": repeats, "time_travel": None if no_time_travel else time_travel, "seed": seed,
            "chunk_latents": chunk_latents, "vae_checkpointing": vae_checkpointing,
            "vae_block_checkpointing": vae_block_checkpointing, "plan": plan,
            "denoiser_checkpointing": denoiser_checkpointing, "estimator_checkpointing": estimator_checkpointing,
            "vae_tiling": vae_tiling, "decoder": decoder, "calibration_step_s": calibration_step_s, "guidance_scale": 6.0,
            "note": "shape-only: fake tensors (FakeTensorMode), no weights; estimator trunks in dtype, heads float32"}


def cost_report(settings: dict[str, Any], mode: str, argv: Sequence[str] = ()) -> dict[str, Any]:
    """Trace the units, count the schedule, combine; the JSON report of ``cost`` for ``settings``
    (:func:`cost_settings`)."""
    start = time.perf_counter()
    unguided = trace_cost(settings, "unguided")
    guided = trace_cost(settings, mode) if mode != "unguided" else None
    counts_unguided = count_schedule_calls("unguided", settings)
    counts = count_schedule_calls(mode, settings) if mode != "unguided" else counts_unguided
    run = whole_run_costs(unguided, guided, counts, counts_unguided)
    main = guided or unguided
    weights = sum(main["weights_bytes"].values())
    calibration = settings["calibration_step_s"]
    # one efficiency for every op, from the measured unguided step on the H200 at the size measured:
    # calibrating at the traced size would give every size the measured step's time
    reference = (run["cfg_call"]["roofline_s"]["H200"] if at_calibration_size(settings)
                 else calibration_call_roofline_s())
    efficiency = reference / calibration
    wall = {}
    for gpu in GPU_SPECS:
        wall[gpu] = {arm: (r["roofline_s"][gpu] / efficiency if r else None) for arm, r in
                     (("unguided", run["unguided"]), ("guided", run["guided"]))}
    per_stage = {}
    for name, s in (run["guided"] or run["unguided"])["stages"].items():
        per_stage[name] = {**{k: v for k, v in s.items() if k != "roofline_s"},
                           "flops": s["flops_forward"] + s["flops_backward"],
                           "time_s": {gpu: s["roofline_s"][gpu] / efficiency for gpu in GPU_SPECS}}
    unit = {}
    for arm, trace in (("unguided", unguided), ("guided", guided)):
        if trace is None:
            continue
        unit[arm] = {name: {kind: {k: v[k] for k in ("flops", "bytes", "ops", "peak_live_bytes")}
                            for kind, v in s.items() if kind in ("forward", "backward")} | {"calls": s["calls"]}
                     for name, s in trace["stages"].items()}
    flops_u, flops_g = run["unguided"]["flops"], (run["guided"] or run["unguided"])["flops"]
    report = {
        "subcommand": "cost",
        "argv": list(argv),
        "mode": mode,
        "settings": settings,
        "flops_unguided": flops_u,
        "flops_guided": flops_g if guided else None,
        "flops_ratio_guided_over_unguided": flops_g / flops_u if guided else None,
        "ops_unguided": run["unguided"]["ops"],
        "ops_guided": run["guided"]["ops"] if guided else None,
        "ops_ratio_guided_over_unguided": run["guided"]["ops"] / run["unguided"]["ops"] if guided else None,
        "peak_memory_gb": (weights + main["peak_live_bytes"]) / GIB,
        "peak_memory_gb_unguided": (sum(unguided["weights_bytes"].values()) + unguided["peak_live_bytes"]) / GIB,
        "peak_at": main["peak_at"],
        "signature": main["signature"],
        "weights_gb": {k: v / GIB for k, v in main["weights_bytes"].items()},
        "activations_peak_gb": main["peak_live_bytes"] / GIB,
        "per_stage": per_stage,
        "counts": counts,
        "unit_traces": unit,
        "roofline": {
            "gpus": GPU_SPECS,
            "efficiency": efficiency,
            "efficiency_note": (f"one efficiency for all ops: the roofline time of one unguided CFG call of "
                                f"CogVideoX-5B at 49x480x720 bfloat16 on the H200 over the measured {calibration} s "
                                f"(docs/benchmarks/sampling_full_h200_*.json), whatever size is traced"),
            "roofline_s_at_peak": {gpu: {arm: (r["roofline_s"][gpu] if r else None) for arm, r in
                                         (("unguided", run["unguided"]), ("guided", run["guided"]))} for gpu in GPU_SPECS},
            "wall_time_s": wall,
            "ratio_guided_over_unguided": {gpu: (wall[gpu]["guided"] / wall[gpu]["unguided"] if guided else None)
                                           for gpu in GPU_SPECS},
        },
        "trace_s": {"unguided": unguided["trace_s"], "guided": guided["trace_s"] if guided else None},
        "elapsed_s": time.perf_counter() - start,
        "environment": environment_info(torch.get_num_threads()),
    }
    return report


#: One direction's bandwidth between two GPUs of one node (bytes/s), from the data sheets: NVLink 4 on
#: the H200 and H100 SXM (900 GB/s both ways), PCIe 4.0 x16 for the PCIe cards (32 GB/s; an A6000
#: pair's NVLink bridge is faster, the common node has none).
INTERCONNECT_BYTES_PER_S = {"H200": 450e9, "H100": 450e9, "L40S": 32e9, "A6000": 32e9, "RTX4090": 32e9, "L4": 32e9}


def several_gpus(report: dict[str, Any], num_gpus: int, split_cfg: bool = False) -> dict[str, Any]:
    """Predicted wall time of ``report``'s guided run with ``run.devices`` over ``num_gpus``
    GPUs of one card: the anchor chunks of an update decode on different GPUs at once (forward and
    backward), so the decode stage takes the time of the ``ceil(chunks / num_gpus)`` chunks one GPU
    decodes, plus the transfers of the chunks decoded elsewhere (their latents out and anchor
    frames back, and both gradients in the backward, fp32) over the card's interconnect. With
    ``split_cfg`` (``run.split_cfg``, two GPUs or more) the denoiser's CFG halves run on two GPUs
    at once: its calls, with gradients and without, take half their time, plus the transfers of the second half (its latents,
    text embeddings and output, and their gradients in faithful mode's backward). The rest (the
    estimators, the loss, the unguided steps) stays on one GPU.

    Returns per card: ``guided_s``, ``over_unguided_1gpu`` (guided on N GPUs over unguided on one)
    and ``over_unguided_ngpus`` (over unguided on N GPUs, which for one video is the one-GPU time:
    an unguided call's denoiser is not split), and ``decode_s`` / ``transfer_s`` / ``denoiser_s``
    per run.
    """
    if num_gpus < 1:
        raise ValueError(f"--num-gpus must be >= 1, got {num_gpus}")
    settings, counts = report["settings"], report["counts"]
    chunks = len(default_anchors(settings["frames"], model_named("cogvideox-5b").temporal_compression))
    per_gpu_chunks = -(-chunks // num_gpus)
    remote = chunks - len(range(0, chunks, num_gpus))  # chunk k runs on GPU k mod N; GPU 0 is the pipeline's
    latent_h, latent_w = settings["height"] // 8, settings["width"] // 8
    chunk_bytes = (settings.get("chunk_latents") or 3) * 16 * latent_h * latent_w * 4 + 3 * settings["height"] * settings["width"] * 4
    decode = report["per_stage"].get("anchor_decode")
    denoiser_stages = [report["per_stage"][name] for name in ("denoiser_cfg", "denoiser") if name in report["per_stage"]]
    split = split_cfg and num_gpus >= 2 and bool(denoiser_stages)
    # the second CFG half's latents in and output back (bf16), its text embeddings in; a call with
    # gradients moves both gradients back the other way
    latent_frames = (settings["frames"] - 1) // model_named("cogvideox-5b").temporal_compression + 1
    half_bytes = 2 * (2 * latent_frames * 16 * latent_h * latent_w) + 2 * 226 * 4096
    half_transfers = counts.get("denoiser_cfg", 0) + 2 * counts.get("denoiser_grad", 0)
    rows = {}
    for gpu in GPU_SPECS:
        wall = report["roofline"]["wall_time_s"][gpu]
        if wall["guided"] is None or decode is None:
            continue
        decode_s = decode["time_s"][gpu] * per_gpu_chunks / chunks
        transfer_s = counts["updates"] * remote * 2 * chunk_bytes / INTERCONNECT_BYTES_PER_S[gpu]
        guided = wall["guided"] - decode["time_s"][gpu] + decode_s + transfer_s
        denoiser_s = sum(stage["time_s"][gpu] for stage in denoiser_stages) if denoiser_stages else None
        if split:
            cfg_transfer_s = half_transfers * half_bytes / INTERCONNECT_BYTES_PER_S[gpu]
            guided += denoiser_s / 2 + cfg_transfer_s - denoiser_s
            denoiser_s, transfer_s = denoiser_s / 2, transfer_s + cfg_transfer_s
        rows[gpu] = {"guided_s": guided, "over_unguided_1gpu": guided / wall["unguided"],
                     "over_unguided_ngpus": guided / wall["unguided"], "decode_s": decode_s, "transfer_s": transfer_s,
                     "denoiser_s": denoiser_s}
    return {"num_gpus": num_gpus, "chunks": chunks, "chunks_per_gpu": per_gpu_chunks, "split_cfg": split, "cards": rows}


def several_gpus_table(rows: dict[str, Any]) -> str:
    """Markdown: :func:`several_gpus` per card."""
    split = ", the CFG halves on two of them (run.split_cfg)" if rows.get("split_cfg") else ""
    lines = [f"run.devices over {rows['num_gpus']} GPUs ({rows['chunks']} anchor chunks, "
             f"{rows['chunks_per_gpu']} per GPU at most{split}), predicted:",
             "| card | guided (s) | / unguided on 1 GPU | / unguided on N GPUs | decode (s) | transfers (s) |",
             "|---|---|---|---|---|---|"]
    lines += [f"| {gpu} | {r['guided_s']:.0f} | {r['over_unguided_1gpu']:.2f} | {r['over_unguided_ngpus']:.2f} | "
              f"{r['decode_s']:.0f} | {r['transfer_s']:.2f} |" for gpu, r in rows["cards"].items()]
    return "\n".join(lines)


#: Measured breakdown keys (``sampling`` JSON) of each cost stage; the denoiser's calls with and
#: without gradients are one measured stage.
MEASURED_STAGES: dict[str, tuple[str, ...]] = {
    "denoiser": ("denoiser_forward_s", "denoiser_backward_s"),
    "anchor_decode": ("vae_slice_decode_forward_s", "vae_slice_decode_backward_s"),
    "vggt": ("vggt_forward_s", "vggt_backward_s"),
    "ufm": ("ufm_forward_s", "ufm_backward_s"),
    "loss": ("loss_s",),
    "final_decode": ("vae_final_decode_s",),
}


#: Keys a ``sampling`` report needs for :func:`compare_with_measured`.
MEASURED_KEYS = ("wall_time_s", "breakdown", "peak_memory_gb")


def load_measured(path: str | Path) -> dict[str, Any]:
    """A ``sampling`` JSON report to compare with.

    Raises:
        ValueError: missing or unreadable file, not JSON, or not a sampling report (the message
            says which).
    """
    try:
        measured = json.loads(Path(path).read_text())
    except FileNotFoundError:
        raise ValueError(f"--measured {str(path)!r}: no such file") from None
    except (OSError, UnicodeDecodeError) as err:
        raise ValueError(f"--measured {str(path)!r}: cannot read it ({err})") from None
    except json.JSONDecodeError as err:
        raise ValueError(f"--measured {str(path)!r}: not JSON ({err.msg}, line {err.lineno})") from None
    missing = [k for k in MEASURED_KEYS if not isinstance(measured, dict) or k not in measured]
    if missing:
        raise ValueError(f"--measured {str(path)!r}: not a `sampling` report (no {', '.join(missing)})")
    return measured


def compare_with_measured(report: dict[str, Any], measured: dict[str, Any], measured_path: str,
                          gpu: str = "H200") -> dict[str, Any]:
    """Predicted vs measured: a ``sampling`` report of the same mode on ``gpu`` (times extrapolated to
    the nominal run when the run was shorter). Stage times: the measured breakdown's seconds per
    stage (forward + backward; the harness's forward of a checkpointed decode includes its
    recomputation, so the measured stage sums can exceed the measured updates a little).
    ``measured`` is the report read by :func:`load_measured` from ``measured_path``."""
    ext = measured.get("extrapolated_to_nominal") or {}
    walls = ext.get("wall_time_s") or measured["wall_time_s"]
    breakdown = ext.get("breakdown") or measured["breakdown"]
    predicted_wall = report["roofline"]["wall_time_s"][gpu]
    stages = {}
    for name, keys in MEASURED_STAGES.items():
        parts = ("denoiser_cfg", "denoiser") if name == "denoiser" else (name,)
        predicted = sum(report["per_stage"][p]["time_s"][gpu] for p in parts if p in report["per_stage"])
        stages[name] = {"predicted_s": predicted, "measured_s": sum(breakdown.get(k, 0.0) for k in keys)}
    return {
        "measured_json": measured_path,
        "gpu": gpu,
        "wall_time_s": {"predicted": predicted_wall, "measured": walls},
        "ratio_guided_over_unguided": {"predicted": report["roofline"]["ratio_guided_over_unguided"][gpu],
                                       "measured": measured.get("ratio_guided_over_unguided")},
        "peak_memory_gb": {"predicted": report["peak_memory_gb"], "measured": measured["peak_memory_gb"]},
        "peak_memory_gb_unguided": {"predicted": report["peak_memory_gb_unguided"],
                                    "measured": measured.get("peak_memory_gb_unguided")},
        "stages": stages,
    }


def cost_table(report: dict[str, Any]) -> str:
    """Markdown: per stage FLOPs and predicted seconds on the GPUs, then the run's totals."""
    lines = ["| stage | count | TFLOP forward | TFLOP backward | TFLOP total | share | "
             + " | ".join(f"{g} (s)" for g in GPU_SPECS) + " |",
             "|---|---|---|---|---|---|" + "---|" * len(GPU_SPECS)]
    total = sum(s["flops"] for s in report["per_stage"].values()) or 1
    for name, s in report["per_stage"].items():
        lines.append(f"| {name} | {s['count']} | {s['flops_forward'] / 1e12:.1f} | {s['flops_backward'] / 1e12:.1f} | "
                     f"{s['flops'] / 1e12:.1f} | {100 * s['flops'] / total:.1f} % | "
                     + " | ".join(f"{s['time_s'][g]:.1f}" for g in GPU_SPECS) + " |")
    ratio = report["flops_ratio_guided_over_unguided"]
    wall = report["roofline"]["wall_time_s"]
    lines.append("")
    lines.append(f"mode {report['mode']}: FLOPs unguided {report['flops_unguided'] / 1e15:.2f} PFLOP"
                 + (f", guided {report['flops_guided'] / 1e15:.2f} PFLOP, ratio {ratio:.2f}" if ratio else ""))
    if report["settings"].get("decoder") == "tiny":
        lines.append("anchor decode: the tiny decoder (an approximation of the VAE; `decoder-agreement` measures "
                     "its fidelity)")
    lines.append(f"peak memory {report['peak_memory_gb']:.1f} GiB (at {report['peak_at']}; weights "
                 f"{sum(report['weights_gb'].values()):.1f} GiB), unguided {report['peak_memory_gb_unguided']:.1f} GiB")
    card = report.get("card")
    if card:
        lines.append(f"{card['gpu']} ({card['memory_gib']:.1f} GiB): memory plan {card['plan']}"
                     + (" with model CPU offload" if card["offload"] else "") + f" ({card['reason']})")
    if report["ops_ratio_guided_over_unguided"]:
        lines.append(f"ATen ops: unguided {report['ops_unguided']:.0f}, guided {report['ops_guided']:.0f}, "
                     f"ratio {report['ops_ratio_guided_over_unguided']:.1f} (what a launch-bound device pays for)")
    if report["settings"]["preset"] == "tiny":
        return "\n".join(lines)  # the calibration is a full-size measurement: no GPU times for tiny models
    validation = report.get("validation")
    if validation:
        v = validation
        lines.append(f"vs measured ({v['measured_json']}): ratio {v['ratio_guided_over_unguided']['predicted']:.2f} "
                     f"predicted / {v['ratio_guided_over_unguided']['measured']:.2f} measured; peak "
                     f"{v['peak_memory_gb']['predicted']:.1f} / {v['peak_memory_gb']['measured']:.1f} GiB; "
                     + ", ".join(f"{k} {x['predicted_s']:.0f} / {x['measured_s']:.0f} s" for k, x in v["stages"].items()))
    for gpu in GPU_SPECS:
        g = wall[gpu]["guided"]
        lines.append(f"{gpu}: unguided {wall[gpu]['unguided']:.0f} s" + (f", guided {g:.0f} s" if g else "")
                     + f" (efficiency {report['roofline']['efficiency']:.2f})")
    return "\n".join(lines)


