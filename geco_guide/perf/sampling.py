"""Sampling benchmark: guided vs unguided :class:`GeCoCogVideoXPipeline` sampling from one seed.

Each arm runs in its own process (:func:`run_sampling_worker`); the guided arm's stages are timed
by a :class:`~.profile.StageProfiler`. With fewer than the nominal 50 steps the paper's schedule
is scaled to the run's steps by the package's rule
(:func:`~geco_guide.sampler.schedule.scale_schedule`: phase boundaries rounded), and the times are
extrapolated to 50 steps and the paper's 111 updates (``extrapolated: true``).
"""

from __future__ import annotations

import logging
import os
import time
import warnings
from collections.abc import Sequence
from dataclasses import replace
from typing import Any

import torch

from ..estimators.bundle import Estimators
from ..estimators.ufm import UFM, UFMConfig
from ..families import default_anchors, model_named
from ..estimators.vggt import VGGT, VGGTConfig
from ..sampler.config import GuidanceConfig, fused_guidance_config
from ..sampler.run_options import RunOptions
from ..sampler.schedule import (
    PAPER_REPEATS,
    PAPER_TIME_TRAVEL,
    parse_repeats,
    scale_schedule,
)
from .measure import (
    GIB,
    environment_info,
    markdown_table,
    memory_kind,
    peak_memory_bytes,
    run_case_subprocess,
    synchronize,
)
from .full_size import FULL_SIZE_VIDEO, TEXT_EMBED_SHAPE, build_full_size_components, cast_components
from .profile import StageProfiler, breakdown_of, summarize_profile

__all__ = ["NOMINAL_STEPS", "SAMPLING_MODES", "paper_schedule_for", "run_sampling_worker",
           "sampling_guidance", "sampling_run_options", "sampling_report", "sampling_spec", "sampling_table"]

logger = logging.getLogger(__name__)

NOMINAL_STEPS = 50
SAMPLING_MODES = ("faithful", "fast", "unguided")
#: Breakdown stages (keys of the profiler) in report order.
STAGES = ("denoiser", "vae_decode", "vggt", "ufm")


def paper_schedule_for(num_steps: int) -> tuple[str, list[int] | None]:
    """The paper's 50-step ``(repeats, time_travel)`` scaled to ``num_steps`` steps by the package's
    rule (:func:`scale_schedule`, phase boundaries rounded); unchanged at 50."""
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", UserWarning)  # scaling is what the harness asks for here
        repeats, window = scale_schedule(PAPER_REPEATS, list(PAPER_TIME_TRAVEL), num_steps)
    return repeats, (list(window) if window is not None else None)


def sampling_guidance(spec: dict[str, Any]) -> GuidanceConfig | bool:
    """The ``guidance=`` argument of an arm: ``False`` (unguided) or a :class:`GuidanceConfig`
    with the paper's schedule scaled to ``spec["steps"]``."""
    if spec["arm"] == "unguided":
        return False
    repeats, time_travel = paper_schedule_for(spec["steps"])
    from ..tiny import tiny_guidance_config  # the tiny models pull in transformers: only when asked for

    # the fused loss (gradients through VGGT too): the costlier of the two presets, what was measured
    base = tiny_guidance_config() if spec["preset"] == "tiny" else fused_guidance_config()
    chunk_latents = base.chunk_latents if spec["chunk_latents"] is None else spec["chunk_latents"]
    anchors = default_anchors(spec["frames"], model_named("cogvideox-5b").temporal_compression)
    return replace(base, anchors=anchors, repeats=repeats, time_travel=time_travel,
                   denoiser_grad=spec["mode"] == "faithful", chunk_latents=chunk_latents)


def sampling_run_options(spec: dict[str, Any]) -> RunOptions:
    """The ``run_options=`` argument of an arm: the preset's checkpointing flags as measured
    (``explicit``) unless a memory plan is asked for, and the arm's devices."""
    from ..tiny import tiny_run_options

    base = tiny_run_options() if spec["preset"] == "tiny" else RunOptions()
    return replace(base, memory_plan=spec.get("memory_plan") or "explicit", devices=spec.get("devices"),
                   gradient_checkpointing=base.gradient_checkpointing and not spec.get("no_denoiser_checkpointing"))


def build_sampling_pipeline(spec: dict[str, Any], device: torch.device,
                            dtype: torch.dtype) -> tuple[Any, dict[str, Any], Estimators]:
    """The pipeline of a sampling case, its call kwargs (random text embeddings for full size) and
    its estimators."""
    from ..sampler.pipeline_cogvideox import GeCoCogVideoXPipeline

    seed = spec["seed"]
    if spec["preset"] == "tiny":
        from ..tiny import TINY_MAX_SEQUENCE_LENGTH, tiny_estimators, tiny_pipeline

        pipe = cast_components(tiny_pipeline(seed), dtype).to(device)
        estimators = tiny_estimators(seed)
        for model in estimators.modules():
            model.to(device=device, dtype=dtype)
        call = {"prompt": "a red cube on a table", "max_sequence_length": TINY_MAX_SEQUENCE_LENGTH}
    else:
        # trunks in the sampling dtype, heads float32: what generate's from_pretrained(dtype=...) builds
        ckpt = spec.get("estimator_checkpointing", False)
        geometry = VGGT.random(VGGTConfig(), seed=seed, gradient_checkpointing=ckpt).trunk_to(dtype)
        flow = UFM.random(UFMConfig(), seed=seed, gradient_checkpointing=ckpt).trunk_to(dtype)
        pipe = GeCoCogVideoXPipeline(**build_full_size_components(device, dtype, seed))
        estimators = Estimators(geometry.eval().to(device), flow.eval().to(device))
        pipe.to(device)
        if spec["vae_tiling"]:  # generate's model.vae_tiling
            pipe.vae.enable_tiling()
        pipe.set_progress_bar_config(disable=True)
        gen = torch.Generator().manual_seed(seed + 1000)
        embeds = [torch.randn(*TEXT_EMBED_SHAPE, generator=gen).to(device, dtype) for _ in range(2)]
        call = {"prompt_embeds": embeds[0], "negative_prompt_embeds": embeds[1],
                "max_sequence_length": TEXT_EMBED_SHAPE[1]}
    call.update(num_frames=spec["frames"], height=spec["height"], width=spec["width"], output_type="pt")
    return pipe, call, estimators


def run_sampling_worker(spec: dict[str, Any]) -> dict[str, Any]:
    """One arm (guided or unguided) of a sampling benchmark in this process."""
    device = torch.device(spec["device"])
    dtype = getattr(torch, spec["dtype"])
    if spec["threads"]:
        torch.set_num_threads(spec["threads"])
    baseline = peak_memory_bytes(device)
    start = time.perf_counter()
    pipe, call, estimators = build_sampling_pipeline(spec, device, dtype)
    synchronize(device)
    setup_s = time.perf_counter() - start
    after_setup = peak_memory_bytes(device)

    profiler = StageProfiler(device)
    profiler.wrap(pipe.transformer, "forward", "denoiser")
    profiler.wrap(pipe.vae, "decode", "vae_decode")
    profiler.wrap(estimators.geometry, "estimate_geometry", "vggt")
    profiler.wrap(estimators.flow, "estimate_flow", "ufm")
    profiler.mark_loop_start(pipe)
    guidance, run = sampling_guidance(spec), sampling_run_options(spec)

    def sample(steps: int, guidance_arg: Any) -> Any:
        return pipe(**call, num_inference_steps=steps, guidance=guidance_arg, run_options=run, guidance_scale=6.0,
                    generator=torch.Generator().manual_seed(spec["seed"]), callback_on_step_end=profiler.on_step_end,
                    estimators=estimators if guidance_arg is not False else None)

    for _ in range(spec["warmup"]):  # 2 steps: with guidance, step 1 has updates (scaled schedule)
        warm = sampling_guidance({**spec, "steps": 2}) if guidance is not False else False
        sample(2, warm)
    profiler.reset()
    load_avg_1m = os.getloadavg()[0]
    cpu_start = time.process_time()
    start = profiler.now()
    out = sample(spec["steps"], guidance)
    wall = profiler.now() - start
    cpu_per_wall = (time.process_time() - cpu_start) / wall
    peak = peak_memory_bytes(device)

    log = out.report.log
    profile = summarize_profile(profiler, log)
    loop_s = profiler.step_ends[-1] - profiler.loop_start
    step_times = [b - a for a, b in zip([profiler.loop_start, *profiler.step_ends[:-1]], profiler.step_ends)]
    frames = out.frames
    return {
        **spec,
        "threads": torch.get_num_threads(),
        "setup_s": setup_s,
        "wall_s": wall,
        "loop_s": loop_s,
        "before_loop_s": profiler.loop_start - start,
        "after_loop_s": start + wall - profiler.step_ends[-1],
        "step_times_s": step_times,
        "time_per_step_s": loop_s / len(step_times),
        "guided_updates": len(log),
        "memory_plan": getattr(out, "memory_plan", None),
        "update_seconds": [r["seconds"] for r in log],
        "skipped_updates": sum(bool(r["skipped"]) for r in log),
        "losses": [r["loss"] for r in log],
        "profile": profile,
        "breakdown": breakdown_of(profile),
        "output_shape": list(frames.shape),
        "output_finite": bool(torch.isfinite(frames).all()),
        "memory_kind": memory_kind(device),
        "baseline_gb": baseline / GIB,
        "after_setup_gb": after_setup / GIB,
        "peak_memory_gb": peak / GIB,
        "load_avg_1m": load_avg_1m,
        "cpu_per_wall": cpu_per_wall,
        "guidance": None if guidance is False else {k: v for k, v in vars(guidance).items() if k != "loss"},
    }


def extrapolate_arm(arm: dict[str, Any], nominal: int, nominal_updates: int) -> dict[str, Any]:
    """Times of ``arm`` extrapolated from its ``steps`` to ``nominal`` steps with
    ``nominal_updates`` guided updates: the per-step part (final predictions, DDIM step) scales by
    ``nominal / steps``, the per-update part by ``nominal_updates / updates``; the time before and
    after the loop (text embeddings, latents, final decode) is kept."""
    steps, updates = arm["steps"], arm["guided_updates"]
    update_s = sum(arm["update_seconds"])
    per_step = (arm["loop_s"] - update_s) / steps
    per_update = update_s / updates if updates else 0.0
    if nominal_updates and not updates:
        raise ValueError(f"{steps} step(s) run no guided update: cannot extrapolate the guided time")
    loop = nominal * per_step + nominal_updates * per_update
    scale = {"update": nominal_updates / updates if updates else 0.0, "loop": nominal / steps, "post": 1.0}
    return {
        "wall_s": arm["before_loop_s"] + loop + arm["after_loop_s"],
        "loop_s": loop,
        "time_per_step_s": loop / nominal,
        "guided_updates": nominal_updates,
        "breakdown": breakdown_of(arm["profile"], scale),
    }


def sampling_spec(*, full_size: bool, mode: str, steps: int | None, frames: int | None, height: int | None,
                  width: int | None, device: str, dtype: str | None, threads: int | None, seed: int, warmup: int,
                  estimator_checkpointing: bool = False, chunk_latents: int | None = None, vae_tiling: bool = False,
                  rss_exact: bool = False, no_denoiser_checkpointing: bool = False,
                  memory_plan: str = "explicit", devices: Sequence[str] | None = None) -> dict[str, Any]:
    """The case of a sampling benchmark with the presets' defaults filled in (``None``: the
    preset's; tiny: 17x32x48 float32; full size: 49x480x720, bfloat16 on CUDA). ``memory_plan``:
    ``run.memory_plan`` (default ``explicit``: the checkpointing flags of the preset and options);
    ``devices``: ``run.devices`` of the guided arm (the anchor decode dealt over them)."""
    preset = "full-size" if full_size else "tiny"
    if preset == "tiny":
        from ..tiny import TINY_HEIGHT, TINY_NUM_FRAMES, TINY_WIDTH

        video = {"frames": TINY_NUM_FRAMES, "height": TINY_HEIGHT, "width": TINY_WIDTH}
    else:
        video = dict(FULL_SIZE_VIDEO)
    video.update({k: v for k, v in (("frames", frames), ("height", height), ("width", width)) if v is not None})
    steps = NOMINAL_STEPS if steps is None else steps  # 0 is an error, not the default
    dtype = dtype or ("bfloat16" if preset == "full-size" and torch.device(device).type == "cuda" else "float32")
    return {"workload": "sampling", "preset": preset, "mode": mode, "steps": steps, **video,
            "device": device, "dtype": dtype, "threads": threads, "seed": seed,
            "warmup": warmup, "estimator_checkpointing": estimator_checkpointing,
            "chunk_latents": chunk_latents, "vae_tiling": vae_tiling, "rss_exact": rss_exact,
            "no_denoiser_checkpointing": no_denoiser_checkpointing, "memory_plan": memory_plan,
            "devices": list(devices) if devices else None}


def sampling_report(spec: dict[str, Any], worker: Sequence[str], argv: Sequence[str] = ()) -> dict[str, Any]:
    """Run the unguided and (unless ``mode`` is unguided) the guided arm of ``spec``
    (:func:`sampling_spec`), each in a ``worker`` subprocess; build the JSON report."""
    device = torch.device(spec["device"])
    preset, mode, steps = spec["preset"], spec["mode"], spec["steps"]
    video = {k: spec[k] for k in ("frames", "height", "width")}
    arms_to_run = ("unguided",) if mode == "unguided" else ("unguided", "guided")
    arms = {}
    for arm in arms_to_run:
        case = {**spec, "arm": arm, "case": f"sampling-{preset}-{arm}"}
        logger.info("running %s (%s, %s steps) ...", case["case"], mode, steps)
        arms[arm] = run_case_subprocess(case, worker)
        logger.info("  wall %.4g s, peak %.3f GiB", arms[arm]["wall_s"], arms[arm]["peak_memory_gb"])

    extrapolated = steps < NOMINAL_STEPS
    paper_updates = sum(parse_repeats(PAPER_REPEATS))
    guided = arms.get("guided")
    main_arm = guided or arms["unguided"]
    report: dict[str, Any] = {
        "subcommand": "sampling",
        "argv": list(argv),
        "environment": environment_info(main_arm["threads"]),
        "device": f"{device.type} ({torch.cuda.get_device_name(device)})" if device.type == "cuda" else "cpu",
        "mode": mode,
        "preset": preset,
        "steps": steps,
        "nominal_steps": NOMINAL_STEPS,
        "extrapolated": extrapolated,
        "config": {**video, "dtype": spec["dtype"], "seed": spec["seed"], "warmup": spec["warmup"],
                   "guidance_scale": 6.0, "estimator_checkpointing": spec["estimator_checkpointing"],
                   "vae_tiling": spec["vae_tiling"], "rss_exact": spec["rss_exact"],
                   "guidance": guided["guidance"] if guided else None,
                   "schedule_note": "paper schedule scaled to the run's steps (scale_schedule: phase boundaries "
                                    "b -> round(b * steps / 50)); scheduler's own steps-step table"},
        "memory_kind": main_arm["memory_kind"],
        "peak_memory_gb": main_arm["peak_memory_gb"],
        "memory_plan": guided.get("memory_plan") if guided else None,
        "peak_memory_gb_unguided": arms["unguided"]["peak_memory_gb"],
        "wall_time_s": {arm: r["wall_s"] for arm, r in arms.items()},
        "time_per_step_s": {arm: r["time_per_step_s"] for arm, r in arms.items()},
        "breakdown": main_arm["breakdown"],
        "breakdown_unguided": arms["unguided"]["breakdown"],
        "arms": arms,
    }
    ratio_basis = "measured"
    if guided:
        ratio = guided["wall_s"] / arms["unguided"]["wall_s"]
    if extrapolated:
        ext = {arm: extrapolate_arm(r, NOMINAL_STEPS, paper_updates if arm == "guided" else 0)
               for arm, r in arms.items()}
        report["extrapolated_to_nominal"] = {
            "note": f"per-step and per-update times of the {steps}-step run scaled to {NOMINAL_STEPS} steps "
                    f"and the paper's {paper_updates} guided updates (not measured)",
            "wall_time_s": {arm: e["wall_s"] for arm, e in ext.items()},
            "time_per_step_s": {arm: e["time_per_step_s"] for arm, e in ext.items()},
            "breakdown": ext.get("guided", ext["unguided"])["breakdown"],
        }
        if guided:
            ratio = ext["guided"]["wall_s"] / ext["unguided"]["wall_s"]
            ratio_basis = "extrapolated"
    report["ratio_guided_over_unguided"] = ratio if guided else None
    report["ratio_basis"] = ratio_basis if guided else None
    return report


SAMPLING_COLUMNS: tuple[tuple[str, str, str], ...] = (
    ("arm", "arm", "{}"),
    ("steps", "steps", "{}"),
    ("updates", "guided_updates", "{}"),
    ("wall (s)", "wall_s", "{:.4g}"),
    ("per step (s)", "time_per_step_s", "{:.4g}"),
    ("denoiser fwd", "denoiser_forward_s", "{:.3g}"),
    ("denoiser bwd", "denoiser_backward_s", "{:.3g}"),
    ("VAE slice fwd", "vae_slice_decode_forward_s", "{:.3g}"),
    ("VAE slice bwd", "vae_slice_decode_backward_s", "{:.3g}"),
    ("VAE final", "vae_final_decode_s", "{:.3g}"),
    ("VGGT fwd", "vggt_forward_s", "{:.3g}"),
    ("VGGT bwd", "vggt_backward_s", "{:.3g}"),
    ("UFM fwd", "ufm_forward_s", "{:.3g}"),
    ("UFM bwd", "ufm_backward_s", "{:.3g}"),
    ("loss", "loss_s", "{:.3g}"),
    ("fwd / bwd", "passes", "{}"),
    ("peak mem (GiB)", "peak_memory_gb", "{:.3f}"),
)


#: Printed under a tiny run's ratio: its models are too small for the ratio to mean anything at full size.
TINY_RATIO_NOTE = ("note: the tiny random models make this ratio meaningless for full size (their denoiser is "
                   "nearly free, so the estimators and the decode dominate), and the unguided arm's sub-second time "
                   "makes it swing between runs: compare the guided arm's seconds to catch a regression; "
                   "`scripts/benchmark.py cost` predicts the full-size run.")


def sampling_table(report: dict[str, Any]) -> str:
    """Markdown table of the arms (measured; the extrapolated rows are marked ``(extrap.)``)."""
    rows = []
    for arm, r in report["arms"].items():
        b = r["breakdown"]
        rows.append({**r, **b, "passes": f"{b['counts']['denoiser_forwards']} / {b['counts']['denoiser_backwards']}"})
    for arm, wall in report.get("extrapolated_to_nominal", {}).get("wall_time_s", {}).items():
        ext = report["extrapolated_to_nominal"]
        b = ext["breakdown"] if arm == ("guided" if "guided" in report["arms"] else "unguided") else {}
        rows.append({"arm": f"{arm} (extrap.)", "steps": report["nominal_steps"], "wall_s": wall,
                     "time_per_step_s": ext["time_per_step_s"][arm], **{k: v for k, v in b.items() if k != "counts"}})
    ratio = report["ratio_guided_over_unguided"]
    footer = f"\nguided / unguided wall time: {ratio:.3g} ({report['ratio_basis']})" if ratio else ""
    if ratio and report.get("preset") == "tiny":
        footer += f"\n{TINY_RATIO_NOTE}"
    return markdown_table(rows, SAMPLING_COLUMNS) + footer


