"""The cost model of a sampling call: FLOPs, bytes, memory and a roofline time, from traces on fake tensors.

:func:`~.tracing.trace_cost` traces one step of a registry model's call (no weights, no GPU);
:func:`~.tracing.count_schedule_calls` counts the units over the model's schedule;
:func:`whole_run_costs` combines units and counts, and :func:`cost_report` adds a roofline time on
the cards of :data:`~.cards.GPU_SPECS` with one efficiency calibrated on the measured unguided H200
step of CogVideoX-5B (always at the size that was measured, so that a smaller video or another
model predicts from its own FLOPs and bytes). :func:`several_gpus` predicts ``run.devices`` over
N GPUs, :func:`compare_with_measured` sets a report against a ``sampling`` report.
"""

from __future__ import annotations

import functools
import json
import logging
import time
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import torch

from ..families import default_anchors
from ..sampler.algorithm.schedule import PAPER_STEPS
from .cards import GPU_SPECS, H200_UNGUIDED_STEP_S, INTERCONNECT_BYTES_PER_S, card_memory_gib
from .full_size import CALIBRATION_MODEL, model_video, text_embed_shape
from .measure import GIB, environment_info
from .tracing import count_schedule_calls, settings_model, trace_cost

__all__ = ["CALIBRATION_SETTINGS", "anchor_chunk_bytes", "at_calibration_size", "calibration_call_roofline_s",
           "compare_with_measured", "cost_report", "cost_settings", "cost_table", "decode_over_gpus", "load_measured",
           "model_schedule",
           "several_gpus", "several_gpus_table", "whole_run_costs"]

logger = logging.getLogger(__name__)

#: The settings of the calibrating measurement (:data:`~.cards.H200_UNGUIDED_STEP_S`): the
#: efficiency is the roofline time of one CFG call of this model at this size over the measured
#: step, whatever model or size a report traces (a report of another reuses it).
CALIBRATION_SETTINGS = {"preset": "full", "model": CALIBRATION_MODEL, **model_video(CALIBRATION_MODEL), "dtype": "bfloat16"}


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


def model_schedule(name: str) -> dict[str, Any]:
    """Registry model ``name``'s guided call as its preset makes it: ``steps``, ``repeats``,
    ``time_travel`` and ``guidance_scale`` (the paper's 50 steps, ``0x3,3x17,2x30`` and [15, 20] for
    CogVideoX-5B)."""
    from ..config import load_config, model_preset

    cfg = load_config(model_preset=model_preset(name), changes={"model.name": name})
    return {"steps": cfg.sampling.num_inference_steps, "repeats": cfg.guidance.repeats,
            "time_travel": None if cfg.guidance.time_travel is None else list(cfg.guidance.time_travel),
            "guidance_scale": cfg.sampling.guidance_scale}


def cost_settings(*, preset: str, steps: int | None, frames: int | None, height: int | None, width: int | None,
                  dtype: str | None, model: str = CALIBRATION_MODEL, no_time_travel: bool = False,
                  paper_schedule: bool = False, seed: int = 0, chunk_latents: int | None = None,
                  vae_checkpointing: bool | None = None, vae_block_checkpointing: bool | None = None,
                  denoiser_checkpointing: bool | None = None, estimator_checkpointing: bool = False,
                  vae_tiling: bool = False, calibration_step_s: float = H200_UNGUIDED_STEP_S,
                  decoder: str = "vae", plan: str | None = None) -> dict[str, Any]:
    """The settings of a cost report, the presets' defaults filled in (``None``: the preset's).
    ``decoder`` decodes the anchor frames (``guidance.decoder``): the VAE, or ``tiny``: the TAEHV
    tiny decoder of the published widths (random weights on fake tensors, like every model here).
    ``plan``: a named memory plan (:data:`~geco_guide.sampler.running.memory_plan.PLANS`), which sets every
    checkpointing flag (the estimators' too) over the flags given; ``None``: the flags as given.

    Full size: registry model ``model`` (:func:`~geco_guide.families.published.traced_models`) at
    its default call (CogVideoX-5B: 49x480x720) in bfloat16, its preset's schedule (the paper's
    50 steps for CogVideoX-5B). Tiny: 17x32x48 float32 and the tiny preset's 4-step schedule, or
    the paper's 50-step one with ``paper_schedule``.
    """
    if preset == "tiny":
        from ..sampler.algorithm.schedule import PAPER_REPEATS, PAPER_TIME_TRAVEL
        from ..tiny import TINY_HEIGHT, TINY_NUM_FRAMES, TINY_WIDTH, tiny_guidance_config

        video = {"frames": TINY_NUM_FRAMES, "height": TINY_HEIGHT, "width": TINY_WIDTH}
        base = tiny_guidance_config()
        schedule = {"steps": 4, "repeats": base.repeats, "time_travel": base.time_travel, "guidance_scale": 6.0}
        if paper_schedule:
            schedule.update(steps=PAPER_STEPS, repeats=PAPER_REPEATS, time_travel=list(PAPER_TIME_TRAVEL))
        dtype, model = dtype or "float32", None
    else:
        video, schedule = model_video(model), model_schedule(model)
        dtype = dtype or "bfloat16"
    video.update({k: v for k, v in (("frames", frames), ("height", height), ("width", width)) if v is not None})
    return {"preset": preset, "model": model, **video, "dtype": dtype,
            "steps": schedule["steps"] if steps is None else steps, "repeats": schedule["repeats"],
            "time_travel": None if no_time_travel else schedule["time_travel"], "seed": seed,
            "chunk_latents": chunk_latents, "vae_checkpointing": vae_checkpointing,
            "vae_block_checkpointing": vae_block_checkpointing, "plan": plan,
            "denoiser_checkpointing": denoiser_checkpointing, "estimator_checkpointing": estimator_checkpointing,
            "vae_tiling": vae_tiling, "decoder": decoder, "calibration_step_s": calibration_step_s,
            "guidance_scale": schedule["guidance_scale"],
            "note": "shape-only: fake tensors (FakeTensorMode), no weights; estimator trunks in dtype, heads float32"}


def cost_report(settings: dict[str, Any], mode: str, argv: Sequence[str] = (),
                unguided: dict[str, Any] | None = None) -> dict[str, Any]:
    """Trace the units, count the schedule, combine; the JSON report of ``cost`` for ``settings``
    (:func:`cost_settings`). ``unguided``: the unguided trace of these settings made already
    (:func:`~.tracing.trace_cost`; a memory plan acts on the guided updates only, so the plans of
    one model share it)."""
    start = time.perf_counter()
    what = f"{settings['model']}'s" if settings["model"] else "the tiny models'"
    if unguided is None:
        unguided = trace_cost(settings, "unguided")
        logger.info("traced %s unguided step in %.0f s", what, unguided["trace_s"])
    guided = None
    if mode != "unguided":
        guided = trace_cost(settings, mode)
        logger.info("traced %s %s update in %.0f s", what, mode, guided["trace_s"])
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
        unit[arm] = {name: {kind: {k: v[k] for k in ("flops", "bytes", "ops", "peak_live_bytes", "roofline_s")}
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


def anchor_chunk_bytes(model: Any, height: int, width: int, chunk_latents: int | None) -> int:
    """What one anchor chunk decoded on another GPU moves each way (fp32): its latents
    ``[chunk_latents, C, h, w]`` out, its anchor frame ``[3, H, W]`` back (the gradients the other
    way in the backward); ``model``: its :class:`~geco_guide.families.VideoModel`."""
    s = model.spatial_compression
    return (chunk_latents or 3) * model.latent_channels * (height // s) * (width // s) * 4 + 3 * height * width * 4


def decode_over_gpus(decode_s: float, chunks: int, num_gpus: int, updates: int, chunk_bytes: int,
                     gpu: str) -> tuple[float, float]:
    """``(decode_s, transfer_s)`` of a run's anchor decode (``decode_s`` on one GPU, ``updates``
    updates of ``chunks`` chunks) dealt over ``num_gpus`` GPUs of card ``gpu``: chunk ``k`` on GPU
    ``k mod N``, each GPU decoding its ``ceil(chunks / N)`` at once, and the chunks decoded off the
    pipeline's GPU moving ``chunk_bytes`` out and back over the card's interconnect."""
    per_gpu_chunks = -(-chunks // num_gpus)
    remote = chunks - len(range(0, chunks, num_gpus))  # GPU 0 is the pipeline's
    return decode_s * per_gpu_chunks / chunks, updates * remote * 2 * chunk_bytes / INTERCONNECT_BYTES_PER_S[gpu]


def several_gpus(report: dict[str, Any], num_gpus: int, split_cfg: bool = False) -> dict[str, Any]:
    """Predicted wall time of ``report``'s guided run with ``run.devices`` over ``num_gpus``
    GPUs of one card: the anchor chunks of an update decode on different GPUs at once (forward and
    backward), so the decode stage takes the time of the ``ceil(chunks / num_gpus)`` chunks one GPU
    decodes, plus the transfers of the chunks decoded elsewhere (:func:`decode_over_gpus`). With
    ``split_cfg`` (``run.split_cfg``, two GPUs or more; the GeCo pipeline's) the denoiser's CFG
    halves run on two GPUs at once: its calls, with gradients and without, take half their time,
    plus the transfers of the second half (its latents, text embeddings and output, and their
    gradients in faithful mode's backward). The rest (the estimators, the loss, the unguided steps)
    stays on one GPU.

    Returns per card: ``guided_s``, ``over_unguided_1gpu`` (guided on N GPUs over unguided on one)
    and ``over_unguided_ngpus`` (over unguided on N GPUs, which for one video is the one-GPU time:
    an unguided call's denoiser is not split), and ``decode_s`` / ``transfer_s`` / ``denoiser_s``
    per run.
    """
    if num_gpus < 1:
        raise ValueError(f"--num-gpus must be >= 1, got {num_gpus}")
    settings, counts = report["settings"], report["counts"]
    model = settings_model(settings)
    r, s = model.temporal_compression, model.spatial_compression
    chunks = len(default_anchors(settings["frames"], r))
    chunk_bytes = anchor_chunk_bytes(model, settings["height"], settings["width"], settings.get("chunk_latents"))
    decode = report["per_stage"].get("anchor_decode")
    denoiser_stages = [report["per_stage"][name] for name in ("denoiser_cfg", "denoiser") if name in report["per_stage"]]
    split = split_cfg and num_gpus >= 2 and bool(denoiser_stages)
    # the second CFG half's latents in and output back (bf16), its text embeddings in; a call with
    # gradients moves both gradients back the other way
    latents = ((settings["frames"] - 1) // r + 1) * model.latent_channels * (settings["height"] // s) * (settings["width"] // s)
    tokens, dim = text_embed_shape(model.name)[1:]
    half_bytes = 2 * (2 * latents) + 2 * tokens * dim
    half_transfers = counts.get("denoiser_cfg", 0) + 2 * counts.get("denoiser_grad", 0)
    rows = {}
    for gpu in GPU_SPECS:
        wall = report["roofline"]["wall_time_s"][gpu]
        if wall["guided"] is None or decode is None:
            continue
        decode_s, transfer_s = decode_over_gpus(decode["time_s"][gpu], chunks, num_gpus, counts["updates"],
                                                chunk_bytes, gpu)
        guided = wall["guided"] - decode["time_s"][gpu] + decode_s + transfer_s
        denoiser_s = sum(stage["time_s"][gpu] for stage in denoiser_stages) if denoiser_stages else None
        if split:
            cfg_transfer_s = half_transfers * half_bytes / INTERCONNECT_BYTES_PER_S[gpu]
            guided += denoiser_s / 2 + cfg_transfer_s - denoiser_s
            denoiser_s, transfer_s = denoiser_s / 2, transfer_s + cfg_transfer_s
        logger.info("%d x %s: guided %.0f s predicted", num_gpus, gpu, guided)
        rows[gpu] = {"guided_s": guided, "over_unguided_1gpu": guided / wall["unguided"],
                     "over_unguided_ngpus": guided / wall["unguided"], "decode_s": decode_s, "transfer_s": transfer_s,
                     "denoiser_s": denoiser_s}
    return {"num_gpus": num_gpus, "chunks": chunks, "chunks_per_gpu": -(-chunks // num_gpus), "split_cfg": split,
            "cards": rows}


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
    fits = {g: report["peak_memory_gb"] <= card_memory_gib(g) for g in GPU_SPECS}  # the guided run's peak
    lines = ["| stage | count | TFLOP forward | TFLOP backward | TFLOP total | share | "
             + " | ".join(f"{g} (s)" if fits[g] else f"{g} (s; the peak does not fit)" for g in GPU_SPECS) + " |",
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
        arms = [("unguided", report["peak_memory_gb_unguided"])] + ([("guided", report["peak_memory_gb"])]
                                                                     if wall[gpu]["guided"] else [])
        lines.append(f"{gpu}: " + ", ".join(_card_time(arm, wall[gpu][arm], peak, card_memory_gib(gpu))
                                            for arm, peak in arms) + f" (efficiency {report['roofline']['efficiency']:.2f})")
    return "\n".join(lines)


def _card_time(arm: str, seconds: float, peak_gb: float, memory_gib: float) -> str:
    """An arm's predicted time on a card, or, where its peak exceeds the card's memory, that it
    does not fit there (no time: the run cannot run there as traced)."""
    if peak_gb <= memory_gib:
        return f"{arm} {seconds:.0f} s"
    return f"{arm} does not fit ({peak_gb:.1f} GiB peak > {memory_gib:.1f} GiB)"


