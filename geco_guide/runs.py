"""Long runs over many videos (the A/B script, GeCo-Eval): resumable, shardable, measured.

* :func:`config_fingerprint` pins an output folder to one config (``run.json``).
* :func:`remove_temp_files` deletes what a killed run left of its atomic writes.
* :class:`PeakMemory` measures the peak memory of a block (CUDA, or peak RSS on CPU).
* :func:`process_state` / :func:`process_config` / :func:`shard`: one process, or many under
  ``accelerate launch`` with the jobs dealt round-robin.
"""

from __future__ import annotations

import hashlib
import sys
from collections.abc import Sequence
from dataclasses import replace
from datetime import timedelta
from pathlib import Path
from typing import Any, TypeVar

import torch

from .config import GeCoConfig, config_to_yaml
from .estimators import resolve_device

MIB = 2**20
T = TypeVar("T")


def config_fingerprint(cfg: GeCoConfig) -> str:
    return hashlib.sha256(config_to_yaml(cfg).encode()).hexdigest()[:16]


def remove_temp_files(folder: Path, stems: Sequence[str]) -> None:
    """Delete temporary files (``.<stem>.*``) that a killed run left behind in ``folder``."""
    if not folder.is_dir():
        return
    for path in folder.iterdir():
        if path.is_file() and any(path.name.startswith(f".{stem}.") for stem in stems):
            path.unlink(missing_ok=True)


class PeakMemory:
    """Peak memory of a block, in MiB: CUDA ``max_memory_allocated`` on a GPU; on CPU the peak
    resident set size, its high-water mark reset at entry on Linux (``/proc/self/clear_refs``),
    else the process's lifetime peak (``kind`` says which)."""

    def __init__(self, device: torch.device):
        self.device = device
        self.kind = "cuda_max_allocated"
        self.peak_mib = 0.0

    def __enter__(self) -> PeakMemory:
        if self.device.type == "cuda":
            torch.cuda.synchronize(self.device)
            torch.cuda.reset_peak_memory_stats(self.device)
        else:
            try:
                Path("/proc/self/clear_refs").write_text("5")  # resets VmHWM (Linux >= 4.0)
                self.kind = "cpu_peak_rss"
            except OSError:
                self.kind = "cpu_peak_rss_since_start"
        return self

    def __exit__(self, *exc: Any) -> None:
        if self.device.type == "cuda":
            torch.cuda.synchronize(self.device)
            self.peak_mib = torch.cuda.max_memory_allocated(self.device) / MIB
        else:
            self.peak_mib = _peak_rss_bytes() / MIB


def _peak_rss_bytes() -> int:
    """``VmHWM`` of ``/proc/self/status`` (Linux), else ``ru_maxrss``."""
    try:
        for line in Path("/proc/self/status").read_text().splitlines():
            if line.startswith("VmHWM:"):
                return int(line.split()[1]) * 1024
    except OSError:
        pass
    import resource

    peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    return peak if sys.platform == "darwin" else peak * 1024  # bytes on macOS, KiB elsewhere


def process_state(cfg: GeCoConfig) -> Any:
    """accelerate's PartialState: rank and world size under ``accelerate launch`` (or torchrun),
    else one process. ``cpu=True`` for a CPU run, without which accelerate ignores CPU launches.

    The barrier at the end waits for the slowest shard, which may take hours: hence the long timeout.
    """
    from accelerate import PartialState

    cpu = resolve_device(cfg.model.device).type == "cpu"
    return PartialState(cpu=cpu, timeout=timedelta(days=7))


def process_config(cfg: GeCoConfig, state: Any) -> GeCoConfig:
    """The config of this process: with one GPU per process, its own GPU instead of ``cuda``."""
    if state.num_processes > 1 and state.device.type == "cuda" and cfg.model.device in ("auto", "cuda"):
        return replace(cfg, model=replace(cfg.model, device=str(state.device)))
    return cfg


def shard(jobs: Sequence[T], index: int, count: int) -> list[T]:
    """Jobs of process ``index`` of ``count``, dealt round-robin."""
    return list(jobs[index::count])
