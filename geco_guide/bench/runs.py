"""Long runs over many videos (the A/B script, GeCo-Eval): resumable, shardable, measured.

* :func:`config_fingerprint` pins an output folder to one config (``run.json``,
  :func:`check_output_folder`).
* :func:`read_finished` reads a finished unit's result file: a damaged one, or one whose outputs
  are gone, means the unit is redone (with a warning naming the file).
* :class:`PeakMemory` measures the peak memory of a block (CUDA, or peak RSS on CPU).
* :func:`process_state` / :func:`process_config` / :func:`shard`: one process, or many under
  ``accelerate launch`` with the jobs dealt round-robin.
"""

from __future__ import annotations

import hashlib
import json
import sys
from collections.abc import Sequence
from dataclasses import replace
from datetime import timedelta
from pathlib import Path
from typing import Any, TypeVar

import torch

from ..config import GeCoConfig, config_to_yaml
from ..io.devices import resolve_device

MIB = 2**20
T = TypeVar("T")


def config_fingerprint(cfg: GeCoConfig) -> str:
    return hashlib.sha256(config_to_yaml(cfg).encode()).hexdigest()[:16]


def check_output_folder(out: Path, cfg: GeCoConfig) -> None:
    """ValueError (one line) unless ``out`` is a folder to create, or one whose ``run.json`` pins
    ``cfg``; a damaged ``run.json`` is named."""
    if out.exists() and not out.is_dir():
        raise ValueError(f"--out {str(out)!r} exists and is not a folder")
    run_file = out / "run.json"
    if not run_file.is_file():
        return
    try:
        previous = json.loads(run_file.read_text(encoding="utf-8"))["config_sha"]
    except (ValueError, KeyError, TypeError):  # UnicodeDecodeError is a ValueError
        raise ValueError(f"{run_file} is damaged; remove it to reuse the folder with this config") from None
    if previous != config_fingerprint(cfg):
        raise ValueError(f"{out} holds results of another config (run.json: {previous}, now: "
                         f"{config_fingerprint(cfg)}); use a new --out folder or the same config")


def read_finished(path: Path, outputs: Sequence[Path], unit: str, warn: bool = True) -> dict[str, Any] | None:
    """The JSON object in ``path`` if the unit of work it records (``unit``, e.g. ``pair a-s0``) is
    finished, else None: no file, a damaged one (not a JSON object), or one of its ``outputs``
    missing. The last two mean the unit is redone; with ``warn`` a warning names the file."""
    if not path.is_file():
        return None
    try:
        result = json.loads(path.read_text(encoding="utf-8"))
    except ValueError:  # UnicodeDecodeError is a ValueError
        result = None
    problem = f"{path} is damaged" if not isinstance(result, dict) else next(
        (f"{output} is missing" for output in outputs if not output.is_file()), None)
    if problem is None:
        return result
    if warn:
        print(f"warning: {problem}; {unit} is redone", file=sys.stderr)
    return None


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
