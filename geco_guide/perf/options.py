"""The option types and checks of ``scripts/benchmark.py``: every bad option is one line before any work.

argparse types (:func:`int_at_least`, :func:`positive_float`) refuse a bad number as it is parsed;
:func:`check_options` makes the checks argparse cannot make alone (devices, frame counts, the
``--json`` path, a ``--measured`` report, the ``decoder-agreement`` config) and :func:`fail` ends
the command with one ``error:`` line and exit code 2, as an argparse error.
"""

from __future__ import annotations

import argparse
import math
import sys
from typing import Any, NoReturn

import torch

from ..config import load_config
from ..families import model_named
from ..estimators.loading import WeightsNotFoundError
from ..io.devices import check_device as check_config_device
from ..sampler.config import DECODERS
from ..sampler.multi_device import resolve_devices
from ..sampler.memory_plan import PLAN_NAMES
from ..sampler.slicing import check_num_frames, check_paired_latent_frames
from .cost import GPU_SPECS, H200_UNGUIDED_STEP_S, load_measured
from .decoder_agreement import check_agreement_config
from .measure import RSS_EXACT_MMAP_THRESHOLD, unwritable_reason
from .sampling import NOMINAL_STEPS, SAMPLING_MODES

__all__ = ["OneLineParser", "add_common_options", "add_cost_parser", "add_plans_parser",
           "add_sampling_parser", "check_frames", "check_options", "fail", "frame_count", "positive_float",
           "positive_int"]


class OneLineParser(argparse.ArgumentParser):
    """An argument parser whose errors are one line (``prog: error: ...``), exit code 2."""

    def error(self, message: str) -> NoReturn:  # type: ignore[override]
        self.exit(2, f"{self.prog}: error: {message} (see --help)\n")


def fail(message: str) -> NoReturn:
    """Stop with one ``error:`` line and exit code 2, as an argparse error."""
    print(f"benchmark.py: error: {message}", file=sys.stderr)
    raise SystemExit(2)


def int_at_least(minimum: int) -> Any:
    """argparse type: an integer >= ``minimum``."""
    def parse(value: str) -> int:
        try:
            number = int(value)
        except ValueError:
            raise argparse.ArgumentTypeError(f"must be an integer, got {value!r}") from None
        if number < minimum:
            raise argparse.ArgumentTypeError(f"must be >= {minimum}, got {number}")
        return number

    parse.__name__ = f"integer >= {minimum}"
    return parse


positive_int, non_negative_int = int_at_least(1), int_at_least(0)
#: GeCo and UFM need at least one pair; a causal chunk at least two latents.
frame_count, chunk_latents = int_at_least(2), int_at_least(2)


def positive_float(value: str) -> float:
    """argparse type: a finite number > 0 (``nan`` and ``inf`` are refused)."""
    try:
        number = float(value)
    except ValueError:
        raise argparse.ArgumentTypeError(f"must be a number, got {value!r}") from None
    if not math.isfinite(number) or number <= 0:
        raise argparse.ArgumentTypeError(f"must be a finite number > 0, got {value}")
    return number


def check_device(device: str) -> None:
    try:
        kind = torch.device(device).type
    except (RuntimeError, ValueError):
        fail(f"--device {device!r} is not a torch device (e.g. cpu, cuda, cuda:1)")
    if kind == "cuda" and not torch.cuda.is_available():
        fail(f"--device {device}: no CUDA GPU is available here (use --device cpu)")


def check_frames(frames: int, guided: bool) -> None:
    """The CogVideoX VAE makes 4k+1 frames, and with guidance (anchors decoded in latent pairs) 8k+1."""
    try:
        (check_paired_latent_frames if guided else check_num_frames)(frames, model_named("cogvideox-5b").temporal_compression)
    except ValueError as err:
        fail(f"--frames: {err}")


#: CogVideoX's VAE downsamples 8x and its transformer patches the latents 2x2: a video side is a
#: multiple of 16 (the config's ``sampling.height`` / ``width`` rule); the VAE alone needs 8.
PIPELINE_SIDE_MULTIPLE, VAE_SIDE_MULTIPLE = 16, 8


def check_video_size(height: int | None, width: int | None, multiple: int) -> None:
    """Refuse a side the model cannot take (``None``: the preset's default, which fits)."""
    for name, value in (("--height", height), ("--width", width)):
        if value is not None and value % multiple:
            fail(f"{name} must be a multiple of {multiple}, got {value}")


def agreement_config(args: argparse.Namespace) -> Any:
    """The validated config of ``decoder-agreement`` (preset <- file <- overrides), its device and
    tiny decoder checked; :func:`fail` on any problem."""
    if not args.prompt.strip():
        fail("--prompt must not be empty")
    try:
        cfg = load_config(args.config, args.preset, args.overrides)
        check_config_device(cfg.model.device)
        check_agreement_config(cfg, args.prompt)
    except (ValueError, FileNotFoundError, WeightsNotFoundError) as err:
        fail(str(err))
    return cfg


def check_options(args: argparse.Namespace) -> None:
    """The checks argparse cannot make alone; run before any work."""
    if getattr(args, "device", None) is not None:
        check_device(args.device)
    if getattr(args, "json", None):
        reason = unwritable_reason(args.json)
        if reason:
            fail(f"--json: {reason}")
    if args.command == "vae":
        check_frames(args.frames, guided=False)
        check_video_size(args.height, args.width, VAE_SIDE_MULTIPLE)
    elif args.command == "sampling":
        if args.devices:
            try:
                resolve_devices(args.devices, "--devices")
            except ValueError as err:
                fail(str(err))
        if args.full_size and torch.device(args.device).type == "cpu" and not args.allow_cpu:
            fail("sampling --full-size on CPU is refused: CogVideoX-5B + VGGT-1B + UFM-Base weights alone are "
                 "about 30 GiB in float32 (7.4 G parameters) and a 49x480x720 step would take hours; run it on a "
                 "GPU (--device cuda) or pass --allow-cpu to insist.")
        if args.steps is not None and not 1 <= args.steps <= NOMINAL_STEPS:
            fail(f"--steps must be in [1, {NOMINAL_STEPS}], got {args.steps}")
        if args.frames is not None:
            check_frames(args.frames, guided=args.mode != "unguided")
        check_video_size(args.height, args.width, PIPELINE_SIDE_MULTIPLE)
    elif args.command == "cost":
        if args.decoder != "vae" and args.mode == "unguided":
            fail(f"--decoder {args.decoder} decodes the anchor frames of guidance: use --mode fast or faithful")
        if args.gpu:
            flags = [name for name, value in (("--vae-checkpointing", args.vae_checkpointing),
                                              ("--vae-block-checkpointing", args.vae_block_checkpointing),
                                              ("--denoiser-checkpointing", args.denoiser_checkpointing),
                                              ("--estimator-checkpointing", args.estimator_checkpointing or None))
                     if value is not None]
            if args.mode == "unguided" or args.preset != "full" or flags:
                fail(f"--gpu chooses the memory plan of guidance for CogVideoX-5B: use it with --preset full and "
                     f"--mode fast or faithful, without {', '.join(flags) or 'the checkpointing flags'}")
        if args.steps is not None and args.steps < 1:
            fail(f"--steps must be >= 1, got {args.steps}")
        if args.split_cfg and (args.num_gpus < 2 or args.mode == "unguided"):
            fail("--split-cfg puts the CFG halves of a guided run on two GPUs: use it with --num-gpus 2 or more and "
                 "--mode fast or faithful")
        if args.frames is not None:
            check_frames(args.frames, guided=args.mode != "unguided")
        check_video_size(args.height, args.width, PIPELINE_SIDE_MULTIPLE)
        if args.measured:
            try:
                args.measured_report = load_measured(args.measured)
            except ValueError as err:
                fail(str(err))
    elif args.command == "decoder-agreement":
        args.cfg = agreement_config(args)


# ---- the options of the subcommands that the package's modules run ---------------------------------


def add_common_options(parser: argparse.ArgumentParser, repeats: int) -> None:
    """The options of every micro-benchmark subcommand (one subprocess per case)."""
    parser.add_argument("--device", default="cpu", help="torch device, e.g. cpu or cuda (default: cpu)")
    parser.add_argument("--threads", type=positive_int, default=None,
                        help="torch.set_num_threads in every case (default: torch's default)")
    parser.add_argument("--warmup", type=non_negative_int, default=1, help="untimed runs before timing (default: 1)")
    parser.add_argument("--repeats", type=positive_int, default=repeats, help=f"timed runs (default: {repeats})")
    parser.add_argument("--seed", type=int, default=0, help="seed of weights and inputs (default: 0)")
    parser.add_argument("--json", metavar="PATH", help="also write the results as JSON to PATH")
    add_rss_exact_option(parser)


def add_rss_exact_option(parser: argparse.ArgumentParser) -> None:
    """``--rss-exact``: CPU peaks that follow the live tensors."""
    parser.add_argument("--rss-exact", action="store_true",
                        help="CPU memory: run the workers with glibc's MALLOC_MMAP_THRESHOLD_="
                             f"{RSS_EXACT_MMAP_THRESHOLD}, so that freed tensors leave the resident set at once "
                             "and peak RSS follows the live tensors (slower: every allocation maps fresh pages)")


def add_sampling_parser(sub: Any) -> argparse.ArgumentParser:
    """The ``sampling`` subcommand's options (:mod:`.sampling`)."""
    samp = sub.add_parser("sampling", help="guided vs unguided CogVideoX sampling, same seed, per-stage breakdown")
    size = samp.add_mutually_exclusive_group()
    size.add_argument("--preset", choices=("tiny",), default="tiny",
                      help="tiny random models (default; 17 frames of 32x48, runs anywhere)")
    size.add_argument("--full-size", action="store_true",
                      help="CogVideoX-5B transformer + VAE, VGGT-1B, UFM-Base with random weights, 49x480x720")
    samp.add_argument("--mode", choices=SAMPLING_MODES, default="faithful",
                      help="faithful: backprop through the denoiser (paper); fast: denoiser output held "
                           "constant; unguided: only the unguided arm (default: faithful)")
    samp.add_argument("--steps", type=int, default=None,
                      help=f"denoising steps run (default {NOMINAL_STEPS}); fewer scale the paper schedule "
                           f"and extrapolate the times to {NOMINAL_STEPS} steps")
    samp.add_argument("--frames", type=positive_int, default=None, help="frames (default: 17 tiny, 49 full size)")
    samp.add_argument("--height", type=positive_int, default=None, help="height, a multiple of 16 (default: 32 tiny, 480 full size)")
    samp.add_argument("--width", type=positive_int, default=None, help="width, a multiple of 16 (default: 48 tiny, 720 full size)")
    samp.add_argument("--dtype", choices=("bfloat16", "float32"), default=None,
                      help="transformer/VAE dtype; estimators autocast to it (default: bfloat16 for full size "
                           "on CUDA, else float32)")
    samp.add_argument("--estimator-checkpointing", action="store_true",
                      help="gradient checkpointing in VGGT and UFM (less memory, more backward time)")
    samp.add_argument("--vae-tiling", action="store_true",
                      help="full size: the VAE's spatial tiles (generate's model.vae_tiling), both arms")
    samp.add_argument("--chunk-latents", type=chunk_latents, default=None,
                      help="latents per anchor chunk (default: the paper's 3; 2 decodes 5 frames per anchor instead of 9)")
    samp.add_argument("--no-denoiser-checkpointing", action="store_true",
                      help="faithful mode: backpropagate through the transformer without gradient checkpointing "
                           "(run.gradient_checkpointing=false: one forward less per update, more memory)")
    samp.add_argument("--memory-plan", choices=PLAN_NAMES, default="explicit",
                      help="run.memory_plan of the guided arm (default: explicit, the flags above as "
                           "measured; auto: the plan chosen for the device's memory, recorded in the report)")
    samp.add_argument("--devices", nargs="+", default=None, metavar="DEVICE",
                      help="run.devices of the guided arm: deal its anchor decode over these devices, e.g. "
                           "cuda:0 cuda:1 (each with a replica of the decoder)")
    samp.add_argument("--allow-cpu", action="store_true",
                      help="allow --full-size on CPU (the weights alone are ~30 GiB in float32)")
    samp.add_argument("--device", default="cpu", help="torch device, e.g. cpu or cuda (default: cpu)")
    samp.add_argument("--threads", type=positive_int, default=None, help="torch.set_num_threads in both arms")
    samp.add_argument("--warmup", type=non_negative_int, default=1,
                      help="untimed 2-step calls of the same arm before the timed one (default: 1)")
    samp.add_argument("--seed", type=int, default=0, help="seed of weights, text embeddings and noise (default: 0)")
    samp.add_argument("--json", metavar="PATH", help="also write the report as JSON to PATH")
    add_rss_exact_option(samp)
    return samp


def add_cost_parser(sub: Any) -> argparse.ArgumentParser:
    """The ``cost`` subcommand's options (:mod:`.cost`)."""
    cost = sub.add_parser("cost", help="FLOPs, memory and a roofline time of sampling at full size, on fake tensors "
                                       "(no weights, no GPU)")
    cost.add_argument("--preset", choices=("full", "tiny"), default="full",
                      help="full: CogVideoX-5B, VGGT-1B, UFM-Base at 49x480x720 (default); tiny: the tiny pipeline")
    cost.add_argument("--mode", choices=SAMPLING_MODES, default="faithful",
                      help="guided mode to model beside the unguided run (default: faithful)")
    cost.add_argument("--steps", type=int, default=None, help="denoising steps (default: 50 full, 4 tiny)")
    cost.add_argument("--frames", type=positive_int, default=None, help="frames (default: 49 full, 17 tiny)")
    cost.add_argument("--height", type=positive_int, default=None, help="height, a multiple of 16 (default: 480 full, 32 tiny)")
    cost.add_argument("--width", type=positive_int, default=None, help="width, a multiple of 16 (default: 720 full, 48 tiny)")
    cost.add_argument("--dtype", choices=("bfloat16", "float32"), default=None,
                      help="transformer/VAE dtype and the estimators' trunks (default: bfloat16 full, float32 tiny)")
    cost.add_argument("--chunk-latents", type=chunk_latents, default=None, help="latents per anchor chunk (default: the preset's)")
    cost.add_argument("--vae-checkpointing", choices=("on", "off"), default=None,
                      help="run.vae_checkpointing, the anchor chunks one at a time (default: the preset's: "
                           "on full, off tiny)")
    cost.add_argument("--vae-block-checkpointing", choices=("on", "off"), default=None,
                      help="run.vae_block_checkpointing: the VAE's own block checkpointing (default: as "
                           "--vae-checkpointing)")
    cost.add_argument("--gpu", choices=tuple(GPU_SPECS), default=None,
                      help="model the memory plan that run.memory_plan=auto picks for this card's memory "
                           "(with model CPU offload where none fits without)")
    cost.add_argument("--denoiser-checkpointing", choices=("on", "off"), default=None,
                      help="run.gradient_checkpointing (default: the preset's: on full, off tiny)")
    cost.add_argument("--estimator-checkpointing", action="store_true", help="VGGT and UFM gradient checkpointing")
    cost.add_argument("--vae-tiling", action="store_true", help="the VAE's spatial tiles (model.vae_tiling)")
    cost.add_argument("--decoder", choices=DECODERS, default="vae",
                      help="what decodes the anchor frames (guidance.decoder): the VAE (exact, default) or the "
                           "tiny TAEHV decoder (an approximation whose fidelity `decoder-agreement` measures)")
    cost.add_argument("--no-time-travel", action="store_true", help="the schedule without its time-travel window")
    cost.add_argument("--paper-schedule", action="store_true",
                      help="tiny preset: the paper's 50-step schedule instead of the tiny 4-step one (as `sampling`)")
    cost.add_argument("--calibration-step-s", type=positive_float, default=H200_UNGUIDED_STEP_S,
                      help=f"measured seconds of one unguided CFG step on the H200 (default {H200_UNGUIDED_STEP_S})")
    cost.add_argument("--measured", metavar="JSON",
                      help="a `sampling` report of the same settings on an H200: add predicted vs measured")
    cost.add_argument("--num-gpus", type=positive_int, default=1,
                      help="also predict the guided run with run.devices over this many GPUs of the card "
                           "(the anchor chunks decoded on different GPUs at once)")
    cost.add_argument("--split-cfg", action="store_true",
                      help="with --num-gpus 2 or more: also the denoiser's CFG halves on two GPUs (run.split_cfg)")
    cost.add_argument("--dynamic-masks", action="store_true",
                      help="add the overhead of guidance.dynamic masks refreshed at each guided step: SAM 3 "
                           "(predicted, its vision encoder) and the automatic masks (measured on a CPU thread)")
    cost.add_argument("--threads", type=positive_int, default=None, help="torch.set_num_threads")
    cost.add_argument("--seed", type=int, default=0, help="seed (shapes only; default: 0)")
    cost.add_argument("--json", metavar="PATH", help="also write the report as JSON to PATH")
    return cost


def add_plans_parser(sub: Any) -> argparse.ArgumentParser:
    """The ``plans`` subcommand's options (:mod:`.plans`)."""
    from .plans import KNOWN_MODELS

    plans = sub.add_parser("plans", help="the memory plans' estimates of the known models (the package data "
                                         "run.memory_plan=auto reads), from the cost model")
    plans.add_argument("--models", nargs="+", choices=tuple(KNOWN_MODELS), default=list(KNOWN_MODELS),
                       help="the models to trace (default: all)")
    plans.add_argument("--threads", type=positive_int, default=None, help="torch.set_num_threads")
    plans.add_argument("--json", metavar="PATH", help="write the estimates as JSON to PATH")
    return plans
