"""One denoising step of a stock pipeline, as the cost model traces it.

The hooks guide a stock pipeline by replaying the denoiser calls its loop made at a step
(:mod:`geco_guide.sampler.hooks`); a trace without values (fake tensors) cannot run the stock
loop itself (its schedulers and the hooks' checks read values). :func:`denoiser_step` builds, for
one pipeline class, the latents the scheduler steps and the step's prediction as the family's pipeline
makes it: the same denoiser calls (the conditional and unconditional branches as separate calls or
one batch, the timestep, the text embeddings of the published prompt length, the family's extra
inputs) combined with the pipeline's CFG. The traced cost is then the pipeline's, whatever the
values.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import torch
from torch import Tensor

from ..families import VideoModel
from ..sampler.adapters import CallGeometry
from ..sampler.levels import FlowLevels, NoiseLevels
from .full_size import text_embed_shape

__all__ = ["DenoiserStep", "denoiser_step"]

#: The timestep of the traced step (the first of a flow-matching schedule): no cost depends on it.
FIRST_TIMESTEP = 1000.0


@dataclass
class DenoiserStep:
    """A step of a stock pipeline's loop, ready to guide.

    Attributes:
        sample: ``z_t`` as the scheduler steps it (``[1, C, F, h, w]``; LTX: tokens ``[1, S, C]``), fp32.
        geometry: the call's frame geometry.
        levels: the step's noise levels (flow matching: sigma 1 to 0).
        predict: ``(z, differentiate) -> model output`` at ``z``: the step's denoiser calls,
            CFG-combined in fp32, as :func:`~geco_guide.sampler.step.guided_step` takes it.
    """

    sample: Tensor
    geometry: CallGeometry
    levels: NoiseLevels
    predict: Callable[[Tensor, bool], Tensor]


def _cfg(uncond: Tensor, cond: Tensor, scale: float) -> Tensor:
    """The CFG combination in fp32: ``uncond + scale (cond - uncond)``."""
    uncond = uncond.float()
    return uncond + scale * (cond.float() - uncond)


def _with_grad(differentiate: bool) -> Any:
    return torch.set_grad_enabled(differentiate and torch.is_grad_enabled())


def _wan(pipe: Any, model: VideoModel, latents: Tensor, dtype: torch.dtype) -> Callable[[Tensor, bool], Tensor]:
    """WanPipeline: two calls a step (text, then empty prompt), timesteps per token with
    ``expand_timesteps`` (Wan 2.2 TI2V-5B). Wan 2.2 A14B steps its high-noise expert first: the
    two experts share one config, so the trace's calls are either's."""
    shape = text_embed_shape(model.name)
    embeds = [torch.empty(shape, dtype=dtype) for _ in range(2)]
    patch = pipe.transformer.config.patch_size
    tokens = latents.shape[2] // patch[0] * (latents.shape[3] // patch[1]) * (latents.shape[4] // patch[2])
    expand = pipe.config.get("expand_timesteps", False)
    timestep = torch.full((1, tokens) if expand else (1,), FIRST_TIMESTEP)
    scale = model.call["guidance_scale"]

    def predict(z: Tensor, differentiate: bool) -> Tensor:
        with _with_grad(differentiate):
            x = z.to(dtype)
            cond, uncond = (pipe.transformer(hidden_states=x, timestep=timestep, encoder_hidden_states=e,
                                             return_dict=False)[0] for e in embeds)
            return _cfg(uncond, cond, scale)

    return predict


def _embedded_guidance(pipe: Any, model: VideoModel, latents: Tensor, dtype: torch.dtype) -> Callable[[Tensor, bool], Tensor]:
    """HunyuanVideoPipeline: guidance-distilled, one call a step with the guidance scale as an input
    (``true_cfg_scale`` 1 by default: no negative call), a pooled text embedding and a text mask."""
    shape = text_embed_shape(model.name)
    config = pipe.transformer.config
    embeds = torch.empty(shape, dtype=dtype)
    mask = torch.ones(shape[:2], dtype=torch.long)
    pooled = torch.empty(1, config.pooled_projection_dim, dtype=dtype)
    guidance = torch.full((1,), model.call["guidance_scale"] * 1000.0, dtype=dtype)
    timestep = torch.full((1,), FIRST_TIMESTEP)

    def predict(z: Tensor, differentiate: bool) -> Tensor:
        with _with_grad(differentiate):
            return pipe.transformer(hidden_states=z.to(dtype), timestep=timestep.to(z.dtype), encoder_hidden_states=embeds,
                                    encoder_attention_mask=mask, pooled_projections=pooled, guidance=guidance,
                                    return_dict=False)[0].float()

    return predict


def _ltx(pipe: Any, model: VideoModel, latents: Tensor, dtype: torch.dtype) -> Callable[[Tensor, bool], Tensor]:
    """LTXPipeline: one call of the unconditional and conditional halves as a batch of two, on the
    packed latent tokens, with the latent grid's size and the rope scale of the frame rate."""
    shape = text_embed_shape(model.name)
    embeds = torch.empty(2, *shape[1:], dtype=dtype)
    mask = torch.ones(2, shape[1], dtype=torch.long)
    timestep = torch.full((2,), FIRST_TIMESTEP)
    frames, height, width = latents.shape[2:]
    r, s = model.temporal_compression, model.spatial_compression
    rope_scale = (r / model.fps, s, s)
    scale = model.call["guidance_scale"]

    def predict(z: Tensor, differentiate: bool) -> Tensor:
        with _with_grad(differentiate):
            x = torch.cat([z] * 2).to(dtype)
            out = pipe.transformer(hidden_states=x, encoder_hidden_states=embeds, timestep=timestep,
                                   encoder_attention_mask=mask, num_frames=frames, height=height, width=width,
                                   rope_interpolation_scale=rope_scale, return_dict=False)[0]
            uncond, cond = out.chunk(2)
            return _cfg(uncond, cond, scale)

    return predict


def _packed(latents: Tensor) -> Tensor:
    """LTX's tokens of ``[B, C, F, h, w]`` latents with patch size 1: ``[B, F h w, C]``."""
    return latents.flatten(2).transpose(1, 2)


#: The step of each stock pipeline class the hooks guide (the registry's ``pipeline``).
PIPELINE_STEPS = {"WanPipeline": _wan, "HunyuanVideoPipeline": _embedded_guidance, "LTXPipeline": _ltx}


def denoiser_step(pipe: Any, model: VideoModel, frames: int, height: int, width: int, dtype: torch.dtype) -> DenoiserStep:
    """The first step of a ``frames x height x width`` call of ``model``'s stock ``pipe`` (fake or
    real weights): fresh latents (zeros: no cost depends on their values), the step's prediction,
    the geometry the hooks would read from ``prepare_latents``.

    Raises:
        ValueError: (one line) a family this module has no step for.
    """
    if model.pipeline not in PIPELINE_STEPS:
        raise ValueError(f"the cost model has no denoiser step for {model.pipeline} ({model.name})")
    r, s = model.temporal_compression, model.spatial_compression
    num_latents = (frames - 1) // r + 1
    latents = torch.zeros(1, model.latent_channels, num_latents, height // s, width // s)
    geometry = CallGeometry(frames, num_latents, 0, height // s, width // s, r)
    predict = PIPELINE_STEPS[model.pipeline](pipe, model, latents, dtype)
    packed = model.pipeline == "LTXPipeline"  # LTX's scheduler steps the tokens
    sample = _packed(latents) if packed else latents
    return DenoiserStep(sample, geometry, FlowLevels(torch.tensor(1.0), torch.tensor(0.0)), predict)
