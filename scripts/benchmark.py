"""Time and memory benchmarks of geco_guide.

Subcommands:

* ``loss`` — the fused GeCo loss core (:func:`geco_from_geometry`) forward and forward+backward,
  geometry and correspondences as random-but-valid leaf tensors requiring grad.
* ``estimators`` — VGGT ``estimate_geometry`` and UFM ``estimate_flow`` forward and
  forward+backward (gradient w.r.t. the input frames; parameters frozen), tiny and/or full-size
  architectures with random weights.
* ``vae`` — the anchor decode of one guided update (:func:`decode_anchor_frames`: the paper's
  3-latent causal chunks, equal-length chunks batched in one call) forward and forward+backward
  w.r.t. the latents, through the CogVideoX-5B VAE (random weights) or the tiny one.
* ``sampling`` — :class:`GeCoCogVideoXPipeline` sampling without and with GeCo guidance from the
  same seed (one subprocess per arm): wall time, time per denoising step, a per-stage breakdown
  of the guided arm (denoiser forward/backward, VAE slice decode forward/backward, VGGT and UFM
  forward/backward, loss), denoiser pass counts and peak memory. ``--preset tiny`` (tiny random
  models, 17x32x48) or ``--full-size`` (CogVideoX-5B transformer + VAE, VGGT-1B, UFM-Base, random
  weights, random ``[1, 226, 4096]`` text embeddings instead of T5, 49x480x720; refused on CPU
  without ``--allow-cpu``). ``--steps N < 50`` runs the paper's guidance schedule scaled to N
  steps by the package's rule (:func:`geco_guide.sampler.schedule.scale_schedule`: each phase
  boundary b moves to ``round(b * N / 50)``; the scheduler's own N-step table) and extrapolates to
  50 steps and the paper's 111 updates (``extrapolated: true``).

  Stage timing (:class:`StageProfiler`) wraps, on the instances only, ``transformer.forward``,
  ``vae.decode``, ``geometry_estimator.estimate_geometry`` and ``flow_estimator.estimate_flow``:
  forward = the call's duration; backward = from the first execution of an output's ``grad_fn``
  (node pre-hook) to the gradient w.r.t. the last input (an identity autograd function on the
  inputs). ``loss`` = the guided updates' own seconds (``guidance_log``) minus every stage
  interval inside them: the GeCo loss math and its backward, resizing, the normalised update.
  On CUDA every timing point synchronises the device, so CUDA timings include syncs added by
  the harness.

* ``cost`` — a cost model of sampling, no weights and no GPU needed: the real pipeline call of one
  step (unguided, or guided with one update of ``--mode``) runs on fake tensors
  (``FakeTensorMode``; full size: CogVideoX-5B transformer + VAE, VGGT-1B, UFM-Base, 49x480x720)
  under :class:`CostTracker`, which counts per stage (denoiser with / without gradients, anchor
  decode, VGGT, UFM, loss, final decode; forward and backward) the FLOPs
  (``torch.utils.flop_counter`` formulas), bytes moved, ATen ops and the live memory (weights +
  activations at the peak). The units are combined with the schedule's counts (the real
  ``guided_step`` driven by counting stubs over R_t and time travel) into whole-run FLOPs, the
  guided / unguided FLOP ratio, peak memory and a roofline time on H100/H200 (one efficiency,
  calibrated on the measured unguided H200 step). About a minute per mode on a 2-core CPU.

Every case (one workload in one mode) runs in its own subprocess (the internal ``worker``
subcommand), so peak memory is per case: ``torch.cuda.max_memory_allocated`` on a GPU, peak RSS
(``ru_maxrss``) on CPU, reported in total and as the increase over the child's post-import
baseline; the peak is then restarted after setup, so that the timed runs' own peak over the
memory in use when they start (activations) is reported too. Each case also records the
1-minute load average at its start and its CPU time per wall-clock second: on a shared machine
timings are only comparable at similar CPU shares.
Results are printed as a Markdown table and written as JSON with ``--json PATH`` (atomically:
a failed write leaves no partial file). Every option is checked before any work starts; a bad
one is a single ``error:`` line on stderr and exit code 2.

This file is the command line only. The work lives in :mod:`geco_guide.perf`: ``measure``
(timing, memory, the per-case subprocess, reports), ``workloads`` (the micro-benchmark cases),
``profile`` (:class:`StageProfiler`), ``sampling``, ``cost`` (:class:`CostTracker`, the roofline),
``models`` (the full-size builders, fake tensors) and ``geco_eval``. A new benchmark adds a
workload builder to :data:`WORKLOADS` and a subcommand that lists its cases.

Examples::

    python scripts/benchmark.py loss --frames 4 --height 480 --width 720 --repeats 3
    python scripts/benchmark.py estimators --size both --frames 2 --height 140 --width 210
    python scripts/benchmark.py vae --size full --height 64 --width 96
    python scripts/benchmark.py sampling --preset tiny --mode faithful --json out.json
    python scripts/benchmark.py sampling --full-size --device cuda --mode fast --steps 10
    python scripts/benchmark.py cost --mode faithful --json cost.json
"""

from __future__ import annotations

import argparse
import math
import sys
from pathlib import Path
from typing import Any, Sequence

import torch
import torch.nn.functional as F
from torch import Tensor

from geco_guide.bench.synthetic import default_intrinsics, orbit_cameras
from geco_guide.config import COGVIDEOX_TEMPORAL_COMPRESSION
from geco_guide.loss.geco import (
    PAIR_MODES,
    GeCoLossConfig,
    frame_pairs,
    geco_from_geometry,
)
from geco_guide.perf import workloads as perf_workloads
from geco_guide.perf.cost import (
    H200_UNGUIDED_STEP_S,
    compare_with_measured,
    cost_report,
    cost_settings,
    cost_table,
    load_measured,
)
from geco_guide.perf.geco_eval import geco_eval_cost, geco_eval_table
from geco_guide.perf.measure import (
    RSS_EXACT_MMAP_THRESHOLD,
    environment_info,
    markdown_table,
    run_cases,
    unwritable_reason,
    write_report,
)
from geco_guide.perf.sampling import (
    NOMINAL_STEPS,
    SAMPLING_MODES,
    run_sampling_worker,
    sampling_report,
    sampling_spec,
    sampling_table,
)
from geco_guide.perf.workloads import MODES, Workload, make_step, run_worker
from geco_guide.sampler.slicing import check_num_frames, check_paired_latent_frames
from geco_guide.types import Correspondences, SceneGeometry

#: The child process of every case: this script's internal ``worker`` subcommand.
WORKER = (sys.executable, str(Path(__file__).resolve()), "worker")
#: The H200 sampling run whose estimator calls give the per-call times of the GeCo-Eval estimate.
H200_FAST_RUN = Path(__file__).resolve().parents[1] / "docs" / "benchmarks" / "sampling_full_h200_fast.json"

def _smooth_field(shape: tuple[int, ...], height: int, width: int, gen: torch.Generator) -> Tensor:
    """Seeded smooth random field ``[*shape, H, W]`` in ``[0, 1]``: a 6x8 grid upsampled bilinearly."""
    coarse = torch.rand(*shape, 6, 8, generator=gen).flatten(0, -3)[:, None]
    fine = F.interpolate(coarse, size=(height, width), mode="bilinear", align_corners=False)
    return fine.reshape(*shape, height, width)


def loss_workload(spec: dict[str, Any], device: torch.device) -> Workload:
    """GeCo loss core on random-but-valid geometry and correspondences.

    Leaf tensors requiring grad: smooth depth in ``[3, 6]``, K of a 60-degree camera, orbiting
    camera-from-world extrinsics (:mod:`geco_guide.bench.synthetic`, which the package's perf layer may not import), smooth flow of up to +-4 px and
    covisibility in ``[0.4, 1]``. A confidence map in ``[1, 2]`` (>= 1 like VGGT's, no grad)
    exercises the confidence-percentile mask as in guidance. All maps are dense, so the cost
    does not depend on the values; nothing is rendered, which keeps the setup's memory small.
    """
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

    def scalar() -> Tensor:
        return geco_from_geometry(geometry, correspondences, pairs, config).loss

    info = {"input": f"{frames}x{height}x{width}, {len(pairs)} {spec['pairs']} pairs"}
    return Workload(make_step(spec["mode"], scalar, leaves), info)


WORKLOADS = {**perf_workloads.WORKLOADS, "loss": loss_workload}


# Report columns: header, result key, format.
COLUMNS: tuple[tuple[str, str, str], ...] = (
    ("case", "case", "{}"),
    ("mode", "mode", "{}"),
    ("input", "input", "{}"),
    ("network input", "network", "{}"),
    ("params (M)", "params_m", "{:.1f}"),
    ("dtype", "dtype", "{}"),
    ("checkpointing", "checkpointing", "{}"),
    ("tiling", "tiling", "{}"),
    ("setup (s)", "setup_s", "{:.1f}"),
    ("median (s)", "time_median_s", "{:.4g}"),
    ("min (s)", "time_min_s", "{:.4g}"),
    ("peak mem (MiB)", "peak_mib", "{:.0f}"),
    ("after setup (MiB)", "after_setup_mib", "{:.0f}"),
    ("increase over import (MiB)", "peak_increase_mib", "{:.0f}"),
    ("runs: peak over in use after setup (MiB)", "run_increase_mib", "{:.0f}"),
    ("load (1 min)", "load_avg_1m", "{:.1f}"),
    ("CPU/wall", "cpu_per_wall", "{:.2f}"),
)


# ----------------------------------------------------------------------------------------------
# Option types and checks: every bad option is one line before any work
# ----------------------------------------------------------------------------------------------


class OneLineParser(argparse.ArgumentParser):
    """An argument parser whose errors are one line (``prog: error: ...``), exit code 2."""

    def error(self, message: str) -> None:  # type: ignore[override]
        self.exit(2, f"{self.prog}: error: {message} (see --help)\n")


def fail(message: str) -> None:
    """Stop with one ``error:`` line and exit code 2, as an argparse error."""
    print(f"benchmark.py: error: {message}", file=sys.stderr)
    raise SystemExit(2)


def _int_at_least(minimum: int) -> Any:
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


positive_int, non_negative_int = _int_at_least(1), _int_at_least(0)
#: GeCo and UFM need at least one pair; a causal chunk at least two latents.
frame_count, chunk_latents = _int_at_least(2), _int_at_least(2)


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
        (check_paired_latent_frames if guided else check_num_frames)(frames, COGVIDEOX_TEMPORAL_COMPRESSION)
    except ValueError as err:
        fail(f"--frames: {err}")


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
    elif args.command == "sampling":
        if args.full_size and torch.device(args.device).type == "cpu" and not args.allow_cpu:
            fail("sampling --full-size on CPU is refused: CogVideoX-5B + VGGT-1B + UFM-Base weights alone are "
                 "about 30 GiB in float32 (7.4 G parameters) and a 49x480x720 step would take hours; run it on a "
                 "GPU (--device cuda) or pass --allow-cpu to insist.")
        if args.steps is not None and not 1 <= args.steps <= NOMINAL_STEPS:
            fail(f"--steps must be in [1, {NOMINAL_STEPS}], got {args.steps}")
        if args.frames is not None:
            check_frames(args.frames, guided=args.mode != "unguided")
    elif args.command == "cost":
        if args.steps is not None and args.steps < 1:
            fail(f"--steps must be >= 1, got {args.steps}")
        if args.frames is not None:
            check_frames(args.frames, guided=args.mode != "unguided")
        if args.measured:
            try:
                args.measured_report = load_measured(args.measured)
            except ValueError as err:
                fail(str(err))


# ----------------------------------------------------------------------------------------------
# Subcommands
# ----------------------------------------------------------------------------------------------


def common_spec(args: argparse.Namespace) -> dict[str, Any]:
    """Options every case shares."""
    return {"device": args.device, "threads": args.threads, "warmup": args.warmup,
            "repeats": args.repeats, "seed": args.seed, "rss_exact": args.rss_exact}


def loss_specs(args: argparse.Namespace) -> list[dict[str, Any]]:
    """Cases of ``loss``: the GeCo loss core, forward and forward+backward."""
    base = {**common_spec(args), "workload": "loss", "case": "geco_from_geometry",
            "frames": args.frames, "height": args.height, "width": args.width, "pairs": args.pairs}
    return [{**base, "mode": mode} for mode in MODES]


def vae_specs(args: argparse.Namespace) -> list[dict[str, Any]]:
    """Cases of ``vae``: the anchor-chunk decode, forward and forward+backward."""
    base = {**common_spec(args), "workload": "vae", "case": f"vae-{args.size}", "size": args.size,
            "frames": args.frames, "height": args.height, "width": args.width, "dtype": args.dtype,
            "vae_checkpointing": args.vae_checkpointing, "vae_tiling": args.vae_tiling}
    return [{**base, "mode": mode} for mode in MODES]


def estimator_specs(args: argparse.Namespace) -> list[dict[str, Any]]:
    """Cases of ``estimators``: VGGT and UFM per size, forward and forward+backward."""
    sizes = ("tiny", "full") if args.size == "both" else (args.size,)
    base = {**common_spec(args), "frames": args.frames, "height": args.height, "width": args.width,
            "dtype": args.dtype}
    return [
        {**base, "workload": model, "case": f"{model}-{size}", "size": size, "mode": mode}
        for size in sizes for model in ("vggt", "ufm") for mode in MODES
    ]


def run_and_report(args: argparse.Namespace) -> None:
    """Run the subcommand's cases, print the Markdown table and write the JSON report."""
    results = run_cases(args.specs(args), WORKER)
    print(markdown_table(results, COLUMNS))
    if args.json:
        write_report(args.json, {"subcommand": args.command, "argv": sys.argv[1:],
                                 "environment": environment_info(results[0]["threads"]), "results": results})


def run_sampling(args: argparse.Namespace) -> None:
    spec = sampling_spec(
        full_size=args.full_size, mode=args.mode, steps=args.steps, frames=args.frames, height=args.height,
        width=args.width, device=args.device, dtype=args.dtype, threads=args.threads, seed=args.seed,
        warmup=args.warmup, estimator_checkpointing=args.estimator_checkpointing, chunk_latents=args.chunk_latents,
        vae_tiling=args.vae_tiling, rss_exact=args.rss_exact, no_denoiser_checkpointing=args.no_denoiser_checkpointing)
    # the defaults filled in: the default frame count of a preset is checked too
    check_frames(spec["frames"], guided=args.mode != "unguided")
    report = sampling_report(spec, WORKER, sys.argv[1:])
    print(sampling_table(report))
    if args.json:
        write_report(args.json, report)


def _on_off(value: str | None) -> bool | None:
    return None if value is None else value == "on"


def run_cost(args: argparse.Namespace) -> None:
    if args.threads:
        torch.set_num_threads(args.threads)
    settings = cost_settings(
        preset=args.preset, steps=args.steps, frames=args.frames, height=args.height, width=args.width,
        dtype=args.dtype, no_time_travel=args.no_time_travel, paper_schedule=args.paper_schedule, seed=args.seed,
        chunk_latents=args.chunk_latents, vae_checkpointing=_on_off(args.vae_checkpointing),
        denoiser_checkpointing=_on_off(args.denoiser_checkpointing),
        estimator_checkpointing=args.estimator_checkpointing, vae_tiling=args.vae_tiling,
        calibration_step_s=args.calibration_step_s)
    report = cost_report(settings, args.mode, sys.argv[1:])
    if args.measured:
        report["validation"] = compare_with_measured(report, args.measured_report, args.measured)
    print(cost_table(report))
    if args.json:
        write_report(args.json, report)


def run_geco_eval_cost(args: argparse.Namespace) -> None:
    if args.threads:
        torch.set_num_threads(args.threads)
    report = geco_eval_cost(frames=args.frames, fps=args.fps, height=args.height, width=args.width, pairs=args.pairs,
                            videos=args.videos, seed=args.seed, h200_run=H200_FAST_RUN, argv=sys.argv[1:])
    print(geco_eval_table(report))
    if args.json:
        write_report(args.json, report)


def _add_common_options(parser: argparse.ArgumentParser, repeats: int) -> None:
    parser.add_argument("--device", default="cpu", help="torch device, e.g. cpu or cuda (default: cpu)")
    parser.add_argument("--threads", type=positive_int, default=None,
                        help="torch.set_num_threads in every case (default: torch's default)")
    parser.add_argument("--warmup", type=non_negative_int, default=1, help="untimed runs before timing (default: 1)")
    parser.add_argument("--repeats", type=positive_int, default=repeats, help=f"timed runs (default: {repeats})")
    parser.add_argument("--seed", type=int, default=0, help="seed of weights and inputs (default: 0)")
    parser.add_argument("--json", metavar="PATH", help="also write the results as JSON to PATH")
    _add_rss_exact_option(parser)


def _add_rss_exact_option(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--rss-exact", action="store_true",
                        help="CPU memory: run the workers with glibc's MALLOC_MMAP_THRESHOLD_="
                             f"{RSS_EXACT_MMAP_THRESHOLD}, so that freed tensors leave the resident set at once "
                             "and peak RSS follows the live tensors (slower: every allocation maps fresh pages)")


def build_parser() -> argparse.ArgumentParser:
    """The CLI: the benchmark subcommands and the internal ``worker``."""
    parser = OneLineParser(description=__doc__.split("\n\n")[0],
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    sub = parser.add_subparsers(dest="command", required=True)

    loss = sub.add_parser("loss", help="GeCo loss core (geco_from_geometry) forward / forward+backward")
    loss.add_argument("--frames", type=frame_count, default=4, help="frames S (default: 4)")
    loss.add_argument("--height", type=positive_int, default=480, help="frame height (default: 480)")
    loss.add_argument("--width", type=positive_int, default=720, help="frame width (default: 720)")
    loss.add_argument("--pairs", choices=PAIR_MODES, default="adjacent", help="frame pairs (default: adjacent)")
    _add_common_options(loss, repeats=3)
    loss.set_defaults(specs=loss_specs)

    est = sub.add_parser("estimators", help="VGGT and UFM forward / forward+backward w.r.t. the frames")
    est.add_argument("--size", choices=("tiny", "full", "both"), default="tiny",
                     help="tiny configs, the VGGT-1B / UFM-Base architectures (random weights), or both")
    est.add_argument("--frames", type=frame_count, default=2,
                     help="frames S; UFM gets the S - 1 adjacent pairs (default: 2)")
    est.add_argument("--height", type=positive_int, default=140, help="input frame height (default: 140)")
    est.add_argument("--width", type=positive_int, default=210, help="input frame width (default: 210)")
    est.add_argument("--dtype", choices=("float32", "bfloat16"), default="float32",
                     help="storage dtype of the ViT trunks (trunk_to); heads stay float32 (default: float32)")
    _add_common_options(est, repeats=3)
    est.set_defaults(specs=estimator_specs)

    vae = sub.add_parser("vae", help="the anchor-chunk VAE decode of one guided update, forward / forward+backward")
    vae.add_argument("--size", choices=("tiny", "full"), default="tiny",
                     help="the tiny VAE or the CogVideoX-5B VAE architecture (random weights)")
    vae.add_argument("--frames", type=positive_int, default=49, help="video frames 4k+1, anchors spread as in sampling (default: 49)")
    vae.add_argument("--height", type=positive_int, default=480, help="video height, a multiple of 8 (default: 480)")
    vae.add_argument("--width", type=positive_int, default=720, help="video width, a multiple of 8 (default: 720)")
    vae.add_argument("--dtype", choices=("float32", "bfloat16"), default="bfloat16",
                     help="VAE dtype (default: bfloat16, as the pipeline on a GPU)")
    vae.add_argument("--vae-checkpointing", action="store_true",
                     help="guidance.vae_checkpointing: one checkpointed decode per chunk, and the VAE's own "
                          "block checkpointing inside")
    vae.add_argument("--vae-tiling", action="store_true",
                     help="vae.enable_tiling with tiles of half the video size, as at 480x720")
    _add_common_options(vae, repeats=1)
    vae.set_defaults(specs=vae_specs)

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
    samp.add_argument("--height", type=positive_int, default=None, help="height (default: 32 tiny, 480 full size)")
    samp.add_argument("--width", type=positive_int, default=None, help="width (default: 48 tiny, 720 full size)")
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
                           "(guidance.gradient_checkpointing=false: one forward less per update, more memory)")
    samp.add_argument("--allow-cpu", action="store_true",
                      help="allow --full-size on CPU (the weights alone are ~30 GiB in float32)")
    samp.add_argument("--device", default="cpu", help="torch device, e.g. cpu or cuda (default: cpu)")
    samp.add_argument("--threads", type=positive_int, default=None, help="torch.set_num_threads in both arms")
    samp.add_argument("--warmup", type=non_negative_int, default=1,
                      help="untimed 2-step calls of the same arm before the timed one (default: 1)")
    samp.add_argument("--seed", type=int, default=0, help="seed of weights, text embeddings and noise (default: 0)")
    samp.add_argument("--json", metavar="PATH", help="also write the report as JSON to PATH")
    _add_rss_exact_option(samp)

    cost = sub.add_parser("cost", help="FLOPs, memory and a roofline time of sampling at full size, on fake tensors "
                                       "(no weights, no GPU)")
    cost.add_argument("--preset", choices=("full", "tiny"), default="full",
                      help="full: CogVideoX-5B, VGGT-1B, UFM-Base at 49x480x720 (default); tiny: the tiny pipeline")
    cost.add_argument("--mode", choices=SAMPLING_MODES, default="faithful",
                      help="guided mode to model beside the unguided run (default: faithful)")
    cost.add_argument("--steps", type=int, default=None, help="denoising steps (default: 50 full, 4 tiny)")
    cost.add_argument("--frames", type=positive_int, default=None, help="frames (default: 49 full, 17 tiny)")
    cost.add_argument("--height", type=positive_int, default=None, help="height (default: 480 full, 32 tiny)")
    cost.add_argument("--width", type=positive_int, default=None, help="width (default: 720 full, 48 tiny)")
    cost.add_argument("--dtype", choices=("bfloat16", "float32"), default=None,
                      help="transformer/VAE dtype and the estimators' trunks (default: bfloat16 full, float32 tiny)")
    cost.add_argument("--chunk-latents", type=chunk_latents, default=None, help="latents per anchor chunk (default: the preset's)")
    cost.add_argument("--vae-checkpointing", choices=("on", "off"), default=None,
                      help="guidance.vae_checkpointing (default: the preset's: on full, off tiny)")
    cost.add_argument("--denoiser-checkpointing", choices=("on", "off"), default=None,
                      help="guidance.gradient_checkpointing (default: the preset's: on full, off tiny)")
    cost.add_argument("--estimator-checkpointing", action="store_true", help="VGGT and UFM gradient checkpointing")
    cost.add_argument("--vae-tiling", action="store_true", help="the VAE's spatial tiles (model.vae_tiling)")
    cost.add_argument("--no-time-travel", action="store_true", help="the schedule without its time-travel window")
    cost.add_argument("--paper-schedule", action="store_true",
                      help="tiny preset: the paper's 50-step schedule instead of the tiny 4-step one (as `sampling`)")
    cost.add_argument("--calibration-step-s", type=positive_float, default=H200_UNGUIDED_STEP_S,
                      help=f"measured seconds of one unguided CFG step on the H200 (default {H200_UNGUIDED_STEP_S})")
    cost.add_argument("--measured", metavar="JSON",
                      help="a `sampling` report of the same settings on an H200: add predicted vs measured")
    cost.add_argument("--threads", type=positive_int, default=None, help="torch.set_num_threads")
    cost.add_argument("--seed", type=int, default=0, help="seed (shapes only; default: 0)")
    cost.add_argument("--json", metavar="PATH", help="also write the report as JSON to PATH")

    geval = sub.add_parser("geco-eval", help="estimator calls and time of scoring one video under each pair mode "
                                             "(tiny on CPU, estimated at full size on an H200)")
    geval.add_argument("--frames", type=frame_count, default=49, help="frames of the clip (default: 49, CogVideoX)")
    geval.add_argument("--fps", type=positive_float, default=16.0, help="its native frame rate (default: 16, CogVideoX)")
    geval.add_argument("--height", type=positive_int, default=32, help="height of the tiny run (default: 32)")
    geval.add_argument("--width", type=positive_int, default=48, help="width of the tiny run (default: 48)")
    geval.add_argument("--pairs", nargs="+", choices=PAIR_MODES, default=["all", "center", "adjacent"])
    geval.add_argument("--videos", type=positive_int, default=320, help="videos per model (default: 320 = 80 prompts x 4 seeds)")
    geval.add_argument("--threads", type=positive_int, default=None, help="torch.set_num_threads")
    geval.add_argument("--seed", type=int, default=0, help="seed of the random clip (default: 0)")
    geval.add_argument("--json", metavar="PATH", help="also write the report as JSON to PATH")

    worker = sub.add_parser("worker", help="internal: run one case given as JSON, print its result as JSON")
    worker.add_argument("spec")
    return parser


def main(argv: Sequence[str] | None = None) -> None:
    parser = build_parser()
    args = parser.parse_args(argv)
    if args.command == "worker":
        import json

        spec = json.loads(args.spec)
        print(json.dumps(run_sampling_worker(spec) if spec["workload"] == "sampling" else run_worker(spec, WORKLOADS)))
        return
    check_options(args)
    if args.command == "sampling":
        run_sampling(args)
    elif args.command == "cost":
        run_cost(args)
    elif args.command == "geco-eval":
        run_geco_eval_cost(args)
    else:
        run_and_report(args)


if __name__ == "__main__":
    main()
