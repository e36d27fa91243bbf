"""Torch devices: what ``auto`` means, and a one-line error for a device this machine lacks."""

from __future__ import annotations

import torch


def resolve_device(name: str | torch.device) -> torch.device:
    """``"auto"`` -> cuda if available, else cpu; anything else as ``torch.device``."""
    if isinstance(name, str) and name == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    return torch.device(name)


def check_device(name: str, key: str = "model.device") -> None:
    """ValueError (one line, naming the config ``key``) unless this torch can use device ``name``
    (``auto`` always works).

    Checked before any model loads: otherwise a missing CUDA shows as a traceback from ``.to()``.
    """
    try:
        device = resolve_device(name)
    except RuntimeError as err:  # e.g. "cuda:x"
        raise ValueError(f"invalid device {name!r} ({key}): {err}") from None
    if device.type == "cuda":
        count = torch.cuda.device_count() if torch.cuda.is_available() else 0
        if (device.index or 0) >= count:
            found = "this torch has no CUDA support or no GPU" if count == 0 else f"only {count} CUDA device(s)"
            raise ValueError(f"device {name!r} is not available ({found}); use {key}=cpu or auto")
    elif device.type == "mps" and not torch.backends.mps.is_available():
        raise ValueError(f"device {name!r} is not available on this machine; use {key}=cpu or auto")
