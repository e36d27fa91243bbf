"""Several devices for one guided call: the anchor chunks of an update decoded on different
devices at once (``run.devices``).

The chunks of one update are independent: they meet only in the loss. Chunk ``k`` goes to device
``k mod N`` with that device's replica of the guidance decoder; each device's forward is issued
without waiting for the others (CUDA kernels are asynchronous and nothing here reads a value
back), and autograd runs each device's part of the backward on its own thread, so the decodes
overlap both ways. Only the anchor frames travel back, to the device of the latents.
"""

from __future__ import annotations

import copy
from collections.abc import Sequence

import torch
from torch import nn

from ..io.devices import check_device

__all__ = ["decoder_replicas", "resolve_devices"]

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


def decoder_replicas(module: nn.Module, devices: Sequence[torch.device]) -> list[nn.Module]:
    """One copy of the frozen ``module`` per entry of ``devices``: the module itself for the first
    (where it already lives there), deep copies moved to the others (a second entry of the same
    device gets a copy of its own, so that the transfers and replicas of several GPUs also run on
    one CPU). The copies keep the module's dtypes, flags and patched forwards."""
    first = next(module.parameters(), None)
    home = first.device if first is not None else torch.device("cpu")
    replicas = []
    for k, device in enumerate(devices):
        if k == 0 and device == home:
            replicas.append(module)
        else:
            replicas.append(copy.deepcopy(module).to(device))
    return replicas
