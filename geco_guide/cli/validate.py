"""``geco validate``: score built benchmarks on the paper's three detection tasks
(:mod:`geco_guide.bench.validate`).

    geco validate bench/synthetic-warp bench/synthetic-occlusion --oracle   # exact geometry, CPU
    geco validate bench/warp bench/occlusion                               # VGGT-1B + UFM-Base
    geco validate bench/warp --preset tiny                                 # tiny random models
    geco validate --dynamic --out validation-dynamic                       # dynamic masks vs ground truth

``--dynamic`` needs no benchmark folder: it renders the synthetic scenes with objects that move on
their own and reports, with the oracle estimators, the false positives, the artifact detection AP,
the automatic mask's quality and the movers scored against their own motion
(:mod:`geco_guide.bench.dynamic_suite`), and ``movers=rigid`` on eight scenes of a box drawn at
random, in ``dynamic.json`` and ``dynamic.md``; ``--dynamic-seed N`` draws other edits and the
drawn scenes of seeds N to N + 7. The exit code is 0 whether or not the targets are met: the
report says which are.

A clip that cannot be read or scored (a damaged ``meta.json`` or ``truth.npz``, ground truth that
contradicts the clip) is one error line and a row of ``errors`` in the report; the others are
scored, and the exit code is 1 when any clip failed (2 for bad options, before any work: a report
of an earlier run in ``--out`` among them, unless ``--overwrite``). Progress (one line per clip, or
per scored clip of ``--dynamic``) goes to stderr as the work happens.
"""

from __future__ import annotations

import argparse
import sys
from dataclasses import asdict
from pathlib import Path

from ..io.files import WriteError, check_output_dir, json_text, write_texts_atomic
from .command_line import command_main
from .kit import add_config_flags, config_from_args, interruptible, output_folder, split_overrides

__all__ = ["DESCRIPTION", "SUMMARY", "main", "register_subcommand", "run"]

SUMMARY = "score built benchmark clips on the paper's three detection tasks"
DESCRIPTION = "Score benchmark clips on the paper's three detection tasks."


def register_subcommand(p: argparse.ArgumentParser) -> argparse.ArgumentParser:
    """The options of ``geco validate`` on ``p``."""
    p.add_argument("inputs", nargs="*", metavar="DIR|key=value", help="benchmark folders; key=value config overrides")
    p.add_argument("--oracle", action="store_true", help="ground-truth estimators (clips built from 'synthetic')")
    add_config_flags(p)
    p.add_argument("--pairs", default=None, metavar="MODE",
                   help="frame pairs per window: all (default), center or adjacent (evaluation.loss.pairs)")
    p.add_argument("--out", type=output_folder, default=None, help="output folder (default: <first input>/validation)")
    p.add_argument("--no-grids", action="store_true", help="skip the per-clip image grids")
    p.add_argument("--overwrite", action="store_true",
                   help="replace the report of an earlier run in --out (without it, an existing report is an error)")
    p.add_argument("--dynamic", action="store_true",
                   help="validate dynamic masks on synthetic scenes with moving objects (oracle estimators; no inputs)")
    p.add_argument("--dynamic-size", type=int, nargs=3, default=None, metavar=("FRAMES", "HEIGHT", "WIDTH"),
                   help="size of the --dynamic clips (default 9 96 128)")
    p.add_argument("--dynamic-seed", type=int, default=None, metavar="N",
                   help="seed of the --dynamic scenes' edits (the warps, the swap) and the first of the eight "
                        "drawn mover scenes (default 0)")
    return p


def check_no_report(paths: list[Path], overwrite: bool) -> None:
    """ValueError (one line) when a report file of an earlier run is there and ``overwrite`` is not
    given: the other commands refuse to replace their outputs silently too."""
    taken = next((path for path in paths if path.exists()), None)
    if taken is not None and not overwrite:
        raise ValueError(f"{str(taken)!r} already exists (the report of an earlier run); pass --overwrite to replace "
                         "it, or choose another --out folder")


def dynamic_main(args: argparse.Namespace) -> int:
    """``--dynamic``: the report of :func:`geco_guide.bench.dynamic_suite.dynamic_validation`."""
    from ..bench.dynamic_suite import DynamicScenes, dynamic_validation, markdown_report

    try:
        if args.inputs:
            raise ValueError("--dynamic renders its own scenes: give no benchmark folder or override")
        scenes = DynamicScenes(*(args.dynamic_size or ()), **({} if args.dynamic_seed is None else {"seed": args.dynamic_seed}))
        out = check_output_dir(Path(args.out) if args.out else Path("validation-dynamic"))
        check_no_report([out / "dynamic.json", out / "dynamic.md"], args.overwrite)
    except (ValueError, WriteError) as err:
        print(f"error: {err}", file=sys.stderr)
        return 2
    _progress(f"rendering and scoring the dynamic scenes ({scenes.num_frames} frames of {scenes.height}x{scenes.width})")
    report = dynamic_validation(scenes)
    table = markdown_report(report)
    try:
        write_texts_atomic({out / "dynamic.json": json_text(report), out / "dynamic.md": f"# GeCo dynamic masks (oracle)\n\n{table}"})
    except WriteError as err:
        print(f"error: {err}", file=sys.stderr)
        return 1
    print(table, end="")
    print(f"wrote {out / 'dynamic.json'} and {out / 'dynamic.md'}")
    return 0


def _progress(message: str) -> None:
    print(message, file=sys.stderr, flush=True)


@interruptible("nothing of this run's report: validation.json and validation.md are written together at the end "
               "(grids of the clips scored so far stay in <out>/grids)")
def run(args: argparse.Namespace) -> int:
    """The validation report ``args`` ask for; 0, 1 (a clip failed, or the report could not be
    written), or 2 after one line on stderr before any work."""
    if args.dynamic:
        return dynamic_main(args)
    if args.dynamic_size or args.dynamic_seed is not None:
        print(f"error: {'--dynamic-size' if args.dynamic_size else '--dynamic-seed'} needs --dynamic", file=sys.stderr)
        return 2
    return _validate_benchmarks(args)


def _validate_benchmarks(args: argparse.Namespace) -> int:
    from ..bench.datasets import find_benchmarks, load_benchmark, oracle_clip
    from ..bench.validate import grid_frames, grid_image, markdown_table, summarise, validate_clip, write_png
    from ..estimators import Estimators, check_weights, load_estimators
    from ..estimators.oracle import OracleFlow, OracleGeometry
    from ..io.devices import check_device
    from ..metric.evaluate import score_frames

    overrides, roots = split_overrides(args.inputs)
    try:
        if not roots:
            raise ValueError("no benchmark folder given")
        folders = [folder for root in roots for folder in find_benchmarks(root)]
        cfg = config_from_args(args, overrides, {"evaluation.loss.pairs": args.pairs})
        check_device(cfg.evaluation.device, "evaluation.device")
        out = check_output_dir(Path(args.out) if args.out else Path(roots[0]) / "validation")
        check_no_report([out / "validation.json", out / "validation.md"], args.overwrite)
        if not args.oracle:
            check_weights(cfg.estimators)  # every missing model named at once, before the loading line
            _progress(f"loading models: {cfg.estimators.geometry} + {cfg.estimators.flow} on {cfg.evaluation.device}")
        estimators = None if args.oracle else load_estimators(cfg.estimators, cfg.evaluation.device)
    except (ValueError, FileNotFoundError, WriteError) as err:  # missing weights among them
        print(f"error: {err}", file=sys.stderr)
        return 2
    records, errors = [], []
    for k, folder in enumerate(folders, 1):
        _progress(f"[{k}/{len(folders)}] scoring {folder}")
        try:
            bench = load_benchmark(folder)
            if args.oracle:
                clip = oracle_clip(bench)
                models = Estimators(OracleGeometry(clip), OracleFlow(clip))
            else:
                models = estimators
            _, result = score_frames(bench.frames, models, cfg.evaluation.loss, flow_batch_size=cfg.evaluation.flow_batch_size)
            record = validate_clip(bench, result)
            if not args.no_grids:
                grid = grid_image(bench, result, grid_frames(bench, record), record.get("task1"))
                record["grid"] = str(write_png(out / "grids" / f"{record['clip']}.png", grid))
        except (ValueError, OSError, RuntimeError) as err:  # one bad clip must not stop the others
            errors.append({"clip": str(folder), "error": str(err).splitlines()[0] if str(err) else type(err).__name__})
            print(f"error: {folder}: {errors[-1]['error']}", file=sys.stderr)
            continue
        records.append(record)
        print(f"{folder}: {bench.kind} scored")
    summary = summarise(records)
    estimator_ids = {"geometry": "oracle", "flow": "oracle"} if args.oracle else estimators.ids()
    report = {"summary": summary, "clips": records, "errors": errors, "estimators": estimator_ids,
              "loss": asdict(cfg.evaluation.loss)}
    table = markdown_table(summary) if summary else "No clip could be scored.\n"
    if errors:
        table += f"\n{len(errors)} of {len(folders)} clip(s) failed: see errors in validation.json.\n"
    try:  # the table describes the JSON: both or neither
        write_texts_atomic({out / "validation.json": json_text(report),
                            out / "validation.md": f"# GeCo validation ({estimator_ids['geometry']} + {estimator_ids['flow']})\n\n{table}"})
    except WriteError as err:
        print(f"error: {err}", file=sys.stderr)
        return 1
    print(table, end="")
    print(f"wrote {out / 'validation.json'} and {out / 'validation.md'}")
    return 1 if errors or not records else 0


main = command_main("geco validate", DESCRIPTION, register_subcommand, run)
