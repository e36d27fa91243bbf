"""``run.context_parallel: N``: the guided call over ``N`` processes, each denoiser's token
sequence split over them with diffusers' own context parallelism (docs/context_parallel.md).

Every process (one per GPU, started by ``torchrun --nproc-per-node N`` or ``accelerate launch``)
runs the whole call: the same seed, text encoding, schedule, anchor decode, GeCo loss and update,
so their latents stay equal. Only the denoisers are split: diffusers' ``enable_parallelism`` with
a ``ContextParallelConfig(ulysses_degree=N)`` and the family's plan
(:meth:`~.adapters.PipelineAdapter.context_parallel_plan`: diffusers' ``_cp_plan`` for Wan,
ours for CogVideoX, HunyuanVideo 1 and 1.5, LTX-Video and LTX-2) shards
the tokens where the plan says, runs each attention as Ulysses (an all-to-all from token shards
to head shards and back) and gathers the output, so each process holds ``1/N`` of the activations a backward through the denoiser keeps.

The backward goes through diffusers' autograd functions (the all-to-all's backward is the
reverse all-to-all; the gather's backward keeps the process's own shard). What they give the
denoiser's input is the gradient of the process's own token shard only, where the split takes
the replicated tokens apart. :class:`GradientSum`, a hook around each denoiser, sums it over the
processes (an all-reduce of the input's gradient), so that every process holds the whole
gradient with respect to the latents, as one process would: each latent element belongs to one
token, so the sum adds zeros to one process's value and is exact.

The guidance's anchor decode is dealt over the processes too
(:class:`~.anchor_decode.AcrossProcessesDecode`): each decodes its share of the anchor chunks,
forward and backward, and :func:`~.process_collectives.gather_from_processes` brings every process the others' anchor
frames, so that all compute the same loss. Its backward keeps the gradient of the process's own
frames: the ``N`` losses are one loss computed ``N`` times, so summing their gradients would count
it ``N`` times. :func:`~.process_collectives.sum_gradient_over_processes` at the decode's input then adds the
processes' shares into the whole gradient with respect to the latents, as one process's.
"""

from __future__ import annotations

import logging
import os
from typing import TYPE_CHECKING, Any

import torch
import torch.distributed as dist
from diffusers.hooks import ModelHook
from torch import Tensor, nn

from ..diffusers_private import (
    active_attention_backend,
    context_parallel_backends,
    context_parallel_processes,
    parallel_config,
    set_parallel_config,
    set_parallel_resolver,
)
from .module_hooks import register_hook
from .process_collectives import SumOverProcesses

if TYPE_CHECKING:
    from ..pipelines.adapters import PipelineAdapter

__all__ = ["GRADIENT_SUM_HOOK", "GradientSum", "check_context_parallel_before_loading",
           "context_parallel_degree", "enable_context_parallel", "init_context_parallel", "is_writing_process",
           "start_context_parallel"]

logger = logging.getLogger(__name__)

#: the name of :class:`GradientSum` in a denoiser's ``HookRegistry``
GRADIENT_SUM_HOOK = "geco_context_parallel_gradient_sum"
#: diffusers' attention backends that split a sequence and differentiate through the split (the
#: others that split it, sage and the NPU kernel, have no backward there)
BACKWARD_BACKENDS = ("flash", "flash_hub", "flash_varlen_hub", "_flash_3_hub", "_flash_3_varlen_hub", "native",
                     "_native_cudnn", "_native_flash")
#: how to start a launch of ``n`` processes, as a refusal says it
LAUNCH = "torchrun --nproc-per-node {n} -m geco_guide.generate ... (or accelerate launch --num-processes {n})"


def context_parallel_degree(run: Any) -> int:
    """The number of processes ``run`` (:class:`~.run_options.RunOptions`) splits the denoiser over: 1 for ``None``."""
    return run.context_parallel or 1


def is_writing_process(run: Any) -> bool:
    """Whether this process writes the outputs of a run of ``run`` (:class:`~.run_options.RunOptions`):
    the only one, or rank 0 of a ``run.context_parallel`` launch (known before its process group starts)."""
    return context_parallel_degree(run) == 1 or int(os.environ.get("RANK", "0")) == 0


def start_context_parallel(pipe: Any, adapter: PipelineAdapter, run: Any, *, differentiates: bool) -> None:
    """What a guided call of ``pipe`` with ``run.context_parallel`` needs first: the checks of
    :func:`check_context_parallel_before_loading`, the process group, the split denoisers
    (:func:`enable_context_parallel`; nothing again where they are split already). Nothing for
    one process."""
    n = context_parallel_degree(run)
    if n == 1:
        return
    check_context_parallel_before_loading(run, adapter, differentiates=differentiates)
    init_context_parallel(n)
    enable_context_parallel(pipe, adapter, n)


def check_context_parallel_before_loading(run: Any, adapter: PipelineAdapter, *, model_device: str | None = None,
                                          differentiates: bool) -> None:
    """ValueError (one line naming the option) for a ``run.context_parallel`` this launch, model
    or run cannot use, before anything loads: a launch of another number of processes, a family
    without a plan, ``run.devices`` (each process owns one GPU), a ``model.device`` naming one GPU
    for all processes, an attention backend without context parallelism, or without a backward
    through it where the guidance differentiates the denoiser (``differentiates``)."""
    n = context_parallel_degree(run)
    if n == 1:
        return
    started = dist.is_available() and dist.is_initialized()
    launched = dist.get_world_size() if started else int(os.environ.get("WORLD_SIZE", "1"))
    if launched != n:
        raise ValueError(f"run.context_parallel={n} runs the call over {n} processes, but this launch has {launched}: "
                         f"start it with {LAUNCH.format(n=n)}")
    if adapter.context_parallel_refusal is not None:
        raise ValueError(f"run.context_parallel cannot split {adapter.name}: {adapter.context_parallel_refusal}")
    if run.devices is not None:
        raise ValueError("run.devices deals the anchor decode over this process's GPUs, and under run.context_parallel "
                         "each process owns one GPU (its LOCAL_RANK): leave run.devices unset")
    if model_device is not None and str(model_device).startswith("cuda:"):
        raise ValueError(f"model.device={model_device} would put every process on one GPU; under run.context_parallel "
                         "each process runs on the GPU of its LOCAL_RANK: use model.device=auto or cuda")
    check_attention_backend(differentiates)


def check_attention_backend(differentiates: bool) -> None:
    """ValueError (one line) unless diffusers' active attention backend (``DIFFUSERS_ATTN_BACKEND``)
    splits a sequence, and, where the guidance ``differentiates`` the denoiser, has a backward
    through the split (the sage and NPU kernels have none)."""
    backend = active_attention_backend()
    if backend not in context_parallel_backends():
        raise ValueError(f"the attention backend {backend!r} has no context parallelism in diffusers: set "
                         f"DIFFUSERS_ATTN_BACKEND to one of {', '.join(BACKWARD_BACKENDS)}")
    if differentiates and backend not in BACKWARD_BACKENDS:
        raise ValueError(f"the attention backend {backend!r} has no backward under context parallelism, and faithful "
                         f"guidance differentiates the denoiser: set DIFFUSERS_ATTN_BACKEND to one of "
                         f"{', '.join(BACKWARD_BACKENDS)} (or guidance.denoiser_grad=false)")


def init_context_parallel(degree: int) -> None:
    """Join the launch's process group (``nccl`` on GPUs, each process on the GPU of its
    ``LOCAL_RANK``; ``gloo`` on CPUs), unless one is started already; ValueError (one line) for a
    group of another size."""
    if degree == 1:
        return
    if not dist.is_initialized():
        if torch.cuda.is_available():
            torch.cuda.set_device(int(os.environ.get("LOCAL_RANK", "0")))
        dist.init_process_group("nccl" if torch.cuda.is_available() else "gloo")
    if dist.get_world_size() != degree:
        raise ValueError(f"run.context_parallel={degree}, but the process group has {dist.get_world_size()} processes")


class GradientSum(ModelHook):
    """A hook around a split denoiser: every tensor input that carries a gradient goes through
    :class:`SumOverProcesses`, so its gradient is the sum of the processes' shards, the whole
    gradient on every process. Registered after diffusers' own hooks, it wraps them, and turns
    their assertion of a sequence that does not split into equal shards into one line."""

    def new_forward(self, module: nn.Module, *args: Any, **kwargs: Any) -> Any:
        args, kwargs = tuple(_summed(a) for a in args), {k: _summed(v) for k, v in kwargs.items()}
        try:
            return self.fn_ref.original_forward(*args, **kwargs)
        except AssertionError as err:  # diffusers asserts equal shards where its plan splits
            if "divisible by mesh size" not in str(err):
                raise
            raise ValueError(f"run.context_parallel={dist.get_world_size()}: the {type(module).__name__}'s token "
                             "sequence of this call does not divide into equal shards among the processes (video "
                             "tokens, and text tokens where the plan splits them): choose a size, frame count or "
                             "prompt length whose tokens do, or another number of processes") from None


def _summed(value: Any) -> Any:
    if isinstance(value, Tensor) and value.requires_grad:
        return SumOverProcesses.apply(value)
    return value


def enable_context_parallel(pipe: Any, adapter: PipelineAdapter, degree: int) -> None:
    """Split each denoiser of ``pipe`` (``adapter.denoisers``) over ``degree`` processes with
    diffusers' ``enable_parallelism`` and the family's plan, and put :class:`GradientSum` around
    it; a denoiser split already over ``degree`` is left as it is. Register the hooks guidance
    puts on the denoisers after this (they then wrap the split).

    Raises:
        ValueError: (one line) a denoiser split over another number of processes, one without a
            plan, or whose attention heads do not divide among the processes.
    """
    from diffusers import ContextParallelConfig

    for denoiser in adapter.denoisers(pipe):
        current = parallel_config(denoiser)
        if current is not None:
            split = current.context_parallel_config
            if split is None or context_parallel_processes(split) != degree:
                raise ValueError(f"the {type(denoiser).__name__} is parallelised otherwise already; run.context_parallel"
                                 f"={degree} needs it split over {degree} processes")
            continue
        plan = adapter.context_parallel_plan(denoiser)
        if plan is None:
            raise ValueError(f"run.context_parallel cannot split {adapter.name}'s {type(denoiser).__name__}: it has no "
                             "context-parallel plan")
        heads = denoiser.config.get("num_attention_heads")
        if heads is not None and heads % degree:
            raise ValueError(f"run.context_parallel={degree}: the {type(denoiser).__name__}'s {heads} attention heads do "
                             f"not divide among {degree} processes (Ulysses attention gives each a share of the heads)")
        adapter.prepare_context_parallel(denoiser)
        if torch._C._get_accelerator().type == "cpu":
            set_parallel_resolver(denoiser, _cpu_resolver(denoiser))
        denoiser.enable_parallelism(config=ContextParallelConfig(ulysses_degree=degree), cp_plan=plan)
        adapter.finish_context_parallel(denoiser)
        register_hook(denoiser, GradientSum(), GRADIENT_SUM_HOOK)
        logger.info("%s: context parallel over %d processes", type(denoiser).__name__, degree)


def _cpu_resolver(denoiser: nn.Module):
    """diffusers' ``_resolve_parallel_config`` for a torch without an accelerator: the same mesh
    and setup on the CPU (diffusers picks the rank's device as ``rank % accelerator count``, a
    division by zero there). The CPU runs are the exactness tests on the ``gloo`` backend."""
    from diffusers import ParallelConfig
    from torch.distributed.device_mesh import init_device_mesh

    def resolve(parallel: Any) -> Any:
        parallel = parallel if isinstance(parallel, ParallelConfig) else ParallelConfig(context_parallel_config=parallel)
        split = parallel.context_parallel_config
        mesh = init_device_mesh("cpu", split.mesh_shape, mesh_dim_names=split.mesh_dim_names)
        parallel.setup(dist.get_rank(), dist.get_world_size(), torch.device("cpu"), mesh=mesh)
        set_parallel_config(denoiser, parallel)
        return parallel

    return resolve
