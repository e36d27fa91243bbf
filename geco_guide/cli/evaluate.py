"""``geco evaluate VIDEO [VIDEO ...|DIR]``: score videos with the GeCo metric.

    geco evaluate clip.mp4 --maps                 # VGGT-1B + UFM-Base from the hub
    geco evaluate videos/ --geometry-estimator /data/VGGT-1B --flow-estimator /data/UFM-Base --out scores
    geco evaluate --preset tiny clip.mp4 frames/   # tiny random models, CPU, offline
    geco evaluate clip.mp4 --model cogvideox-5b    # timed at the model's native 16 fps

The protocol is :func:`geco_guide.metric.evaluate.evaluate_video`'s. Per video:
``<out>/<stem>.geco.json`` and with ``--maps`` ``<out>/<stem>.maps.mp4`` (source | motion |
structure | fused on the fixed colour scale of :data:`geco_guide.metric.render.MAP_RANGE`, with a
legend). Several inputs (or a folder of videos) add ``<out>/geco_scores.csv`` (one row per video,
failures with an ``error``) and ``<out>/geco_summary.json`` (means over videos). Every output is
written atomically, the table and summary both or neither, a video's score JSON after its other
outputs (one that cannot be written takes those back). While it runs, the command holds an output
lock on each file it writes (:func:`~geco_guide.io.files.output_lock`): a second run into the same
files is refused. A bad input is one error line and does not stop the others; the exit code is
non-zero only when every input failed or the table could not be written (2 before any model loads:
a bad config, an unusable ``--out``, a mask file that is unreadable or fits no input, the weights
of any model missing (all of them named at once), another run writing the same outputs).
Progress goes to stderr: the models being loaded, then one line per input and per window.
"""

from __future__ import annotations

import argparse
import contextlib
import math
import sys
from dataclasses import asdict
from pathlib import Path
from typing import Any

from .. import __version__
from ..io.files import WriteError, check_output_dir, output_lock
from .command_line import command_main
from .kit import (
    add_config_flags,
    config_from_args,
    interruptible,
    is_config_key,
    output_folder,
    split_overrides,
)

__all__ = ["DESCRIPTION", "SUMMARY", "main", "register_subcommand", "run"]

SUMMARY = "score videos with the GeCo protocol"
DESCRIPTION = "Score videos with GeCo (M_motion, M_struct, M_geo, Total/Mean Motion)."


def register_subcommand(p: argparse.ArgumentParser) -> argparse.ArgumentParser:
    """The options of ``geco evaluate`` on ``p``."""
    p.add_argument("--version", action="version", version=f"geco_guide {__version__}")
    p.add_argument("inputs", nargs="+", metavar="VIDEO|DIR|key=value",
                   help="video files (mp4, gif, ...), folders of frames or of videos; key=value config overrides")
    add_config_flags(p)
    p.add_argument("--model", dest="source_model", default=None, metavar="NAME",
                   help="the video model that made the inputs (e.g. cogvideox-5b): its native frame rate "
                        "(evaluation.model_fps, the paper's table) replaces the file's")
    p.add_argument("--fps", type=float, default=None, help="source frame rate, overriding --model and the file's")
    p.add_argument("--out", type=output_folder, default=None, help="output folder (default: the config's output.dir)")
    p.add_argument("--maps", action="store_true", help="also write <stem>.maps.mp4 with the heat maps")
    p.add_argument("--overwrite", action="store_true",
                   help="replace the outputs of an earlier run in --out (without it, an existing output is an error)")
    p.add_argument("--detection", action="store_true",
                   help="also write <stem>.detection.mp4: every frame's own maps against a window of 20 frames "
                        "around it (geco detection for the window, anchor and formats)")
    p.add_argument("--pairs", default=None, metavar="MODE",
                   help="frame pairs per window: all (default, the paper's script: n(n-1) flow pairs for n frames), "
                        "center (2(n-1)) or adjacent (n-1)")
    p.add_argument("--dynamic-masks", default=None, metavar="PATH|auto|TEXT",
                   help="leave content that moves on its own out of the scores: a mask video, PNG folder or .npz "
                        "(one video's masks), 'auto' (movers found from GeCo's own depth and flow) or text naming "
                        "what moves (a segmenter); docs/metric.md, 'Dynamic masks'")
    p.add_argument("--max-frames", type=int, default=None, metavar="N",
                   help="score only the first N frames of each input (evaluation.max_frames): the motion "
                        "statistics cover a whole clip, so a long one takes time in proportion to its length")
    return p


def _progress(message: str) -> None:
    print(message, file=sys.stderr, flush=True)


@interruptible("the <stem>.geco.json (and maps) of the videos finished so far; geco_scores.csv and geco_summary.json were not written")
def run(args: argparse.Namespace) -> int:
    """Score the inputs ``args`` name; 0, 1 (every input failed, or the table could not be
    written), or 2 after one line on stderr before any model loads."""
    with contextlib.ExitStack() as locks:  # the output locks, held until the run ends
        return _run(args, locks)


def _run(args: argparse.Namespace, locks: contextlib.ExitStack) -> int:
    from ..estimators import check_weights, load_estimators, load_segmenter, segmenter_id
    from ..io.devices import check_device
    from ..metric.evaluate import finite_or_none
    from ..metric.score_files import SUMMARY_KEYS, ScoreOptions, one_line, score_line, score_one, write_table
    from ..metric.video_inputs import (check_detection_masks, check_inputs_and_outputs, check_masks_fit,
                                       dynamic_mask_option, expand_inputs, holds_frames, needs_segmenter, run_outputs)

    overrides, videos = split_overrides(args.inputs)
    # Neither an input nor an option (a=b.mp4): a missing file, or a mistyped key.
    strays = [a for a in overrides if not is_config_key(a.partition("=")[0])]
    try:
        if strays:
            raise ValueError(f"{strays[0]!r} is neither an existing file nor a config override "
                             f"({strays[0].partition('=')[0]!r} is not a config key)")
        if not videos:
            raise ValueError("no input video given")
        if args.fps is not None and not (args.fps > 0 and math.isfinite(args.fps)):
            raise ValueError(f"--fps must be a finite number > 0, got {args.fps}")
        cfg = config_from_args(args, overrides, {"evaluation.loss.pairs": args.pairs,
                                                 "evaluation.max_frames": args.max_frames})
        if args.source_model is not None:
            cfg.evaluation.fps_of_model(args.source_model)  # an unknown name fails before the estimators load
        device = check_device(cfg.evaluation.device, "evaluation.device")  # "auto" resolved once
        out = check_output_dir(args.out if args.out is not None else cfg.output.dir)
        items = expand_inputs(videos)
        dynamic = dynamic_mask_option(args.dynamic_masks, device)
        check_detection_masks(args.detection, dynamic)
        check_masks_fit(items, dynamic, cfg.evaluation)
        table = len(items) > 1 or any(Path(v).is_dir() and not holds_frames(Path(v)) for v in videos)
        if not all(item.error is not None for item in items):  # else check_inputs_and_outputs says why
            for path in run_outputs(items, out, args.maps, args.detection, table):
                locks.enter_context(output_lock(path, "choose another --out"))
        check_inputs_and_outputs(items, out, args.overwrite, args.maps, args.detection)  # under the locks: an output of a run that ended meanwhile counts
        segmenter = needs_segmenter(dynamic)
        check_weights(cfg.estimators, segmenter=segmenter)  # every missing model named at once, nothing loaded yet
        segment = None
        if segmenter:  # loaded first, each load under its own line: an error follows the line of what failed
            _progress(f"loading segmenter: {cfg.estimators.segmenter} for {dynamic!r} ...")
            segment = load_segmenter(cfg.estimators, device)
        _progress(f"loading models: {cfg.estimators.geometry} + {cfg.estimators.flow} on {device}")
        estimators = load_estimators(cfg.estimators, device).with_segmenter(segment, segmenter_id(cfg.estimators))
    except (ValueError, FileNotFoundError, WriteError) as err:  # WeightsNotFoundError is a FileNotFoundError
        print(f"error: {err}", file=sys.stderr)
        return 2

    options = ScoreOptions(args.fps, args.source_model, args.maps, args.detection)
    rows: list[dict[str, Any]] = []
    for k, item in enumerate(items, 1):
        row: dict[str, Any] = {"name": item.name, "path": str(item.path), "error": item.error}
        if item.error is None:
            _progress(f"[{k}/{len(items)}] scoring {item.path}")
            try:
                result, json_path, notes = score_one(item, out, estimators, cfg.evaluation, options, dynamic,
                                                     lambda line, k=k: _progress(f"[{k}/{len(items)}]   {line}"))
            except Exception as err:  # one bad input must not stop the others
                row["error"] = one_line(err)
            else:
                row.update({key: finite_or_none(getattr(result, key)) for key in SUMMARY_KEYS})
                row.update(num_frames=result.num_frames, fps=result.fps, fps_source=result.fps_source,
                           sampled_fps=result.sampled_fps,
                           num_windows=len(result.windows), json=str(json_path))
                print(score_line(item.name, result, json_path, notes))
        if row["error"] is not None:
            print(f"error: {item.path}: {row['error']}", file=sys.stderr)
        rows.append(row)

    if table:
        try:
            csv_path, summary_path = write_table(out, rows, estimators.ids(), asdict(cfg.evaluation))
        except WriteError as err:
            print(f"error: {err}", file=sys.stderr)
            return 1
        print(f"wrote {csv_path} and {summary_path}")
    return 1 if all(row["error"] is not None for row in rows) else 0


main = command_main("geco evaluate", DESCRIPTION, register_subcommand, run)
