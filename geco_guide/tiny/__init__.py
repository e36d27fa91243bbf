"""Tiny, randomly initialised, offline stand-ins for the real models: the ``tiny`` preset and the
``tiny-random`` ids, GeCo-Eval's ``--preset tiny``, the tests and the runnable examples.

:func:`tiny_pipeline` returns a ready :class:`GeCoCogVideoXPipeline` whose every component is
built here from a seed (:func:`tiny_cogvideox_components`: a word-level T5-style tokenizer made
with the ``tokenizers`` library, a tiny T5 encoder, the default model's transformer and VAE at a
few pixels, with its temporal compression 4 and spatial 8, so the real frame <-> latent mapping
is exercised, and the paper's DDIM scheduler); :func:`tiny_estimators` the tiny random VGGT (or,
with ``geometry="da3"``, Depth Anything 3: the ``tiny-random-da3`` id) and UFM.
Every family of the model registry (:mod:`geco_guide.families`) has its builder in
:mod:`.pipelines`, which its entry names (:func:`tiny_video_components`), and its entry says what
its tiny calls need (:func:`tiny_call_kwargs`). Nothing is downloaded. The outputs are noise-like
videos; only the mechanics are real.
"""

from __future__ import annotations

import copy
import inspect
from typing import Any

from ..estimators import tiny_estimators, tiny_random_decoder
from ..families import VideoModel, models_of_pipeline
from ..sampler.pipelines.adapters import adapter_for
from ..sampler.pipelines.sampling import SamplingConfig, fit_to_model
from . import pipelines
from .components import (
    TINY_ANCHORS,
    TINY_HEIGHT,
    TINY_MAX_SEQUENCE_LENGTH,
    TINY_NUM_FRAMES,
    TINY_WIDTH,
    TinySizes,
    TinyTokenizer,
    tiny_cogvideox_components,
    tiny_cogvideox_transformer,
    tiny_tokenizer,
)
from .pipelines import (
    HUNYUAN15_LATENT_CHANNELS,
    WAN22_LATENT_CHANNELS,
    tiny_cogvideox15_pipeline,
    tiny_cogvideox_i2v_pipeline,
    tiny_cogvideox_pipeline,
    tiny_hunyuan15_i2v_pipeline,
    tiny_hunyuan15_pipeline,
    tiny_hunyuan_pipeline,
    tiny_image,
    tiny_ltx2_pipeline,
    tiny_ltx_pipeline,
    tiny_wan22_a14b_pipeline,
    tiny_wan22_ti2v_pipeline,
    tiny_wan_modular_pipeline,
    tiny_wan_pipeline,
)

__all__ = ["HUNYUAN15_LATENT_CHANNELS", "TINY_ANCHORS", "TINY_CALL_KWARGS", "TINY_HEIGHT",
           "TINY_MAX_SEQUENCE_LENGTH", "TINY_NUM_FRAMES", "TINY_WIDTH", "TinySizes", "TinyTokenizer",
           "WAN22_LATENT_CHANNELS", "tiny_call_extras", "tiny_call_kwargs", "tiny_cogvideox15_pipeline",
           "tiny_cogvideox_components", "tiny_cogvideox_i2v_pipeline", "tiny_cogvideox_pipeline",
           "tiny_cogvideox_transformer", "tiny_estimators", "tiny_guidance_config", "tiny_guidance_decoder",
           "tiny_hunyuan15_i2v_pipeline", "tiny_hunyuan15_pipeline", "tiny_hunyuan_pipeline", "tiny_image", "tiny_ltx2_pipeline",
           "tiny_ltx_pipeline", "tiny_pipeline", "tiny_run_options", "tiny_sampling", "tiny_tokenizer",
           "tiny_video_components", "tiny_wan22_a14b_pipeline", "tiny_wan22_ti2v_pipeline", "tiny_wan_modular_pipeline",
           "tiny_wan_pipeline"]

# Tiny sampling settings that fit the tiny models (17 frames = 5 latents, 32x48 pixels).

def tiny_video_components(model: VideoModel, seed: int = 0) -> dict[str, Any]:
    """What ``model``'s tiny random stand-in (the builder its registry entry names), seeded with
    ``seed``, is built from: its components and the settings of its config that its class takes
    (Wan 2.2's ``boundary_ratio``, ``expand_timesteps``): what ``model.id=tiny-random`` loads."""
    if model.tiny is None:
        raise ValueError(f"{model.name} has no tiny random stand-in")
    pipe = getattr(pipelines, model.tiny)(seed)
    accepted = inspect.signature(type(pipe).__init__).parameters
    settings = {key: value for key, value in pipe.config.items() if key in accepted and key not in pipe.components}
    return {**pipe.components, **settings}


def tiny_sampling(model: VideoModel) -> dict[str, int]:
    """The ``sampling`` of a tiny stand-in of ``model``'s family: 17 frames of 32x48 pixels, fitted
    to the model (:func:`~geco_guide.sampler.pipelines.sampling.fit_to_model`: the width of 64 where it wants
    sizes in multiples of 32)."""
    fitted = fit_to_model(SamplingConfig(num_frames=TINY_NUM_FRAMES, height=TINY_HEIGHT, width=TINY_WIDTH), model)
    return {"num_frames": fitted.num_frames, "height": fitted.height, "width": fitted.width}


def tiny_guidance_decoder(variant: str | None = None, seed: int = 0, latent_channels: int = TinySizes.latent_channels):
    """A tiny random :class:`~geco_guide.estimators.tiny_decoder.TinyDecoder` of ``variant`` (default:
    the default model's) for the tiny models' latents (their channel count; the published variants
    take 16 or more)."""
    return tiny_random_decoder(variant, seed, latent_channels)


def tiny_guidance_config(**changes: Any):
    """A short guidance schedule for the tiny models and a few steps (default: 4 steps), with the
    fused loss (the cues all get gradients, so the tests see every path)."""
    from dataclasses import replace

    from ..loss.presets import fused_guidance_loss
    from ..sampler.algorithm.config import GuidanceConfig

    base = GuidanceConfig(
        anchors=list(TINY_ANCHORS),
        chunk_latents=3,
        repeats="0x1,2x2,1x1",
        step_size=3.0,
        time_travel=[2, 2],
        denoiser_grad=True,
        loss=fused_guidance_loss(),
    )
    return replace(base, **changes)


def tiny_run_options(**changes: Any):
    """How guidance runs on the tiny models: no checkpointing (``explicit`` plan, flags off: the
    batched chunk decode; they need no memory plan), as ``configs/tiny.yaml``'s ``run``."""
    from ..sampler.running.run_options import RunOptions

    return RunOptions(**{"memory_plan": "explicit", "gradient_checkpointing": False, "vae_checkpointing": False,
                         **changes})


def tiny_pipeline(seed: int = 0, *, guidance_config: Any = None):
    """A ready tiny :class:`GeCoCogVideoXPipeline` (CPU, fp32); guide its calls with
    :func:`tiny_estimators`.

    Call it with ``num_frames=TINY_NUM_FRAMES, height=TINY_HEIGHT, width=TINY_WIDTH,
    num_inference_steps=4, max_sequence_length=TINY_MAX_SEQUENCE_LENGTH`` (the guidance default
    is :func:`tiny_guidance_config`, a 4-step schedule) and ``run_options=tiny_run_options()``.
    """
    from ..sampler.pipelines.pipeline_cogvideox import GeCoCogVideoXPipeline

    pipe = GeCoCogVideoXPipeline(
        **tiny_cogvideox_components(seed),
        guidance_config=guidance_config if guidance_config is not None else tiny_guidance_config(),
    )
    pipe.set_progress_bar_config(disable=True)
    return pipe


TINY_CALL_KWARGS = dict(
    num_frames=TINY_NUM_FRAMES,
    height=TINY_HEIGHT,
    width=TINY_WIDTH,
    num_inference_steps=4,
    max_sequence_length=TINY_MAX_SEQUENCE_LENGTH,
)


def tiny_call_extras(pipeline: str) -> dict[str, Any]:
    """What the calls of the tiny stand-in of the pipeline class named ``pipeline`` need beyond the
    config's sampling: its registry entry's ``tiny_call`` (HunyuanVideo's bare ``"{}"`` prompt
    template: the tiny tokenizer cannot crop the real template's system text)."""
    models = models_of_pipeline([pipeline])
    return copy.deepcopy(models[0].tiny_call) if models else {}


def _stood_for(pipe) -> VideoModel | None:
    """The registry entry the tiny stand-in ``pipe`` stands for: one of its pipeline class (or a
    base class); where that class's models want different sizes, the one of its VAE's compression
    (a Wan with the Wan 2.2 16x VAE)."""
    models = models_of_pipeline(cls.__name__ for cls in type(pipe).__mro__)
    if len({model.size_multiple for model in models}) > 1:
        scale = adapter_for(pipe).spatial_compression(pipe)
        models = [model for model in models if model.spatial_compression == scale] or models
    return models[0] if models else None


def tiny_call_kwargs(pipe, **changes: Any) -> dict[str, Any]:
    """Call arguments that fit the tiny pipelines: 17 frames of 32x48, 4 steps, short prompts, of
    them those its call takes (HunyuanVideo 1.5's takes no ``max_sequence_length``, its
    image-to-video pipeline no size: it comes from the image); the size fitted to the registry
    entry it stands for (:func:`tiny_sampling`: 32x64 where the model wants multiples of 32), with
    that entry's ``tiny_call`` (:func:`tiny_call_extras`); plus the conditioning image where its
    call takes one, and spatio-temporal guidance on the tiny transformer's last block where its
    call takes a block list (LTX-2's default list does not name the tiny one's blocks)."""
    accepted = inspect.signature(pipe.__call__).parameters
    takes_any = any(p.kind is inspect.Parameter.VAR_KEYWORD for p in accepted.values())
    model = _stood_for(pipe)
    kwargs: dict[str, Any] = dict(
        num_frames=TINY_NUM_FRAMES,
        height=TINY_HEIGHT,
        width=TINY_WIDTH,
        num_inference_steps=4,
        max_sequence_length=TINY_MAX_SEQUENCE_LENGTH,
    )
    if model is not None:
        kwargs.update(tiny_sampling(model))
    if "image" in accepted:
        kwargs["image"] = tiny_image(0)
    if "spatio_temporal_guidance_blocks" in accepted:
        kwargs["spatio_temporal_guidance_blocks"] = [pipe.transformer.config.num_layers - 1]
    kwargs = {key: value for key, value in kwargs.items() if takes_any or key in accepted}
    if model is not None:
        kwargs.update(copy.deepcopy(model.tiny_call))
    kwargs.update(changes)
    return kwargs
