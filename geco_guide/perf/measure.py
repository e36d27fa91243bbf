"""Measuring one case: timing, memory, a fresh subprocess per case, environment facts, reports.

Every case runs in its own Python process so that its peak memory is its own:
``torch.cuda.max_memory_allocated`` on a GPU, peak RSS (``ru_maxrss``) on CPU. Reports are
written with the house's atomic writer, so an interrupted or failed write (a full disk) leaves
no truncated file behind.
"""

from __future__ import annotations

import json
import logging
import os
import platform
import resource
import statistics
import subprocess
import sys
import time
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

import torch

from ..io.files import write_json_atomic

__all__ = ["CASE_COLUMNS", "GIB", "MIB", "current_memory_bytes",
           "environment_info", "markdown_table", "memory_kind", "peak_memory_bytes", "reset_peak_memory",
           "run_case_subprocess", "run_cases", "synchronize", "time_callable", "unwritable_reason",
           "write_report"]

#: ``--rss-exact``: allocations from 64 KiB up are mapped on their own and unmapped when freed.
RSS_EXACT_MMAP_THRESHOLD = 64 * 1024

logger = logging.getLogger(__name__)

MIB = 2**20
GIB = 2**30


def synchronize(device: torch.device) -> None:
    """Wait for queued GPU work so wall-clock times cover it (no-op on CPU)."""
    if device.type == "cuda":
        torch.cuda.synchronize(device)


def time_callable(fn: Callable[[], object], device: torch.device, warmup: int, repeats: int) -> dict[str, Any]:
    """Run ``fn`` ``warmup`` times untimed, then ``repeats`` times timed.

    Returns:
        ``times_s`` (every timed run), ``time_median_s``, ``time_min_s`` and ``cpu_per_wall``:
        this process's CPU time over the timed wall time, about the thread count on an idle
        machine and lower when other processes take the cores.
    """
    if repeats < 1:
        raise ValueError(f"repeats must be >= 1, got {repeats}")
    for _ in range(warmup):
        fn()
    synchronize(device)
    times = []
    cpu_start = time.process_time()
    for _ in range(repeats):
        start = time.perf_counter()
        fn()
        synchronize(device)
        times.append(time.perf_counter() - start)
    return {"times_s": times, "time_median_s": statistics.median(times), "time_min_s": min(times),
            "cpu_per_wall": (time.process_time() - cpu_start) / sum(times)}


def peak_memory_bytes(device: torch.device) -> int:
    """Peak memory of this process so far: CUDA ``max_memory_allocated`` on a GPU, else peak RSS."""
    if device.type == "cuda":
        return torch.cuda.max_memory_allocated(device)
    peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    return peak if sys.platform == "darwin" else peak * 1024  # bytes on macOS, KiB on Linux


def current_memory_bytes(device: torch.device) -> int | None:
    """Memory in use now: CUDA ``memory_allocated`` on a GPU, else resident set size (Linux only)."""
    if device.type == "cuda":
        return torch.cuda.memory_allocated(device)
    try:
        status = Path("/proc/self/status").read_text()
    except OSError:
        return None
    kib = next((line.split()[1] for line in status.splitlines() if line.startswith("VmRSS:")), None)
    return int(kib) * 1024 if kib is not None else None


def reset_peak_memory(device: torch.device) -> bool:
    """Restart :func:`peak_memory_bytes` from the current use (CUDA peak stats; on Linux the
    process's RSS high-water mark via ``/proc/self/clear_refs``). False where that is impossible."""
    if device.type == "cuda":
        torch.cuda.reset_peak_memory_stats(device)
        return True
    try:
        Path("/proc/self/clear_refs").write_text("5")
    except OSError:
        return False
    return True


def memory_kind(device: torch.device) -> str:
    """What :func:`peak_memory_bytes` measures on ``device``."""
    return "cuda_max_memory_allocated" if device.type == "cuda" else "peak_rss"


def run_case_subprocess(spec: dict[str, Any], worker: Sequence[str]) -> dict[str, Any]:
    """Run one case in a fresh Python process and return its result.

    Args:
        spec: the case, passed to the child as its last argument (JSON).
        worker: the child's command line before the spec, e.g. ``[python, script, "worker"]``; the
            child prints its result as JSON on its last stdout line.

    Raises:
        RuntimeError: the child failed (its stderr in the message).
    """
    command = [*worker, json.dumps(spec)]
    env = dict(os.environ)
    # the child imports the package the parent runs, wherever it is on the parent's path
    root = str(Path(__file__).resolve().parents[2])
    env["PYTHONPATH"] = os.pathsep.join([root, *filter(None, [env.get("PYTHONPATH")])])
    if spec.get("rss_exact"):
        # glibc otherwise raises its mmap threshold to 32 MiB after the first large free and keeps
        # freed blocks below it in the heap, so peak RSS overstates the live tensors.
        env["MALLOC_MMAP_THRESHOLD_"] = str(RSS_EXACT_MMAP_THRESHOLD)
    proc = subprocess.run(command, capture_output=True, text=True, env=env)
    if proc.returncode != 0:
        raise RuntimeError(f"case {spec['case']} / {spec['mode']} failed:\n{proc.stderr}")
    return json.loads(proc.stdout.strip().splitlines()[-1])


def run_cases(specs: Sequence[dict[str, Any]], worker: Sequence[str]) -> list[dict[str, Any]]:
    """Run every case in its own subprocess, logging its progress."""
    results = []
    for spec in specs:
        logger.info("running %s / %s ...", spec["case"], spec["mode"])
        result = run_case_subprocess(spec, worker)
        logger.info("  median %.4g s, peak %.0f MiB", result["time_median_s"], result["peak_mib"])
        results.append(result)
    return results


def environment_info(threads: int) -> dict[str, Any]:
    """Machine and software facts for the report (the children use ``threads`` threads)."""
    return {
        "platform": platform.platform(),
        "processor": _cpu_model(),
        "cpu_count": os.cpu_count(),
        "python": platform.python_version(),
        "torch": torch.__version__,
        "torch_threads": threads,
        "cuda": torch.cuda.get_device_name() if torch.cuda.is_available() else None,
    }


def _cpu_model() -> str:
    """CPU model name from ``/proc/cpuinfo`` (Linux), else :func:`platform.processor`."""
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor()


#: Columns of the micro-benchmarks' table: header, result key, format.
CASE_COLUMNS: tuple[tuple[str, str, str], ...] = (
    ("case", "case", "{}"),
    ("mode", "mode", "{}"),
    ("input", "input", "{}"),
    ("network input", "network", "{}"),
    ("params (M)", "params_m", "{:.1f}"),
    ("dtype", "dtype", "{}"),
    ("checkpointing", "checkpointing", "{}"),
    ("tiling", "tiling", "{}"),
    ("setup (s)", "setup_s", "{:.1f}"),
    ("median (s)", "time_median_s", "{:.4g}"),
    ("min (s)", "time_min_s", "{:.4g}"),
    ("peak mem (MiB)", "peak_mib", "{:.0f}"),
    ("after setup (MiB)", "after_setup_mib", "{:.0f}"),
    ("increase over import (MiB)", "peak_increase_mib", "{:.0f}"),
    ("runs: peak over in use after setup (MiB)", "run_increase_mib", "{:.0f}"),
    ("load (1 min)", "load_avg_1m", "{:.1f}"),
    ("CPU/wall", "cpu_per_wall", "{:.2f}"),
)


def markdown_table(results: Sequence[dict[str, Any]], columns: Sequence[tuple[str, str, str]]) -> str:
    """A Markdown table of ``results``, one row each; ``columns`` are ``(header, key, format)``;
    missing values are shown as ``-``."""
    lines = ["| " + " | ".join(header for header, _, _ in columns) + " |",
             "|" + "|".join("---" for _ in columns) + "|"]
    for result in results:
        cells = [fmt.format(result[key]) if result.get(key) is not None else "-" for _, key, fmt in columns]
        lines.append("| " + " | ".join(cells) + " |")
    return "\n".join(lines)


def write_report(path: str | os.PathLike, report: dict[str, Any]) -> Path:
    """Write ``report`` as indented JSON to ``path`` atomically, creating its folder."""
    Path(path).parent.mkdir(parents=True, exist_ok=True)
    return write_json_atomic(path, report)


def unwritable_reason(path: str | os.PathLike) -> str | None:
    """Why a report could not be written to ``path`` (a folder, a parent that is a file, no write
    permission on the first existing ancestor), or None; creates nothing, so that a bad path fails
    before a long run rather than after it."""
    target = Path(path)
    if target.is_dir():
        return f"{str(target)!r} is a folder"
    parent = target.absolute().parent
    while not parent.exists():
        parent = parent.parent
    if not parent.is_dir():
        return f"cannot create the folder of {str(target)!r}: {str(parent)!r} is a file"
    if not os.access(parent, os.W_OK | os.X_OK):
        return f"cannot write to {str(parent)!r} (permission denied)"
    return None
