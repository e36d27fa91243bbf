"""``geco bench``: time and memory of geco_guide, measured or predicted (the perf harness over :mod:`geco_guide.perf`).

    geco bench loss --frames 4 --height 480 --width 720 --repeats 3
    geco bench sampling --preset tiny --mode fast --steps 2 --warmup 0
    geco bench cost --model wan2.1-t2v-14b --mode faithful --gpu H200
    geco bench cost --all-models
    geco bench cost --model wan2.2-t2v-a14b --context-parallel 4
    geco bench plans --threads 1 --json geco_guide/sampler/data/memory_plans.json

Subcommands (docs/performance.md says what each measures and how to read it):

* ``loss``, ``estimators``, ``vae``: micro-benchmarks of the GeCo loss core, VGGT / UFM and the
  anchor-chunk VAE decode, forward and forward+backward, one subprocess per case (the internal
  ``worker`` subcommand), so that each case's peak memory is its own.
* ``sampling``: guided vs unguided sampling from the same seed through the generation path
  (``--preset tiny``, or ``--full-size``: CogVideoX-5B with random weights), wall time, a
  per-stage breakdown and peak memory.
* ``cost``: FLOPs, memory and a roofline GPU time of a registry model's sampling on fake tensors
  (no weights, no GPU); ``--all-models``: the per-family table from the shipped estimates;
  ``--context-parallel N``: one model over N GPUs of each card (context parallelism, split CFG,
  ``run.devices``), from the shipped estimates and attention shapes.
* ``plans``: the memory plans' estimates of every traced model (the package data
  ``run.memory_plan=auto`` reads); ``attention-shapes``: the denoisers' traced attention calls (the
  package data the several-GPU costs read).
* ``decoder-agreement``: one guided generation with both decoders at every update.
* ``geco-eval``: the estimator calls and time of scoring one video under each pair mode.

Results are printed as Markdown and written as JSON with ``--json PATH`` (atomically). Every option
is checked before any work starts: a bad one is a single ``error:`` line and exit code 2.
"""

from __future__ import annotations

import argparse
import json
import math
import sys
from typing import Any

from ..families.published import PackageDataError, traced_models
from ..perf.cards import GPU_SPECS, H200_UNGUIDED_STEP_S
from .kit import Parser, check_choice, command_main, interruptible, print_error

__all__ = ["DESCRIPTION", "SUMMARY", "main", "register_subcommand", "run"]

SUMMARY = "time and memory: micro-benchmarks, sampling, the cost model of every family, memory plans, search"
DESCRIPTION = ("Time and memory of geco_guide: micro-benchmarks and sampling measured here, the cost model's "
               "predictions for every family on fake tensors (no weights, no GPU), the memory plans' estimates.")
#: The prompt of ``decoder-agreement`` unless ``--prompt`` says otherwise.
AGREEMENT_PROMPT = "a marble bust on a wooden table, the camera orbiting it slowly"
#: The public subcommands, in ``--help``'s order (``worker`` is internal: it runs one case).
#: the geometry backbones ``estimators.geometry`` names (written here: the parser imports no torch)
GEOMETRY_CHOICES = ("vggt-1b", "da3-small", "da3-base")
SUBCOMMANDS = ("loss", "estimators", "vae", "sampling", "cost", "plans", "attention-shapes", "decoder-agreement",
               "geco-eval")
#: Named memory plans and anchor decoders, checked in :func:`run` (their lists live with torch).
CHECKED_LATER = "checked before any work"
#: faithful: backpropagate through the denoiser (the paper); fast: its output held constant;
#: unguided: no guidance.
SAMPLING_MODES = ("faithful", "fast", "unguided")


class BadOption(ValueError):
    """An option value the parser could not refuse alone (one line)."""


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


# ---- the options --------------------------------------------------------------------------------


def _threads(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--threads", type=positive_int, default=None, help="torch.set_num_threads")


def _json(parser: argparse.ArgumentParser, what: str = "also write the report as JSON to PATH") -> None:
    parser.add_argument("--json", metavar="PATH", help=what)


def _rss_exact(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--rss-exact", action="store_true",
                        help="CPU memory: run the workers with a small glibc MALLOC_MMAP_THRESHOLD_ (64 KiB), "
                             "so that freed tensors leave the resident set at once "
                             "and peak RSS follows the live tensors (slower: every allocation maps fresh pages)")


def _common(parser: argparse.ArgumentParser, repeats: int) -> None:
    """The options of every micro-benchmark subcommand (one subprocess per case)."""
    parser.add_argument("--device", default="cpu", help="torch device, e.g. cpu or cuda (default: cpu)")
    parser.add_argument("--threads", type=positive_int, default=None,
                        help="torch.set_num_threads in every case (default: torch's default)")
    parser.add_argument("--warmup", type=non_negative_int, default=1, help="untimed runs before timing (default: 1)")
    parser.add_argument("--repeats", type=positive_int, default=repeats, help=f"timed runs (default: {repeats})")
    parser.add_argument("--seed", type=int, default=0, help="seed of weights and inputs (default: 0)")
    _json(parser, "also write the results as JSON to PATH")
    _rss_exact(parser)


def _micro(sub: Any) -> None:
    loss = sub.add_parser("loss", help="GeCo loss core (geco_from_geometry) forward / forward+backward")
    loss.add_argument("--frames", type=frame_count, default=4, help="frames S (default: 4)")
    loss.add_argument("--height", type=positive_int, default=480, help="frame height (default: 480)")
    loss.add_argument("--width", type=positive_int, default=720, help="frame width (default: 720)")
    loss.add_argument("--pairs", default="adjacent", metavar="MODE",
                      help=f"frame pairs: adjacent (default), center or all ({CHECKED_LATER})")
    _common(loss, repeats=3)

    est = sub.add_parser("estimators", help="the geometry backbone (VGGT-1B or DA3) and UFM forward / "
                                            "forward+backward w.r.t. the frames")
    est.add_argument("--geometry-estimator", choices=GEOMETRY_CHOICES, default="vggt-1b",
                     help="the geometry backbone timed (default: vggt-1b)")
    est.add_argument("--size", choices=("tiny", "full", "both"), default="tiny",
                     help="tiny configs, the full architectures (the geometry backbone's and UFM-Base's; random "
                          "weights), or both")
    est.add_argument("--frames", type=frame_count, default=2,
                     help="frames S; UFM gets the S - 1 adjacent pairs (default: 2)")
    est.add_argument("--height", type=positive_int, default=140, help="input frame height (default: 140)")
    est.add_argument("--width", type=positive_int, default=210, help="input frame width (default: 210)")
    est.add_argument("--dtype", choices=("float32", "bfloat16"), default="float32",
                     help="storage dtype of the ViT trunks (trunk_to); heads stay float32 (default: float32)")
    _common(est, repeats=3)

    vae = sub.add_parser("vae", help="the anchor-chunk VAE decode of one guided update, forward / forward+backward")
    vae.add_argument("--size", choices=("tiny", "full"), default="tiny",
                     help="the tiny VAE or the CogVideoX-5B VAE architecture (random weights)")
    vae.add_argument("--frames", type=positive_int, default=49,
                     help="video frames 4k+1, anchors spread as in sampling (default: 49)")
    vae.add_argument("--height", type=positive_int, default=480, help="video height, a multiple of 8 (default: 480)")
    vae.add_argument("--width", type=positive_int, default=720, help="video width, a multiple of 8 (default: 720)")
    vae.add_argument("--dtype", choices=("float32", "bfloat16"), default="bfloat16",
                     help="VAE dtype (default: bfloat16, as the pipeline on a GPU)")
    vae.add_argument("--vae-checkpointing", action="store_true",
                     help="run.vae_checkpointing: one checkpointed decode per chunk, and the VAE's own "
                          "block checkpointing inside")
    vae.add_argument("--vae-tiling", action="store_true",
                     help="vae.enable_tiling with tiles of half the video size, as at 480x720")
    _common(vae, repeats=1)


def _sampling(sub: Any) -> None:
    samp = sub.add_parser("sampling", help="guided vs unguided sampling through the generation path, same seed, "
                                           "per-stage breakdown")
    size = samp.add_mutually_exclusive_group()
    size.add_argument("--preset", choices=("tiny",), default="tiny",
                      help="tiny random models (default; 17 frames of 32x48, runs anywhere)")
    size.add_argument("--full-size", action="store_true",
                      help="CogVideoX-5B transformer + VAE, VGGT-1B, UFM-Base with random weights, 49x480x720")
    samp.add_argument("--mode", choices=SAMPLING_MODES, default="faithful",
                      help="faithful: backprop through the denoiser (paper); fast: denoiser output held "
                           "constant; unguided: only the unguided arm (default: faithful)")
    samp.add_argument("--steps", type=int, default=None,
                      help="denoising steps run (default: the paper's 50); fewer scale the paper schedule "
                           "and extrapolate the times to 50 steps")
    samp.add_argument("--frames", type=positive_int, default=None, help="frames (default: 17 tiny, 49 full size)")
    samp.add_argument("--height", type=positive_int, default=None,
                      help="height, a multiple of 16 (default: 32 tiny, 480 full size)")
    samp.add_argument("--width", type=positive_int, default=None,
                      help="width, a multiple of 16 (default: 48 tiny, 720 full size)")
    samp.add_argument("--dtype", choices=("bfloat16", "float32"), default=None,
                      help="transformer/VAE dtype; estimators autocast to it (default: bfloat16 for full size "
                           "on CUDA, else float32)")
    samp.add_argument("--estimator-checkpointing", action="store_true",
                      help="gradient checkpointing in VGGT and UFM (less memory, more backward time)")
    samp.add_argument("--vae-tiling", action="store_true",
                      help="full size: the VAE's spatial tiles (model.vae_tiling), both arms")
    samp.add_argument("--chunk-latents", type=chunk_latents, default=None,
                      help="latents per anchor chunk (default: the paper's 3; 2 decodes 5 frames per anchor instead of 9)")
    samp.add_argument("--no-denoiser-checkpointing", action="store_true",
                      help="faithful mode: backpropagate through the transformer without gradient checkpointing "
                           "(run.gradient_checkpointing=false: one forward less per update, more memory)")
    samp.add_argument("--memory-plan", default="explicit", metavar="PLAN",
                      help="run.memory_plan of the guided arm: explicit (default: the flags above as measured), "
                           f"auto (the plan chosen for the device's memory, recorded in the report) or a named plan "
                           f"({CHECKED_LATER})")
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
    _json(samp)
    _rss_exact(samp)


def _cost(sub: Any) -> None:
    cost = sub.add_parser("cost", help="FLOPs, memory and a roofline time of a model's sampling on fake tensors "
                                       "(no weights, no GPU); --all-models: the per-family table")
    cost.add_argument("--all-models", action="store_true",
                      help="print the per-family table (every traced model on an H200 and a 24 GB card: unguided, "
                           "fast, faithful, tiny decoder, search at matched particles, 4 GPUs) from the shipped "
                           "estimates that `geco bench plans` writes; traces nothing")
    cost.add_argument("--model", choices=traced_models(), default="cogvideox-5b",
                      help="the registry model to trace at its default call (default: cogvideox-5b, the paper's)")
    cost.add_argument("--preset", choices=("full", "tiny"), default="full",
                      help="full: --model with VGGT-1B and UFM-Base (default); tiny: the tiny CogVideoX pipeline")
    cost.add_argument("--mode", choices=SAMPLING_MODES, default="faithful",
                      help="guided mode to model beside the unguided run (default: faithful)")
    cost.add_argument("--steps", type=int, default=None, help="denoising steps (default: the model's, 4 tiny)")
    cost.add_argument("--frames", type=positive_int, default=None, help="frames (default: the model's, 17 tiny)")
    cost.add_argument("--height", type=positive_int, default=None, help="height (default: the model's, 32 tiny)")
    cost.add_argument("--width", type=positive_int, default=None, help="width (default: the model's, 48 tiny)")
    cost.add_argument("--dtype", choices=("bfloat16", "float32"), default=None,
                      help="transformer/VAE dtype and the estimators' trunks (default: bfloat16 full, float32 tiny)")
    cost.add_argument("--chunk-latents", type=chunk_latents, default=None,
                      help="latents per anchor chunk (default: the preset's)")
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
    cost.add_argument("--decoder", default="vae", metavar="DECODER",
                      help="what decodes the anchor frames (guidance.decoder): vae (exact, default) or tiny (the "
                           "model's TAEHV decoder, an approximation whose fidelity `decoder-agreement` measures)")
    cost.add_argument("--no-time-travel", action="store_true", help="the schedule without its time-travel window")
    cost.add_argument("--paper-schedule", action="store_true",
                      help="tiny preset: the paper's 50-step schedule instead of the tiny 4-step one (as `sampling`)")
    cost.add_argument("--calibration-step-s", type=positive_float, default=H200_UNGUIDED_STEP_S,
                      help=f"measured seconds of one unguided CFG step on the H200 (default {H200_UNGUIDED_STEP_S})")
    cost.add_argument("--measured", metavar="JSON",
                      help="a `sampling` report of the same settings on an H200: add predicted vs measured")
    cost.add_argument("--num-gpus", type=positive_int, default=1,
                      help="also predict the guided run with run.devices over this many GPUs of each card "
                           "(the anchor chunks decoded on different GPUs at once)")
    cost.add_argument("--split-cfg", action="store_true",
                      help="with --num-gpus 2 or more: also the denoiser's CFG halves on two GPUs (run.split_cfg)")
    cost.add_argument("--context-parallel", type=int_at_least(2), default=None, metavar="N",
                      help="predict --model over N GPUs of each card with the denoiser's tokens split over them "
                           "(run.context_parallel), beside run.devices and one GPU, from the shipped estimates and "
                           "attention shapes; traces nothing (with --mode and --json only)")
    cost.add_argument("--dynamic-masks", action="store_true",
                      help="add the overhead of guidance.dynamic masks refreshed at each guided step: SAM 3 "
                           "(predicted, its vision encoder), the automatic masks and guidance.loss.movers=rigid "
                           "(measured on a CPU thread)")
    _threads(cost)
    cost.add_argument("--seed", type=int, default=0, help="seed (shapes only; default: 0)")
    _json(cost)


def _plans(sub: Any) -> None:
    plans = sub.add_parser("plans", help="the memory plans' estimates of every traced model (the package data "
                                         "run.memory_plan=auto reads), from the cost model")
    models = [*traced_models(), "tiny"]
    plans.add_argument("--models", nargs="+", choices=models, default=models, help="the models to trace (default: all)")
    _threads(plans)
    _json(plans, "write the estimates as JSON to PATH")
    shapes = sub.add_parser("attention-shapes", help="the attention calls of every traced model's denoiser (the "
                                                     "package data of the several-GPU costs), traced on fake tensors")
    shapes.add_argument("--models", nargs="+", choices=traced_models(), default=traced_models(),
                        help="the models to trace (default: all)")
    _threads(shapes)
    _json(shapes, "write the attention shapes as JSON to PATH")


def _others(sub: Any) -> None:
    agree = sub.add_parser("decoder-agreement", help="both decoders at every guidance update of one guided call: "
                                                     "gradient cosine, losses, anchor-frame PSNR")
    agree.add_argument("--preset", default=None,
                       help="a preset of configs/ (tiny: the tiny random models, offline); default: the schema's")
    agree.add_argument("--config", metavar="YAML", default=None, help="a config file over the preset")
    agree.add_argument("--prompt", default=AGREEMENT_PROMPT, help="the prompt (default: a marble bust, orbiting)")
    _threads(agree)
    _json(agree)
    agree.add_argument("overrides", nargs="*", metavar="key=value",
                       help="config overrides, e.g. estimators.tiny_decoder=/path/to/taecvx.pth guidance.decoder=tiny")

    geval = sub.add_parser("geco-eval", help="estimator calls and time of scoring one video under each pair mode "
                                             "(tiny on CPU, estimated at full size on an H200)")
    geval.add_argument("--frames", type=frame_count, default=49, help="frames of the clip (default: 49, CogVideoX)")
    geval.add_argument("--fps", type=positive_float, default=16.0, help="its native frame rate (default: 16, CogVideoX)")
    geval.add_argument("--height", type=positive_int, default=32, help="height of the tiny run (default: 32)")
    geval.add_argument("--width", type=positive_int, default=48, help="width of the tiny run (default: 48)")
    geval.add_argument("--pairs", nargs="+", default=["all", "center", "adjacent"], metavar="MODE",
                       help="the frame pairs of each window to estimate, one row each (default: all center adjacent)")
    geval.add_argument("--videos", type=positive_int, default=320,
                       help="videos per model (default: 320 = 80 prompts x 4 seeds)")
    geval.add_argument("--geometry-estimator", choices=GEOMETRY_CHOICES, default="vggt-1b",
                       help="the geometry backbone of the estimate (default: vggt-1b; a DA3 backbone's time is "
                            "VGGT-1B's scaled by their FLOPs: predicted)")
    _threads(geval)
    geval.add_argument("--seed", type=int, default=0, help="seed of the random clip (default: 0)")
    _json(geval)


def register_subcommand(parser: argparse.ArgumentParser) -> argparse.ArgumentParser:
    """The subcommands of ``geco bench`` and their options on ``parser``; the internal ``worker``
    (one case in its own process) stays out of ``--help``."""
    sub = parser.add_subparsers(dest="command", required=True, parser_class=Parser)
    _micro(sub)
    _sampling(sub)
    _cost(sub)
    _plans(sub)
    _others(sub)
    worker = sub.add_parser("worker", description="internal: run one case given as JSON, print its result as JSON")
    worker.add_argument("spec", help="the case, as JSON")
    sub.metavar = "{" + ",".join(SUBCOMMANDS) + "}"
    return parser


# ---- the checks argparse cannot make alone ---------------------------------------------------------


#: A video side the CogVideoX pipeline takes (its VAE's 8x and the transformer's 2x2 patches), and the VAE's.
PIPELINE_SIDE_MULTIPLE, VAE_SIDE_MULTIPLE = 16, 8


def _check_device(device: str) -> None:
    import torch

    try:
        kind = torch.device(device).type
    except (RuntimeError, ValueError):
        raise BadOption(f"--device {device!r} is not a torch device (e.g. cpu, cuda, cuda:1)") from None
    if kind == "cuda" and not torch.cuda.is_available():
        raise BadOption(f"--device {device}: no CUDA GPU is available here (use --device cpu)")


def _check_frames(frames: int, guided: bool, model: str = "cogvideox-5b") -> None:
    """A frame count registry ``model``'s VAE makes (its ``frame_multiple k + 1``); the CogVideoX
    VAE 4k+1, and with guidance (anchors decoded in latent pairs) 8k+1."""
    from ..families import frames_problem, model_named
    from ..sampler.slicing import check_num_frames, check_paired_latent_frames

    entry = model_named(model)
    if not entry.cogvideox_vae:
        problem = frames_problem(frames, entry.frame_multiple)
        if problem is not None:
            raise BadOption(f"--frames {problem}")
        return
    try:
        (check_paired_latent_frames if guided else check_num_frames)(frames, entry.temporal_compression)
    except ValueError as err:
        raise BadOption(f"--frames: {err}") from None


def _check_sides(height: int | None, width: int | None, multiple: int) -> None:
    for name, value in (("--height", height), ("--width", width)):
        if value is not None and value % multiple:
            raise BadOption(f"{name} must be a multiple of {multiple}, got {value}")


def _size_multiple(model: str) -> int:
    from ..families import model_named

    return model_named(model).size_multiple


#: ``cost`` options that trace one model, which ``--all-models`` (a table of the shipped estimates) does not take.
TRACE_OPTIONS = ("model", "preset", "mode", "steps", "frames", "height", "width", "dtype", "chunk_latents",
                 "vae_checkpointing", "vae_block_checkpointing", "gpu", "denoiser_checkpointing",
                 "estimator_checkpointing", "vae_tiling", "decoder", "no_time_travel", "paper_schedule",
                 "calibration_step_s", "measured", "num_gpus", "split_cfg", "dynamic_masks", "threads", "seed")


def _check_all_models(args: argparse.Namespace, parser_defaults: dict[str, Any]) -> None:
    from ..perf.measure import unwritable_reason

    given = [f"--{name.replace('_', '-')}" for name in TRACE_OPTIONS if getattr(args, name) != parser_defaults[name]]
    if given:
        raise BadOption(f"--all-models prints the table of the shipped estimates and traces nothing: leave out "
                        f"{', '.join(given)} (or trace one model without --all-models)")
    reason = unwritable_reason(args.json) if args.json else None
    if reason:
        raise BadOption(f"--json: {reason}")


def _check_context_parallel(args: argparse.Namespace, parser_defaults: dict[str, Any]) -> None:
    given = [f"--{name.replace('_', '-')}" for name in TRACE_OPTIONS
             if name not in ("model", "mode") and getattr(args, name) != parser_defaults[name]]
    if args.all_models or given:
        raise BadOption(f"--context-parallel predicts from the shipped estimates and traces nothing: leave out "
                        f"{', '.join(given or ['--all-models'])} (the table of --all-models has its 4-GPU columns)")
    _check_all_models(args, {**parser_defaults, "model": args.model, "mode": args.mode})  # and --json's path


def _check_cost(args: argparse.Namespace) -> None:
    from ..perf.cost import load_measured
    from ..sampler.config import DECODERS

    if args.preset == "tiny" and args.model != COST_DEFAULTS["model"]:
        raise BadOption(f"--model {args.model} traces a full-size model: leave out --preset tiny (the tiny models "
                        "are CogVideoX's)")
    if args.decoder not in DECODERS:
        raise BadOption(f"--decoder must be one of {', '.join(DECODERS)}, got {args.decoder!r}")
    if args.decoder != "vae" and args.mode == "unguided":
        raise BadOption(f"--decoder {args.decoder} decodes the anchor frames of guidance: use --mode fast or faithful")
    if args.gpu:
        flags = [name for name, value in (("--vae-checkpointing", args.vae_checkpointing),
                                          ("--vae-block-checkpointing", args.vae_block_checkpointing),
                                          ("--denoiser-checkpointing", args.denoiser_checkpointing),
                                          ("--estimator-checkpointing", args.estimator_checkpointing or None))
                 if value is not None]
        if args.mode == "unguided" or args.preset != "full" or flags:
            raise BadOption(f"--gpu chooses the memory plan of guidance for a full-size model: use it with --preset "
                            f"full and --mode fast or faithful, without {', '.join(flags) or 'the checkpointing flags'}")
    if args.steps is not None and args.steps < 1:
        raise BadOption(f"--steps must be >= 1, got {args.steps}")
    if args.split_cfg and (args.num_gpus < 2 or args.mode == "unguided"):
        raise BadOption("--split-cfg puts the CFG halves of a guided run on two GPUs: use it with --num-gpus 2 or "
                        "more and --mode fast or faithful")
    if args.frames is not None:
        _check_frames(args.frames, guided=args.mode != "unguided",
                      model="cogvideox-5b" if args.preset == "tiny" else args.model)
    _check_sides(args.height, args.width, PIPELINE_SIDE_MULTIPLE if args.preset == "tiny" else
                 _size_multiple(args.model))
    args.measured_report = load_measured(args.measured) if args.measured else None


def check_options(args: argparse.Namespace) -> None:
    """The checks argparse cannot make alone, before any work; :class:`BadOption` (one line)."""
    from ..perf.measure import unwritable_reason

    if getattr(args, "device", None) is not None:
        _check_device(args.device)
    if getattr(args, "json", None):
        reason = unwritable_reason(args.json)
        if reason:
            raise BadOption(f"--json: {reason}")
    if args.command in ("loss", "geco-eval"):
        from ..loss.geco import PAIR_MODES

        check_choice("--pairs", args.pairs, PAIR_MODES)
    elif args.command == "vae":
        _check_frames(args.frames, guided=False)
        _check_sides(args.height, args.width, VAE_SIDE_MULTIPLE)
    elif args.command == "sampling":
        _check_sampling(args)
    elif args.command == "cost":
        _check_cost(args)
    elif args.command == "decoder-agreement":
        args.cfg = _agreement_config(args)


def _check_sampling(args: argparse.Namespace) -> None:
    import torch

    from ..io.devices import resolve_devices
    from ..sampler.memory_plan import PLAN_NAMES
    from ..sampler.schedule import PAPER_STEPS

    if args.memory_plan not in PLAN_NAMES:
        raise BadOption(f"--memory-plan must be one of {', '.join(PLAN_NAMES)}, got {args.memory_plan!r}")
    if args.devices:
        resolve_devices(args.devices, "--devices")
    if args.full_size and torch.device(args.device).type == "cpu" and not args.allow_cpu:
        raise BadOption("sampling --full-size on CPU is refused: CogVideoX-5B + VGGT-1B + UFM-Base weights alone are "
                        "about 30 GiB in float32 (7.4 G parameters) and a 49x480x720 step would take hours; run it on "
                        "a GPU (--device cuda) or pass --allow-cpu to insist.")
    if args.steps is not None and not 1 <= args.steps <= PAPER_STEPS:
        raise BadOption(f"--steps must be in [1, {PAPER_STEPS}], got {args.steps}")
    if args.frames is not None:
        _check_frames(args.frames, guided=args.mode != "unguided")
    _check_sides(args.height, args.width, PIPELINE_SIDE_MULTIPLE)


def _agreement_config(args: argparse.Namespace) -> Any:
    """The validated config of ``decoder-agreement`` (preset <- file <- overrides), its device and
    tiny decoder checked."""
    from ..config import load_config
    from ..io.devices import check_device
    from ..perf.decoder_agreement import check_agreement_config

    if not args.prompt.strip():
        raise BadOption("--prompt must not be empty")
    cfg = load_config(args.config, args.preset, args.overrides)
    check_device(cfg.model.device)
    check_agreement_config(cfg, args.prompt)
    return cfg


# ---- the work -----------------------------------------------------------------------------------


#: The child process of every case: this command's internal ``worker`` subcommand.
WORKER = (sys.executable, "-m", "geco_guide.cli.bench", "worker")


def _write(args: argparse.Namespace, report: dict[str, Any]) -> None:
    from ..perf.measure import write_report

    if args.json:
        write_report(args.json, report)


def _micro_benchmark(args: argparse.Namespace) -> None:
    from ..perf.measure import CASE_COLUMNS, environment_info, markdown_table, run_cases
    from ..perf.workloads import estimator_specs, loss_specs, vae_specs

    specs = {"loss": loss_specs, "estimators": estimator_specs, "vae": vae_specs}[args.command](args)
    results = run_cases(specs, WORKER)
    print(markdown_table(results, CASE_COLUMNS))
    _write(args, {"subcommand": args.command, "argv": sys.argv[1:],
                  "environment": environment_info(results[0]["threads"]), "results": results})


def _sampling_benchmark(args: argparse.Namespace) -> None:
    from ..perf.sampling import sampling_report, sampling_spec, sampling_table

    spec = sampling_spec(
        full_size=args.full_size, mode=args.mode, steps=args.steps, frames=args.frames, height=args.height,
        width=args.width, device=args.device, dtype=args.dtype, threads=args.threads, seed=args.seed,
        warmup=args.warmup, estimator_checkpointing=args.estimator_checkpointing, chunk_latents=args.chunk_latents,
        vae_tiling=args.vae_tiling, rss_exact=args.rss_exact, no_denoiser_checkpointing=args.no_denoiser_checkpointing,
        memory_plan=args.memory_plan, devices=args.devices)
    _check_frames(spec["frames"], guided=args.mode != "unguided")  # a preset's default frame count too
    report = sampling_report(spec, WORKER, sys.argv[1:])
    print(sampling_table(report))
    _write(args, report)


def _on_off(value: str | None) -> bool | None:
    return None if value is None else value == "on"


def _cost_report(args: argparse.Namespace) -> None:
    import torch

    from ..perf.cost import compare_with_measured, cost_report, cost_settings, cost_table, several_gpus, several_gpus_table
    from ..perf.plans import card_plan, with_card

    if args.dynamic_masks and args.mode == "unguided":
        print("warning: --dynamic-masks has no effect with --mode unguided (the masks act on guided updates only)",
              file=sys.stderr)
    if args.threads:
        torch.set_num_threads(args.threads)
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
    report = cost_report(settings, args.mode, sys.argv[1:])
    if card:
        report = with_card(report, card)
    if args.measured_report is not None:
        report["validation"] = compare_with_measured(report, args.measured_report, args.measured)
    if args.dynamic_masks and args.mode != "unguided":
        from ..perf.mask_cost import dynamic_mask_costs

        report["dynamic_masks"] = dynamic_mask_costs(settings["steps"])
    if args.num_gpus > 1 and args.mode != "unguided":
        report["several_gpus"] = several_gpus(report, args.num_gpus, split_cfg=args.split_cfg)
    print(cost_table(report))
    if "several_gpus" in report:
        print(several_gpus_table(report["several_gpus"]))
    if "dynamic_masks" in report:
        from ..perf.mask_cost import dynamic_masks_table

        print(dynamic_masks_table(report["dynamic_masks"]))
    _write(args, report)


def _family_table(args: argparse.Namespace) -> None:
    from ..perf.family_table import family_rows, family_table

    print(family_table())
    _write(args, {"subcommand": "cost --all-models", "note": "predicted by the cost model, from the shipped "
                  "estimates (geco_guide/sampler/data/memory_plans.json)", "rows": family_rows()})


def _parallel_table(args: argparse.Namespace) -> None:
    from ..perf.parallel_cost import parallel_report, parallel_table

    report = parallel_report(args.model, args.mode, args.context_parallel)
    print(parallel_table(report))
    _write(args, {**report, "argv": sys.argv[1:]})


def _attention_shapes(args: argparse.Namespace) -> None:
    import torch

    from ..perf.attention_shapes import attention_file

    if args.threads:
        torch.set_num_threads(args.threads)
    _write(args, attention_file(args.models, sys.argv[1:], on_model=print))


def _plan_estimates(args: argparse.Namespace) -> None:
    import torch

    from ..perf.plans import plan_estimates

    if args.threads:
        torch.set_num_threads(args.threads)
    _write(args, plan_estimates(args.models, sys.argv[1:], on_report=print))


def _decoder_agreement(args: argparse.Namespace) -> None:
    import torch

    from ..perf.decoder_agreement import agreement_table, decoder_agreement

    if args.threads:
        torch.set_num_threads(args.threads)
    try:
        report = decoder_agreement(args.cfg, args.prompt, sys.argv[1:])
    except (ValueError, FileNotFoundError) as err:  # a checkpoint that is not there or not readable
        raise BadOption(str(err)) from None
    print(agreement_table(report))
    _write(args, report)


def _geco_eval_cost(args: argparse.Namespace) -> None:
    from pathlib import Path

    import torch

    from ..perf.scoring_cost import geco_eval_cost, geco_eval_table

    if args.threads:
        torch.set_num_threads(args.threads)
    # the H200 sampling run whose estimator calls give the per-call times of the estimate
    h200_run = Path(__file__).resolve().parents[2] / "docs" / "benchmarks" / "sampling_full_h200_fast.json"
    report = geco_eval_cost(frames=args.frames, fps=args.fps, height=args.height, width=args.width, pairs=args.pairs,
                            videos=args.videos, seed=args.seed, h200_run=h200_run, argv=sys.argv[1:],
                            geometry=args.geometry_estimator)
    print(geco_eval_table(report))
    _write(args, report)


def _smooth_field(shape: tuple[int, ...], height: int, width: int, gen: Any) -> Any:
    """Seeded smooth random field ``[*shape, H, W]`` in ``[0, 1]``: a 6x8 grid upsampled bilinearly."""
    import torch
    import torch.nn.functional as F

    coarse = torch.rand(*shape, 6, 8, generator=gen).flatten(0, -3)[:, None]
    fine = F.interpolate(coarse, size=(height, width), mode="bilinear", align_corners=False)
    return fine.reshape(*shape, height, width)


def loss_workload(spec: dict[str, Any], device: Any) -> Any:
    """The ``loss`` case: the GeCo loss core on random-but-valid geometry and correspondences.

    Leaf tensors requiring grad: smooth depth in ``[3, 6]``, K of a 60-degree camera, orbiting
    camera-from-world extrinsics (:mod:`geco_guide.bench.synthetic`, which the perf layer may not
    import: this command may), smooth flow of up to +-4 px and covisibility in ``[0.4, 1]``. A
    confidence map in ``[1, 2]`` (>= 1 like VGGT's, no grad) exercises the confidence-percentile
    mask as in guidance. All maps are dense, so the cost does not depend on the values; nothing is
    rendered, which keeps the setup's memory small.
    """
    import torch

    from ..bench.synthetic import default_intrinsics, orbit_cameras
    from ..loss.geco import GeCoLossConfig, frame_pairs, geco_from_geometry
    from ..perf.workloads import Workload, make_step
    from ..types import Correspondences, SceneGeometry

    frames, height, width = spec["frames"], spec["height"], spec["width"]
    pairs = frame_pairs(frames, spec["pairs"])
    gen = torch.Generator().manual_seed(spec["seed"])
    depth = 3 + 3 * _smooth_field((1, frames), height, width, gen)
    intrinsics = default_intrinsics(height, width, dtype=torch.float32).expand(1, frames, 3, 3).clone()
    extrinsics = orbit_cameras(frames, dtype=torch.float32)[None]
    flow = 8 * _smooth_field((len(pairs), 2), height, width, gen) - 4
    covisibility = 0.4 + 0.6 * torch.rand(len(pairs), height, width, generator=gen)
    confidence = 1 + torch.rand(1, frames, height, width, generator=gen)
    leaves = [t.to(device).requires_grad_() for t in (depth, intrinsics, extrinsics, flow, covisibility)]
    geometry = SceneGeometry(depth=leaves[0], intrinsics=leaves[1], extrinsics=leaves[2],
                             confidence=confidence.to(device))
    correspondences = Correspondences(flow=leaves[3], covisibility=leaves[4])
    config = GeCoLossConfig(pairs=spec["pairs"])

    def scalar() -> Any:
        return geco_from_geometry(geometry, correspondences, pairs, config).loss

    info = {"input": f"{frames}x{height}x{width}, {len(pairs)} {spec['pairs']} pairs"}
    return Workload(make_step(spec["mode"], scalar, leaves), info)


def _worker(args: argparse.Namespace) -> None:
    from ..perf.sampling import run_sampling_worker
    from ..perf.workloads import WORKLOADS, run_worker

    spec = json.loads(args.spec)
    if spec["workload"] == "sampling":
        print(json.dumps(run_sampling_worker(spec)))
    else:
        print(json.dumps(run_worker(spec, {**WORKLOADS, "loss": loss_workload})))


WORK = {"loss": _micro_benchmark, "estimators": _micro_benchmark, "vae": _micro_benchmark,
        "sampling": _sampling_benchmark, "cost": _cost_report, "plans": _plan_estimates,
        "attention-shapes": _attention_shapes,
        "decoder-agreement": _decoder_agreement, "geco-eval": _geco_eval_cost}


@interruptible("the reports are written with --json at the end, atomically: nothing of this run was kept")
def run(args: argparse.Namespace) -> int:
    """The subcommand ``args`` name; 0, or 2 after one line on stderr for a bad option (checked
    before any work) or a card no plan fits."""
    from ..estimators.loading import WeightsNotFoundError

    if args.command == "worker":
        _worker(args)
        return 0
    try:
        if args.command == "cost" and args.context_parallel is not None:
            _check_context_parallel(args, COST_DEFAULTS)
            _parallel_table(args)
            return 0
        if args.command == "cost" and args.all_models:
            _check_all_models(args, COST_DEFAULTS)
            _family_table(args)
            return 0
        check_options(args)
    except (ValueError, FileNotFoundError, WeightsNotFoundError) as err:  # BadOption among them
        return print_error(err)
    try:
        WORK[args.command](args)
    except (BadOption, PackageDataError) as err:
        return print_error(err)
    return 0


def _cost_defaults() -> dict[str, Any]:
    """The defaults of ``cost``'s options (what ``--all-models`` leaves as they are)."""
    parser = Parser(prog="geco bench")
    register_subcommand(parser)
    return vars(parser.parse_args(["cost"]))


COST_DEFAULTS = _cost_defaults()


main = command_main("geco bench", DESCRIPTION, register_subcommand, run)

if __name__ == "__main__":  # the workers' processes: python -m geco_guide.cli.bench worker SPEC
    sys.exit(main())
