"""Time and memory benchmarks of geco_guide: the thin command line over :mod:`geco_guide.perf`.

Subcommands (docs/performance.md says what each measures and how to read it):

* ``loss``, ``estimators``, ``vae``: micro-benchmarks of the GeCo loss core, VGGT / UFM and the
  anchor-chunk VAE decode, forward and forward+backward, one subprocess per case (the internal
  ``worker`` subcommand), so that each case's peak memory is its own.
* ``sampling``: guided vs unguided CogVideoX sampling from the same seed (``--preset tiny`` or
  ``--full-size`` with random weights), wall time, a per-stage breakdown and peak memory.
* ``cost``: FLOPs, memory and a roofline GPU time of full-size sampling on fake tensors (no
  weights, no GPU); ``--decoder tiny`` models the tiny decoder decoding the anchor frames.
* ``decoder-agreement``: one guided generation with both decoders at every update: the gradient
  cosine, both losses and the anchor frames' PSNR (the tiny decoder's fidelity, measured).
* ``geco-eval``: the estimator calls and time of scoring one video under each pair mode.

Results are printed as Markdown and written as JSON with ``--json PATH`` (atomically). Every option
is checked before any work starts (:mod:`geco_guide.perf.options`): a bad one is a single
``error:`` line on stderr and exit code 2.

Examples::

    python scripts/benchmark.py loss --frames 4 --height 480 --width 720 --repeats 3
    python scripts/benchmark.py vae --size full --height 64 --width 96
    python scripts/benchmark.py sampling --preset tiny --mode faithful --json out.json
    python scripts/benchmark.py sampling --full-size --device cuda --mode fast --steps 10
    python scripts/benchmark.py cost --mode fast --decoder tiny --json cost.json
    python scripts/benchmark.py decoder-agreement --preset tiny --json agreement.json
"""

from __future__ import annotations

import argparse
import sys
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import torch
import torch.nn.functional as F
from torch import Tensor

from geco_guide.bench.synthetic import default_intrinsics, orbit_cameras
from geco_guide.config import CONFIG_DIR
from geco_guide.io.logs import log_to_stderr
from geco_guide.loss.geco import (
    PAIR_MODES,
    GeCoLossConfig,
    frame_pairs,
    geco_from_geometry,
)
from geco_guide.perf import workloads as perf_workloads
from geco_guide.perf.cost import (
    compare_with_measured,
    cost_report,
    cost_settings,
    cost_table,
    dynamic_mask_costs,
    dynamic_masks_table,
    several_gpus,
    several_gpus_table,
)
from geco_guide.perf.decoder_agreement import agreement_table, decoder_agreement
from geco_guide.perf.scoring_cost import geco_eval_cost, geco_eval_table
from geco_guide.perf.measure import (
    CASE_COLUMNS,
    environment_info,
    markdown_table,
    run_cases,
    write_report,
)
from geco_guide.perf.options import (
    OneLineParser,
    add_common_options,
    add_cost_parser,
    add_plans_parser,
    add_sampling_parser,
    check_frames,
    check_options,
    fail,
    frame_count,
    positive_float,
    positive_int,
)
from geco_guide.perf.plans import card_plan, plan_estimates, with_card
from geco_guide.perf.sampling import (
    run_sampling_worker,
    sampling_report,
    sampling_spec,
    sampling_table,
)
from geco_guide.perf.workloads import (
    Workload,
    estimator_specs,
    loss_specs,
    make_step,
    run_worker,
    vae_specs,
)
from geco_guide.types import Correspondences, SceneGeometry

#: The child process of every case: this script's internal ``worker`` subcommand.
WORKER = (sys.executable, str(Path(__file__).resolve()), "worker")
#: The H200 sampling run whose estimator calls give the per-call times of the GeCo-Eval estimate.
H200_FAST_RUN = Path(__file__).resolve().parents[1] / "docs" / "benchmarks" / "sampling_full_h200_fast.json"
#: The prompt of ``decoder-agreement`` unless ``--prompt`` says otherwise.
AGREEMENT_PROMPT = "a marble bust on a wooden table, the camera orbiting it slowly"


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


def run_and_report(args: argparse.Namespace) -> None:
    """Run the subcommand's cases, print the Markdown table and write the JSON report."""
    results = run_cases(args.specs(args), WORKER)
    print(markdown_table(results, CASE_COLUMNS))
    if args.json:
        write_report(args.json, {"subcommand": args.command, "argv": sys.argv[1:],
                                 "environment": environment_info(results[0]["threads"]), "results": results})


def run_sampling(args: argparse.Namespace) -> None:
    spec = sampling_spec(
        full_size=args.full_size, mode=args.mode, steps=args.steps, frames=args.frames, height=args.height,
        width=args.width, device=args.device, dtype=args.dtype, threads=args.threads, seed=args.seed,
        warmup=args.warmup, estimator_checkpointing=args.estimator_checkpointing, chunk_latents=args.chunk_latents,
        vae_tiling=args.vae_tiling, rss_exact=args.rss_exact, no_denoiser_checkpointing=args.no_denoiser_checkpointing,
        memory_plan=args.memory_plan, devices=args.devices)
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
    card = None
    if args.gpu:
        card = card_plan(args.gpu, args.mode, args.decoder, *(args.frames or 49, args.height or 480, args.width or 720))
        if card["plan"] is None:
            fail(f"--gpu {args.gpu}: {card['reason']}")
    settings = cost_settings(
        preset=args.preset, steps=args.steps, frames=args.frames, height=args.height, width=args.width,
        dtype=args.dtype, no_time_travel=args.no_time_travel, paper_schedule=args.paper_schedule, seed=args.seed,
        chunk_latents=args.chunk_latents, vae_checkpointing=_on_off(args.vae_checkpointing),
        vae_block_checkpointing=_on_off(args.vae_block_checkpointing),
        denoiser_checkpointing=_on_off(args.denoiser_checkpointing),
        estimator_checkpointing=args.estimator_checkpointing, vae_tiling=args.vae_tiling,
        calibration_step_s=args.calibration_step_s, decoder=args.decoder, plan=card["plan"] if card else None)
    report = cost_report(settings, args.mode, sys.argv[1:])
    if card:
        report = with_card(report, card)
    if args.measured:
        report["validation"] = compare_with_measured(report, args.measured_report, args.measured)
    if args.dynamic_masks:
        report["dynamic_masks"] = dynamic_mask_costs(settings["steps"])
    if args.num_gpus > 1 and args.mode != "unguided":
        report["several_gpus"] = several_gpus(report, args.num_gpus, split_cfg=args.split_cfg)
    print(cost_table(report))
    if "several_gpus" in report:
        print(several_gpus_table(report["several_gpus"]))
    if args.dynamic_masks:
        print(dynamic_masks_table(report["dynamic_masks"]))
    if args.json:
        write_report(args.json, report)


def run_plans(args: argparse.Namespace) -> None:
    if args.threads:
        torch.set_num_threads(args.threads)
    report = plan_estimates(args.models, sys.argv[1:], on_report=print)
    if args.json:
        write_report(args.json, report)


def run_decoder_agreement(args: argparse.Namespace) -> None:
    if args.threads:
        torch.set_num_threads(args.threads)
    try:
        report = decoder_agreement(args.cfg, args.prompt, sys.argv[1:])
    except (ValueError, FileNotFoundError) as err:  # a checkpoint that is not there or not readable
        fail(str(err))
    print(agreement_table(report))
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


def build_parser() -> argparse.ArgumentParser:
    """The CLI: the benchmark subcommands and the internal ``worker``."""
    parser = OneLineParser(description=__doc__.split("\n\n")[0], formatter_class=argparse.RawDescriptionHelpFormatter)
    sub = parser.add_subparsers(dest="command", required=True)

    loss = sub.add_parser("loss", help="GeCo loss core (geco_from_geometry) forward / forward+backward")
    loss.add_argument("--frames", type=frame_count, default=4, help="frames S (default: 4)")
    loss.add_argument("--height", type=positive_int, default=480, help="frame height (default: 480)")
    loss.add_argument("--width", type=positive_int, default=720, help="frame width (default: 720)")
    loss.add_argument("--pairs", choices=PAIR_MODES, default="adjacent", help="frame pairs (default: adjacent)")
    add_common_options(loss, repeats=3)
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
    add_common_options(est, repeats=3)
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
                     help="run.vae_checkpointing: one checkpointed decode per chunk, and the VAE's own "
                          "block checkpointing inside")
    vae.add_argument("--vae-tiling", action="store_true",
                     help="vae.enable_tiling with tiles of half the video size, as at 480x720")
    add_common_options(vae, repeats=1)
    vae.set_defaults(specs=vae_specs)

    add_sampling_parser(sub)
    add_cost_parser(sub)
    add_plans_parser(sub)

    agree = sub.add_parser("decoder-agreement", help="both decoders at every guidance update of one guided call: "
                                                     "gradient cosine, losses, anchor-frame PSNR")
    presets = sorted(p.stem for p in CONFIG_DIR.glob("*.yaml"))
    agree.add_argument("--preset", choices=presets, default=None,
                       help="a preset of configs/ (tiny: the tiny random models, offline); default: the schema's")
    agree.add_argument("--config", metavar="YAML", default=None, help="a config file over the preset")
    agree.add_argument("--prompt", default=AGREEMENT_PROMPT, help="the prompt (default: a marble bust, orbiting)")
    agree.add_argument("--threads", type=positive_int, default=None, help="torch.set_num_threads")
    agree.add_argument("--json", metavar="PATH", help="also write the report as JSON to PATH")
    agree.add_argument("overrides", nargs="*", metavar="key=value",
                       help="config overrides, e.g. estimators.tiny_decoder=/path/to/taecvx.pth guidance.decoder=tiny")

    geval = sub.add_parser("geco-eval", help="estimator calls and time of scoring one video under each pair mode "
                                             "(tiny on CPU, estimated at full size on an H200)")
    geval.add_argument("--frames", type=frame_count, default=49, help="frames of the clip (default: 49, CogVideoX)")
    geval.add_argument("--fps", type=positive_float, default=16.0, help="its native frame rate (default: 16, CogVideoX)")
    geval.add_argument("--height", type=positive_int, default=32, help="height of the tiny run (default: 32)")
    geval.add_argument("--width", type=positive_int, default=48, help="width of the tiny run (default: 48)")
    geval.add_argument("--pairs", nargs="+", choices=PAIR_MODES, default=["all", "center", "adjacent"],
                       help="the frame pairs of each window to estimate, one row each (default: all center adjacent)")
    geval.add_argument("--videos", type=positive_int, default=320, help="videos per model (default: 320 = 80 prompts x 4 seeds)")
    geval.add_argument("--threads", type=positive_int, default=None, help="torch.set_num_threads")
    geval.add_argument("--seed", type=int, default=0, help="seed of the random clip (default: 0)")
    geval.add_argument("--json", metavar="PATH", help="also write the report as JSON to PATH")

    # internal: one case in its own process (no help= entry: it stays out of --help)
    public = list(sub.choices)
    worker = sub.add_parser("worker", description="internal: run one case given as JSON, print its result as JSON")
    worker.add_argument("spec", help="the case, as JSON")
    sub.metavar = "{" + ",".join(public) + "}"
    return parser


def main(argv: Sequence[str] | None = None) -> None:
    parser = build_parser()
    args = parser.parse_args(argv)
    if args.command == "worker":
        import json

        spec = json.loads(args.spec)
        print(json.dumps(run_sampling_worker(spec) if spec["workload"] == "sampling" else run_worker(spec, WORKLOADS)))
        return
    log_to_stderr()  # each case's progress lines
    check_options(args)
    if args.command == "sampling":
        run_sampling(args)
    elif args.command == "cost":
        run_cost(args)
    elif args.command == "plans":
        run_plans(args)
    elif args.command == "decoder-agreement":
        run_decoder_agreement(args)
    elif args.command == "geco-eval":
        run_geco_eval_cost(args)
    else:
        run_and_report(args)


if __name__ == "__main__":
    main()
