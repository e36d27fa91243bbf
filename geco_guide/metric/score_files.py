"""What a scoring run (``geco evaluate``) writes: an input's scores, maps and detection maps (its
score JSON last), the line that says so, and the table and summary of several inputs."""

from __future__ import annotations

import csv
import io
import os
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from ..estimators import Estimators
from ..io.files import json_text, write_json_atomic, write_texts_atomic
from ..loss.cues import CUES
from ..types import plural
from .evaluate import PAPER_NAMES, evaluate_video, finite_or_none, mean_or_nan, write_maps_video
from .protocol import EvaluationConfig
from .video_inputs import VideoInput

__all__ = ["CSV_COLUMNS", "SUMMARY_KEYS", "ScoreOptions", "one_line", "score_line", "score_one",
           "write_detection_video", "write_table"]


@dataclass(frozen=True)
class ScoreOptions:
    """How each input is scored: its source rate (``fps``; ``model``: the model whose native rate
    replaces the file's) and the maps videos written beside its scores."""

    fps: float | None = None
    model: str | None = None
    maps: bool = False
    detection: bool = False


def write_detection_video(video: str | os.PathLike, stem: Path, estimators: Estimators, evaluation: EvaluationConfig,
                          masks: Any = None) -> Path:
    """``<stem>.detection.mp4``: the per-frame detection maps of every frame of ``video``
    (:mod:`geco_guide.metric.detection`, its defaults: a 20-frame window centred on the frame), the first
    ``evaluation.max_frames`` of them when it is set; ``masks``: the video's given masks
    (a :class:`~geco_guide.estimators.dynamic_masks.GivenMasks`), left out of the maps as the scores
    leave them out."""
    from ..io.video import read_frames
    from .detection import detection_maps, frame_scores, render_detection, write_detection

    limit = evaluation.max_frames
    first = None if limit is None else (lambda num_frames, fps: list(range(min(num_frames, limit))))
    clip = read_frames(video, default_fps=evaluation.default_fps, min_frames=2, select=first)
    if masks is not None:  # the masks of the frames read, as the scores cut them
        masks = masks.at(range(clip.frames.shape[0]), clip.num_frames).masks
    maps = detection_maps(clip.frames, estimators, evaluation.loss,
                          flow_batch_size=evaluation.flow_batch_size, dynamic_masks=masks)
    (path,) = write_detection(render_detection(maps, frame_scores(maps)), stem, ["mp4"], clip.fps)
    return path


def score_one(item: VideoInput, out: Path, estimators: Estimators, evaluation: EvaluationConfig, options: ScoreOptions,
              dynamic: Any, progress: Any) -> tuple[Any, Path, str]:
    """Score one input and write its outputs, the score JSON last: ``(result, json path, what
    else was written)``. When one output cannot be written (a full disk), the ones this input
    wrote before it are removed, so that a rerun needs no ``--overwrite``."""
    result = evaluate_video(item.path, estimators, evaluation, fps=options.fps, model=options.model,
                            maps=options.maps, dynamic_masks=dynamic, progress=progress)
    written: list[Path] = []
    try:
        notes = ""
        if options.maps:
            written.append(write_maps_video(result, out / f"{item.name}.maps.mp4"))
            notes += f", maps {written[-1]}"
        if options.detection:
            written.append(write_detection_video(item.path, out / item.name, estimators, evaluation, dynamic))
            notes += f", detection maps {written[-1]}"
        return result, write_json_atomic(out / f"{item.name}.geco.json", result.to_dict()), notes
    except BaseException:
        for path in written:
            path.unlink(missing_ok=True)
        raise


def score_line(name: str, result: Any, json_path: Path, notes: str) -> str:
    """The line of one scored input: its scores (a NaN one with its reason), windows, rate and files."""
    nan = f" (NaN: {result.nan_reason})" if result.nan_reason is not None else ""
    masks = result.dynamic_masks
    masked = ("" if masks is None else
              f", dynamic masks {masks['source']} masking {100 * masks['masked_fraction']:.1f}% of the pixels scored")
    scores = " ".join(f"{CUES[cue].symbol}={getattr(result, cue):.4f}" for cue in CUES)
    return (f"{name}: {scores}{nan} "
            f"TM={result.total_motion:.2f}% MM={result.mean_motion:.2f}%/s "
            f"({plural(len(result.windows), 'window')} at {result.sampled_fps:g} fps, source {result.fps:g} fps "
            f"from {result.fps_source}{masked}) -> {json_path}{notes}")


def one_line(err: BaseException) -> str:
    """The first line of ``err``, its type named unless it is a ValueError (a bad input's own words)."""
    text = str(err).strip().splitlines()
    message = text[0] if text else ""
    return message if isinstance(err, ValueError) else f"{type(err).__name__}: {message}"


CSV_COLUMNS = (
    "name", "path", *CUES, "total_motion", "mean_motion",
    "num_frames", "fps", "fps_source", "sampled_fps", "num_windows", "json", "error",
)
SUMMARY_KEYS = (*CUES, "total_motion", "mean_motion")


def write_table(out: Path, rows: list[dict[str, Any]], estimators: dict[str, str], config: dict[str, Any]) -> tuple[Path, Path]:
    """``geco_scores.csv`` and ``geco_summary.json``, both or neither (:class:`WriteError`)."""
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
