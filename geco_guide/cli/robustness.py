"""``python -m geco_guide.robustness``: the noise sweep of :mod:`geco_guide.bench.robustness`.

    python -m geco_guide.robustness --out robustness            # CPU, offline, about a minute
"""

from __future__ import annotations

import sys
from dataclasses import replace
from pathlib import Path

from ..bench.robustness import CUES, DEPTH_SIGMAS, FLOW_SIGMAS, plot, run_sweep
from ..io.files import write_bytes_atomic, write_json_atomic
from ..metric.protocol import EvaluationConfig
from .kit import Parser


def _sigmas(values: list[float], name: str) -> tuple[float, ...]:
    if not values or any(not (v >= 0 and v < float("inf")) for v in values):
        raise ValueError(f"{name} must be finite numbers >= 0, got {values}")
    return tuple(sorted(values))


def main(argv: list[str] | None = None) -> int:
    p = Parser(prog="python -m geco_guide.robustness",
               description="Sweep Gaussian noise on depth and flow; plot each cue's detection AP.")
    p.add_argument("--out", required=True, help="output folder")
    p.add_argument("--size", type=int, nargs=3, default=(9, 48, 64), metavar=("FRAMES", "H", "W"))
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--depth-sigmas", type=float, nargs="+", default=list(DEPTH_SIGMAS))
    p.add_argument("--flow-sigmas", type=float, nargs="+", default=list(FLOW_SIGMAS))
    p.add_argument("--pairs", choices=("all", "center", "adjacent"), default="all")
    p.add_argument("--no-depth-edges", action="store_true",
                   help="keep structure pixels on depth edges (depth_edge_tau=None, the paper's behaviour)")
    args = p.parse_args(argv)
    try:
        frames, height, width = args.size
        if frames < 3 or height < 8 or width < 8:
            raise ValueError(f"--size must be at least 3 frames of 8x8, got {args.size}")
        report = run_sweep(frames, height, width, args.seed, _sigmas(args.depth_sigmas, "--depth-sigmas"),
                           _sigmas(args.flow_sigmas, "--flow-sigmas"),
                           replace(EvaluationConfig().loss, pairs=args.pairs,
                                   depth_edge_tau=None if args.no_depth_edges else EvaluationConfig().loss.depth_edge_tau))
    except ValueError as err:
        print(f"error: {err}", file=sys.stderr)
        return 2
    out = Path(args.out)
    write_json_atomic(out / "robustness.json", report)
    write_bytes_atomic(out / "robustness.png", plot(report))
    for noisy_input in ("depth", "flow"):
        rows = report[noisy_input]
        for k, sigma in enumerate(rows["sigmas"]):
            cells = " ".join(f"{task}/{cue} {rows[task][cue][k]:.3f}" for task in ("warp", "occlusion") for cue in CUES)
            print(f"{noisy_input} sigma={sigma:g}: {cells} rigid fused {rows['rigid_fused'][k]:.4f}")
    print(f"wrote {out / 'robustness.json'} and {out / 'robustness.png'}")
    return 0

