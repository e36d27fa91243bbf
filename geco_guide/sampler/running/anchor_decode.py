"""The anchor decode of a guided update: ``latents [B, F, C, h, w] -> anchor frames [B, S, 3, H, W]``.

Two choices make it. *What* decodes a chunk is an :class:`AnchorDecode`: the pipeline's VAE or
the tiny decoder (:func:`anchor_decoder`, checked at the start of a call). *How* the chunks of an
update are decoded is a strategy, picked by the call's memory plan once, and again after an
out-of-memory fallback (:func:`plan_anchor_decode`), so that no update passes flags:

* :class:`BatchedDecode`: the chunks of one length stacked along the batch, one decode call each
  (fastest; the ``explicit`` plan without chunk checkpointing).
* :class:`ChunkedDecode`: one decode call per chunk, each in its own checkpointed region where the
  plan checkpoints chunks (the named plans; the same numbers to the last bit with or without the
  regions).
* :class:`AcrossDevicesDecode`: :class:`ChunkedDecode`'s calls dealt round-robin over several
  devices (``run.devices``), each with a replica of the decoder.
* :class:`AcrossProcessesDecode`: under ``run.context_parallel``, the chunks dealt round-robin
  over the processes, each decoding its share as the plan decodes, the anchor frames gathered to
  every process.

Each strategy is ``latents -> frames`` over the pure functions of :mod:`.slicing`.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Any

import torch
import torch.distributed as dist
from torch import Tensor, nn

from ..algorithm.config import GuidanceConfig
from ..algorithm.slicing import (AnchorChunk, chunk_spans, deal_spans, decode_anchor_frames,
                                 decode_anchor_frames_across, vae_latent_channels)
from .fast_decode import check_channels_last_vae
from .memory_plan import MemoryPlan
from .multi_device import module_replicas
from .process_collectives import gather_from_processes, sum_gradient_over_processes
from .run_options import RunOptions

__all__ = ["AcrossDevicesDecode", "AcrossProcessesDecode", "AnchorDecode", "BatchedDecode", "ChunkedDecode", "anchor_decoder",
           "plan_anchor_decode"]


class AnchorDecode:
    """The chunk decode of the loss' anchor frames: ``latents [N, F, C, h, w] -> frames [N, T, 3,
    H, W]`` in ``[0, 1]`` by ``module`` (the VAE, or the tiny decoder), and :meth:`on` a replica
    of that module (another device's).

    Args:
        module: the frozen decoder.
        decode_with: ``module -> decode``: the decode by a given copy of ``module``.
    """

    def __init__(self, module: nn.Module, decode_with: Callable[[nn.Module], Callable[[Tensor], Tensor]]):
        self.module, self.decode_with = module, decode_with
        self._decode = decode_with(module)

    def __call__(self, latents: Tensor) -> Tensor:
        return self._decode(latents)

    def on(self, replica: nn.Module) -> Callable[[Tensor], Tensor]:
        """The same decode by ``replica`` (a copy of :attr:`module`, e.g. on another device)."""
        return self.decode_with(replica)


def anchor_decoder(config: GuidanceConfig, run: RunOptions, vae_decode_with: Callable[[nn.Module], Callable[[Tensor], Tensor]],
                   tiny_decoder: Any, vae: Any) -> AnchorDecode:
    """The :class:`AnchorDecode` of the loss' anchor frames: ``vae_decode_with(vae)`` with
    ``decoder="vae"`` (``vae_decode_with``: a VAE -> its chunk decode); with ``"tiny"`` the tiny
    decoder on the pipeline's latents ``[N, F, C, h, w]``, in its family's convention taken from
    ``vae``'s config (CogVideoX's divided by ``scaling_factor``, Wan's and HunyuanVideo's as they
    are). Checked at the start of a call, before any denoiser runs: ValueError (one line) for a
    missing or mismatched decoder, TypeError for ``run.decode_layout="channels_last"`` on a VAE it
    is not written for."""
    if run.decode_layout == "channels_last":
        check_channels_last_vae(vae)
    if config.decoder == "vae":
        return AnchorDecode(vae, vae_decode_with)
    if tiny_decoder is None:
        raise ValueError(
            "guidance.decoder='tiny' needs a tiny decoder: give the estimators one, "
            "Estimators(..., tiny_decoder=TinyDecoder.from_pretrained(PATH)) (weights such as taecvx.pth from "
            "github.com/madebyollin/taehv; from a config: estimators.tiny_decoder=/path/to/taecvx.pth), or use "
            "guidance.decoder=vae"
        )
    vae_config = vae.config
    channels = vae_latent_channels(vae)
    if channels is not None and tiny_decoder.latent_channels != channels:
        raise ValueError(
            f"the tiny decoder ({tiny_decoder.variant.name}) takes {tiny_decoder.latent_channels} latent "
            f"channels but this VAE makes {channels}: load the tiny decoder trained for this model"
        )
    return AnchorDecode(tiny_decoder, lambda decoder: lambda latents: decoder.decode(
        decoder.pipeline_latents(latents, vae_config, layout="NTCHW")))


@dataclass(frozen=True)
class BatchedDecode:
    """The anchor frames with the chunks of one length decoded in one call (a batch of
    ``len(group) * B`` videos): the fewest calls, every chunk's activations kept for the backward.

    Attributes:
        decode: ``latents [N, F', C, h, w] -> frames [N, T, 3, H, W]`` in ``[0, 1]``, the ``N``
            videos independent (an :class:`AnchorDecode`).
        chunks: the anchors' causal latent chunks.
    """

    decode: Callable[[Tensor], Tensor]
    chunks: Sequence[AnchorChunk]

    def __call__(self, latents: Tensor) -> Tensor:
        """``latents [B, F, C, h, w] -> [B, S, 3, H, W]`` fp32 in ``[0, 1]``."""
        return decode_anchor_frames(self.decode, latents, self.chunks, batch_chunks=True)


@dataclass(frozen=True)
class ChunkedDecode:
    """The anchor frames with one decode call per chunk; with ``checkpointed``, each call in its own
    checkpointed region while gradients are enabled (the forward keeps only the chunk's latents,
    the backward decodes each chunk again). One call per chunk gives the checkpointed regions'
    numbers to the last bit, where a batched convolution may round differently.

    Attributes:
        decode: as :attr:`BatchedDecode.decode`.
        chunks: the anchors' causal latent chunks.
        checkpointed: one checkpointed region per chunk.
    """

    decode: Callable[[Tensor], Tensor]
    chunks: Sequence[AnchorChunk]
    checkpointed: bool

    def __call__(self, latents: Tensor) -> Tensor:
        """``latents [B, F, C, h, w] -> [B, S, 3, H, W]`` fp32 in ``[0, 1]``."""
        return decode_anchor_frames(self.decode, latents, self.chunks, checkpoint_chunks=self.checkpointed,
                                    batch_chunks=False)


class AcrossDevicesDecode:
    """The plan's decode (:class:`BatchedDecode` or :class:`ChunkedDecode`) with chunk span ``k``
    decoded on ``devices[k mod N]`` by that device's replica of ``decode.module``
    (:func:`~.multi_device.module_replicas`): a device's spans of one length batched where the plan
    batches, one call each otherwise; only the anchor frames come back. The frames equal one
    device's under the same plan (each video of a batch is decoded on its own). The replicas are
    copied at the first call: inside the call's models block, so that they carry the memory plan's
    switches and the decode layout's forwards.

    Args:
        decode: the :class:`AnchorDecode` whose module is replicated.
        devices: where the spans go, in turn.
        chunks: the anchors' causal latent chunks.
        checkpointed: one checkpointed region per span.
        batched: a device's spans of one length in one call (the plan batches).
    """

    def __init__(self, decode: AnchorDecode, devices: Sequence[torch.device], chunks: Sequence[AnchorChunk],
                 checkpointed: bool, batched: bool = False):
        self.decode, self.devices, self.chunks = decode, list(devices), chunks
        self.checkpointed, self.batched = checkpointed, batched
        self._placed: list[tuple[torch.device, Callable[[Tensor], Tensor]]] | None = None

    def __call__(self, latents: Tensor) -> Tensor:
        """``latents [B, F, C, h, w] -> [B, S, 3, H, W]`` fp32 in ``[0, 1]`` on ``latents``' device."""
        if self._placed is None:
            replicas = module_replicas(self.decode.module, self.devices)
            self._placed = [(device, self.decode.on(replica)) for device, replica in zip(self.devices, replicas)]
        return decode_anchor_frames_across(self._placed, latents, self.chunks, checkpoint_chunks=self.checkpointed,
                                           batch_chunks=self.batched)


@dataclass(frozen=True)
class AcrossProcessesDecode:
    """The anchor decode of a ``run.context_parallel`` call, whose processes all hold the same
    latents: chunk span ``k`` is decoded by process ``k mod P`` (:func:`~.slicing.deal_spans`, the
    rule of :class:`AcrossDevicesDecode`), a process's spans decoded as ``plan`` decodes them
    (:class:`BatchedDecode` or :class:`ChunkedDecode`, checkpointed regions and all, so the
    backward decodes again only the process's own spans); the anchor frames are gathered to every
    process (:func:`~.process_collectives.gather_from_processes`), and the gradient with respect to
    the latents is summed over the processes
    (:func:`~.process_collectives.sum_gradient_over_processes`): one process's frames and gradient.

    Attributes:
        share: the plan's decode of this process's chunks, ``chunks -> (latents -> frames)``.
        chunks: the anchors' causal latent chunks.
    """

    share: Callable[[Sequence[AnchorChunk]], Callable[[Tensor], Tensor]]
    chunks: Sequence[AnchorChunk]

    def __call__(self, latents: Tensor) -> Tensor:
        """``latents [B, F, C, h, w]`` (equal on every process) -> ``[B, S, 3, H, W]`` fp32 in ``[0, 1]``."""
        rank, processes = dist.get_rank(), dist.get_world_size()
        owner = deal_spans(chunk_spans(latents, self.chunks), processes)
        owners = [owner[(chunk.start, chunk.stop)] for chunk in self.chunks]
        mine = [chunk for chunk, r in zip(self.chunks, owners) if r == rank]
        latents = sum_gradient_over_processes(latents)
        frames = self.share(mine)(latents) if mine else None  # [B, len(mine), 3, H, W]
        if len(set(owners)) < processes:  # some process decodes nothing: it learns the frames' size from rank 0
            size = torch.tensor(frames.shape[2:] if rank == 0 else [0, 0, 0], device=latents.device)
            dist.broadcast(size, 0)
            if frames is None:  # no frames, yet on the latents' graph: every process's backward runs the all-reduce
                frames = latents[:, :0].float().reshape(latents.shape[0], 0, *size.tolist())
        width = max(owners.count(r) for r in range(processes))  # the gather takes parts of one shape
        padded = torch.cat([frames, frames.new_zeros(frames.shape[0], width - frames.shape[1], *frames.shape[2:])], 1)
        gathered = gather_from_processes(padded)  # [P, B, width, 3, H, W]
        columns = [owners[:k].count(r) for k, r in enumerate(owners)]
        return torch.stack([gathered[r, :, c] for r, c in zip(owners, columns)], dim=1)


def plan_anchor_decode(plan: MemoryPlan, decode: AnchorDecode, chunks: Sequence[AnchorChunk],
                       devices: Sequence[torch.device] | None = None, processes: int = 1
                       ) -> BatchedDecode | ChunkedDecode | AcrossDevicesDecode | AcrossProcessesDecode:
    """The anchor decode strategy of ``plan``: dealt over the ``processes`` of a
    ``run.context_parallel`` call when there are several (:class:`AcrossProcessesDecode`), else
    over ``devices`` when given (``None`` or empty: one device), else batched where the plan
    batches and checkpoints no chunk, else one call per chunk, checkpointed as the plan says."""
    if processes > 1:
        return AcrossProcessesDecode(lambda mine: plan_anchor_decode(plan, decode, mine, devices), list(chunks))
    if devices:
        return AcrossDevicesDecode(decode, devices, chunks, checkpointed=plan.chunk_checkpointing,
                                   batched=plan.batch_chunks and not plan.chunk_checkpointing)
    if plan.batch_chunks and not plan.chunk_checkpointing:
        return BatchedDecode(decode, chunks)
    return ChunkedDecode(decode, chunks, checkpointed=plan.chunk_checkpointing)
