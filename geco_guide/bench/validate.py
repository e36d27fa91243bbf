"""Score built benchmarks on the GeCo paper's three detection tasks (the command is
:mod:`geco_guide.cli.validate`).

Each input is a folder made by :mod:`geco_guide.cli.benchmarks` (one clip, or a folder of clips).
GeCo runs on the whole clip (the config's ``evaluation.loss``: every ordered pair by default) and
each cue's frame maps (motion, structure, fused; invalid pixels score 0) are judged against the
ground truth:

* Task 1, anomalous-frame detection (warp clips built with ``--mode frame``): is
  ``argmax_t`` of the frame score the replaced frame? Accuracy over clips.
* Task 2, deformation localisation (warp clips, frames with a warp): ranking AP, IoU and F1 at
  the per-image best threshold, and Spearman's correlation with the displacement magnitude
  over the frame's valid pixels; macro-averaged over frames.
* Task 3, inconsistent-object localisation (occlusion clips, re-revealed frames with the object
  in view): AP, IoU, F1 as above, macro-averaged over frames.

Output (``--out``, default ``<first input>/validation``): ``validation.json`` (per clip, per
frame and the means), ``validation.md`` (the paper's table layout) and ``grids/<clip>.png``
(frame | ground truth | motion | structure | fused, a captioned row for each of up to
:data:`GRID_ROWS` judged frames and for the frame Task 1's fused score picks, the maps' colour scale
below). Written atomically.
"""

from __future__ import annotations

import io
import math
from pathlib import Path
from typing import Any

import numpy as np
import torch
from PIL import Image
from torch import Tensor

from ..io.files import write_bytes_atomic
from ..loss.cues import CUES, MAP_ORDER, PAPER_ORDER
from ..loss.geco import GeCoResult
from ..metric.render import colorbar, colorize, enlarge, side_by_side, text_scale, text_strip
from .datasets import Benchmark
from .ranking import average_precision, best_threshold_iou_f1, spearman

__all__ = ["GRID_ROWS", "cue_map", "grid_caption", "grid_frames", "grid_image", "localisation", "markdown_table",
           "summarise", "validate_clip", "write_png"]

GRID_ROWS = 4


def cue_map(result: GeCoResult, cue: str) -> tuple[Tensor, Tensor]:
    """``(map [S, H, W] with invalid pixels at 0, valid [S, H, W])`` of cue ``cue``, on the CPU."""
    values, valid = result.frame_maps.cue(cue)
    return torch.where(valid, values, torch.zeros_like(values))[0].cpu().double(), valid[0].cpu()


def detected_frame(scores: Tensor, has_valid: Tensor) -> int:
    """Task 1's prediction ``argmax_t`` of frame scores ``[S]`` over frames with valid pixels."""
    return int(torch.where(has_valid, scores.double(), torch.full_like(scores.double(), -math.inf)).argmax())


def localisation(score_map: Tensor, valid: Tensor, truth: Tensor, magnitude: Tensor | None = None) -> dict[str, float]:
    """Tasks 2/3 on one frame: ``ap``, ``iou``, ``f1`` of ``score_map [H, W]`` against ``truth
    [H, W]`` and, given ``magnitude [H, W]``, ``srcc`` over the ``valid [H, W]`` pixels."""
    iou, f1 = best_threshold_iou_f1(score_map, truth)
    row = {"ap": average_precision(score_map, truth), "iou": iou, "f1": f1}
    if magnitude is not None:
        row["srcc"] = spearman(score_map[valid], magnitude[valid])
    return row


def judged_frames(bench: Benchmark) -> list[int]:
    """Frames of Tasks 2/3: those with ground-truth artifact pixels (for an occlusion clip, the
    re-revealed frames with the object in view)."""
    return [t for t in range(bench.truth["mask"].shape[0]) if bool(bench.truth["mask"][t].any())]


def clip_name(folder: Path) -> str:
    """``<benchmark>-<clip>``: unique across benchmark folders that reuse clip names."""
    return f"{folder.parent.name}-{folder.name}"


def validate_clip(bench: Benchmark, result: GeCoResult) -> dict[str, Any]:
    """The task records of one scored clip (JSON-ready)."""
    record: dict[str, Any] = {"clip": clip_name(bench.path), "path": str(bench.path), "kind": bench.kind,
                              "mode": bench.meta.get("mode")}
    maps = {cue: cue_map(result, cue) for cue in PAPER_ORDER}
    if bench.kind == "warp" and bench.meta.get("anomalous_frame") is not None:
        truth = int(bench.meta["anomalous_frame"])
        predicted = {cue: detected_frame(result.frame_scores[cue][0].cpu(), result.frame_has_valid[cue][0].cpu()) for cue in PAPER_ORDER}
        record["task1"] = {"anomalous_frame": truth, "predicted": predicted,
                           "correct": {cue: predicted[cue] == truth for cue in PAPER_ORDER}}
    task = "task2" if bench.kind == "warp" else "task3"
    magnitude = bench.truth.get("magnitude")
    record[task] = [
        {"frame": t, **{cue: localisation(maps[cue][0][t], maps[cue][1][t], bench.truth["mask"][t],
                                          None if magnitude is None else magnitude[t].double()) for cue in PAPER_ORDER}}
        for t in judged_frames(bench)
    ]
    return record


def _mean(values: list[float]) -> float | None:
    finite = [v for v in values if v is not None and math.isfinite(v)]
    return sum(finite) / len(finite) if finite else None


def summarise(records: list[dict[str, Any]]) -> dict[str, Any]:
    """Means over clips (Task 1) and over judged frames of all clips (Tasks 2/3), per cue."""
    summary: dict[str, Any] = {}
    task1 = [r["task1"] for r in records if "task1" in r]
    if task1:
        summary["task1"] = {"clips": len(task1), **{cue: {"accuracy": _mean([float(t["correct"][cue]) for t in task1])} for cue in PAPER_ORDER}}
    for task in ("task2", "task3"):
        rows = [row for r in records for row in r.get(task, [])]
        if rows:
            keys = list(dict.fromkeys(k for row in rows for k in row[PAPER_ORDER[0]]))  # srcc needs a magnitude
            summary[task] = {"frames": len(rows), **{cue: {k: _mean([row[cue].get(k) for row in rows]) for k in keys} for cue in PAPER_ORDER}}
    return summary


def _cell(value: float | None, percent: bool = True) -> str:
    if value is None:
        return "-"
    return f"{100 * value:.2f}" if percent else f"{value:.3f}"


def markdown_table(summary: dict[str, Any]) -> str:
    """The paper's layout: one row per cue, Task 1 accuracy, Task 2 AP/IoU/F1/SRCC, Task 3 AP/IoU/F1."""
    head = ["Cue"]
    columns: list[tuple[str, str, bool]] = []
    if "task1" in summary:
        head.append(f"Task 1 Acc (%) [{summary['task1']['clips']} clips]")
        columns.append(("task1", "accuracy", True))
    if "task2" in summary:
        n = summary["task2"]["frames"]
        head += [f"Task 2 AP (%) [{n} frames]", "Task 2 IoU (%)", "Task 2 F1 (%)", "Task 2 SRCC"]
        columns += [("task2", "ap", True), ("task2", "iou", True), ("task2", "f1", True), ("task2", "srcc", False)]
    if "task3" in summary:
        n = summary["task3"]["frames"]
        head += [f"Task 3 AP (%) [{n} frames]", "Task 3 IoU (%)", "Task 3 F1 (%)"]
        columns += [("task3", "ap", True), ("task3", "iou", True), ("task3", "f1", True)]
    lines = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    for cue in PAPER_ORDER:
        cells = [_cell(summary[task][cue][key], percent) for task, key, percent in columns]
        lines.append("| " + " | ".join([f"{CUES[cue].title} {CUES[cue].symbol}", *cells]) + " |")
    return "\n".join(lines) + "\n"


def grid_caption(bench: Benchmark, frame: int, task1: dict[str, Any] | None = None) -> str:
    """The caption over a grid row: the frame, whether it holds ground-truth artifact pixels and,
    for a Task 1 clip (``task1``: its record in :func:`validate_clip`), whether the fused score
    picks it as the replaced frame."""
    note = "ground-truth artifact" if bool(bench.truth["mask"][frame].any()) else "no artifact"
    if task1 is not None and frame == task1["predicted"]["fused"]:
        right = frame == task1["anomalous_frame"]
        note += ("; Task 1: the fused score picks it as the replaced frame, "
                 + ("rightly" if right else f"wrongly: frame {task1['anomalous_frame']} was"))
    return f"frame {frame} ({note}); maps: residual, 0 = consistent"


def grid_image(bench: Benchmark, result: GeCoResult, frames: list[int], task1: dict[str, Any] | None = None) -> Tensor:
    """``[3, H', W']`` rows of frame | ground truth | motion | structure | fused (viridis on the
    fixed map range, grey: no valid pixel) for ``frames``, each row under a caption naming its
    frame (:func:`grid_caption`; ``task1``: the clip's Task 1 record, whose pick the caption
    names), and the colour scale of the maps (with the grey of "no valid pixel") at the bottom."""
    truth = bench.truth["mask"][frames].float()[:, None].expand(-1, 3, -1, -1)
    panels = [bench.frames[frames], truth]
    for cue in MAP_ORDER:
        values, valid = result.frame_maps.cue(cue)
        panels.append(colorize(values[0, frames].cpu(), valid[0, frames].cpu()))
    panels = [enlarge(panel.float()) for panel in panels]  # legible labels at the PNG's native size
    rows = side_by_side(panels, ["FRAME", "TRUTH (ARTIFACT)", *(cue.upper() for cue in MAP_ORDER)])
    width, scale = rows.shape[-1], text_scale(panels[0].shape[-2])
    body = []
    for t, row in zip(frames, rows):
        body += [text_strip(grid_caption(bench, t, task1), width, scale), row]
    return torch.cat([*body, colorbar(width, scale)], dim=-2)


def write_png(path: Path, image: Tensor) -> Path:
    """``image [3, H, W]`` in ``[0, 1]`` as a PNG, atomically."""
    array = (image.clamp(0, 1).permute(1, 2, 0).numpy() * 255.0 + 0.5).astype(np.uint8)
    buffer = io.BytesIO()
    Image.fromarray(array).save(buffer, format="PNG")
    return write_bytes_atomic(path, buffer.getvalue())


def grid_frames(bench: Benchmark, record: dict[str, Any]) -> list[int]:
    """Up to :data:`GRID_ROWS` judged frames (evenly spaced: a clip warped throughout would
    otherwise make a picture thousands of pixels high), plus the frame Task 1's fused score picks."""
    judged = judged_frames(bench)
    picked = [judged[round(k * (len(judged) - 1) / max(GRID_ROWS - 1, 1))] for k in range(min(GRID_ROWS, len(judged)))]
    if "task1" in record:
        picked.append(record["task1"]["predicted"]["fused"])
    return sorted(set(picked))
