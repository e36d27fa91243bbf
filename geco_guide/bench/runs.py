"""Long runs over many videos (the A/B script, GeCo-Eval): resumable, shardable, measured.

* :func:`config_fingerprint` pins an output folder to one config (``run.json``,
  :func:`check_output_folder`, which names the keys another config changed).
* :func:`read_finished` reads a finished unit's result file: a damaged one, one without the
  fields its reader needs, or one whose outputs are gone or unreadable, means the unit is redone
  (with a warning naming the file).
* :func:`run_lock` keeps a second run out of a folder a live run writes to.
* :class:`PeakMemory` measures the peak memory of a block (CUDA, or peak RSS on CPU).
* :func:`process_state` / :func:`process_config` / :func:`shard`: one process, or many under
  ``accelerate launch`` with the jobs dealt round-robin.
"""

from __future__ import annotations

import contextlib
import errno
import hashlib
import json
import logging
import os
import sys
from collections.abc import Iterator, Sequence
from dataclasses import replace
from datetime import timedelta
from pathlib import Path
from typing import Any, Self, TypeVar

import torch

from ..config import GeCoConfig, config_to_dict, config_to_yaml
from ..io.devices import resolve_device
from ..io.files import json_text, probe_writable, take_pid_lock, write_json_atomic

__all__ = ["LOCK_NAME", "PeakMemory", "check_output_folder", "config_fingerprint", "pin_config",
           "process_config", "process_state", "read_finished", "run_lock", "shard", "take_run_lock"]

logger = logging.getLogger(__name__)

MIB = 2**20
#: The file that pins a run folder to one config (:func:`pin_config`).
RUN_FILE = "run.json"
T = TypeVar("T")


def config_fingerprint(cfg: GeCoConfig) -> str:
    return hashlib.sha256(config_to_yaml(cfg).encode()).hexdigest()[:16]


def config_differences(previous: Any, current: Any, prefix: str = "") -> list[str]:
    """``key: old -> new`` for each dotted key whose value differs between two config dicts (as
    ``run.json`` stores them), in the config's order; a key only one side has shows ``-``."""
    if not (isinstance(previous, dict) and isinstance(current, dict)):
        return [] if previous == current else [f"{prefix}: {json.dumps(previous)} -> {json.dumps(current)}"]
    changes = []
    for key in dict.fromkeys([*current, *previous]):
        name = f"{prefix}.{key}" if prefix else str(key)
        if key not in previous or key not in current:
            old, new = (json.dumps(previous[key]) if key in previous else "-"), (
                json.dumps(current[key]) if key in current else "-")
            changes.append(f"{name}: {old} -> {new}")
        else:
            changes += config_differences(previous[key], current[key], name)
    return changes


def pin_config(out: Path, cfg: GeCoConfig) -> None:
    """Write ``out/run.json``: the fingerprint and the config that :func:`check_output_folder`
    compares a later run's config with."""
    write_json_atomic(out / RUN_FILE, {"config_sha": config_fingerprint(cfg), "config": config_to_dict(cfg)})


def _check_writable(out: Path) -> None:
    """ValueError (one line) unless files can be made in ``out``, or, when it does not exist yet,
    in the nearest folder above it (which is probed, ``out`` is not created: a run refused later
    leaves nothing behind)."""
    try:
        folder = out
        while not folder.exists():
            folder = folder.parent
        if not folder.is_dir():
            raise ValueError(f"--out {str(out)!r} exists and is not a folder" if folder == out else
                             f"--out {str(out)!r} cannot be made: a file is in the way ({str(folder)!r})")
        probe_writable(folder)
    except OSError as err:
        reason = "a file name in it is too long" if err.errno == errno.ENAMETOOLONG else (
            err.strerror or type(err).__name__)
        raise ValueError(f"cannot write to --out {str(out)!r}: {reason}") from None


def check_output_folder(out: Path, cfg: GeCoConfig, overwrite: bool | None = None) -> None:
    """ValueError (one line) unless ``out`` is a folder that can be written: one to create, or one
    whose ``run.json`` pins ``cfg`` (another config is refused naming the first keys it changed; a
    damaged ``run.json`` is named). ``overwrite``: True, the folder's config is not compared (the
    caller starts afresh); False, the refusal mentions ``--overwrite``; None, the command has none."""
    _check_writable(out)
    run_file = out / RUN_FILE
    if overwrite or not run_file.is_file():  # also when out does not exist yet
        return
    try:
        pinned = json.loads(run_file.read_text(encoding="utf-8"))
        previous = pinned["config_sha"]
    except (ValueError, KeyError, TypeError):  # UnicodeDecodeError is a ValueError
        raise ValueError(f"{run_file} is damaged; remove it to reuse the folder with this config") from None
    if previous != config_fingerprint(cfg):
        now = json.loads(json_text(config_to_dict(cfg)))  # as run.json stores it
        changes = config_differences(pinned.get("config"), now) if isinstance(pinned.get("config"), dict) else []
        what = "; ".join(changes[:3]) + (f"; {len(changes) - 3} more" if len(changes) > 3 else "") if changes else (
            f"run.json: {previous}, now: {config_fingerprint(cfg)}")
        ways = "a new --out folder, the same config, or --overwrite to start afresh" if overwrite is False else (
            "a new --out folder or the same config")
        raise ValueError(f"{out} holds results of another config ({what}); use {ways}")


def _unreadable(path: Path) -> str | None:
    """Why ``path`` is not a readable, non-empty file, or None."""
    if not path.is_file():
        return "is missing"
    try:
        with open(path, "rb") as fh:
            if not fh.read(1):
                return "is empty"
    except OSError as err:
        return f"cannot be read ({err.strerror or type(err).__name__})"
    return None


def read_finished(path: Path, outputs: Sequence[Path], unit: str, warn: bool = True,
                  required: Sequence[str] = ()) -> dict[str, Any] | None:
    """The JSON object in ``path`` if the unit of work it records (``unit``, e.g. ``pair a-s0``) is
    finished, else None: no file, a damaged one (not a JSON object, or without one of the
    ``required`` keys), or one of its ``outputs`` missing, empty or unreadable. All but the first
    mean the unit is redone; with ``warn`` a warning names the file."""
    if not path.is_file():
        return None
    try:
        result = json.loads(path.read_text(encoding="utf-8"))
    except ValueError:  # UnicodeDecodeError is a ValueError
        result = None
    if not isinstance(result, dict):
        problem: str | None = f"{path} is damaged"
    else:
        lacking = [key for key in required if key not in result]
        problem = f"{path} lacks {', '.join(map(repr, lacking))}" if lacking else next(
            (f"{output} {why}" for output in outputs if (why := _unreadable(output)) is not None), None)
    if problem is None:
        return result
    if warn:
        logger.warning("warning: %s; %s is redone", problem, unit)
    return None


class PeakMemory:
    """Peak memory of a block, in MiB: CUDA ``max_memory_allocated`` on a GPU; on CPU the peak
    resident set size, its high-water mark reset at entry on Linux (``/proc/self/clear_refs``),
    else the process's lifetime peak (``kind`` says which)."""

    def __init__(self, device: torch.device):
        self.device = device
        self.kind = "cuda_max_allocated"
        self.peak_mib = 0.0

    def __enter__(self) -> Self:
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

    def __exit__(self, *exc: object) -> None:
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


#: The lock file of a run folder (:func:`run_lock`).
LOCK_NAME = ".run.lock"


def is_launch_main() -> bool:
    """Whether this is the main process of its launch, known before accelerate starts: torchrun
    and ``accelerate launch`` set ``RANK``; a plain run is the main process."""
    return os.environ.get("RANK", "0") == "0"


def take_run_lock(out: Path, command: str) -> Path:
    """Create ``out/.run.lock`` holding this pid (:func:`~geco_guide.io.files.take_pid_lock`: one
    run wins, a killed run's lock is taken over). ValueError (one line) while a live run holds it
    (two runs in one folder delete each other's live temporary files) or if ``out`` cannot be
    written; ``command`` names the run in the message."""
    try:
        out.mkdir(parents=True, exist_ok=True)
    except OSError as err:
        raise ValueError(f"cannot write to --out {str(out)!r}: {err.strerror or err}") from None
    return take_pid_lock(out / LOCK_NAME, f"another {command} run (pid {{pid}}) is writing to {out}; wait for it to "
                                          "end or use another --out folder", "use another --out folder")


@contextlib.contextmanager
def run_lock(out: Path, command: str) -> Iterator[None]:
    """Hold :func:`take_run_lock` for the block on the launch's main process (the other ranks of
    a sharded run share their main process' lock); released however the block ends."""
    lock = take_run_lock(out, command) if is_launch_main() else None
    try:
        yield
    finally:
        if lock is not None:
            lock.unlink(missing_ok=True)
