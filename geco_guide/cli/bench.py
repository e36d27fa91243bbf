"""``geco bench``: time and memory of geco_guide, measured or predicted (the perf harness over :mod:`geco_guide.perf`).

    geco bench loss --frames 4 --height 480 --width 720 --repeats 3
    geco bench sampling --preset tiny --mode fast --steps 2 --warmup 0
    geco bench cost --model wan2.1-t2v-14b --mode faithful --gpu H200
    geco bench cost --all-models
    geco bench cost --model wan2.2-t2v-a14b --context-parallel 4
    geco bench plans --threads 1 --json geco_guide/sampler/running/data/memory_plans.json

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
import sys
from typing import Any

from ..families.published import PackageDataError, traced_models
from .bench_options import (
    AGREEMENT_PROMPT,
    GEOMETRY_CHOICES,
    add_cost,
    add_json,
    add_micro,
    add_sampling,
    add_threads,
    frame_count,
    positive_float,
    positive_int,
)
from .command_line import command_main
from .kit import Parser, check_choice, interruptible, print_error

__all__ = ["DESCRIPTION", "SUMMARY", "main", "register_subcommand", "run"]

SUMMARY = "time and memory: micro-benchmarks, sampling, the cost model of every family, memory plans, search"
DESCRIPTION = ("Time and memory of geco_guide: micro-benchmarks and sampling measured here, the cost model's "
               "predictions for every family on fake tensors (no weights, no GPU), the memory plans' estimates.")
#: The public subcommands, in ``--help``'s order (``worker`` is internal: it runs one case).
SUBCOMMANDS = ("loss", "estimators", "vae", "sampling", "cost", "plans", "attention-shapes", "decoder-agreement",
               "geco-eval")


def _plans(sub: Any) -> None:
    plans = sub.add_parser("plans", help="the memory plans' estimates of every traced model (the package data "
                                         "run.memory_plan=auto reads), from the cost model")
    models = [*traced_models(), "tiny"]
    plans.add_argument("--models", nargs="+", choices=models, default=models, help="the models to trace (default: all)")
    add_threads(plans)
    add_json(plans, "write the estimates as JSON to PATH")
    shapes = sub.add_parser("attention-shapes", help="the attention calls of every traced model's denoiser (the "
                                                     "package data of the several-GPU costs), traced on fake tensors")
    shapes.add_argument("--models", nargs="+", choices=traced_models(), default=traced_models(),
                        help="the models to trace (default: all)")
    add_threads(shapes)
    add_json(shapes, "write the attention shapes as JSON to PATH")


def _others(sub: Any) -> None:
    agree = sub.add_parser("decoder-agreement", help="both decoders at every guidance update of one guided call: "
                                                     "gradient cosine, losses, anchor-frame PSNR")
    agree.add_argument("--preset", default=None,
                       help="a preset of configs/ (tiny: the tiny random models, offline); default: the schema's")
    agree.add_argument("--config", metavar="YAML", default=None, help="a config file over the preset")
    agree.add_argument("--prompt", default=AGREEMENT_PROMPT, help="the prompt (default: a marble bust, orbiting)")
    add_threads(agree)
    add_json(agree)
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
    add_threads(geval)
    geval.add_argument("--seed", type=int, default=0, help="seed of the random clip (default: 0)")
    add_json(geval)


def register_subcommand(parser: argparse.ArgumentParser) -> argparse.ArgumentParser:
    """The subcommands of ``geco bench`` and their options on ``parser``; the internal ``worker``
    (one case in its own process) stays out of ``--help``."""
    sub = parser.add_subparsers(dest="command", required=True, parser_class=Parser)
    add_micro(sub)
    add_sampling(sub)
    add_cost(sub)
    _plans(sub)
    _others(sub)
    worker = sub.add_parser("worker", description="internal: run one case given as JSON, print its result as JSON")
    worker.add_argument("spec", help="the case, as JSON")
    sub.metavar = "{" + ",".join(SUBCOMMANDS) + "}"
    return parser


def loss_workload(spec: dict[str, Any], device: Any) -> Any:
    """The ``loss`` case (:func:`geco_guide.perf.loss_workload.loss_workload`) on the cameras of
    the synthetic scenes: a 60-degree camera's K and an orbit (:mod:`geco_guide.bench.synthetic`,
    which the perf layer may not import: this command may)."""
    import torch

    from ..bench.synthetic import default_intrinsics, orbit_cameras
    from ..perf.loss_workload import loss_workload as workload

    intrinsics = default_intrinsics(spec["height"], spec["width"], dtype=torch.float32)
    return workload(spec, device, intrinsics, orbit_cameras(spec["frames"], dtype=torch.float32))


def _worker(args: argparse.Namespace) -> None:
    from ..perf.sampling import run_sampling_worker
    from ..perf.workloads import WORKLOADS, run_worker

    spec = json.loads(args.spec)
    if spec["workload"] == "sampling":
        print(json.dumps(run_sampling_worker(spec)))
    else:
        print(json.dumps(run_worker(spec, {**WORKLOADS, "loss": loss_workload})))


def _check(args: argparse.Namespace) -> Any:
    """The work of ``args``' subcommand, once every option passed its checks (:class:`BadOption`)."""
    from ..perf import bench_checks as checks
    from ..perf.subcommands import WORK, family_report, parallel_report_of

    if args.command == "cost" and args.context_parallel is not None:
        checks.check_context_parallel(args, COST_DEFAULTS)
        return parallel_report_of
    if args.command == "cost" and args.all_models:
        checks.check_all_models(args, COST_DEFAULTS)
        return family_report
    checks.check_options(args, COST_DEFAULTS)
    if args.command in ("loss", "geco-eval"):
        from ..loss.geco import PAIR_MODES

        check_choice("--pairs", args.pairs, PAIR_MODES)
    return WORK[args.command]


@interruptible("the reports are written with --json at the end, atomically: nothing of this run was kept")
def run(args: argparse.Namespace) -> int:
    """The subcommand ``args`` name; 0, or 2 after one line on stderr for a bad option (checked
    before any work) or a card no plan fits."""
    from ..estimators.loading import WeightsNotFoundError
    from ..perf.bench_checks import BadOption
    from ..perf.subcommands import family_report, parallel_report_of

    if args.command == "worker":
        _worker(args)
        return 0
    try:
        work = _check(args)
        if work in (family_report, parallel_report_of):  # the shipped estimates' tables, read as they are checked
            return _finish(args, work)
    except (ValueError, FileNotFoundError, WeightsNotFoundError) as err:  # BadOption among them
        return print_error(err)
    try:
        return _finish(args, work)
    except (BadOption, PackageDataError) as err:
        return print_error(err)


def _finish(args: argparse.Namespace, work: Any) -> int:
    """Run ``work``, print its Markdown and write its report with ``--json``; 0."""
    from ..perf.measure import write_report

    report, text = work(args, sys.argv[1:], print)
    if text is not None:
        print(text)
    if args.json:
        write_report(args.json, report)
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
