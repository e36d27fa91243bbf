"""Anchor frame <-> latent chunk mapping for causal video VAEs, and the chunked anchor decode.

A causal video VAE with temporal compression ``r`` (CogVideoX, Wan, Hunyuan: ``r = 4``) maps
latent frame 0 to pixel frame 0 alone and latent ``k >= 1`` to pixel frames
``r(k-1)+1 ... rk``; ``L`` latents therefore decode to ``1 + r(L-1)`` frames.

Guidance only needs a few *anchor* frames, so instead of decoding the whole video it decodes, for
each anchor, a short causal chunk of latents that ends at the anchor's latent (``chunk_latents``
latents, 3 by default as in the paper's code). The VAE treats the first latent of a chunk as a
"first frame" (one pixel frame; the CogVideoX VAE only does so for an odd number of latents); the
anchor's latent, at the end of the chunk, gets its full ``r`` frames with ``chunk_latents - 1``
latents of causal context, so the anchor is picked counting from the chunk's last frame. Everything here is pure index
arithmetic except :func:`decode_anchor_frames`, which only needs ``vae.decode``, and
:func:`check_latents`, which looks at the caller's latents.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass

import torch
from torch import Tensor
from torch.utils.checkpoint import checkpoint


__all__ = ["AnchorChunk", "anchor_latent_chunks", "check_latents", "check_num_frames",
           "check_paired_latent_frames", "deal_spans", "decode_anchor_frames", "decode_anchor_frames_across",
           "decode_chunk", "latent_to_pixels", "pixel_to_latent", "vae_latent_channels"]


def check_num_frames(num_frames: int, temporal_compression: int) -> int:
    """Number of latent frames of a ``num_frames`` video; ValueError if the VAE cannot make it."""
    if temporal_compression < 1:
        raise ValueError(f"temporal_compression must be >= 1, got {temporal_compression}")
    if num_frames < 1 or (num_frames - 1) % temporal_compression != 0:
        raise ValueError(
            f"num_frames={num_frames} cannot be produced by a causal VAE with temporal compression "
            f"{temporal_compression}: it must be {temporal_compression}*k + 1 "
            f"(e.g. {temporal_compression * max(1, (num_frames - 1) // temporal_compression) + 1})"
        )
    return (num_frames - 1) // temporal_compression + 1


def check_paired_latent_frames(num_frames: int, temporal_compression: int) -> int:
    """:func:`check_num_frames` for a VAE that decodes latents in pairs (CogVideoX's): it keeps the
    causal first frame only when the latent count is odd, so an even count would decode to
    ``r * n`` frames instead of ``1 + r * (n - 1)``; the video needs ``2r k + 1`` frames."""
    step = 2 * temporal_compression
    if num_frames < 1 or (num_frames - 1) % step:
        nearest = step * max(1, round((num_frames - 1) / step)) + 1
        why = ""
        if num_frames > 1 and (num_frames - 1) % temporal_compression == 0:
            why = (f": {num_frames} frames are {(num_frames - 1) // temporal_compression + 1} latents, and from an even "
                   f"number of latents it decodes {num_frames + temporal_compression - 1} frames")
        raise ValueError(f"num_frames={num_frames} cannot be produced: the CogVideoX VAE makes {step}k+1 frames "
                         f"({temporal_compression}*k + 1 with an odd number of latents), e.g. {nearest} or 49{why}")
    return check_num_frames(num_frames, temporal_compression)


def check_latents(latents: object, shape: Sequence[int] | None, call: str) -> None:
    """A one-line ValueError unless the caller's ``latents`` (``None``: drawn from the generator)
    are finite and of ``shape``, the one the call makes (``None``: not known, not checked; ``call``
    says which call that is), TypeError for a non-tensor. Pipelines take given latents as they
    are: a wrong shape fails in the denoiser's first layer, a NaN comes out as an all-NaN video."""
    if latents is None:
        return
    if not isinstance(latents, Tensor):
        raise TypeError(f"latents must be a torch.Tensor, got {type(latents).__name__}")
    if shape is not None and tuple(latents.shape) != tuple(shape):
        raise ValueError(f"latents must have shape {list(shape)} (those of {call}), got {list(latents.shape)}")
    finite = torch.isfinite(latents)
    if not finite.all():
        raise ValueError(
            f"latents hold {int((~finite).sum())} NaN or infinite value(s) of {latents.numel()}: pass finite latents, "
            "or latents=None to draw them from the generator"
        )


def pixel_to_latent(frame: int, temporal_compression: int) -> int:
    """Latent frame whose decode produces pixel frame ``frame`` (0-based)."""
    if frame < 0:
        raise ValueError(f"frame index must be >= 0, got {frame}")
    return 0 if frame == 0 else (frame - 1) // temporal_compression + 1


def latent_to_pixels(latent: int, temporal_compression: int) -> range:
    """Pixel frames produced by latent frame ``latent`` (0-based)."""
    if latent < 0:
        raise ValueError(f"latent index must be >= 0, got {latent}")
    if latent == 0:
        return range(0, 1)
    return range(temporal_compression * (latent - 1) + 1, temporal_compression * latent + 1)


@dataclass(frozen=True)
class AnchorChunk:
    """Where one anchor frame comes from.

    Attributes:
        anchor: 0-based pixel frame index in the full video.
        latent: latent frame that produces it.
        start, stop: the causal chunk of latents ``[start, stop)`` decoded for it
            (``stop = latent + 1``).
        index_in_chunk: index of the anchor among the ``1 + r*(stop-start-1)`` frames of a causal
            decode of the chunk.
        from_end: position of the anchor counted from the chunk's last decoded frame (0 = last).
            The anchor's latent is the chunk's last, so its ``r`` frames are the last ``r`` decoded
            frames whatever the VAE does with the chunk's first latent; the decode uses this.
    """

    anchor: int
    latent: int
    start: int
    stop: int
    index_in_chunk: int
    from_end: int


def anchor_latent_chunks(
    anchors: Sequence[int],
    num_frames: int,
    temporal_compression: int = 4,
    chunk_latents: int = 3,
) -> list[AnchorChunk]:
    """Map anchor pixel frames to the causal latent chunks that decode them.

    Args:
        anchors: strictly increasing 0-based pixel frame indices, at least two, none in latent 0's
            group (frame 0), all ``< num_frames``.
        num_frames: frames of the decoded video (``r*k + 1``).
        temporal_compression: the VAE's ``r``.
        chunk_latents: latents per chunk, ending at the anchor's latent (clipped at latent 0).

    Returns:
        One :class:`AnchorChunk` per anchor, in order.

    Raises:
        ValueError: naming the problem (frame count, anchor range/order/count, chunk length).
    """
    num_latents = check_num_frames(num_frames, temporal_compression)
    anchors = [int(a) for a in anchors]
    if len(anchors) < 2:
        raise ValueError(f"guidance needs at least two anchor frames to form a pair, got anchors={anchors}")
    if any(b <= a for a, b in zip(anchors, anchors[1:])):
        raise ValueError(f"anchors must be strictly increasing, got {anchors}")
    first_group = list(latent_to_pixels(0, temporal_compression))
    bad = [a for a in anchors if not 0 <= a < num_frames]
    if bad:
        raise ValueError(
            f"anchors {bad} are out of range for a {num_frames}-frame video: set anchors (guidance.anchors) to "
            f"frames in {first_group[-1] + 1}..{num_frames - 1}, or to null (the paper's four, spread over the video)"
        )
    inside = [a for a in anchors if a in first_group]
    if inside:
        raise ValueError(
            f"anchors {inside} lie in latent 0's group (pixel frames {first_group}); a causal chunk cannot end "
            "there. Use anchors >= 1 (the paper uses 12, 24, 36, 48)."
        )
    if chunk_latents < 2:
        raise ValueError(
            f"chunk_latents must be >= 2 (the chunk's first latent decodes to a single frame), got {chunk_latents}"
        )
    chunks = []
    for anchor in anchors:
        latent = pixel_to_latent(anchor, temporal_compression)
        assert latent < num_latents
        start = max(0, latent - chunk_latents + 1)
        offset = anchor - latent_to_pixels(latent, temporal_compression).start
        decoded = 1 + temporal_compression * (latent - start)
        index = decoded - temporal_compression + offset
        chunks.append(
            AnchorChunk(anchor=anchor, latent=latent, start=start, stop=latent + 1, index_in_chunk=index, from_end=decoded - 1 - index)
        )
    return chunks


def decode_chunk(vae, latents: Tensor, scaling_factor: float) -> Tensor:
    """Decode ``latents [B, F, C, h, w]`` (diffusers CogVideoX layout) to ``[B, T, 3, H, W]`` in [0, 1]."""
    param = next(vae.parameters(), None)
    dtype = param.dtype if param is not None else latents.dtype
    z = latents.permute(0, 2, 1, 3, 4).to(dtype) / scaling_factor
    video = vae.decode(z).sample  # [B, 3, T, H, W] in [-1, 1]
    return (video.float() / 2 + 0.5).clamp(0, 1).permute(0, 2, 1, 3, 4)


def chunk_spans(latents: Tensor, chunks: Sequence[AnchorChunk]) -> list[tuple[int, int]]:
    """The distinct ``(start, stop)`` latent spans of ``chunks``, in order, after checking that
    there are chunks and that ``latents [B, F, C, h, w]`` hold every latent they need."""
    if len(chunks) == 0:
        raise ValueError("chunks must not be empty")
    num_latents = latents.shape[1]
    for chunk in chunks:
        if chunk.stop > num_latents:
            raise ValueError(f"anchor {chunk.anchor} needs latent {chunk.latent} but latents has only {num_latents}")
    return sorted({(chunk.start, chunk.stop) for chunk in chunks})


def deal_spans(spans: Sequence[tuple[int, int]], decoders: int) -> dict[tuple[int, int], int]:
    """Who decodes each of ``spans`` (in order) among ``decoders`` devices or processes: span
    ``k`` goes to ``k mod decoders``, round-robin."""
    return {span: k % decoders for k, span in enumerate(spans)}


def decode_anchor_frames(
    decode: Callable[[Tensor], Tensor],
    latents: Tensor,
    chunks: Sequence[AnchorChunk],
    checkpoint_chunks: bool = False,
    batch_chunks: bool = True,
) -> Tensor:
    """Decode only the anchor frames, each from its causal chunk, through a frozen VAE.

    Chunks shared by several anchors are decoded once. By default chunks of the same length are
    stacked along the batch and decoded in one call (the paper's anchors give four chunks of
    three latents: one call instead of four), which is fastest; batching is exact for the VAEs
    supported here, which normalise and convolve each video separately. But a differentiated
    decode keeps every activation of every chunk until the backward: for the CogVideoX-5B VAE at
    480x720 that is far more than a GPU holds (see docs/performance.md). ``checkpoint_chunks``
    decodes one chunk per call, each in its own checkpointed region: the forward keeps only the
    chunk's latents, and the backward re-decodes the chunks one at a time (autograd finishes the
    last-created region before it starts the previous one), for one extra forward decode per
    chunk.

    Args:
        decode: ``latents [N, F', C, h, w] -> frames [N, T, 3, H, W]`` in ``[0, 1]``, treating
            the ``N`` videos of a batch independently: :func:`decode_chunk` of a CogVideoX VAE
            (``functools.partial(decode_chunk, vae, scaling_factor=...)``), or a pipeline
            adapter's decode for other layouts.
        latents: ``[B, F, C, h, w]`` clean-latent estimate (differentiable).
        chunks: from :func:`anchor_latent_chunks`.
        checkpoint_chunks: one checkpointed decode per chunk when gradients are enabled
            (memory of one chunk's decode instead of all of them; one more forward each).
        batch_chunks: otherwise, decode chunks of the same length in one call (``False``: one call
            per chunk, as the checkpointed decode makes them: the same numbers to the last bit,
            where a batched convolution may round differently).

    Returns:
        ``[B, S, 3, H, W]`` fp32 frames in ``[0, 1]``, one per chunk, in order.
    """
    spans = chunk_spans(latents, chunks)
    batch = latents.shape[0]
    decoded: dict[tuple[int, int], Tensor] = {}
    if checkpoint_chunks and torch.is_grad_enabled():
        for start, stop in spans:
            decoded[(start, stop)] = checkpoint(decode, latents[:, start:stop], use_reentrant=False)
    elif not batch_chunks:
        for start, stop in spans:
            decoded[(start, stop)] = decode(latents[:, start:stop])
    else:
        for length in sorted({stop - start for start, stop in spans}):
            group = [span for span in spans if span[1] - span[0] == length]
            video = decode(torch.cat([latents[:, start:stop] for start, stop in group]))  # [len(group)*B, T, 3, H, W]
            decoded.update(zip(group, video.unflatten(0, (len(group), batch))))
    frames = []
    for chunk in chunks:
        video = decoded[(chunk.start, chunk.stop)]
        if chunk.from_end >= video.shape[1]:
            raise ValueError(
                f"decoding latents [{chunk.start}, {chunk.stop}) gave {video.shape[1]} frames, expected at least "
                f"{chunk.from_end + 1}: is the VAE causal with the configured temporal compression?"
            )
        frames.append(video[:, video.shape[1] - 1 - chunk.from_end])
    return torch.stack(frames, dim=1).float()


def decode_anchor_frames_across(
    placed: Sequence[tuple[torch.device, Callable[[Tensor], Tensor]]],
    latents: Tensor,
    chunks: Sequence[AnchorChunk],
    checkpoint_chunks: bool = False,
    batch_chunks: bool = False,
) -> Tensor:
    """:func:`decode_anchor_frames` with the chunks dealt round-robin over several devices.

    Chunk span ``k`` (in order) is decoded by ``placed[k mod N]``: its latents go to that device,
    its decode (that device's replica of the decoder) runs there, and only its anchor frames come
    back to ``latents``' device. Each span is one decode call (checkpointed with
    ``checkpoint_chunks`` when gradients are enabled); with ``batch_chunks`` the calls are those of
    :func:`decode_anchor_frames` on one device, the spans of one length batched, and the devices
    take whole batches in turn. Either way every call is the one device's call, so the frames are
    one device's to the last bit on devices of one kind (a batch of another size can round
    differently).

    Args:
        placed: ``(device, decode)`` pairs, ``decode`` as in :func:`decode_anchor_frames`, with a
            decoder that lives on ``device``.
        latents: ``[B, F, C, h, w]`` clean-latent estimate (differentiable).
        chunks: from :func:`anchor_latent_chunks`.
        checkpoint_chunks: one checkpointed region per span.
        batch_chunks: the spans of one length in one call (without ``checkpoint_chunks``), a batch per
            device in turn.

    Returns:
        ``[B, S, 3, H, W]`` fp32 frames in ``[0, 1]`` on ``latents``' device, one per chunk, in order.
    """
    if len(placed) == 0:
        raise ValueError("placed must hold at least one (device, decode) pair")
    spans, home, batch = chunk_spans(latents, chunks), latents.device, latents.shape[0]
    ends = {span: sorted({chunk.from_end for chunk in chunks if (chunk.start, chunk.stop) == span}) for span in spans}
    # the calls: (device index, the spans it decodes together)
    if batch_chunks and not checkpoint_chunks:
        lengths = sorted({stop - start for start, stop in spans})
        calls = [(k % len(placed), [span for span in spans if span[1] - span[0] == length])
                 for k, length in enumerate(lengths)]
    else:
        calls = [(d, [span]) for span, d in deal_spans(spans, len(placed)).items()]
    picked: dict[tuple[tuple[int, int], int], Tensor] = {}
    for d, group in calls:
        device, decode = placed[d]

        def anchors_of(part: Tensor, decode=decode, device=device, group=group) -> Tensor:
            video = decode(part.to(device, non_blocking=True))  # [len(group) * B, T, 3, H, W]
            needed = max(end for span in group for end in ends[span])
            if needed >= video.shape[1]:
                raise ValueError(f"decoding a chunk gave {video.shape[1]} frames, expected at least {needed + 1}: "
                                 "is the VAE causal with the configured temporal compression?")
            last = video.shape[1] - 1
            frames = torch.cat([video[g * batch:(g + 1) * batch, [last - end for end in ends[span]]]
                                for g, span in enumerate(group)], dim=1)
            return frames.to(home, non_blocking=True)  # only the anchor frames travel: [B, anchors, 3, H, W]

        part = torch.cat([latents[:, start:stop] for start, stop in group])
        frames = (checkpoint(anchors_of, part, use_reentrant=False) if checkpoint_chunks and torch.is_grad_enabled()
                  else anchors_of(part))
        columns = iter(range(frames.shape[1]))
        picked.update({(span, end): frames[:, next(columns)] for span in group for end in ends[span]})
    return torch.stack([picked[((chunk.start, chunk.stop), chunk.from_end)] for chunk in chunks], dim=1).float()


def vae_latent_channels(vae: torch.nn.Module) -> int | None:
    """Channels of the latents ``vae`` decodes (its config's ``z_dim`` for Wan's), or None."""
    return getattr(vae.config, "latent_channels", None) or getattr(vae.config, "z_dim", None)
