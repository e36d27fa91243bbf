"""One denoising step of a stock pipeline, as the cost model traces it.

The hooks guide a stock pipeline by replaying the denoiser calls its loop made at a step
(:mod:`geco_guide.sampler.pipelines.hooks`); a trace without values (fake tensors) cannot run the stock
loop itself (its schedulers and the hooks' checks read values). :func:`denoiser_step` builds, for
one model, the latents the scheduler steps and the step's prediction as the family's pipeline
makes it (its adapter's :meth:`~geco_guide.sampler.pipelines.adapters.PipelineAdapter.traced_prediction`):
the same denoiser calls (the conditional and unconditional branches as separate calls or one
batch, the timestep, the text embeddings of the published prompt length, the family's extra
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
from ..sampler.algorithm.levels import FlowLevels, NoiseLevels
from ..sampler.pipelines.adapters import ADAPTERS, CallGeometry
from .full_size import text_embed_shape

__all__ = ["DenoiserStep", "denoiser_step"]


@dataclass
class DenoiserStep:
    """A step of a stock pipeline's loop, ready to guide.

    Attributes:
        sample: ``z_t`` as the scheduler steps it (``[1, C, F, h, w]``; LTX: tokens ``[1, S, C]``), fp32.
        geometry: the call's frame geometry.
        levels: the step's noise levels (flow matching: sigma 1 to 0).
        predict: ``(z, differentiate) -> model output`` at ``z``: the step's denoiser calls,
            CFG-combined in fp32, as :func:`~geco_guide.sampler.algorithm.step.guided_step` takes it.
    """

    sample: Tensor
    geometry: CallGeometry
    levels: NoiseLevels
    predict: Callable[[Tensor, bool], Tensor]


def denoiser_step(pipe: Any, model: VideoModel, frames: int, height: int, width: int, dtype: torch.dtype) -> DenoiserStep:
    """The first step of a ``frames x height x width`` call of ``model``'s stock ``pipe`` (fake or
    real weights): fresh latents (zeros: no cost depends on their values), the step's prediction,
    the geometry the hooks would read from ``prepare_latents``.

    Raises:
        ValueError: (one line) a family whose adapter has no traced step.
    """
    adapter = ADAPTERS[model.adapter]()
    r, s = model.temporal_compression, model.spatial_compression
    num_latents = (frames - 1) // r + 1
    latents = torch.zeros(1, model.latent_channels, num_latents, height // s, width // s)
    geometry = CallGeometry(frames, num_latents, 0, height // s, width // s, r)
    predict = adapter.traced_prediction(pipe, model, latents, text_embed_shape(model.name), dtype)
    sample = adapter.traced_sample(latents)
    return DenoiserStep(sample, geometry, FlowLevels(torch.tensor(1.0), torch.tensor(0.0)), predict)
