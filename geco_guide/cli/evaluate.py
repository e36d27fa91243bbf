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
import csv
import io
import math
import os
import sys
from dataclasses import asdict, dataclass, replace
from pathlib import Path
from typing import TYPE_CHECKING, Any

from .. import __version__
from ..io.files import (
    WriteError,
    check_output_dir,
    json_text,
    output_lock,
    unique_names,
    write_json_atomic,
    write_texts_atomic,
)
from .kit import (
    add_config_flags,
    command_main,
    config_from_args,
    interruptible,
    is_config_key,
    output_folder,
    split_overrides,
)

if TYPE_CHECKING:
    from ..config import GeCoConfig
    from ..estimators import Estimators

__all__ = ["DESCRIPTION", "SUMMARY", "check_masks_fit", "check_scorable", "expand_inputs", "main", "register_subcommand",
           "run", "score_line"]

SUMMARY = "score videos with the GeCo protocol"
DESCRIPTION = "Score videos with GeCo (M_motion, M_struct, M_geo, Total/Mean Motion)."


def write_detection_video(video: str | os.PathLike, stem: Path, estimators: Estimators, cfg: GeCoConfig,
                          masks: Any = None) -> Path:
    """``<stem>.detection.mp4``: the per-frame detection maps of every frame of ``video``
    (:mod:`geco_guide.metric.detection`, its defaults: a 20-frame window centred on the frame), the first
    ``evaluation.max_frames`` of them when it is set; ``masks``: the video's given masks
    (a :class:`~geco_guide.estimators.dynamic_masks.GivenMasks`), left out of the maps as the scores
    leave them out."""
    from ..io.video import read_frames
    from ..metric.detection import detection_maps, frame_scores, render_detection, write_detection

    limit = cfg.evaluation.max_frames
    first = None if limit is None else (lambda num_frames, fps: list(range(min(num_frames, limit))))
    clip = read_frames(video, default_fps=cfg.evaluation.default_fps, min_frames=2, select=first)
    if masks is not None:  # the masks of the frames read, as the scores cut them
        masks = masks.at(range(clip.frames.shape[0]), clip.num_frames).masks
    maps = detection_maps(clip.frames, estimators, cfg.evaluation.loss,
                          flow_batch_size=cfg.evaluation.flow_batch_size, dynamic_masks=masks)
    (path,) = write_detection(render_detection(maps, frame_scores(maps)), stem, ["mp4"], clip.fps)
    return path


def check_detection_masks(detection: bool, masks: Any) -> None:
    """ValueError (one line) for ``--detection`` with automatic or text ``--dynamic-masks``: the
    detection maps judge each frame against a window of its own, which those masks are not made
    for (given masks of the video are applied to them)."""
    from ..estimators.dynamic_masks import GivenMasks

    if detection and masks is not None and not isinstance(masks, GivenMasks):
        raise ValueError("--detection draws its maps with given masks only (a mask file of the video); with "
                         "--dynamic-masks auto or subject text, score without --detection or write the masks to a "
                         "file first")


@dataclass
class _Input:
    """One video to score (a file or a frame folder), or an input that already failed."""

    path: Path
    name: str
    error: str | None = None


def _holds_frames(folder: Path) -> bool:
    from ..io.video import frame_files

    return bool(frame_files(folder))


def expand_inputs(paths: list[str]) -> list[_Input]:
    """Command-line inputs -> videos. A folder with png/jpg frames is one video; any other
    folder stands for its video files and frame sub-folders (one level), and is an error when it
    holds none. Names (output stems) are made unique with ``-2``, ``-3``, ..."""
    from ..io.video import IMAGE_SUFFIXES, VIDEO_SUFFIXES, input_stem

    items: list[_Input] = []
    for arg in paths:
        path = Path(arg)
        if path.is_dir() and not _holds_frames(path):
            entries = sorted(p for p in path.iterdir() if not p.name.startswith("."))
            videos = [p for p in entries if (p.is_file() and p.suffix.lower() in VIDEO_SUFFIXES) or (p.is_dir() and _holds_frames(p))]
            if not videos:
                kinds = "/".join(s.lstrip(".") for s in VIDEO_SUFFIXES + IMAGE_SUFFIXES)
                items.append(_Input(path, input_stem(path), f"folder {str(path)!r} holds no video ({kinds})"))
            items.extend(_Input(p, input_stem(p)) for p in videos)
        elif not path.exists():
            items.append(_Input(path, input_stem(path), "no such file or folder"))
        else:
            items.append(_Input(path, input_stem(path)))
    for item, name in zip(items, unique_names(item.name for item in items)):
        item.name = name
    return items


def output_files(out: Path, name: str, maps: bool, detection: bool) -> list[Path]:
    """What scoring the input ``name`` writes into ``out``."""
    return [out / f"{name}.geco.json", *([out / f"{name}.maps.mp4"] if maps else []),
            *([out / f"{name}.detection.mp4"] if detection else [])]


def check_scorable(items: list[_Input]) -> None:
    """ValueError (one line naming each input and why), before any model loads, when no input
    can be scored (all missing, or folders without a video)."""
    if all(item.error is not None for item in items):
        raise ValueError("; ".join(f"{item.path}: {item.error}" for item in items))


def check_inputs_and_outputs(items: list[_Input], out: Path, args: argparse.Namespace) -> None:
    """ValueError (one line), before any model loads, when no input can be scored
    (:func:`check_scorable`), or when an output is already there without ``--overwrite``
    (another input's score of the same name, perhaps: ``b/g17.gif`` would replace the score of
    ``a/g17.gif``)."""
    check_scorable(items)
    if args.overwrite:
        return
    for item in items:
        taken = [p for p in output_files(out, item.name, args.maps, args.detection) if p.exists()]
        if item.error is None and taken:
            raise ValueError(f"{str(taken[0])!r} already exists (the score of an earlier run); pass --overwrite to "
                             "replace it, or choose another --out folder")



def _one_line(err: BaseException) -> str:
    text = str(err).strip().splitlines()
    message = text[0] if text else ""
    return message if isinstance(err, ValueError) else f"{type(err).__name__}: {message}"


CSV_COLUMNS = (
    "name", "path", "fused", "motion", "structure", "total_motion", "mean_motion",
    "num_frames", "fps", "fps_source", "sampled_fps", "num_windows", "json", "error",
)
SUMMARY_KEYS = ("fused", "motion", "structure", "total_motion", "mean_motion")


def _write_table(out: Path, rows: list[dict[str, Any]], estimators: dict[str, str], config: dict[str, Any]) -> tuple[Path, Path]:
    """``geco_scores.csv`` and ``geco_summary.json``, both or neither (:class:`WriteError`)."""
    from ..metric.evaluate import PAPER_NAMES, finite_or_none, mean_or_nan

    buffer = io.StringIO()
    writer = csv.DictWriter(buffer, fieldnames=CSV_COLUMNS, lineterminator="\n")
    writer.writeheader()
    for row in rows:
        writer.writerow({key: "" if row.get(key) is None else row[key] for key in CSV_COLUMNS})
    ok = [row for row in rows if row.get("error") is None]
    summary = {
        "num_videos": len(rows),
        "num_ok": len(ok),
        "num_failed": len(rows) - len(ok),
        "mean": {key: finite_or_none(mean_or_nan([row[key] for row in ok if row[key] is not None])) for key in SUMMARY_KEYS},
        "paper_names": PAPER_NAMES,
        "videos": [{key: row.get(key) for key in ("name", "path", "json", "error")} for row in rows],
        "estimators": estimators,
        "config": config,
    }
    csv_path, summary_path = out / "geco_scores.csv", out / "geco_summary.json"
    write_texts_atomic({csv_path: buffer.getvalue(), summary_path: json_text(summary)})
    return csv_path, summary_path


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


def dynamic_mask_option(spec: str | None, device: Any) -> Any:
    """``--dynamic-masks``: a mask path is read and checked now, once, before any model loads (a
    :class:`~geco_guide.estimators.dynamic_masks.GivenMasks` of the whole file, which each video
    cuts to the frames its protocol picks); ``auto`` becomes one mask source for every input; text
    stays text, after checking that it names subjects: the segmenter of ``estimators.segmenter``,
    loaded once with the estimators (:func:`wants_segmenter`), masks them.

    Raises:
        MaskReadError: one sentence about the mask file (unreadable, not binary, wrong shape ...).
    """
    from ..estimators.dynamic_masks import AUTO, GivenMasks, looks_like_path, mask_source

    if spec is None:
        return None
    if looks_like_path(spec):
        return GivenMasks.from_path(spec)
    if spec.strip() == AUTO:
        return mask_source(AUTO, device=device)
    from ..estimators.segmenters import subjects_of

    subjects_of(spec)
    return spec


def wants_segmenter(dynamic: Any) -> bool:
    """Whether the ``--dynamic-masks`` of :func:`dynamic_mask_option` is text for the segmenter."""
    return isinstance(dynamic, str)


def check_masks_fit(items: list[_Input], masks: Any, cfg: GeCoConfig) -> None:
    """Given masks against each input, before any model loads: an input whose frame count or
    aspect ratio the masks do not fit (:func:`~geco_guide.metric.evaluate.clip_mask_source`, with
    ``evaluation.max_frames``) gets that one line as its error, as does one that cannot be read."""
    from ..estimators.dynamic_masks import GivenMasks
    from ..io.video import read_frames
    from ..metric.evaluate import clip_mask_source

    if not isinstance(masks, GivenMasks):
        return
    limit = cfg.evaluation.max_frames
    for item in items:
        if item.error is not None:
            continue
        try:  # the first frame only is kept: its size, and the count
            probe = read_frames(item.path, default_fps=cfg.evaluation.default_fps, select=lambda count, fps: [0])
            clip = replace(probe, num_frames=min(probe.num_frames, limit or probe.num_frames))
            clip_mask_source(masks, clip, probe.num_frames)
        except ValueError as err:  # MaskReadError and VideoReadError are ValueErrors
            item.error = str(err)


def _progress(message: str) -> None:
    print(message, file=sys.stderr, flush=True)


def _outputs_of_run(items: list[_Input], out: Path, args: argparse.Namespace, table: bool) -> list[Path]:
    """Every file this run may write into ``out``: what it holds the output locks of."""
    paths = [p for item in items if item.error is None for p in output_files(out, item.name, args.maps, args.detection)]
    return paths + ([out / "geco_scores.csv", out / "geco_summary.json"] if table else [])


def _score_one(item: _Input, out: Path, estimators: Estimators, cfg: GeCoConfig, args: argparse.Namespace,
               dynamic: Any, progress: Any) -> tuple[Any, Path, str]:
    """Score one input and write its outputs, the score JSON last: ``(result, json path, what
    else was written)``. When one output cannot be written (a full disk), the ones this input
    wrote before it are removed, so that a rerun needs no ``--overwrite``."""
    from ..metric.evaluate import evaluate_video, write_maps_video

    result = evaluate_video(item.path, estimators, cfg.evaluation, fps=args.fps, model=args.source_model,
                            maps=args.maps, dynamic_masks=dynamic, progress=progress)
    written: list[Path] = []
    try:
        notes = ""
        if args.maps:
            written.append(write_maps_video(result, out / f"{item.name}.maps.mp4"))
            notes += f", maps {written[-1]}"
        if args.detection:
            written.append(write_detection_video(item.path, out / item.name, estimators, cfg, dynamic))
            notes += f", detection maps {written[-1]}"
        return result, write_json_atomic(out / f"{item.name}.geco.json", result.to_dict()), notes
    except BaseException:
        for path in written:
            path.unlink(missing_ok=True)
        raise


def score_line(name: str, result: Any, json_path: Path, notes: str) -> str:
    """The line of one scored input: its scores (a NaN one with its reason), windows, rate and files."""
    from ..types import plural

    nan = f" (NaN: {result.nan_reason})" if result.nan_reason is not None else ""
    masks = result.dynamic_masks
    masked = ("" if masks is None else
              f", dynamic masks {masks['source']} masking {100 * masks['masked_fraction']:.1f}% of the pixels scored")
    return (f"{name}: M_geo={result.fused:.4f} M_motion={result.motion:.4f} M_struct={result.structure:.4f}{nan} "
            f"TM={result.total_motion:.2f}% MM={result.mean_motion:.2f}%/s "
            f"({plural(len(result.windows), 'window')} at {result.sampled_fps:g} fps, source {result.fps:g} fps "
            f"from {result.fps_source}{masked}) -> {json_path}{notes}")


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
        check_masks_fit(items, dynamic, cfg)
        table = len(items) > 1 or any(Path(v).is_dir() and not _holds_frames(Path(v)) for v in videos)
        if not all(item.error is not None for item in items):  # else check_inputs_and_outputs says why
            for path in _outputs_of_run(items, out, args, table):
                locks.enter_context(output_lock(path, "choose another --out"))
        check_inputs_and_outputs(items, out, args)  # under the locks: an output of a run that ended meanwhile counts
        segmenter = wants_segmenter(dynamic)
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

    rows: list[dict[str, Any]] = []
    for k, item in enumerate(items, 1):
        row: dict[str, Any] = {"name": item.name, "path": str(item.path), "error": item.error}
        if item.error is None:
            _progress(f"[{k}/{len(items)}] scoring {item.path}")
            try:
                result, json_path, notes = _score_one(item, out, estimators, cfg, args, dynamic,
                                                      lambda line, k=k: _progress(f"[{k}/{len(items)}]   {line}"))
            except Exception as err:  # one bad input must not stop the others
                row["error"] = _one_line(err)
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
            csv_path, summary_path = _write_table(out, rows, estimators.ids(), asdict(cfg.evaluation))
        except WriteError as err:
            print(f"error: {err}", file=sys.stderr)
            return 1
        print(f"wrote {csv_path} and {summary_path}")
    return 1 if all(row["error"] is not None for row in rows) else 0


main = command_main("geco evaluate", DESCRIPTION, register_subcommand, run)
