"""Torch devices: what ``auto`` means, a one-line error for a device this machine lacks (the model's
device and the devices of ``run.devices``), how much memory each has, and a one-line error for a
working set that cannot fit in it."""

from __future__ import annotations

import os
from collections.abc import Sequence
from typing import Any

import torch

__all__ = ["AUTO", "COMPUTE_DEVICES", "check_device", "check_memory_fits", "device_memory_gb", "memory_limit",
           "planning_memory_gb", "resolve_device", "resolve_devices"]


def resolve_device(name: str | torch.device) -> torch.device:
    """``"auto"`` -> cuda if available, else cpu; anything else as ``torch.device``."""
    if isinstance(name, str) and name == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    return torch.device(name)


#: The kinds of device the models run on.
COMPUTE_DEVICES = ("cpu", "cuda", "mps")


def check_device(name: str | torch.device, key: str = "model.device", fix: str | None = None) -> torch.device:
    """The device ``name`` stands for (``auto`` resolved), after checking that this torch can use
    it; ValueError (one line, naming the config ``key``) otherwise.

    Called once before any model loads, and its answer is what the memory planner, the loaders
    and the sidecar see: otherwise a missing CUDA shows as a traceback from ``.to()``, and
    ``auto`` reaches code that only knows real devices. ``fix`` ends the message of a device this
    machine lacks (default: use ``key=cpu or auto``).
    """
    fix = fix or f"use {key}=cpu or auto"
    try:
        device = resolve_device(name)
    except RuntimeError as err:  # e.g. "cuda:x"
        raise ValueError(f"invalid device {str(name)!r} ({key}): {err.__str__().splitlines()[0]}") from None
    if device.type == "cuda":
        count = torch.cuda.device_count() if torch.cuda.is_available() else 0
        if (device.index or 0) >= count:
            found = "this torch has no CUDA support or no GPU" if count == 0 else f"only {count} CUDA device(s)"
            raise ValueError(f"device {name!r} is not available ({found}); {fix}")
    elif device.type == "mps" and not torch.backends.mps.is_available():
        raise ValueError(f"device {name!r} is not available on this machine; {fix}")
    elif device.type not in COMPUTE_DEVICES:  # e.g. meta: shapes without values, nothing to compute with
        raise ValueError(f"device {name!r} cannot run the models (they run on {', '.join(COMPUTE_DEVICES)}); {fix}")
    return device


#: ``run.devices: [auto]``: every GPU torch sees.
AUTO = "auto"


def resolve_devices(names: Sequence[str] | None, key: str = "run.devices") -> list[torch.device] | None:
    """The devices of ``run.devices``: ``None`` (the pipeline's one device) -> ``None``;
    ``["auto"]`` -> every visible CUDA device; names -> those devices, each checked.

    Raises:
        ValueError: (one line naming ``key``) a device this machine lacks, or ``auto`` without a GPU.
    """
    if names is None:
        return None
    if list(names) == [AUTO]:
        count = torch.cuda.device_count() if torch.cuda.is_available() else 0
        if count == 0:
            raise ValueError(f"{key}=[auto] means every visible GPU, and this machine has none: leave {key} unset "
                             "(null) or list the devices")
        return [torch.device("cuda", index) for index in range(count)]
    return [check_device(name, key, fix=f"list devices this machine has, or leave {key} unset (one device)")
            for name in names]


def memory_limit(device: str | torch.device) -> int | None:
    """Bytes of memory that ``device`` has in all: a CUDA device's total memory, the machine's
    physical RAM for the CPU (and any other device); None where the system does not say."""
    device = resolve_device(device)
    if device.type == "cuda" and torch.cuda.is_available():
        return int(torch.cuda.get_device_properties(device.index or 0).total_memory)
    try:
        return int(os.sysconf("SC_PAGE_SIZE")) * int(os.sysconf("SC_PHYS_PAGES"))
    except (AttributeError, ValueError, OSError):  # not a POSIX system
        return None


def device_memory_gb(device: Any) -> float | None:
    """Total memory (GiB) of a CUDA device (``auto`` resolved), or a CPU's physical RAM; ``None``
    where unknown.

    Raises:
        ValueError: (one line) a device this machine lacks, e.g. ``cuda`` without CUDA.
    """
    device = check_device(device)
    limit = memory_limit(device) if device.type in ("cuda", "cpu") else None
    return None if limit is None else limit / 2**30


def planning_memory_gb(home: Any, devices: Sequence[Any] | None = None) -> float | None:
    """The device memory (GiB) a guided call plans for: ``home``'s (the pipeline's execution
    device, :func:`device_memory_gb`), or with ``run.devices`` the smallest of ``home``'s and
    theirs. One plan then fits every device, and an out-of-memory fallback is one decision for all
    of them. Conservative: each device is held to the one-device peak, though the replicas hold
    only the decoder and their share of the anchor chunks. ``None`` where no memory is known."""
    known = [gb for gb in (device_memory_gb(d) for d in [home, *(devices or [])]) if gb is not None]
    return min(known) if known else None


def _gib(nbytes: float) -> str:
    return f"{nbytes / 2**30:.3g} GiB"


def check_memory_fits(nbytes: float, device: str | torch.device, what: str) -> None:
    """ValueError (one line) when ``nbytes``, a prediction of the peak memory of ``what`` (e.g.
    "--size 9 4000 4000"), exceeds all the memory of ``device`` (:func:`memory_limit`).

    Called before any heavy work, so that a size that cannot fit fails at once instead of after
    minutes in the allocator. The prediction should be a lower bound of what the work must hold
    (its unavoidable tensors): a refusal is then certain, and a size close to the limit is left to
    try. Nothing is checked where the limit is unknown.
    """
    limit = memory_limit(device)
    if limit is not None and nbytes > limit:
        where = "GPU memory" if resolve_device(device).type == "cuda" else "RAM"
        raise ValueError(f"{what} needs at least {_gib(nbytes)} of memory, more than the {_gib(limit)} of "
                         f"{where} of device {str(device)!r}: choose a smaller size")
