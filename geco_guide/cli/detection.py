"""``geco detection``: per-frame detection maps (:mod:`geco_guide.metric.detection`).

    geco detection clip.mp4 --out maps                  # VGGT-1B + UFM-Base, mp4
    geco detection frames/ --preset tiny --window 8 --anchor end --format gif png

Each input writes, inside ``--out``, ``<name>.detection.mp4`` / ``.gif`` / ``<name>.detection/NNNNN.png``
(``--format``) and last ``<name>.detection.json``. Inputs are named as ``evaluate`` names them (a
file's stem, a frame folder's name, a folder of videos stands for its videos), numbered ``-2``,
``-3``, ... when two share a name. Existing outputs and missing weights (every model named at
once) are refused before the estimators load, existing outputs unless ``--overwrite``; a PNG folder
keeps no frame of an earlier, longer run. Progress goes to stderr: the models being loaded, then
each input and what its maps take.
"""

from __future__ import annotations

import argparse
import math
import re
import sys
from collections.abc import Callable
from dataclasses import asdict
from pathlib import Path

from ..io.files import write_json_atomic
from ..metric.video_inputs import check_scorable, expand_inputs
from .command_line import command_main
from .kit import (
    add_config_flags,
    check_choice,
    config_from_args,
    interruptible,
    output_folder,
    split_overrides,
)

__all__ = ["DESCRIPTION", "SUMMARY", "main", "register_subcommand", "remove_other_formats", "run", "work_line"]

SUMMARY = "per-frame detection maps: where a video breaks, frame by frame"
DESCRIPTION = "Per-frame GeCo detection maps (a window per frame)."

#: The names :func:`geco_guide.metric.detection.write_pngs` gives the frames of a PNG folder.
FRAME_PNG = re.compile(r"(\d{5})\.png")
#: Inputs longer than this are told how to bound the work (a 49-frame clip is one typical video).
LONG_INPUT_FRAMES = 200


def register_subcommand(p: argparse.ArgumentParser) -> argparse.ArgumentParser:
    """The options of ``geco detection`` on ``p``."""
    p.add_argument("inputs", nargs="+", metavar="VIDEO|FRAMES_DIR|key=value",
                   help="videos, frame folders or folders of videos, and config overrides (key=value)")
    p.add_argument("--out", type=output_folder, default="detection", help="output folder: every file goes inside it")
    p.add_argument("--window", type=int, default=20, help="frames per window (the demo's default: 20)")
    p.add_argument("--anchor", default="center", metavar="WHERE",
                   help="where the frame sits in its window: start, center (default) or end")
    p.add_argument("--one-way", action="store_true", help="structure occlusion test in one direction only")
    p.add_argument("--format", nargs="+", default=["mp4"], dest="formats", metavar="FORMAT",
                   help="what to write: an mp4, a gif and/or a folder of PNG frames (default: mp4)")
    p.add_argument("--fps", type=float, default=None, help="output frame rate (default: the input's)")
    p.add_argument("--overwrite", action="store_true", help="replace the outputs of an earlier run of the same names")
    p.add_argument("--max-frames", type=int, default=None, metavar="N",
                   help="only the first N frames of each input (every frame costs a window of --window frames)")
    add_config_flags(p)
    return p


def output_paths(stem: Path, formats: list[str]) -> list[Path]:
    """What one input writes for ``formats`` (``stem`` = ``<out>/<name>``), the JSON last."""
    paths = {"mp4": f"{stem.name}.detection.mp4", "gif": f"{stem.name}.detection.gif", "png": f"{stem.name}.detection"}
    return [stem.with_name(paths[f]) for f in formats] + [stem.with_name(f"{stem.name}.detection.json")]


def _has_output(path: Path) -> bool:
    """Whether ``path`` holds an output: a file, or a folder with frame PNGs."""
    if path.is_dir():
        return any(FRAME_PNG.fullmatch(p.name) for p in path.iterdir())
    return path.exists()


def check_outputs(out: Path, stems: list[Path], formats: list[str], overwrite: bool) -> None:
    """ValueError (one line) for ``--out`` that is a file, or, without ``overwrite``, an output
    of one of ``stems`` that is already there."""
    if out.exists() and not out.is_dir():
        raise ValueError(f"--out {str(out)!r} is a file, not a folder")
    if overwrite:
        return
    for stem in stems:
        existing = next((path for path in output_paths(stem, formats) if _has_output(path)), None)
        if existing is not None:
            raise ValueError(f"{str(existing)!r} already exists; pass --overwrite to replace it, or use another --out")


def remove_stale_frames(folder: Path, count: int) -> None:
    """Delete the frame PNGs ``NNNNN.png`` of index ``>= count`` that an earlier, longer run left
    in ``folder`` (only files of that name: nothing else in the folder is touched)."""
    for path in folder.iterdir():
        match = FRAME_PNG.fullmatch(path.name)
        if match and int(match.group(1)) >= count and path.is_file():
            path.unlink()


def remove_other_formats(stem: Path, formats: list[str]) -> None:
    """Delete what an earlier run of ``stem`` wrote in the formats this run does not (an
    ``--overwrite`` run's outputs are exactly the formats it was asked for): the files, and of a
    PNG folder its frame PNGs (the folder too, once empty)."""
    from ..metric.detection import FORMATS

    for path in output_paths(stem, [f for f in FORMATS if f not in formats])[:-1]:
        if path.is_dir():
            remove_stale_frames(path, 0)
            if not any(path.iterdir()):
                path.rmdir()
        elif path.is_file():
            path.unlink()


def first_frames(limit: int | None) -> Callable[[int, float], list[int]] | None:
    """The frame selector of ``--max-frames``: the first ``limit`` frames (``None``: all)."""
    if limit is None:
        return None
    return lambda num_frames, fps: list(range(min(num_frames, limit)))


def work_line(count: int, total: int, window: int) -> str:
    """What the maps of ``count`` frames (of ``total`` in the input) take, said before the work:
    a window of ``window`` frames per frame."""
    from ..types import plural

    of = f" (the first of {total}: --max-frames)" if count < total else ""
    hint = "" if count < total or count <= LONG_INPUT_FRAMES else "; --max-frames N bounds it"
    return (f"{plural(count, 'frame')}{of}: one window of {window} frames per frame, {count} geometry-estimator "
            f"calls and {count * (window - 1)} flow pairs{hint}")


def _resolved(video: str) -> str:
    """``.`` and ``..`` as the folder they name, so that the output is named after it (and stays inside ``--out``)."""
    return str(Path(video).resolve()) if Path(video).name in ("", "..") else video


@interruptible("the videos already done keep their outputs (each .detection.json is written last)")
def run(args: argparse.Namespace) -> int:
    """The detection maps of the inputs ``args`` name; 0, 1 (every input failed), or 2 after one
    line on stderr before any model loads."""
    from ..estimators import check_weights, load_estimators
    from ..io.devices import check_device
    from ..io.video import check_fps, read_frames
    from ..metric.detection import ANCHORS, FORMATS, detection_maps, frame_scores, render_detection, write_detection
    from ..types import plural

    overrides, videos = split_overrides(args.inputs)
    out = Path(args.out)
    try:
        if not videos:
            raise ValueError("no input video given")
        check_choice("--anchor", args.anchor, ANCHORS)
        check_choice("--format", args.formats, FORMATS)
        if args.window < 2:
            raise ValueError(f"--window must be >= 2, got {args.window}")
        if args.max_frames is not None and args.max_frames < 2:
            raise ValueError(f"--max-frames must be >= 2 (a window compares frames), got {args.max_frames}")
        if args.fps is not None and not (math.isfinite(args.fps) and args.fps > 0):
            raise ValueError(f"--fps must be a finite number > 0, got {args.fps}")
        if args.fps is not None:
            for video_format in set(args.formats) - {"png"}:  # the writers' bounds, before any map is computed
                check_fps(args.fps, f".{video_format}")
        cfg = config_from_args(args, overrides)
        items = expand_inputs([_resolved(v) for v in videos])
        check_scorable(items)
        check_outputs(out, [out / item.name for item in items if item.error is None], args.formats, args.overwrite)
        device = check_device(cfg.evaluation.device, "evaluation.device")  # "auto" resolved once
        check_weights(cfg.estimators)  # every missing model named at once, before anything loads
        print(f"loading models: {cfg.estimators.geometry} + {cfg.estimators.flow} on {device}", file=sys.stderr,
              flush=True)
        estimators = load_estimators(cfg.estimators, device)
    except (ValueError, FileNotFoundError) as err:
        print(f"error: {err}", file=sys.stderr)
        return 2
    failed = 0
    for index, item in enumerate(items, start=1):
        video = str(item.path)
        print(f"[{index}/{len(items)}] {video} ...", file=sys.stderr, flush=True)
        try:
            if item.error is not None:
                raise ValueError(item.error)
            clip = read_frames(item.path, min_frames=2, select=first_frames(args.max_frames))
            count = clip.frames.shape[0]
            if args.window > count:
                print(f"warning: {video}: --window {args.window} is longer than its {count} frames; "
                      f"each window holds all {count}", file=sys.stderr)
            print(f"  {work_line(count, clip.num_frames, min(args.window, count))}", file=sys.stderr, flush=True)
            maps = detection_maps(clip.frames, estimators, cfg.evaluation.loss, window=args.window,
                                  anchor=args.anchor, two_way=not args.one_way,
                                  flow_batch_size=cfg.evaluation.flow_batch_size)
            scores = frame_scores(maps)
            stem = out / item.name
            written = write_detection(render_detection(maps, scores), stem, args.formats, args.fps or clip.fps)
            if "png" in args.formats:
                remove_stale_frames(output_paths(stem, ["png"])[0], len(scores))
            remove_other_formats(stem, args.formats)
            write_json_atomic(output_paths(stem, [])[0], {
                "source": video, "window": min(args.window, count), "anchor": args.anchor,
                "two_way": not args.one_way, "frames": [{"index": k, **row} for k, row in enumerate(scores)],
                "estimators": estimators.ids(),
                "loss": asdict(cfg.evaluation.loss)})
        except (ValueError, OSError, RuntimeError) as err:  # one bad input must not stop the others
            failed += 1
            print(f"error: {video}: {str(err).splitlines()[0] if str(err) else type(err).__name__}", file=sys.stderr)
            continue
        worst = max(range(len(scores)), key=lambda k: -1.0 if scores[k]["fused"] is None else scores[k]["fused"])
        print(f"{video}: {plural(len(scores), 'frame')}, least consistent frame {worst} -> {', '.join(map(str, written))}")
    return 1 if failed == len(items) else 0


main = command_main("geco detection", DESCRIPTION, register_subcommand, run)
