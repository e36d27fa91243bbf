"""The report files of a benchmark run (GeCo-Eval, the A/B script): CSV, Markdown tables, the
PNG plot, what the run ran with, each written atomically (a killed run never leaves half a file)."""

from __future__ import annotations

import csv
import io
import math
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

from ..estimators import TINY_RANDOM
from ..io.files import write_bytes_atomic, write_json_atomic, write_text_atomic
from ..types import plural

__all__ = ["MIN_INTERVAL_N", "TINY_NOTE", "csv_text", "fmt", "interval_text", "markdown_table",
           "models_section", "png_bytes", "uses_tiny_models", "write_report_files"]

TINY_NOTE = "tiny random models: the numbers show the mechanics, not quality"


def fmt(value: float | None, digits: int = 4) -> str:
    """A number for a table: ``-`` for missing or non-finite values."""
    return "-" if value is None or not math.isfinite(value) else f"{value:.{digits}g}"


def csv_text(rows: Sequence[Mapping[str, Any]], columns: Sequence[str]) -> str:
    """CSV of ``rows`` restricted to ``columns``; ``None`` becomes an empty cell."""
    buffer = io.StringIO()
    writer = csv.DictWriter(buffer, fieldnames=list(columns), extrasaction="ignore", lineterminator="\n")
    writer.writeheader()
    for row in rows:
        writer.writerow({k: "" if row.get(k) is None else row[k] for k in columns})
    return buffer.getvalue()


#: Fewer values than this get no confidence interval: a bootstrap of a handful of values has few
#: distinct resamples and covers the true mean far less often than its stated level.
MIN_INTERVAL_N = 10


def interval_text(ci: Sequence[float] | None, n: int, noun: str = "value") -> str:
    """A confidence interval ``[low, high]`` for a table or a line, or, where ``ci`` is ``None``,
    that ``n`` of ``noun`` (singular) are too few for one (:data:`MIN_INTERVAL_N`)."""
    if ci is not None:
        return f"[{fmt(ci[0])}, {fmt(ci[1])}]"
    return f"none from {plural(n, noun)} (an interval needs {MIN_INTERVAL_N})"


def markdown_table(header: Sequence[str], rows: Sequence[Sequence[str]]) -> list[str]:
    """The lines of a Markdown table."""
    lines = ["| " + " | ".join(header) + " |", "|" + "---|" * len(header)]
    return lines + ["| " + " | ".join(row) + " |" for row in rows]


def uses_tiny_models(cfg: Any) -> bool:
    """Whether the run's video model or an estimator is a tiny random one."""
    return TINY_RANDOM in (cfg.model.id, cfg.estimators.geometry, cfg.estimators.flow)


def models_section(cfg: Any, models: Mapping[str, str] | None = None) -> list[str]:
    """Markdown lines naming the video model(s) and weights and the estimators the run used (a
    report says :data:`TINY_NOTE` once, at its top, when they were the tiny random ones)."""
    lines = ["## Models and weights", ""]
    video = models or {"video model": cfg.model.id}
    rows = [[name, weights] for name, weights in video.items()]
    rows += [["geometry estimator", cfg.estimators.geometry], ["flow estimator", cfg.estimators.flow]]
    return lines + markdown_table(["role", "weights"], rows) + [""]


def png_bytes(image: Any) -> bytes:
    buffer = io.BytesIO()
    image.save(buffer, format="PNG")
    return buffer.getvalue()


def write_report_files(out: Path, *, table: str, summary: dict[str, Any], plot: bytes, markdown: str,
                       stems: Sequence[str] = ("results", "summary", "pareto", "report")) -> None:
    """``results.csv``, ``summary.json``, ``pareto.png``, ``report.md`` (the report last: it
    links the others)."""
    names = dict(zip(("csv", "summary", "plot", "report"), stems))
    write_text_atomic(out / f"{names['csv']}.csv", table)
    write_json_atomic(out / f"{names['summary']}.json", summary)
    write_bytes_atomic(out / f"{names['plot']}.png", plot)
    write_text_atomic(out / f"{names['report']}.md", markdown)
