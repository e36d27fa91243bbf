"""``geco compare RUN_A RUN_B --out DIR``: how far the estimators move GeCo-Eval's
rankings (:mod:`geco_guide.bench.backbone_compare`).

    geco geco-eval --models cogvideox-5b wan2.1-t2v-1.3b --limit 8 --out eval-vggt
    geco geco-eval --videos cogvideox-5b=eval-vggt/videos/cogvideox-5b \\
        wan2.1-t2v-1.3b=eval-vggt/videos/wan2.1-t2v-1.3b --limit 8 --geometry-estimator da3-base --out eval-da3
    geco compare eval-vggt eval-da3 --out compare-vggt-da3

writes ``comparison.json`` and ``comparison.md`` in ``--out``: the estimators of each run,
Spearman between the runs over the paired videos and over the models, and each model's mean
scores under both.
"""

from __future__ import annotations

import argparse
from pathlib import Path

from .. import __version__
from ..io.files import WriteError
from .command_line import command_main
from .kit import output_folder, print_error

__all__ = ["DESCRIPTION", "SUMMARY", "main", "register_subcommand", "run"]

SUMMARY = "compare two GeCo-Eval runs of the same videos scored with different estimators (Spearman)"
DESCRIPTION = ("Compare two GeCo-Eval runs that scored the same videos with different estimators (geometry "
               "backbone, flow): Spearman between their scores over videos and over models, and each model's means.")


def register_subcommand(parser: argparse.ArgumentParser) -> argparse.ArgumentParser:
    """The options of ``geco compare`` on ``parser``."""
    parser.add_argument("--version", action="version", version=f"geco_guide {__version__}")
    parser.add_argument("runs", nargs=2, metavar="RUN", help="two geco geco-eval --out folders (A, then B)")
    parser.add_argument("--out", type=output_folder, required=True,
                        help="output folder of comparison.json and comparison.md")
    parser.add_argument("--overwrite", action="store_true", help="replace the comparison of an earlier run in --out")
    return parser


def run(args: argparse.Namespace) -> int:
    """The comparison of the two runs; 0, or 2 after one line on stderr."""
    from ..bench.backbone_compare import COMPARISON_FILES, compare_runs, comparison_markdown, read_run
    from ..bench.report import fmt
    from ..io.files import check_output_dir, json_text, write_texts_atomic

    try:
        first, second = (read_run(Path(folder)) for folder in args.runs)
        out = Path(args.out)
        taken = next((out / name for name in COMPARISON_FILES if (out / name).exists()), None)
        if taken is not None and not args.overwrite:
            raise ValueError(f"{str(taken)!r} already exists; pass --overwrite to replace it, or choose another --out")
        comparison = compare_runs(first, second)
        check_output_dir(out)
        json_path, markdown_path = (out / name for name in COMPARISON_FILES)
        write_texts_atomic({json_path: json_text(comparison), markdown_path: comparison_markdown(comparison)})
    except (ValueError, WriteError) as err:
        return print_error(err)
    fused = comparison["spearman"]["fused"]
    print(f"fused score, Spearman A vs B: {fmt(fused['videos'])} over {fused['n_videos']} videos, "
          f"{fmt(fused['models'])} over {fused['n_models']} models; report: {markdown_path}")
    return 0


main = command_main("geco compare", DESCRIPTION, register_subcommand, run)
