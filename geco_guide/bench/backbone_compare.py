"""What the choice of estimators changes: two GeCo-Eval runs over the same videos, scored with
different estimators (a geometry backbone such as ``da3-base`` instead of ``vggt-1b``, or another
flow estimator), compared by the rankings they give (the command is
:mod:`geco_guide.cli.compare`).

Each run is a GeCo-Eval output folder (:mod:`geco_guide.bench.geco_eval`): its ``results.csv``
gives one row per video, its ``summary.json`` the estimators that scored it, its ``run.json`` the
config. Videos are paired by (arm, prompt id, seed); for each score (fused, motion, structure) the
comparison gives Spearman's rank correlation between the two runs over the paired videos and
over the models (their mean scores over the paired videos), and the per-model means. Whether a
pair's two files hold the same bytes is checked, since a guided arm is guided by each run's own
estimators and a regenerated video may differ.
"""

from __future__ import annotations

import csv
import filecmp
import json
import math
from dataclasses import dataclass
from datetime import datetime, timezone
from pathlib import Path
from typing import Any

import torch

from ..loss.geco import CUES
from . import report
from .ranking import spearman
from .report import fmt
from .runs import RUN_FILE, config_differences

__all__ = ["COMPARISON_FILES", "LABELS", "ScoredRun", "compare_runs", "comparison_markdown", "read_run"]

#: The files a comparison writes: the numbers, and the tables for a reader.
COMPARISON_FILES = ("comparison.json", "comparison.md")
#: The two runs, in the order given.
LABELS = ("A", "B")

#: A video of a run: (arm, prompt id, seed), the arm being ``<model>`` or ``<model>-guided``.
VideoKey = tuple[str, str, int]


@dataclass(frozen=True)
class ScoredRun:
    """A GeCo-Eval run folder as the comparison reads it: the estimators that scored it (their
    ids, as ``summary.json`` records them), its config (``run.json``; None where absent), whether
    it ran tiny random models, and per video its scores and video file."""

    folder: Path
    estimators: dict[str, str]
    config: dict[str, Any] | None
    tiny_models: bool
    videos: dict[VideoKey, dict[str, Any]]


def _read_json(path: Path) -> dict[str, Any]:
    try:
        data = json.loads(path.read_text(encoding="utf-8"))
    except ValueError:  # UnicodeDecodeError is a ValueError
        raise ValueError(f"{path} is damaged (not JSON)") from None
    if not isinstance(data, dict):
        raise ValueError(f"{path} is damaged (not a JSON object)")
    return data


def _number(text: str) -> float | None:
    """A score cell of ``results.csv``: empty (no score) is None, as a non-finite value."""
    value = float(text) if text else math.nan
    return value if math.isfinite(value) else None


def _video_rows(path: Path) -> dict[VideoKey, dict[str, Any]]:
    """The scored videos of ``results.csv`` (failed rows, which carry an ``error``, left out)."""
    try:
        rows = list(csv.DictReader(path.read_text(encoding="utf-8").splitlines()))
        videos = {}
        for row in rows:
            if row.get("error"):
                continue
            arm = f"{row['model']}-guided" if row["guided"] == "True" else row["model"]
            videos[(arm, row["prompt_id"], int(row["seed"]))] = {
                "video": row["video"], **{score: _number(row[score]) for score in CUES}}
    except (KeyError, ValueError, TypeError):
        raise ValueError(f"{path} is damaged (a row lacks a field or holds a value that is not a number)") from None
    return videos


def read_run(folder: Path) -> ScoredRun:
    """The GeCo-Eval run in ``folder``.

    Raises:
        ValueError: one line: not a finished GeCo-Eval folder, a damaged file, or a report that
            does not record its estimators.
    """
    summary_path, results_path = folder / "summary.json", folder / "results.csv"
    if not folder.is_dir():
        raise ValueError(f"{folder}: no such folder")
    if not (summary_path.is_file() and results_path.is_file()):
        raise ValueError(f"{folder} holds no GeCo-Eval report (summary.json and results.csv): score its videos with "
                         f"geco geco-eval --out {folder} first")
    summary = _read_json(summary_path)
    estimators = summary.get("estimators")
    if not isinstance(estimators, dict) or "geometry" not in estimators:
        raise ValueError(f"{summary_path} does not record the estimators that scored the videos; score them again "
                         "with this version of geco geco-eval")
    run_file = folder / RUN_FILE
    config = _read_json(run_file).get("config") if run_file.is_file() else None
    return ScoredRun(folder, dict(estimators), config if isinstance(config, dict) else None,
                     bool(summary.get("tiny_models")), _video_rows(results_path))


def _video_file(run: ScoredRun, key: VideoKey) -> Path:
    """The file a video's row points at: as given, or relative to the run folder (a generated one)."""
    path = Path(run.videos[key]["video"])
    return path if path.is_absolute() else run.folder / path


def _file_agreement(a: ScoredRun, b: ScoredRun, keys: list[VideoKey]) -> dict[str, int]:
    """How many pairs' two files hold the same bytes, differ, or are not found (moved, deleted)."""
    counts = {"same_bytes": 0, "different_bytes": 0, "not_found": 0}
    for key in keys:
        first, second = _video_file(a, key), _video_file(b, key)
        if not (first.is_file() and second.is_file()):
            counts["not_found"] += 1
        else:
            counts["same_bytes" if filecmp.cmp(first, second, shallow=False) else "different_bytes"] += 1
    return counts


def _pairs(a: ScoredRun, b: ScoredRun, keys: list[VideoKey], score: str) -> tuple[list[float], list[float]]:
    """The ``score`` of the videos ``keys`` that both runs scored with a finite value."""
    kept = [k for k in keys if a.videos[k][score] is not None and b.videos[k][score] is not None]
    return [a.videos[k][score] for k in kept], [b.videos[k][score] for k in kept]


def _correlation(first: list[float], second: list[float]) -> float:
    return spearman(torch.tensor(first, dtype=torch.float64), torch.tensor(second, dtype=torch.float64))


def _model_means(a: ScoredRun, b: ScoredRun, keys: list[VideoKey]) -> dict[str, dict[str, Any]]:
    """Per arm and score: each run's mean over the arm's paired videos scored finite by both, and their count."""
    means: dict[str, dict[str, Any]] = {}
    for arm in dict.fromkeys(key[0] for key in keys):
        first_second = {score: _pairs(a, b, [k for k in keys if k[0] == arm], score) for score in CUES}
        means[arm] = {score: {"A": sum(x) / len(x) if x else None, "B": sum(y) / len(y) if y else None, "n": len(x)}
                      for score, (x, y) in first_second.items()}
    return means


def compare_runs(a: ScoredRun, b: ScoredRun) -> dict[str, Any]:
    """The comparison of run ``a`` with run ``b`` over the videos both scored (``comparison.json``).

    Raises:
        ValueError: one line when the runs share no video.
    """
    keys = sorted(set(a.videos) & set(b.videos))
    if not keys:
        raise ValueError(f"{a.folder} and {b.folder} share no scored video (model, prompt, seed): score the same "
                         "videos in both, e.g. the second with geco geco-eval --videos NAME=<first>/videos/NAME")
    models = _model_means(a, b, keys)
    correlations = {}
    for score in CUES:
        over_videos = _pairs(a, b, keys, score)
        over_models = [(m[score]["A"], m[score]["B"]) for m in models.values() if m[score]["n"]]
        correlations[score] = {"videos": _correlation(*over_videos), "n_videos": len(over_videos[0]),
                               "models": _correlation([x for x, _ in over_models], [y for _, y in over_models]),
                               "n_models": len(over_models)}
    differences = (config_differences(a.config, b.config) if a.config is not None and b.config is not None else None)
    return {
        "runs": {label: {"folder": str(run.folder), "estimators": run.estimators}
                 for label, run in zip(LABELS, (a, b))},
        "config_differences": differences,
        "tiny_models": a.tiny_models or b.tiny_models,
        "videos": {"paired": len(keys), "only_in_A": [_name(k) for k in sorted(set(a.videos) - set(b.videos))],
                   "only_in_B": [_name(k) for k in sorted(set(b.videos) - set(a.videos))],
                   **_file_agreement(a, b, keys)},
        "spearman": correlations,
        "models": models,
        "created": datetime.now(timezone.utc).isoformat(timespec="seconds"),
    }


def _name(key: VideoKey) -> str:
    return f"{key[0]}/{key[1]}-s{key[2]}"


def _estimators_text(estimators: dict[str, str]) -> str:
    return ", ".join(f"{role} `{name}`" for role, name in estimators.items())


def comparison_markdown(comparison: dict[str, Any]) -> str:
    """``comparison.md``: the runs and their estimators, the Spearman table, the per-model means."""
    runs, videos = comparison["runs"], comparison["videos"]
    lines = ["# Estimators compared over the same GeCo-Eval videos", ""]
    if comparison["tiny_models"]:
        lines += [f"**{report.TINY_NOTE}.**", ""]
    lines += [f"- {label}: `{run['folder']}`: {_estimators_text(run['estimators'])}" for label, run in runs.items()]
    differences = comparison["config_differences"]
    if differences is not None:
        lines.append("- config, A -> B: " + ("; ".join(f"`{d}`" for d in differences) or "the same"))
    lines += [f"- {videos['paired']} videos paired by model, prompt and seed ({len(videos['only_in_A'])} only in A, "
              f"{len(videos['only_in_B'])} only in B); their files: {videos['same_bytes']} the same bytes, "
              f"{videos['different_bytes']} different, {videos['not_found']} not found", ""]
    if videos["different_bytes"]:
        lines += [f"**{videos['different_bytes']} paired videos differ between the runs** (a guided arm is guided by "
                  "each run's own estimators; a video generated again may differ): there the scores compare "
                  "different videos.", ""]
    lines += ["## Spearman between A and B", "",
              "1: the same ranking; lower scores are more consistent in both.", ""]
    lines += report.markdown_table(
        ["score", "over videos", "videos", "over models", "models"],
        [[score, fmt(c["videos"]), str(c["n_videos"]), fmt(c["models"]), str(c["n_models"])]
         for score, c in comparison["spearman"].items()])
    lines += ["", "## Mean score per model (over the videos both runs scored)", ""]
    lines += report.markdown_table(
        ["model", "videos", *(f"{score} {label}" for score in CUES for label in LABELS)],
        [[arm, str(m["fused"]["n"]), *(fmt(m[score][label]) for score in CUES for label in LABELS)]
         for arm, m in comparison["models"].items()])
    return "\n".join(lines) + "\n"
