"""The options of ``geco bench``'s micro-benchmarks, ``sampling`` and ``cost`` subcommands
(:mod:`geco_guide.cli.bench`), and the argparse types and option groups its subcommands share.
Imports no torch: ``--help`` answers at once."""

from __future__ import annotations

import argparse
import math
from typing import Any

from ..families import DEFAULT_MODEL
from ..families.published import traced_models
from ..perf.cards import GPU_SPECS, H200_UNGUIDED_STEP_S

__all__ = ["AGREEMENT_PROMPT", "GEOMETRY_CHOICES", "SAMPLING_MODES", "add_cost", "add_json", "add_micro",
           "add_sampling", "add_threads", "frame_count", "positive_float", "positive_int"]

#: The prompt of ``decoder-agreement`` unless ``--prompt`` says otherwise.
AGREEMENT_PROMPT = "a marble bust on a wooden table, the camera orbiting it slowly"
#: the geometry backbones ``estimators.geometry`` names (written here: the parser imports no torch)
GEOMETRY_CHOICES = ("vggt-1b", "da3-small", "da3-base")
#: Named memory plans and anchor decoders, checked in :func:`run` (their lists live with torch).
CHECKED_LATER = "checked before any work"
#: faithful: backpropagate through the denoiser (the paper); fast: its output held constant;
#: unguided: no guidance.
SAMPLING_MODES = ("faithful", "fast", "unguided")


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


def add_threads(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--threads", type=positive_int, default=None, help="torch.set_num_threads")


def add_json(parser: argparse.ArgumentParser, what: str = "also write the report as JSON to PATH") -> None:
    parser.add_argument("--json", metavar="PATH", help=what)


def add_rss_exact(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--rss-exact", action="store_true",
                        help="CPU memory: run the workers with a small glibc MALLOC_MMAP_THRESHOLD_ (64 KiB), "
                             "so that freed tensors leave the resident set at once "
                             "and peak RSS follows the live tensors (slower: every allocation maps fresh pages)")


def add_common(parser: argparse.ArgumentParser, repeats: int) -> None:
    """The options of every micro-benchmark subcommand (one subprocess per case)."""
    parser.add_argument("--device", default="cpu", help="torch device, e.g. cpu or cuda (default: cpu)")
    parser.add_argument("--threads", type=positive_int, default=None,
                        help="torch.set_num_threads in every case (default: torch's default)")
    parser.add_argument("--warmup", type=non_negative_int, default=1, help="untimed runs before timing (default: 1)")
    parser.add_argument("--repeats", type=positive_int, default=repeats, help=f"timed runs (default: {repeats})")
    parser.add_argument("--seed", type=int, default=0, help="seed of weights and inputs (default: 0)")
    add_json(parser, "also write the results as JSON to PATH")
    add_rss_exact(parser)


def add_micro(sub: Any) -> None:
    loss = sub.add_parser("loss", help="GeCo loss core (geco_from_geometry) forward / forward+backward")
    loss.add_argument("--frames", type=frame_count, default=4, help="frames S (default: 4)")
    loss.add_argument("--height", type=positive_int, default=480, help="frame height (default: 480)")
    loss.add_argument("--width", type=positive_int, default=720, help="frame width (default: 720)")
    loss.add_argument("--pairs", default="adjacent", metavar="MODE",
                      help=f"frame pairs: adjacent (default), center or all ({CHECKED_LATER})")
    add_common(loss, repeats=3)

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
    add_common(est, repeats=3)

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
    add_common(vae, repeats=1)


def add_sampling(sub: Any) -> None:
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
    add_json(samp)
    add_rss_exact(samp)


def add_cost(sub: Any) -> None:
    cost = sub.add_parser("cost", help="FLOPs, memory and a roofline time of a model's sampling on fake tensors "
                                       "(no weights, no GPU); --all-models: the per-family table")
    cost.add_argument("--all-models", action="store_true",
                      help="print the per-family table (every traced model on an H200 and a 24 GB card: unguided, "
                           "fast, faithful, tiny decoder, search at matched particles, 4 GPUs) from the shipped "
                           "estimates that `geco bench plans` writes; traces nothing")
    cost.add_argument("--model", choices=traced_models(), default=DEFAULT_MODEL,
                      help=f"the registry model to trace at its default call (default: {DEFAULT_MODEL}, the paper's)")
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
    add_threads(cost)
    cost.add_argument("--seed", type=int, default=0, help="seed (shapes only; default: 0)")
    add_json(cost)
