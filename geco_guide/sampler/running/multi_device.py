"""Several devices for one guided call: the anchor chunks of an update decoded on different
devices at once (``run.devices``).

The chunks of one update are independent: they meet only in the loss. Chunk ``k`` goes to device
``k mod N`` with that device's replica of the guidance decoder; each device's forward is issued
without waiting for the others (CUDA kernels are asynchronous and nothing here reads a value
back), and autograd runs each device's part of the backward on its own thread, so the decodes
overlap both ways. Only the anchor frames travel back, to the device of the latents.

With ``run.split_cfg`` the denoiser's classifier-free-guidance batch (unconditional and
conditional halves) runs as two calls (:class:`CfgHalves`): on the first two devices, each with
its own replica of the denoiser, or one after the other on one device. Both halves of faithful
mode's backward then run on their own devices too.
"""

from __future__ import annotations

import copy
from collections.abc import Callable, Iterator, Sequence
from concurrent.futures import ThreadPoolExecutor
from typing import Any, TypeVar

import torch
from torch import nn

__all__ = ["CfgHalves", "dealt_work", "module_replicas", "to_device"]

def module_replicas(module: nn.Module, devices: Sequence[torch.device]) -> list[nn.Module]:
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


def to_device(value: Any, device: torch.device) -> Any:
    """``value`` (a tensor, or a tuple/list of them, e.g. rotary embeddings) on ``device``."""
    if isinstance(value, torch.Tensor):
        return value.to(device)
    if isinstance(value, (tuple, list)):
        return type(value)(to_device(v, device) for v in value)
    return value


_T = TypeVar("_T")


def dealt_work(count: int, places: int, work: Callable[[int, int], _T]) -> Iterator[_T]:
    """``work(k, k mod places)`` for ``k`` in ``range(count)``, yielded in order of ``k``: the items
    of one place one after another in a thread of that place's own, so that the places (devices)
    work at once even where an item reads a value back (a score), which would stall a loop
    issuing every device's kernels from one thread. Each thread works in the caller's grad mode.
    One place: the items run in the caller's thread."""
    if places <= 1:
        yield from (work(k, 0) for k in range(count))
        return
    grad = torch.is_grad_enabled()

    def in_grad_mode(k: int) -> _T:
        with torch.set_grad_enabled(grad):
            return work(k, k % places)

    pools = [ThreadPoolExecutor(max_workers=1) for _ in range(places)]
    try:
        futures = [pools[k % places].submit(in_grad_mode, k) for k in range(count)]
        for future in futures:
            yield future.result()
    finally:
        for pool in pools:
            pool.shutdown(wait=True, cancel_futures=True)


class CfgHalves:
    """A denoiser called on a classifier-free-guidance batch ``[2B, ...]`` as two calls of ``B``,
    the first half (unconditional) on ``devices[0]``, the second (conditional) on the last of
    ``devices[:2]``, each device with its own replica of ``denoiser`` (:func:`module_replicas`):
    the two calls run at once across devices, forward and backward. With one device (or none:
    the denoiser's own) the halves run one after the other. Outputs meet on ``home``.

    The halves are batch-``B`` calls where the stock call is one of ``2B``, so the output equals
    the stock one to float rounding only (kernels of another batch size may sum in another
    order); the same on one device or several, bitwise where the devices compute alike.

    Args:
        denoiser: ``(hidden_states=, encoder_hidden_states=, timestep=, ...) -> (output, ...)``,
            e.g. a diffusers transformer.
        devices: where the halves run (the first two are used), or ``None``.
        home: the device of the inputs and outputs.
    """

    def __init__(self, denoiser: nn.Module, devices: Sequence[torch.device] | None, home: torch.device):
        places = list(devices[:2]) if devices else [home]
        self.home = home
        self.replicas = module_replicas(denoiser, places)
        self.places = places

    def __call__(self, **inputs: Any) -> torch.Tensor:
        """The denoiser's first output ``[2B, ...]`` on ``home`` for ``inputs`` of batch ``2B``
        (each tensor is split in halves along dim 0; ``image_rotary_emb`` and other non-batch
        inputs go whole to each device)."""
        batched = {key: value.chunk(2) for key, value in inputs.items()
                   if isinstance(value, torch.Tensor) and key != "image_rotary_emb"}
        outputs = []
        for k in range(2):
            replica, device = self.replicas[k % len(self.replicas)], self.places[k % len(self.places)]
            half = {key: (batched[key][k] if key in batched else value) for key, value in inputs.items()}
            outputs.append(replica(**{key: to_device(value, device) for key, value in half.items()})[0].to(self.home))
        return torch.cat(outputs)
