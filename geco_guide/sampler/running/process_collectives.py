"""Collectives over the processes of a ``run.context_parallel`` launch that autograd goes through.

Plain ``torch.distributed``, nothing of diffusers: the anchor decode (which scoring without
diffusion imports through the guidance context) deals its chunks over the processes with them,
and :mod:`.context_parallel` sums the split denoisers' input gradients with them.
"""

from __future__ import annotations

import torch
import torch.distributed as dist
from torch import Tensor

__all__ = ["SumOverProcesses", "gather_from_processes", "sum_gradient_over_processes"]


class SumOverProcesses(torch.autograd.Function):
    """The identity forward; the backward sums the gradient over the processes (all-reduce)."""

    @staticmethod
    def forward(ctx, x: Tensor) -> Tensor:
        return x.view_as(x)

    @staticmethod
    def backward(ctx, grad: Tensor) -> Tensor:
        grad = grad.contiguous().clone()
        dist.all_reduce(grad)
        return grad


def sum_gradient_over_processes(x: Tensor) -> Tensor:
    """``x`` itself, whose gradient is summed over the processes in the backward (an all-reduce):
    each process's gradient there is its share of the whole."""
    return SumOverProcesses.apply(x)


class _GatherKeepOwnGradient(torch.autograd.Function):
    """Forward: every process's ``part`` (of one shape), stacked ``[P, ...]``; backward: the
    gradient of this process's own part, with nothing added from the others."""

    @staticmethod
    def forward(ctx, part: Tensor) -> Tensor:
        ctx.rank = dist.get_rank()
        parts = [torch.empty_like(part) for _ in range(dist.get_world_size())]
        dist.all_gather(parts, part.contiguous())
        return torch.stack(parts)

    @staticmethod
    def backward(ctx, grad: Tensor) -> Tensor:
        return grad[ctx.rank]


def gather_from_processes(part: Tensor) -> Tensor:
    """Every process's ``part`` (all of one shape) on every process: ``[P, *part.shape]`` in rank
    order. The backward gives ``part`` the gradient of its own slot only: every process computes
    the same loss from the gathered tensor, and one process's gradient is that of one loss."""
    return _GatherKeepOwnGradient.apply(part)
