"""``geco robustness``: the noise sweep of :mod:`geco_guide.bench.robustness`.

    geco robustness --out robustness            # CPU, offline, about a minute

Every option is checked, the output folder included, and the sweep's memory predicted
(:func:`~geco_guide.bench.robustness.sweep_memory_bytes`) before the sweep runs.
"""

from __future__ import annotations

import argparse
import sys
from dataclasses import replace
from pathlib import Path

from ..io.files import WriteError, check_output_dir, json_text, write_texts_atomic
from .command_line import command_main
from .kit import check_choice, interruptible, output_folder

__all__ = ["DESCRIPTION", "SUMMARY", "main", "register_subcommand", "run"]

SUMMARY = "the metric against noisy depth and flow"
DESCRIPTION = "Sweep Gaussian noise on depth and flow; plot each cue's detection AP."


def _sigmas(values: list[float], name: str) -> tuple[float, ...]:
    if not values or any(not (v >= 0 and v < float("inf")) for v in values):
        raise ValueError(f"{name} must be finite numbers >= 0, got {values}")
    return tuple(sorted(values))


def register_subcommand(p: argparse.ArgumentParser) -> argparse.ArgumentParser:
    """The options of ``geco robustness`` on ``p`` (the default noise levels:
    :data:`~geco_guide.bench.robustness.DEPTH_SIGMAS` and ``FLOW_SIGMAS``)."""
    p.add_argument("--out", type=output_folder, required=True, help="output folder")
    p.add_argument("--size", type=int, nargs=3, default=(9, 48, 64), metavar=("FRAMES", "H", "W"),
                   help="the synthetic scene the noise is added to: frames, height, width (default: 9 48 64)")
    p.add_argument("--seed", type=int, default=0, help="seed of the scene's warps and occlusions and of the noise "
                                                       "(default: 0); the same seed gives the same report")
    p.add_argument("--depth-sigmas", type=float, nargs="+", default=None, metavar="SIGMA",
                   help="depth noise levels: each depth is multiplied by exp(sigma n), n ~ N(0, 1), so sigma is "
                        "about the relative error (default: 0 0.01 0.02 0.05 0.1 0.15 0.2 0.3 0.5 1)")
    p.add_argument("--flow-sigmas", type=float, nargs="+", default=None, metavar="SIGMA",
                   help="flow noise levels in pixels: sigma n is added to each flow vector "
                        "(default: 0 0.25 0.5 1 2 5 10 20)")
    p.add_argument("--pairs", default="all", metavar="MODE",
                   help="frame pairs GeCo compares: all (default, the evaluation protocol's), center or adjacent")
    p.add_argument("--no-depth-edges", action="store_true",
                   help="keep structure pixels on depth edges (depth_edge_tau=None, the paper's behaviour)")
    return p


@interruptible("nothing: the sweep writes its files only when it is complete")
def run(args: argparse.Namespace) -> int:
    """The sweep ``args`` ask for; 0, 1 (its files could not be written), or 2 after one line on
    stderr before the sweep runs."""
    from ..bench.robustness import DEPTH_SIGMAS, FLOW_SIGMAS, markdown_report, plot, run_sweep, sweep_memory_bytes
    from ..config import SEED_RANGE
    from ..io.devices import check_memory_fits
    from ..loss.geco import PAIR_MODES
    from ..metric.protocol import EvaluationConfig

    out = Path(args.out)
    try:
        check_choice("--pairs", args.pairs, PAIR_MODES)
        frames, height, width = args.size
        if frames < 3 or height < 8 or width < 8:
            raise ValueError(f"--size must be at least 3 frames of 8x8, got {args.size}")
        if not SEED_RANGE[0] <= args.seed <= SEED_RANGE[1]:
            raise ValueError(f"--seed must be a 64-bit integer in [{SEED_RANGE[0]}, {SEED_RANGE[1]}], got {args.seed}")
        depth_sigmas = _sigmas(DEPTH_SIGMAS if args.depth_sigmas is None else args.depth_sigmas, "--depth-sigmas")
        flow_sigmas = _sigmas(FLOW_SIGMAS if args.flow_sigmas is None else args.flow_sigmas, "--flow-sigmas")
        check_memory_fits(sweep_memory_bytes(frames, height, width, args.pairs), "cpu",
                          f"--size {frames} {height} {width} (--pairs {args.pairs})")
        check_output_dir(out)
    except (ValueError, WriteError) as err:
        print(f"error: {err}", file=sys.stderr)
        return 2
    defaults = EvaluationConfig().loss
    # a line per noise level as soon as it is scored (flushed: a pipe would hold them to the end)
    report = run_sweep(frames, height, width, args.seed, depth_sigmas, flow_sigmas,
                       replace(defaults, pairs=args.pairs, depth_edge_tau=None if args.no_depth_edges else defaults.depth_edge_tau),
                       progress=lambda line: print(line, flush=True))
    try:  # the table and the plot describe the JSON: all or none
        write_texts_atomic({out / "robustness.json": json_text(report), out / "robustness.md": markdown_report(report),
                            out / "robustness.png": plot(report)})
    except WriteError as err:
        print(f"error: {err}", file=sys.stderr)
        return 1
    print(f"wrote {out / 'robustness.json'}, {out / 'robustness.md'} and {out / 'robustness.png'}")
    return 0


main = command_main("geco robustness", DESCRIPTION, register_subcommand, run)
