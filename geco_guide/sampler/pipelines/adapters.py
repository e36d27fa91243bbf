"""Per-family knowledge GeCo guidance needs to steer a stock diffusers video pipeline.

A :class:`PipelineAdapter` knows, for one family of pipelines:

- which modules are the denoisers (whose calls the hook captures and replays),
- the frame geometry of a call (from the arguments of ``pipe.prepare_latents``): frames of the
  output video, latent frames, front padding, latent height/width,
- how the latents the scheduler steps are laid out, and how to bring a clean estimate to the
  frames-first layout ``[B, F, C, h, w]`` that :mod:`.slicing` cuts into causal chunks,
- how to de-normalise and decode such a chunk into frames ``[B, T, 3, H, W]`` in ``[0, 1]``,
- how the denoiser outputs of one step combine into the model output the scheduler gets
  (default: a linear combination fitted to the captured outputs, which covers CFG in one
  batched call, CFG in two calls, dynamic CFG and no CFG; LTX adds ``guidance_rescale``,
  HunyuanVideo 1.5 combines through its guider, LTX-2 on clean estimates).

The noise parametrisation is a property of the scheduler, not the family: see
:func:`noise_levels` (v-prediction DDIM/DPM tables for CogVideoX, flow-matching ``sigmas`` for
Wan, HunyuanVideo and LTX-Video), and :func:`~geco_guide.sampler.algorithm.levels.keep_update` for multistep schedulers whose history
would otherwise discard a change of the sample (UniPC's corrector).

The cost model traces a step of a stock pipeline through its adapter too (:meth:`PipelineAdapter.traced_prediction`).

Each registry entry (:mod:`geco_guide.families`) names its adapter (:data:`ADAPTERS`), registered for
its pipeline class. New families: a :class:`PipelineAdapter` subclass in :data:`ADAPTERS`, named by
the entry; out of tree, ``register_adapter(PipelineClass, adapter)``.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, replace
from typing import Any

import torch
from torch import Tensor, nn

from ...families import MODELS, VideoModel
from ..algorithm.levels import FlowLevels, NoiseLevels, VPLevels
from ..algorithm.slicing import decode_chunk, vae_latent_channels
from ..diffusers_private import (cache_config, context_parallel_plan, denormalize_ltx_latents, guidance_rescale,
                                unpack_ltx_latents)

__all__ = ["ADAPTERS", "TRACED_TIMESTEP", "CallGeometry", "CogVideoXAdapter", "HunyuanVideo15Adapter", "HunyuanVideoAdapter", "LTX2Adapter", "LTXAdapter",
           "PipelineAdapter", "WanAdapter", "adapter_for", "adapter_for_class", "check_no_denoiser_cache",
           "check_requested_frames", "check_scheduler", "fit_combination", "noise_levels",
           "register_adapter"]


@dataclass(frozen=True)
class CallGeometry:
    """Frame geometry of one pipeline call.

    Attributes:
        num_frames: frames of the decoded output video (what anchors index).
        num_latents: latent frames that decode to it (without padding).
        pad: latent frames the pipeline adds in front (CogVideoX 1.5) and drops before decoding.
        latent_height, latent_width: spatial size of the latents (before any transformer patching).
        temporal_compression: the VAE's ``r``.
        requested_frames: the ``num_frames`` the call asked for, where the pipeline hands it to
            ``prepare_latents`` as asked (HunyuanVideo 1.5, LTX-2: they make ``num_frames`` frames
            only when it is ``r k + 1``, and fewer otherwise, silently); ``None`` where it is not
            known or the pipeline rounded it already (Wan, with a warning).
    """

    num_frames: int
    num_latents: int
    pad: int
    latent_height: int
    latent_width: int
    temporal_compression: int
    requested_frames: int | None = None


def _to_unit(video: Tensor) -> Tensor:
    """``[B, 3, T, H, W]`` in ``[-1, 1]`` -> fp32 ``[B, T, 3, H, W]`` in ``[0, 1]``."""
    return (video.float() / 2 + 0.5).clamp(0, 1).permute(0, 2, 1, 3, 4)


def _module_dtype(module: nn.Module, fallback: torch.dtype) -> torch.dtype:
    param = next(module.parameters(), None)
    return param.dtype if param is not None else fallback


TRACED_TIMESTEP = 1000.0  # of a traced step (the first of a flow-matching schedule): no cost depends on it


def _cfg(uncond: Tensor, cond: Tensor, scale: float) -> Tensor:
    """The CFG combination in fp32: ``uncond + scale (cond - uncond)``."""
    uncond = uncond.float()
    return uncond + scale * (cond.float() - uncond)


class PipelineAdapter:
    """Base adapter: latents ``[B, C, F, h, w]`` (channels first), no padding, plain VAE decode."""

    #: shown in messages
    name = "pipeline"

    def denoisers(self, pipe) -> list[nn.Module]:
        """The denoiser modules whose calls are captured (``transformer``, Wan 2.2's ``transformer_2``)."""
        return [m for m in (getattr(pipe, "transformer", None), getattr(pipe, "transformer_2", None)) if m is not None]

    def frozen_modules(self, pipe) -> list[Any]:
        """Modules frozen (``requires_grad=False``) while guidance differentiates."""
        return [*self.denoisers(pipe), pipe.vae]

    def temporal_compression(self, pipe) -> int:
        return int(pipe.vae_scale_factor_temporal)

    def spatial_compression(self, pipe) -> int:
        """Pixels per latent of ``pipe``'s VAE, each way."""
        return int(pipe.vae_scale_factor_spatial)

    def call_geometry(self, pipe, args: dict[str, Any], latents: Tensor) -> CallGeometry:
        """Geometry of a call from ``prepare_latents``' bound arguments and the latents it returned."""
        r = self.temporal_compression(pipe)
        num_latents = latents.shape[2]
        return CallGeometry(1 + r * (num_latents - 1), num_latents, 0, latents.shape[-2], latents.shape[-1], r)

    def check(self, pipe, geometry: CallGeometry) -> None:
        """Extra up-front checks of a call (ValueError naming the problem)."""

    def latents_shape(self, pipe, args: dict[str, Any]) -> tuple[int, ...] | None:
        """The shape of the latents ``prepare_latents`` makes for its bound ``args`` (what latents the
        caller passes must have), or None where the adapter does not know it."""
        return None

    def frames_first(self, pipe, x0: Tensor, geometry: CallGeometry) -> Tensor:
        """Scheduler-layout clean latents -> ``[B, F, C, h, w]`` without padding (differentiable)."""
        return x0.permute(0, 2, 1, 3, 4)

    def decode(self, pipe, latents: Tensor) -> Tensor:
        """Decode a chunk ``[B, F', C, h, w]`` to frames ``[B, T, 3, H, W]`` in ``[0, 1]`` (differentiable)."""
        z = self.denormalize(pipe, latents.permute(0, 2, 1, 3, 4).float())
        return _to_unit(pipe.vae.decode(z.to(_module_dtype(pipe.vae, z.dtype))).sample)

    def denormalize(self, pipe, z: Tensor) -> Tensor:
        """Model latents ``[B, C, F, h, w]`` -> what ``vae.decode`` takes."""
        return z / pipe.vae.config.scaling_factor

    def combine(self, pipe, parts: list[Tensor], weights: Tensor, *, sample: Tensor, step: int) -> Tensor:
        """The model output from the outputs of one step's denoiser calls (fp32), given the weights
        fitted on the captured outputs (:func:`fit_combination`), the ``sample`` the calls saw (the
        scheduler's layout) and the step's index in the call (``step``; what LTX-2's combination,
        made on clean estimates, needs)."""
        out = weights[0].item() * parts[0].float()
        for w, p in zip(weights[1:], parts[1:]):
            out = out + w.item() * p.float()
        return out

    #: why the family's denoiser cannot run under ``run.context_parallel`` (one line), or None
    context_parallel_refusal: str | None = None

    def context_parallel_plan(self, denoiser: nn.Module) -> dict[str, Any] | None:
        """How ``run.context_parallel`` splits ``denoiser``'s token sequence over the processes and
        gathers it back (a diffusers ``ContextParallelModelPlan``): the denoiser's own ``_cp_plan``
        (diffusers writes one for Wan, LTX-Video and LTX-2), None where it has none."""
        return context_parallel_plan(denoiser)

    def prepare_context_parallel(self, denoiser: nn.Module) -> None:
        """What ``denoiser`` needs before diffusers' context parallelism is enabled on it: nothing
        where its attention processors dispatch through diffusers' attention already."""

    def finish_context_parallel(self, denoiser: nn.Module) -> None:
        """What ``denoiser`` needs after diffusers' context parallelism is enabled on it (hooks that
        wrap diffusers' own): nothing by default."""

    def traced_prediction(self, pipe, model: VideoModel, latents: Tensor, text_shape: tuple[int, ...],
                          dtype: torch.dtype) -> Callable[[Tensor, bool], Tensor]:
        """``(z, differentiate) -> model output`` (fp32) of the first step of a call of ``model``'s
        stock ``pipe`` on ``latents`` ``[1, C, F, h, w]`` (fake or real weights): the step's denoiser
        calls as the pipeline makes them (text embeddings ``text_shape``, in ``dtype``), combined
        with its CFG, for the cost model's trace. ValueError (one line) where the family has none."""
        raise ValueError(f"the cost model has no denoiser step for {model.pipeline} ({model.name})")

    def traced_sample(self, latents: Tensor) -> Tensor:
        """``[B, C, F, h, w]`` latents as the pipeline's scheduler steps them."""
        return latents


class CogVideoXAdapter(PipelineAdapter):
    """``CogVideoXPipeline`` and ``CogVideoXImageToVideoPipeline`` (1.0 and 1.5).

    Latents ``[B, F, C, h, w]``, v-prediction on a VP schedule. CogVideoX 1.5 (``patch_size_t=2``)
    pads the latent frames at the front to a multiple of ``patch_size_t`` and drops the padding
    before decoding. The pipeline does not expose the unpadded count, so the adapter takes the
    odd count below the padded one: the only kind the CogVideoX VAE decodes into ``4k+1`` frames
    (and the only kind guidance accepts, as ``GeCoCogVideoXPipeline``). The image-to-video
    variant concatenates image latents to the denoiser input along channels; the hook replaces
    only the latent channels.
    """

    name = "CogVideoX"

    def frozen_modules(self, pipe):
        return [pipe.transformer, pipe.vae]

    def call_geometry(self, pipe, args, latents):
        r = self.temporal_compression(pipe)
        padded = latents.shape[1]
        patch_t = pipe.transformer.config.patch_size_t
        pad = 0
        if patch_t is not None and patch_t > 1:
            pad = next(p for p in range(patch_t) if (padded - p) % 2 == 1) if padded > 1 else 0
        num_latents = padded - pad
        return CallGeometry(1 + r * (num_latents - 1), num_latents, pad, latents.shape[-2], latents.shape[-1], r)

    def check(self, pipe, geometry):
        if geometry.num_latents % 2 == 0 and getattr(pipe.vae, "num_latent_frames_batch_size", None) == 2:
            r = geometry.temporal_compression
            raise ValueError(
                f"{geometry.num_latents} latent frames: the CogVideoX VAE cannot make a 4k+1-frame video from an even "
                f"number of latents (it decodes them to {r * geometry.num_latents} frames). "
                f"Use {2 * r}k+1 frames, e.g. 49."
            )

    def latents_shape(self, pipe, args):
        if "image" in args:  # image-to-video: its own frame count and padding rule
            return None
        s = pipe.vae_scale_factor_spatial
        frames = (int(args["num_frames"]) - 1) // self.temporal_compression(pipe) + 1  # padded already (1.5)
        return (int(args["batch_size"]), frames, int(args["num_channels_latents"]), int(args["height"]) // s,
                int(args["width"]) // s)

    def frames_first(self, pipe, x0, geometry):
        return x0[:, geometry.pad :]

    def decode(self, pipe, latents):
        # as CogVideoXPipeline.decode_latents: divide by the scaling factor, decode (also for
        # the 1.5 I2V models with invert_scale_latents, whose decode path is the same)
        return decode_chunk(pipe.vae, latents, pipe.vae_scaling_factor_image)

    def context_parallel_plan(self, denoiser):
        """CogVideoX's plan, written as diffusers writes ``_cp_plan``: the video and text tokens
        split where the first block takes them (after the patch embedding, which sees the whole
        video), the video tokens gathered after ``proj_out`` (the unpatchify needs all of them).
        The attention, :class:`~.split_attention.CogVideoXContextParallelAttention`, takes its shard of the rotary
        tables itself, and :class:`~.split_attention.PaddedTokens` pads the tokens to equal shards where they do not
        divide (the 49x480x720 call's 226 + 17,550 over 4 processes)."""
        from diffusers.models._modeling_parallel import ContextParallelInput, ContextParallelOutput

        tokens = ContextParallelInput(split_dim=1, expected_dims=3)
        return {
            "transformer_blocks.0": {"hidden_states": tokens, "encoder_hidden_states": tokens},
            "proj_out": ContextParallelOutput(gather_dim=1, expected_dims=3),
        }

    def prepare_context_parallel(self, denoiser):
        from ..running.split_attention import CogVideoXContextParallelAttention

        denoiser.set_attn_processor(CogVideoXContextParallelAttention())

    def finish_context_parallel(self, denoiser):
        # registered after diffusers' hooks, which they then wrap: the padding before the split,
        # the cut after the gather
        from ..running.module_hooks import register_hook
        from ..running.split_attention import PADDED_TOKENS_HOOK, PaddedTokens

        padding = PaddedTokens(denoiser.transformer_blocks[0].attn1.processor)
        register_hook(denoiser.transformer_blocks[0], padding, PADDED_TOKENS_HOOK)
        register_hook(denoiser.proj_out, padding.cut, PADDED_TOKENS_HOOK)


def _channels_first_shape(pipe, args: dict[str, Any], temporal_compression: int) -> tuple[int, ...]:
    """``[B, C, F, h, w]`` of the ``prepare_latents`` of Wan and HunyuanVideo for its bound ``args``."""
    s = pipe.vae_scale_factor_spatial
    frames = (int(args["num_frames"]) - 1) // temporal_compression + 1
    return (int(args["batch_size"]), int(args["num_channels_latents"]), frames, int(args["height"]) // s,
            int(args["width"]) // s)


class WanAdapter(PipelineAdapter):
    """``WanPipeline``: latents ``[B, C, F, h, w]``, flow matching, CFG as two calls, per-channel
    ``latents_mean/std`` (decode input ``z * std + mean``); Wan 2.2's ``transformer_2`` is hooked too."""

    name = "Wan"

    def latents_shape(self, pipe, args):
        return _channels_first_shape(pipe, args, self.temporal_compression(pipe))

    def denormalize(self, pipe, z):
        cfg = pipe.vae.config
        mean = torch.tensor(cfg.latents_mean, dtype=z.dtype, device=z.device).view(1, -1, 1, 1, 1)
        std = torch.tensor(cfg.latents_std, dtype=z.dtype, device=z.device).view(1, -1, 1, 1, 1)
        return z * std + mean

    def traced_prediction(self, pipe, model, latents, text_shape, dtype):
        """Two calls a step (text, then empty prompt), timesteps per token with ``expand_timesteps``
        (Wan 2.2 TI2V-5B). Wan 2.2 A14B steps its high-noise expert first: the two experts share
        one config, so the trace's calls are either's."""
        embeds = [torch.empty(text_shape, dtype=dtype) for _ in range(2)]
        patch = pipe.transformer.config.patch_size
        tokens = latents.shape[2] // patch[0] * (latents.shape[3] // patch[1]) * (latents.shape[4] // patch[2])
        expand = pipe.config.get("expand_timesteps", False)
        timestep = torch.full((1, tokens) if expand else (1,), TRACED_TIMESTEP)
        scale = model.call["guidance_scale"]

        def predict(z: Tensor, differentiate: bool) -> Tensor:
            with torch.set_grad_enabled(differentiate and torch.is_grad_enabled()):
                x = z.to(dtype)
                cond, uncond = (pipe.transformer(hidden_states=x, timestep=timestep, encoder_hidden_states=e,
                                                 return_dict=False)[0] for e in embeds)
                return _cfg(uncond, cond, scale)

        return predict


class HunyuanVideoAdapter(PipelineAdapter):
    """``HunyuanVideoPipeline``: latents ``[B, C, F, h, w]``, flow matching, the distilled guidance
    embedding in one call (true CFG, when on, as a second call); decode input ``z / scaling_factor``."""

    name = "HunyuanVideo"

    def latents_shape(self, pipe, args):
        return _channels_first_shape(pipe, args, self.temporal_compression(pipe))

    def traced_prediction(self, pipe, model, latents, text_shape, dtype):
        """Guidance-distilled: one call a step with the guidance scale as an input (``true_cfg_scale``
        1 by default: no negative call), a pooled text embedding and a text mask."""
        embeds = torch.empty(text_shape, dtype=dtype)
        mask = torch.ones(text_shape[:2], dtype=torch.long)
        pooled = torch.empty(1, pipe.transformer.config.pooled_projection_dim, dtype=dtype)
        guidance = torch.full((1,), model.call["guidance_scale"] * 1000.0, dtype=dtype)
        timestep = torch.full((1,), TRACED_TIMESTEP)

        def predict(z: Tensor, differentiate: bool) -> Tensor:
            with torch.set_grad_enabled(differentiate and torch.is_grad_enabled()):
                return pipe.transformer(hidden_states=z.to(dtype), timestep=timestep.to(z.dtype),
                                        encoder_hidden_states=embeds, encoder_attention_mask=mask,
                                        pooled_projections=pooled, guidance=guidance, return_dict=False)[0].float()

        return predict

    def context_parallel_plan(self, denoiser):
        """HunyuanVideo's plan, written as diffusers writes ``_cp_plan``: the rotary tables of the
        video tokens split as ``rope`` makes them, the video and text tokens split where the first
        dual-stream block takes them (after the embedders and the token refiner, which see the whole
        sequence), the video tokens gathered after ``proj_out``. The text mask of the whole
        sequence that every block takes is made the process's own by :class:`~.split_attention.ShardedJointMask`."""
        from diffusers.models._modeling_parallel import ContextParallelInput, ContextParallelOutput

        tokens = ContextParallelInput(split_dim=1, expected_dims=3)
        rotary = ContextParallelInput(split_dim=0, expected_dims=2, split_output=True)
        return {
            "rope": {0: rotary, 1: rotary},
            "transformer_blocks.0": {"hidden_states": tokens, "encoder_hidden_states": tokens},
            "proj_out": ContextParallelOutput(gather_dim=1, expected_dims=3),
        }

    def prepare_context_parallel(self, denoiser):
        # registered before diffusers' split hooks, which then wrap them: the blocks' tokens are
        # the process's shards when the mask is cut to them
        from ..running.module_hooks import register_hook
        from ..running.split_attention import SHARDED_MASK_HOOK, ShardedJointMask

        for block in [*denoiser.transformer_blocks, *denoiser.single_transformer_blocks]:
            register_hook(block, ShardedJointMask(), SHARDED_MASK_HOOK)


class LTXAdapter(PipelineAdapter):
    """``LTXPipeline``: packed latent tokens ``[B, S, C]``, flow matching with dynamic shifting,
    per-channel ``latents_mean/std``; the VAE has ``r = 8`` and a non-causal decoder (the anchor's
    chunk still ends at its latent). For a timestep-conditioned VAE the chunk is decoded at
    timestep 0 without decode noise (deterministic). CFG in one batched call, with
    ``guidance_rescale`` applied as the pipeline does."""

    name = "LTX-Video"

    def context_parallel_plan(self, denoiser):
        """LTX-Video's plan, written as diffusers writes ``_cp_plan``: the video tokens split at the
        denoiser's input, their rotary tables as ``rope`` makes them, the video tokens gathered after
        ``proj_out``. The text stays whole on every process, as Wan's: the cross-attention of each
        process's video tokens to the whole text is its own (:func:`~.split_attention.attend_within_process`), so
        neither the text's length nor its mask (repeated for every head by the stock attention)
        meets the split. (diffusers' own plan splits the text, which its attention cannot take.)"""
        from diffusers.models._modeling_parallel import ContextParallelInput, ContextParallelOutput

        rotary = ContextParallelInput(split_dim=1, expected_dims=3, split_output=True)
        return {
            "": {"hidden_states": ContextParallelInput(split_dim=1, expected_dims=3, split_output=False)},
            "rope": {0: rotary, 1: rotary},
            "proj_out": ContextParallelOutput(gather_dim=1, expected_dims=3),
        }

    def finish_context_parallel(self, denoiser):
        from ..running.split_attention import attend_within_process

        attend_within_process(denoiser, lambda name: not name.endswith(".attn1"))

    def temporal_compression(self, pipe):
        return int(pipe.vae_temporal_compression_ratio)

    def spatial_compression(self, pipe):
        return int(pipe.vae_spatial_compression_ratio)

    def traced_prediction(self, pipe, model, latents, text_shape, dtype):
        """One call of the unconditional and conditional halves as a batch of two, on the packed
        latent tokens, with the latent grid's size and the rope scale of the frame rate."""
        embeds = torch.empty(2, *text_shape[1:], dtype=dtype)
        mask = torch.ones(2, text_shape[1], dtype=torch.long)
        timestep = torch.full((2,), TRACED_TIMESTEP)
        frames, height, width = latents.shape[2:]
        r, s = model.temporal_compression, model.spatial_compression
        rope_scale = (r / model.fps, s, s)
        scale = model.call["guidance_scale"]

        def predict(z: Tensor, differentiate: bool) -> Tensor:
            with torch.set_grad_enabled(differentiate and torch.is_grad_enabled()):
                x = torch.cat([z] * 2).to(dtype)
                out = pipe.transformer(hidden_states=x, encoder_hidden_states=embeds, timestep=timestep,
                                       encoder_attention_mask=mask, num_frames=frames, height=height, width=width,
                                       rope_interpolation_scale=rope_scale, return_dict=False)[0]
                uncond, cond = out.chunk(2)
                return _cfg(uncond, cond, scale)

        return predict

    def traced_sample(self, latents):
        """The tokens of ``[B, C, F, h, w]`` latents with patch size 1: ``[B, F h w, C]``."""
        return latents.flatten(2).transpose(1, 2)

    def call_geometry(self, pipe, args, latents):
        r = self.temporal_compression(pipe)
        num_latents = (int(args["num_frames"]) - 1) // r + 1
        s = pipe.vae_spatial_compression_ratio
        height, width = int(args["height"]) // s, int(args["width"]) // s
        return CallGeometry(1 + r * (num_latents - 1), num_latents, 0, height, width, r)

    def frames_first(self, pipe, x0, geometry):
        z = unpack_ltx_latents(pipe, x0, geometry.num_latents, geometry.latent_height, geometry.latent_width)
        return z.permute(0, 2, 1, 3, 4)

    def denormalize(self, pipe, z):
        return denormalize_ltx_latents(pipe, z)

    def decode(self, pipe, latents):
        z = self.denormalize(pipe, latents.permute(0, 2, 1, 3, 4).float())
        z = z.to(_module_dtype(pipe.vae, z.dtype))
        temb = None
        if pipe.vae.config.timestep_conditioning:  # decode timestep 0, no decode noise
            temb = torch.zeros(z.shape[0], device=z.device, dtype=z.dtype)
        return _to_unit(pipe.vae.decode(z, temb).sample)

    def combine(self, pipe, parts, weights, *, sample, step):
        rescale = guidance_rescale(pipe)
        if rescale > 0 and len(parts) == 2:  # not linear: CFG as the pipeline does, then the rescale
            from diffusers.pipelines.ltx.pipeline_ltx import rescale_noise_cfg

            uncond, text = parts[0].float(), parts[1].float()
            out = uncond + pipe.guidance_scale * (text - uncond)
            return rescale_noise_cfg(out, text, guidance_rescale=rescale)
        return super().combine(pipe, parts, weights, sample=sample, step=step)


def check_requested_frames(geometry: CallGeometry, vae: str) -> None:
    """One-line ValueError when the call asked for a frame count the ``vae`` cannot make
    (``geometry.requested_frames`` not ``r k + 1``): the pipeline would silently make fewer frames
    than asked, and the anchors would index a shorter video than the one the caller counted."""
    asked, r = geometry.requested_frames, geometry.temporal_compression
    if asked is None or asked == geometry.num_frames:
        return
    raise ValueError(
        f"num_frames={asked} cannot be made by the {vae} VAE: it makes {r}k+1 frames (temporal compression {r}), so "
        f"this call would make {geometry.num_frames}. Ask for num_frames={geometry.num_frames} or "
        f"{geometry.num_frames + r}"
    )


class HunyuanVideo15Adapter(PipelineAdapter):
    """``HunyuanVideo15Pipeline`` and ``HunyuanVideo15ImageToVideoPipeline``: latents ``[B, C, F,
    h, w]`` (32 channels), flow matching; the denoiser sees the latents with the image-condition
    latents and their mask concatenated along channels (zeros for text-to-video; the hook replaces
    only the latent channels); decode input ``z / scaling_factor`` through the causal
    ``AutoencoderKLHunyuanVideo15`` (``r = 4``, 16x spatial). CFG comes from the pipeline's
    guider: with diffusers' ``ClassifierFreeGuidance`` the step's output is rebuilt by the guider
    itself (so its ``guidance_rescale`` and CFG window hold); other guiders get the fitted
    linear combination, checked against the pipeline's output."""

    name = "HunyuanVideo 1.5"

    def context_parallel_plan(self, denoiser):
        """HunyuanVideo 1.5's plan (diffusers writes none), as diffusers writes ``_cp_plan``: the
        video's rotary tables split as ``rope`` makes them, its tokens where the first block takes
        them (after the embedders, which see the whole video), gathered after ``proj_out``. The text
        stays whole on every process (its length varies with the prompt), seen as keys once
        (:class:`~.split_attention.HunyuanVideo15ContextParallelAttention`)."""
        from diffusers.models._modeling_parallel import ContextParallelInput, ContextParallelOutput

        rotary = ContextParallelInput(split_dim=0, expected_dims=2, split_output=True)
        return {
            "rope": {0: rotary, 1: rotary},
            "transformer_blocks.0": {"hidden_states": ContextParallelInput(split_dim=1, expected_dims=3)},
            "proj_out": ContextParallelOutput(gather_dim=1, expected_dims=3),
        }

    def prepare_context_parallel(self, denoiser):
        from ..running.split_attention import HunyuanVideo15ContextParallelAttention

        for block in denoiser.transformer_blocks:
            block.attn.set_processor(HunyuanVideo15ContextParallelAttention())

    def finish_context_parallel(self, denoiser):  # the token refiner's attention: the whole text
        from ..running.split_attention import attend_within_process

        attend_within_process(denoiser, lambda name: not name.startswith("transformer_blocks."))

    def call_geometry(self, pipe, args, latents):
        return replace(super().call_geometry(pipe, args, latents), requested_frames=int(args["num_frames"]))

    def check(self, pipe, geometry):
        check_requested_frames(geometry, self.name)

    def latents_shape(self, pipe, args):
        return _channels_first_shape(pipe, args, self.temporal_compression(pipe))

    def decode(self, pipe, latents):
        # the VAE's mid-block attention masks a batch of one only (diffusers 0.42: a batch of
        # several chunks fails to broadcast), so each chunk of a batched anchor decode is its own call
        return torch.cat([super(HunyuanVideo15Adapter, self).decode(pipe, chunk) for chunk in latents.split(1)])

    def combine(self, pipe, parts, weights, *, sample, step):
        from diffusers.guiders import ClassifierFreeGuidance

        guider = getattr(pipe, "guider", None)
        if type(guider) is not ClassifierFreeGuidance or len(parts) > 2:
            return super().combine(pipe, parts, weights, sample=sample, step=step)
        # the guider runs its conditional batch first, then the unconditional one (when CFG is on
        # at this step: its state is the step's, set by the pipeline before the denoiser calls)
        return guider.forward(*[part.float() for part in parts]).pred


def _ltx2_flags(pipe) -> tuple[bool, bool, bool]:
    """Which extra denoiser calls an ``LTX2Pipeline`` step makes: CFG (the call is batched
    ``[uncond, cond]``), spatio-temporal guidance, modality isolation; as the pipeline decides
    them (audio's scales count: the video and audio streams share every call)."""
    return (bool(pipe.do_classifier_free_guidance), bool(pipe.do_spatio_temporal_guidance),
            bool(pipe.do_modality_isolation_guidance))


class LTX2Adapter(LTXAdapter):
    """``LTX2Pipeline``: the video stream only. Video latents are packed tokens ``[B, S, C]`` (128
    channels), flow matching, per-channel ``latents_mean/std``; ``AutoencoderKLLTX2Video`` has
    ``r = 8`` (32x spatial) and a non-causal decoder: an anchor's chunk decode lacks the later
    latents the whole video's decode sees (as :class:`LTXAdapter`'s). The pipeline's one
    transformer denoises the video and the audio jointly; the hook guides the video latents
    (``pipe.scheduler``) and leaves the audio latents, their scheduler (a copy of the video one,
    which steps itself) and the audio decode alone. Re-running the denoiser keeps the audio
    inputs of the step.

    A step's video model output is made on clean estimates ``x0 = z - sigma v``: CFG, spatio-
    temporal guidance (another call, with perturbed blocks) and modality isolation (another call)
    as deltas, then ``guidance_rescale`` (not linear), then back to a velocity: :meth:`combine`
    does the same, from the outputs of the step's 1 to 3 denoiser calls.
    """

    name = "LTX-2"
    # none: its denoiser's call carries the audio stream, which the cost model does not trace
    traced_prediction = PipelineAdapter.traced_prediction

    def context_parallel_plan(self, denoiser):
        """LTX-2's plan, written as diffusers writes ``_cp_plan``: the video tokens split at the
        denoiser's input, their rotary tables as ``rope`` makes them (``[B, S, D]``, or ``[B, heads,
        S, D]`` for the split rotary type, which diffusers' own plan leaves whole), the video tokens
        gathered after ``proj_out``; the video's tables of its cross-attention with the audio, as
        ``cross_attn_rope`` makes them, likewise. The text and the audio stay whole on every process: only
        the video self-attention is split; the cross-attentions to the text, the audio's attentions
        and the audio-to-video attention are each process's own (:func:`~.split_attention.attend_within_process`);
        the video-to-audio attention takes the whole video, gathered by :class:`~.split_attention.GatheredVideoKeys`."""
        from diffusers.models._modeling_parallel import ContextParallelInput, ContextParallelOutput

        split = denoiser.config.rope_type == "split"
        rotary = ContextParallelInput(split_dim=2 if split else 1, expected_dims=4 if split else 3, split_output=True)
        return {
            "": {"hidden_states": ContextParallelInput(split_dim=1, expected_dims=3, split_output=False)},
            "rope": {0: rotary, 1: rotary},
            "cross_attn_rope": {0: rotary, 1: rotary},
            "proj_out": ContextParallelOutput(gather_dim=1, expected_dims=3),
        }

    def finish_context_parallel(self, denoiser):
        from ..running.module_hooks import register_hook
        from ..running.split_attention import GATHERED_KEYS_HOOK, GatheredVideoKeys, attend_within_process

        attend_within_process(denoiser, lambda name: not name.endswith(".attn1"))  # all but the video's self-attention
        for block in denoiser.transformer_blocks:
            register_hook(block.video_to_audio_attn, GatheredVideoKeys(denoiser.config.rope_type == "split"),
                          GATHERED_KEYS_HOOK)

    def call_geometry(self, pipe, args, latents):
        return replace(super().call_geometry(pipe, args, latents), requested_frames=int(args["num_frames"]))

    def check(self, pipe, geometry):
        check_requested_frames(geometry, self.name)

    def latents_shape(self, pipe, args):
        # the caller's latents are [B, C, F, h, w] (the pipeline packs them); it would take the video's
        # size from them, so guidance asks that they be the size the call's arguments say
        r, s = self.temporal_compression(pipe), pipe.vae_spatial_compression_ratio
        return (int(args["batch_size"]), int(args["num_channels_latents"]), (int(args["num_frames"]) - 1) // r + 1,
                int(args["height"]) // s, int(args["width"]) // s)

    def combine(self, pipe, parts, weights, *, sample, step):
        from diffusers.pipelines.ltx2.pipeline_ltx2 import rescale_noise_cfg

        cfg, stg, modality = _ltx2_flags(pipe)
        if len(parts) != 1 + cfg + stg + modality:
            raise ValueError(
                f"LTX-2 step with {len(parts)} denoiser outputs, expected {1 + cfg + stg + modality} (CFG {cfg}, "
                f"spatio-temporal guidance {stg}, modality isolation {modality}): the pipeline makes its model output "
                "in a way this adapter does not know"
            )
        sigma = pipe.scheduler.sigmas[step]
        z = sample.float()
        x0 = [z - part.float() * sigma for part in parts]  # as LTX2Pipeline.convert_velocity_to_x0
        cond = x0[1] if cfg else x0[0]
        rest = iter(x0[2:] if cfg else x0[1:])
        cfg_delta = (pipe.guidance_scale - 1) * (cond - x0[0]) if cfg else 0
        stg_delta = pipe.stg_scale * (cond - next(rest)) if stg else 0
        modality_delta = (pipe.modality_scale - 1) * (cond - next(rest)) if modality else 0
        guided = cond + cfg_delta + stg_delta + modality_delta
        if pipe.guidance_rescale > 0:
            guided = rescale_noise_cfg(guided, cond, guidance_rescale=pipe.guidance_rescale)
        return (z - guided) / sigma  # as LTX2Pipeline.convert_x0_to_velocity


def fit_combination(parts: list[Tensor], target: Tensor) -> tuple[Tensor, float]:
    """Weights ``w`` with ``sum_k w_k parts_k ~= target`` (least squares, float64) and the relative
    residual. CFG ``u + s (c - u)`` gives ``w = (1 - s, s)``; one call without CFG gives ``w = (1,)``."""
    a = torch.stack([p.detach().double().flatten() for p in parts], dim=1)
    y = target.detach().double().flatten()
    gram = a.T @ a
    w = torch.linalg.pinv(gram) @ (a.T @ y)
    residual = float((a @ w - y).norm() / y.norm().clamp_min(1e-30))
    return w.float().cpu(), residual


# --------------------------------------------------------------------------------------------
# schedulers


def _scheduler_index(scheduler, timestep, counter: int) -> int:
    timesteps = scheduler.timesteps
    if counter < len(timesteps) and float(timesteps[counter]) == float(timestep):
        return counter
    matches = (timesteps.float() == float(timestep)).nonzero().flatten()
    if len(matches) == 0:
        raise ValueError(f"timestep {float(timestep)} is not in the scheduler's table")
    return int(matches[0])


def is_flow_scheduler(scheduler) -> bool:
    from diffusers import FlowMatchEulerDiscreteScheduler

    if isinstance(scheduler, FlowMatchEulerDiscreteScheduler):
        return True
    cfg = scheduler.config
    return cfg.get("prediction_type") == "flow_prediction" and bool(cfg.get("use_flow_sigmas", False))


def is_vp_vprediction_scheduler(scheduler) -> bool:
    return hasattr(scheduler, "alphas_cumprod") and scheduler.config.get("prediction_type") == "v_prediction"


def noise_levels(scheduler, timestep, counter: int) -> NoiseLevels:
    """The :class:`NoiseLevels` of the step at ``timestep`` (``counter``: the step's index in the call).

    Flow matching (``FlowMatchEulerDiscreteScheduler``; UniPC/DPM-Solver with ``use_flow_sigmas`` and
    ``prediction_type="flow_prediction"``): ``sigmas[i]``, ``sigmas[i + 1]``. VP v-prediction
    (``CogVideoXDDIMScheduler``, ``CogVideoXDPMScheduler``, ``DDIMScheduler``): cumulative alphas of
    ``t`` and of ``t - num_train_timesteps // num_inference_steps`` (the final alpha below 0), the
    rule those schedulers step with.
    """
    if is_flow_scheduler(scheduler):
        i = _scheduler_index(scheduler, timestep, counter)
        return FlowLevels(scheduler.sigmas[i], scheduler.sigmas[i + 1])
    if is_vp_vprediction_scheduler(scheduler):
        t = int(timestep)
        prev = t - scheduler.config.num_train_timesteps // scheduler.num_inference_steps
        alphas = scheduler.alphas_cumprod
        alpha_prev = alphas[prev] if prev >= 0 else scheduler.final_alpha_cumprod
        return VPLevels(alphas[t], alpha_prev)
    raise ValueError(
        f"GeCo guidance does not know the noise parametrisation of {type(scheduler).__name__} "
        f"(prediction_type={scheduler.config.get('prediction_type')!r}); supported: flow matching "
        "(FlowMatchEulerDiscreteScheduler, UniPC/DPM-Solver with use_flow_sigmas) and v-prediction DDIM/DPM"
    )


def check_no_denoiser_cache(modules) -> None:
    """ValueError (one line) naming the cache of a denoiser that has a diffusers cache enabled
    (pyramid attention broadcast, FasterCache, First Block Cache, ...): guidance runs the denoiser
    ``R_t + 1`` times per step and differentiates it, which such caches count as steps or cannot
    recompute."""
    for module in modules:
        config = cache_config(module)
        if config is not None:
            name = type(config).__name__.removesuffix("Config")
            raise ValueError(
                f"GeCo guidance cannot run with the {type(module).__name__}'s {name} cache enabled (guidance runs and "
                f"differentiates the denoiser several times per step, which the cache cannot follow): call "
                f"disable_cache() on it, or sample with guidance off"
            )


def check_scheduler(scheduler) -> None:
    """ValueError unless :func:`noise_levels` supports ``scheduler``."""
    if not (is_flow_scheduler(scheduler) or is_vp_vprediction_scheduler(scheduler)):
        noise_levels(scheduler, 0, 0)  # raises with the message


# --------------------------------------------------------------------------------------------
# registry

_REGISTRY: dict[type, PipelineAdapter] = {}


def register_adapter(pipeline_class: type, adapter: PipelineAdapter) -> None:
    """Let :func:`~geco_guide.sampler.pipelines.hooks.attach_geco_guidance` guide ``pipeline_class`` (and subclasses)."""
    if not isinstance(adapter, PipelineAdapter):
        raise TypeError(f"adapter must be a PipelineAdapter, got {type(adapter).__name__}")
    _REGISTRY[pipeline_class] = adapter


#: The adapters by class name: what a registry entry's ``adapter`` names.
ADAPTERS: dict[str, type[PipelineAdapter]] = {cls.__name__: cls for cls in (
    CogVideoXAdapter, WanAdapter, HunyuanVideoAdapter, LTXAdapter, HunyuanVideo15Adapter, LTX2Adapter)}


def _register_defaults() -> None:
    """Each registry entry's adapter (one of a kind) for its pipeline class, where diffusers has it."""
    import diffusers

    adapters = {name: adapter() for name, adapter in ADAPTERS.items()}
    for model in (model for model in MODELS.values() if model.adapter is not None):
        cls = getattr(diffusers, model.pipeline, None)
        if cls is not None and cls not in _REGISTRY:
            _REGISTRY[cls] = adapters[model.adapter]


def supported_pipelines() -> list[str]:
    _register_defaults()
    return [cls.__name__ for cls in _REGISTRY]


def adapter_for(pipe) -> PipelineAdapter:
    """The adapter of ``pipe``'s class (the most derived registered base); ValueError listing the
    supported pipelines and how to register one otherwise."""
    return adapter_for_class(type(pipe))


def adapter_for_class(pipeline_class: type) -> PipelineAdapter:
    """:func:`adapter_for` of a pipeline class (before any pipeline is built)."""
    _register_defaults()
    for cls in pipeline_class.__mro__:
        if cls in _REGISTRY:
            return _REGISTRY[cls]
    raise ValueError(
        f"GeCo guidance has no adapter for {pipeline_class.__name__}. Supported: {', '.join(supported_pipelines())}. "
        "To add one, subclass geco_guide.sampler.pipelines.adapters.PipelineAdapter (latent layout, de-normalisation, "
        "chunk decode) and call geco_guide.sampler.pipelines.adapters.register_adapter(YourPipeline, YourAdapter())."
    )
