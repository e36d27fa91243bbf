"""The work of each ``geco bench`` subcommand once its options passed their checks
(:mod:`geco_guide.perf.bench_checks`): each takes the parsed options, the command line's arguments
(recorded in the report) and where the lines of its progress go, and returns the report that
``--json`` writes and the Markdown the command prints (None where it prints none).
"""

from __future__ import annotations

import argparse
import logging
import sys
from collections.abc import Callable
from pathlib import Path
from typing import Any

from .bench_checks import BadOption, check_frames

__all__ = ["WORK", "WORKER", "Work", "attention_shapes", "cost_report_of", "decoder_agreement_of", "family_report",
           "geco_eval_cost_of", "micro_benchmark", "parallel_report_of", "plan_estimates_of", "sampling_benchmark"]

logger = logging.getLogger(__name__)

#: The child process of every case: the internal ``worker`` subcommand of ``geco bench``, whose
#: module runs as a script.
WORKER = (sys.executable, "-m", "geco_guide.cli.bench", "worker")
#: What a subcommand's work returns: the report (``--json``) and the Markdown printed, if any.
Report = tuple[dict[str, Any], str | None]
Work = Callable[[argparse.Namespace, list[str], Callable[[str], None]], Report]
#: The H200 sampling run whose estimator calls give the per-call times of the ``geco-eval`` estimate.
H200_SAMPLING_RUN = Path(__file__).resolve().parents[2] / "docs" / "benchmarks" / "sampling_full_h200_fast.json"


def micro_benchmark(args: argparse.Namespace, argv: list[str], say: Callable[[str], None]) -> Report:
    """``loss``, ``estimators``, ``vae``: each case in a worker process of its own."""
    from .measure import CASE_COLUMNS, environment_info, markdown_table, run_cases
    from .workloads import estimator_specs, loss_specs, vae_specs

    specs = {"loss": loss_specs, "estimators": estimator_specs, "vae": vae_specs}[args.command](args)
    results = run_cases(specs, WORKER)
    return ({"subcommand": args.command, "argv": argv, "environment": environment_info(results[0]["threads"]),
             "results": results}, markdown_table(results, CASE_COLUMNS))


def sampling_benchmark(args: argparse.Namespace, argv: list[str], say: Callable[[str], None]) -> Report:
    """``sampling``: guided vs unguided sampling through the generation path, in workers."""
    from .sampling import sampling_report, sampling_spec, sampling_table

    spec = sampling_spec(
        full_size=args.full_size, mode=args.mode, steps=args.steps, frames=args.frames, height=args.height,
        width=args.width, device=args.device, dtype=args.dtype, threads=args.threads, seed=args.seed,
        warmup=args.warmup, estimator_checkpointing=args.estimator_checkpointing, chunk_latents=args.chunk_latents,
        vae_tiling=args.vae_tiling, rss_exact=args.rss_exact, no_denoiser_checkpointing=args.no_denoiser_checkpointing,
        memory_plan=args.memory_plan, devices=args.devices)
    check_frames(spec["frames"], guided=args.mode != "unguided")  # a preset's default frame count too
    report = sampling_report(spec, WORKER, argv)
    return report, sampling_table(report)


def _on_off(value: str | None) -> bool | None:
    return None if value is None else value == "on"


def _set_threads(args: argparse.Namespace) -> None:
    import torch

    if args.threads:
        torch.set_num_threads(args.threads)


def cost_report_of(args: argparse.Namespace, argv: list[str], say: Callable[[str], None]) -> Report:
    """``cost``: one model's sampling traced on fake tensors, with a card's memory plan (``--gpu``),
    the measured report beside it (``--measured``), the dynamic masks' overhead and several GPUs."""
    from .cost import compare_with_measured, cost_report, cost_settings, cost_table, several_gpus, several_gpus_table
    from .plans import card_plan, with_card

    if args.dynamic_masks and args.mode == "unguided":
        logger.warning("warning: --dynamic-masks has no effect with --mode unguided (the masks act on guided updates "
                       "only)")
    _set_threads(args)
    settings = cost_settings(
        preset=args.preset, model=args.model, steps=args.steps, frames=args.frames, height=args.height,
        width=args.width, dtype=args.dtype, no_time_travel=args.no_time_travel, paper_schedule=args.paper_schedule,
        seed=args.seed, chunk_latents=args.chunk_latents, vae_checkpointing=_on_off(args.vae_checkpointing),
        vae_block_checkpointing=_on_off(args.vae_block_checkpointing),
        denoiser_checkpointing=_on_off(args.denoiser_checkpointing), estimator_checkpointing=args.estimator_checkpointing,
        vae_tiling=args.vae_tiling, calibration_step_s=args.calibration_step_s, decoder=args.decoder)
    card = None
    if args.gpu:
        card = card_plan(args.gpu, args.mode, args.decoder, settings["frames"], settings["height"], settings["width"],
                         model=args.model)
        if card["plan"] is None:
            raise BadOption(f"--gpu {args.gpu}: {card['reason']}")
        settings["plan"] = card["plan"]
    report = cost_report(settings, args.mode, argv)
    if card:
        report = with_card(report, card)
    if args.measured_report is not None:
        report["validation"] = compare_with_measured(report, args.measured_report, args.measured)
    tables = [cost_table(report)]
    if args.dynamic_masks and args.mode != "unguided":
        from .mask_cost import dynamic_mask_costs

        report["dynamic_masks"] = dynamic_mask_costs(settings["steps"])
    if args.num_gpus > 1 and args.mode != "unguided":
        report["several_gpus"] = several_gpus(report, args.num_gpus, split_cfg=args.split_cfg)
        tables.append(several_gpus_table(report["several_gpus"]))
    if "dynamic_masks" in report:
        from .mask_cost import dynamic_masks_table

        tables.append(dynamic_masks_table(report["dynamic_masks"]))
    return report, "\n".join(tables)


def family_report(args: argparse.Namespace, argv: list[str], say: Callable[[str], None]) -> Report:
    """``cost --all-models``: the per-family table of the shipped estimates."""
    from .family_table import family_rows, family_table

    return ({"subcommand": "cost --all-models", "note": "predicted by the cost model, from the shipped estimates "
             "(geco_guide/sampler/running/data/memory_plans.json)", "rows": family_rows()}, family_table())


def parallel_report_of(args: argparse.Namespace, argv: list[str], say: Callable[[str], None]) -> Report:
    """``cost --context-parallel N``: one model over N GPUs of each card, from the shipped estimates."""
    from .parallel_cost import parallel_report, parallel_table

    report = parallel_report(args.model, args.mode, args.context_parallel)
    return {**report, "argv": argv}, parallel_table(report)


def attention_shapes(args: argparse.Namespace, argv: list[str], say: Callable[[str], None]) -> Report:
    """``attention-shapes``: the denoisers' attention calls traced; ``say`` gets a line per model."""
    from .attention_shapes import attention_file

    _set_threads(args)
    return attention_file(args.models, argv, on_model=say), None


def plan_estimates_of(args: argparse.Namespace, argv: list[str], say: Callable[[str], None]) -> Report:
    """``plans``: the memory plans' estimates of every traced model; ``say`` gets a line per report."""
    from .plans import plan_estimates

    _set_threads(args)
    return plan_estimates(args.models, argv, on_report=say), None


def decoder_agreement_of(args: argparse.Namespace, argv: list[str], say: Callable[[str], None]) -> Report:
    """``decoder-agreement``: one guided call with both decoders at every update (``args.cfg``:
    the config checked before, :func:`~geco_guide.perf.bench_checks.agreement_config`)."""
    from .decoder_agreement import agreement_table, decoder_agreement

    _set_threads(args)
    try:
        report = decoder_agreement(args.cfg, args.prompt, argv)
    except (ValueError, FileNotFoundError) as err:  # a checkpoint that is not there or not readable
        raise BadOption(str(err)) from None
    return report, agreement_table(report)


def geco_eval_cost_of(args: argparse.Namespace, argv: list[str], say: Callable[[str], None]) -> Report:
    """``geco-eval``: the estimator calls and time of scoring one video under each pair mode."""
    from .scoring_cost import geco_eval_cost, geco_eval_table

    _set_threads(args)
    report = geco_eval_cost(frames=args.frames, fps=args.fps, height=args.height, width=args.width, pairs=args.pairs,
                            videos=args.videos, seed=args.seed, h200_run=H200_SAMPLING_RUN, argv=argv,
                            geometry=args.geometry_estimator)
    return report, geco_eval_table(report)


#: The work of each subcommand (``cost``'s two table modes are :func:`family_report` and
#: :func:`parallel_report_of`).
WORK: dict[str, Work] = {
    "loss": micro_benchmark, "estimators": micro_benchmark, "vae": micro_benchmark, "sampling": sampling_benchmark,
    "cost": cost_report_of, "plans": plan_estimates_of, "attention-shapes": attention_shapes,
    "decoder-agreement": decoder_agreement_of, "geco-eval": geco_eval_cost_of}
