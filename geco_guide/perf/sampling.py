"""Sampling benchmark: guided vs unguided sampling from one seed, through the one generation path.

Each arm runs in its own process (:func:`run_sampling_worker`): its config (the tiny preset, or
CogVideoX-5B's with random full-size weights) goes to :func:`geco_guide.generation.load_models`
and :func:`geco_guide.generation.sample`, as ``geco generate`` makes a video; the guided arm's
stages are timed by a :class:`~.profile.StageProfiler`. With fewer than the nominal 50 steps the
paper's schedule is scaled to the run's steps by the package's rule
(:func:`~geco_guide.sampler.algorithm.schedule.scale_schedule`: phase boundaries rounded), and the times are
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
from ..estimators.vggt import VGGT, VGGTConfig
from ..families import default_anchors, model_named
from ..sampler.algorithm.config import GuidanceConfig, fused_guidance_config
from ..sampler.algorithm.schedule import (
    PAPER_REPEATS,
    PAPER_TIME_TRAVEL,
    parse_repeats,
    scale_schedule,
)
from ..sampler.algorithm.schedule import PAPER_STEPS
from ..sampler.running.run_options import RunOptions
from .full_size import CALIBRATION_MODEL, build_full_size_components, model_video, text_encoder_stand_in
from .measure import (
    GIB,
    environment_info,
    markdown_table,
    memory_kind,
    peak_memory_bytes,
    run_case_subprocess,
    synchronize,
)
from .profile import StageProfiler, breakdown_of, summarize_profile

__all__ = ["PROMPT", "paper_schedule_for", "run_sampling_worker", "sampling_config", "sampling_guidance",
           "sampling_models", "sampling_run_options", "sampling_report", "sampling_spec", "sampling_table"]

logger = logging.getLogger(__name__)

#: The prompt of every arm (the full-size models' random weights make any prompt noise).
PROMPT = "a red cube on a table"


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
    anchors = default_anchors(spec["frames"], model_named(CALIBRATION_MODEL).temporal_compression)
    return replace(base, anchors=anchors, repeats=repeats, time_travel=time_travel,
                   denoiser_grad=spec["mode"] == "faithful", chunk_latents=chunk_latents)


def sampling_run_options(spec: dict[str, Any]) -> RunOptions:
    """The ``run_options=`` argument of an arm: the preset's checkpointing flags as measured
    (``explicit``) unless a memory plan is asked for, and the arm's devices."""
    from ..tiny import tiny_run_options

    base = tiny_run_options() if spec["preset"] == "tiny" else RunOptions()
    return replace(base, memory_plan=spec.get("memory_plan") or "explicit", devices=spec.get("devices"),
                   gradient_checkpointing=base.gradient_checkpointing and not spec.get("no_denoiser_checkpointing"))


def sampling_config(spec: dict[str, Any]) -> Any:
    """The :class:`~geco_guide.config.GeCoConfig` of one arm of ``spec``: the tiny preset or
    CogVideoX-5B's (the paper's call), with the arm's size, steps, dtype, device and seed, the
    harness's guidance (:func:`sampling_guidance`: off for the unguided arm) and run options
    (:func:`sampling_run_options`), and no scoring of the anchors afterwards."""
    from ..config import load_config

    tiny = spec["preset"] == "tiny"
    changes = {"sampling.num_frames": spec["frames"], "sampling.height": spec["height"],
               "sampling.width": spec["width"], "sampling.num_inference_steps": spec["steps"],
               "sampling.guidance_scale": 6.0, "model.dtype": spec["dtype"], "model.device": spec["device"],
               "estimators.dtype": spec["dtype"], "model.vae_tiling": bool(spec.get("vae_tiling")),
               "seed": spec["seed"], "output.score_anchors": False}
    if tiny:
        changes.update({"model.init_seed": spec["seed"], "estimators.init_seed": spec["seed"]})
    cfg = load_config(preset="tiny" if tiny else CALIBRATION_MODEL, changes=changes)
    guidance = sampling_guidance(spec)
    return replace(cfg, guidance=replace(cfg.guidance, enabled=False) if guidance is False else guidance,
                   run=sampling_run_options(spec))


def sampling_models(spec: dict[str, Any], cfg: Any) -> Any:
    """The models of an arm, loaded by :func:`geco_guide.generation.load_models`: the tiny preset's
    (its tiny-random models, seeded with the case's seed), or CogVideoX-5B's transformer and VAE
    with random weights (:func:`~.full_size.build_full_size_components`), a one-layer T5 of T5-XXL's
    width over a small tokenizer for the prompt (:func:`~.full_size.text_encoder_stand_in`: the
    random models make noise of any prompt), and VGGT-1B and UFM-Base with random weights (trunks in
    the sampling dtype, heads float32: what generate's ``from_pretrained(dtype=...)`` builds)."""
    from ..generation import load_models

    if spec["preset"] == "tiny":
        return load_models(cfg)
    device, dtype, seed = torch.device(spec["device"]), getattr(torch, spec["dtype"]), spec["seed"]
    ckpt = spec.get("estimator_checkpointing", False)
    geometry = VGGT.random(VGGTConfig(), seed=seed, gradient_checkpointing=ckpt).trunk_to(dtype)
    flow = UFM.random(UFMConfig(), seed=seed, gradient_checkpointing=ckpt).trunk_to(dtype)
    estimators = Estimators(geometry.eval().to(device), flow.eval().to(device))
    components = {**build_full_size_components(CALIBRATION_MODEL, device, dtype, seed),
                  **text_encoder_stand_in(CALIBRATION_MODEL, seed + 1000)}
    return load_models(cfg, estimators=estimators, components=components)


def run_sampling_worker(spec: dict[str, Any]) -> dict[str, Any]:
    """One arm (guided or unguided) of a sampling benchmark in this process, through the
    generation path (:func:`sampling_config`, :func:`sampling_models`,
    :func:`geco_guide.generation.sample`)."""
    from ..generation import sample

    device = torch.device(spec["device"])
    if spec["threads"]:
        torch.set_num_threads(spec["threads"])
    baseline = peak_memory_bytes(device)
    start = time.perf_counter()
    cfg = sampling_config(spec)
    models = sampling_models(spec, cfg)
    pipe, estimators = models.pipe, models.estimators
    synchronize(device)
    setup_s = time.perf_counter() - start
    after_setup = peak_memory_bytes(device)

    profiler = StageProfiler(device)
    profiler.wrap(pipe.transformer, "forward", "denoiser")
    profiler.wrap(pipe.vae, "decode", "vae_decode")
    profiler.wrap(estimators.geometry, "estimate_geometry", "vggt")
    profiler.wrap(estimators.flow, "estimate_flow", "ufm")
    profiler.mark_loop_start(pipe, "model_output")
    profiler.mark_step_ends(pipe.scheduler)

    for _ in range(spec["warmup"]):  # 2 steps: with guidance, step 1 has updates (scaled schedule)
        warm = sampling_guidance({**spec, "steps": 2})
        warm_guidance = replace(cfg.guidance, enabled=False) if warm is False else warm
        sample(models, replace(cfg, guidance=warm_guidance, sampling=replace(cfg.sampling, num_inference_steps=2)),
               PROMPT, progress=False)
    profiler.reset()
    load_avg_1m = os.getloadavg()[0]
    cpu_start = time.process_time()
    start = profiler.now()
    made = sample(models, cfg, PROMPT, progress=False)
    wall = profiler.now() - start
    cpu_per_wall = (time.process_time() - cpu_start) / wall
    peak = peak_memory_bytes(device)

    log = made.report.log
    profile = summarize_profile(profiler, log)
    loop_s = profiler.step_ends[-1] - profiler.loop_start
    step_times = [b - a for a, b in zip([profiler.loop_start, *profiler.step_ends[:-1]], profiler.step_ends)]
    guidance = cfg.guidance if cfg.guidance.enabled else None
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
        "memory_plan": made.report.memory_plan,
        "update_seconds": [r["seconds"] for r in log],
        "skipped_updates": sum(bool(r["skipped"]) for r in log),
        "losses": [r["loss"] for r in log],
        "profile": profile,
        "breakdown": breakdown_of(profile),
        "output_shape": list(made.frames.shape),
        "output_finite": bool(torch.isfinite(made.frames).all()),
        "memory_kind": memory_kind(device),
        "baseline_gb": baseline / GIB,
        "after_setup_gb": after_setup / GIB,
        "peak_memory_gb": peak / GIB,
        "load_avg_1m": load_avg_1m,
        "cpu_per_wall": cpu_per_wall,
        "guidance": None if guidance is None else {k: v for k, v in vars(guidance).items() if k != "loss"},
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
        video = model_video(CALIBRATION_MODEL)
    video.update({k: v for k, v in (("frames", frames), ("height", height), ("width", width)) if v is not None})
    steps = PAPER_STEPS if steps is None else steps  # 0 is an error, not the default
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

    extrapolated = steps < PAPER_STEPS
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
        "nominal_steps": PAPER_STEPS,
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
        ext = {arm: extrapolate_arm(r, PAPER_STEPS, paper_updates if arm == "guided" else 0)
               for arm, r in arms.items()}
        report["extrapolated_to_nominal"] = {
            "note": f"per-step and per-update times of the {steps}-step run scaled to {PAPER_STEPS} steps "
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
                   "`geco bench cost` predicts the full-size run.")


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


