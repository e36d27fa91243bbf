"""Full-size models without weights: the CogVideoX-5B transformer and VAE from their published
configs, random-initialised cheaply or left on the meta device, and fake-tensor copies of any model.

Nothing is downloaded: the configs are written out below. On the meta device nothing is allocated
(for tests and the cost model); :func:`to_fake` then gives a model fake CPU tensors of the same
shapes and dtypes, so a ``FakeTensorMode`` can run it.
"""

from __future__ import annotations

from typing import Any

import torch
from torch import Tensor

from ..estimators.bundle import Estimators
from ..estimators.tiny_decoder import TinyDecoder
from ..estimators.ufm import UFM, UFMConfig
from ..estimators.vggt import VGGT, VGGTConfig
from ..sampler.loading import cast_model

__all__ = ["FULL_SIZE_VIDEO", "TEXT_EMBED_SHAPE", "build_cost_pipeline", "build_full_size_components",
           "cast_components", "full_size_vae", "model_bytes", "to_fake"]

#: Published ``THUDM/CogVideoX-5b`` configs (``transformer/config.json``, ``vae/config.json``,
#: ``scheduler/scheduler_config.json``), written out so nothing is downloaded. The checkpoint ships
#: ``CogVideoXDPMScheduler``; the GeCo pipeline samples with DDIM from the same settings.
COGVIDEOX_5B_TRANSFORMER: dict[str, Any] = {
    "activation_fn": "gelu-approximate",
    "attention_bias": True,
    "attention_head_dim": 64,
    "dropout": 0.0,
    "flip_sin_to_cos": True,
    "freq_shift": 0,
    "in_channels": 16,
    "max_text_seq_length": 226,
    "norm_elementwise_affine": True,
    "norm_eps": 1e-5,
    "num_attention_heads": 48,
    "num_layers": 42,
    "out_channels": 16,
    "patch_size": 2,
    "sample_frames": 49,
    "sample_height": 60,
    "sample_width": 90,
    "spatial_interpolation_scale": 1.875,
    "temporal_compression_ratio": 4,
    "temporal_interpolation_scale": 1.0,
    "text_embed_dim": 4096,
    "time_embed_dim": 512,
    "timestep_activation_fn": "silu",
    "use_learned_positional_embeddings": False,
    "use_rotary_positional_embeddings": True,
}
COGVIDEOX_5B_VAE: dict[str, Any] = {
    "act_fn": "silu",
    "block_out_channels": (128, 256, 256, 512),
    "down_block_types": ("CogVideoXDownBlock3D",) * 4,
    "force_upcast": True,
    "in_channels": 3,
    "latent_channels": 16,
    "layers_per_block": 3,
    "norm_eps": 1e-6,
    "norm_num_groups": 32,
    "out_channels": 3,
    "sample_height": 480,
    "sample_width": 720,
    "scaling_factor": 0.7,
    "temporal_compression_ratio": 4,
    "up_block_types": ("CogVideoXUpBlock3D",) * 4,
    "use_post_quant_conv": False,
    "use_quant_conv": False,
}
COGVIDEOX_5B_SCHEDULER: dict[str, Any] = {
    "beta_end": 0.012,
    "beta_schedule": "scaled_linear",
    "beta_start": 0.00085,
    "clip_sample": False,
    "num_train_timesteps": 1000,
    "prediction_type": "v_prediction",
    "rescale_betas_zero_snr": True,
    "set_alpha_to_one": True,
    "snr_shift_scale": 1.0,
    "steps_offset": 0,
    "timestep_spacing": "trailing",
}
#: The paper's setting: 49 frames of 480x720, 50 DDIM steps, CFG 6; T5 embeddings are [1, 226, 4096].
FULL_SIZE_VIDEO = {"frames": 49, "height": 480, "width": 720}
TEXT_EMBED_SHAPE = (1, 226, 4096)


def cast_components(pipe: Any, dtype: torch.dtype) -> Any:
    """Every model of the diffusers pipeline ``pipe`` cast to ``dtype`` (:func:`cast_model`: no
    empty float32 warning per model), as ``pipe.to(dtype=dtype)``; returns ``pipe``."""
    for model in pipe.components.values():
        if isinstance(model, torch.nn.Module):
            cast_model(model, dtype)
    return pipe


def init_weights_(model: torch.nn.Module, seed: int) -> None:
    """Cheap random init of a model materialised with ``to_empty``: weight matrices / kernels
    ``N(0, 1 / fan_in)``, other weights (norm scales) 1, biases and other 1-D tensors 0; buffers
    must not exist (their values would be garbage)."""
    device = next(model.parameters()).device
    gen = torch.Generator(device=device).manual_seed(seed)
    with torch.no_grad():
        for name, param in model.named_parameters():
            if param.ndim >= 2:
                fan_in = param[0].numel()
                param.normal_(0.0, fan_in**-0.5, generator=gen)
            elif name.endswith("weight"):
                param.fill_(1.0)
            else:
                param.zero_()
    buffers = [name for name, _ in model.named_buffers()]
    if buffers:
        raise RuntimeError(f"{type(model).__name__} has buffers {buffers[:5]}; init_weights_ cannot fill them")


def materialise(cls: type, config: dict[str, Any], device: str | torch.device, dtype: torch.dtype, seed: int) -> Any:
    """``cls(**config)`` built on the meta device, then allocated in ``dtype`` on ``device`` with
    :func:`init_weights_` (left on meta when ``device`` is meta), in eval mode."""
    with torch.device("meta"):
        model = cls(**config)
    cast_model(model, dtype)
    if torch.device(device).type != "meta":
        model.to_empty(device=device)
        init_weights_(model, seed)
    return model.eval()


def full_size_vae(device: str | torch.device, dtype: torch.dtype, seed: int) -> Any:
    """The CogVideoX-5B VAE with random weights (:func:`materialise`)."""
    from diffusers import AutoencoderKLCogVideoX

    return materialise(AutoencoderKLCogVideoX, COGVIDEOX_5B_VAE, device, dtype, seed)


def build_full_size_components(device: str | torch.device, dtype: torch.dtype, seed: int = 0) -> dict[str, Any]:
    """CogVideoX-5B transformer and VAE (random weights, ``dtype``, on ``device``), DDIM scheduler.

    Built on the meta device and materialised with ``to_empty`` directly in ``dtype``; with
    ``device="meta"`` nothing is allocated (for tests). No tokenizer or text encoder.
    """
    from diffusers import CogVideoXDDIMScheduler, CogVideoXTransformer3DModel

    return {"tokenizer": None, "text_encoder": None,
            "vae": full_size_vae(device, dtype, seed + 1),
            "transformer": materialise(CogVideoXTransformer3DModel, COGVIDEOX_5B_TRANSFORMER, device, dtype, seed),
            "scheduler": CogVideoXDDIMScheduler(**COGVIDEOX_5B_SCHEDULER)}


def to_fake(model: torch.nn.Module, fake_mode: Any) -> torch.nn.Module:
    """Replace the parameters and buffers of ``model`` (real or on the meta device) by fake CPU
    tensors of the same shapes and dtypes, in place."""
    memo: dict[int, Tensor] = {}
    cpu = torch.device("cpu")

    def fake(t: Tensor) -> Tensor:
        if id(t) not in memo:
            t_ = t.detach()
            memo[id(t)] = (fake_mode.fake_tensor_converter.from_meta_and_device(fake_mode, t_, cpu)
                           if t_.is_meta else fake_mode.from_tensor(t_))
        return memo[id(t)]

    for module in model.modules():
        for name, param in list(module._parameters.items()):
            if param is not None:
                module._parameters[name] = torch.nn.Parameter(fake(param), requires_grad=param.requires_grad)
        for name, buf in list(module._buffers.items()):
            if buf is not None:
                module._buffers[name] = fake(buf)
    return model


def model_bytes(model: Any) -> int:
    """Bytes of the parameters and buffers of ``model`` (shared storages once); 0 for a non-module."""
    if not isinstance(model, torch.nn.Module):
        return 0
    seen = {}
    for t in [*model.parameters(), *model.buffers()]:
        seen[t.untyped_storage()._cdata] = t.untyped_storage().nbytes()
    return sum(seen.values())


def build_cost_pipeline(settings: dict[str, Any], fake_mode: Any) -> tuple[Any, dict[str, Any], Estimators]:
    """The pipeline of the cost model with fake weights, its call kwargs (the text embeddings are
    left to the caller for full size; the tiny preset runs its tiny T5 on fake tensors) and its
    estimators. Full size: the CogVideoX-5B transformer and VAE, VGGT-1B and UFM-Base (trunks in
    ``dtype``, heads float32), built on the meta device: nothing is allocated."""
    from ..sampler.pipeline_cogvideox import GeCoCogVideoXPipeline

    dtype = getattr(torch, settings["dtype"])
    if settings["preset"] == "tiny":
        from ..tiny import TINY_MAX_SEQUENCE_LENGTH, tiny_estimators, tiny_guidance_decoder, tiny_pipeline

        pipe = tiny_pipeline(settings["seed"])
        tiny = tiny_estimators(settings["seed"])
        geometry, flow = tiny.geometry, tiny.flow
        decoder = tiny_guidance_decoder("cogvideox", settings["seed"]) if settings.get("decoder") == "tiny" else None
        cast_components(pipe, dtype)
        call = {"prompt": "a red cube on a table", "max_sequence_length": TINY_MAX_SEQUENCE_LENGTH}
    else:
        ckpt = settings["estimator_checkpointing"]
        with torch.device("meta"):
            geometry = VGGT(VGGTConfig(), gradient_checkpointing=ckpt)
            flow = UFM(UFMConfig(), gradient_checkpointing=ckpt)
        geometry.trunk_to(dtype).eval()
        flow.trunk_to(dtype).eval()
        with torch.device("meta"):
            decoder = TinyDecoder("cogvideox").to(dtype).requires_grad_(False) if settings.get("decoder") == "tiny" else None
        pipe = GeCoCogVideoXPipeline(**build_full_size_components("meta", dtype, settings["seed"]))
        call = {"max_sequence_length": TEXT_EMBED_SHAPE[1]}
    estimators = Estimators(geometry, flow, tiny_decoder=decoder)
    for model in (pipe.text_encoder, pipe.transformer, pipe.vae, *estimators.modules()):
        if isinstance(model, torch.nn.Module):
            to_fake(model, fake_mode)
    if settings["vae_tiling"]:
        pipe.vae.enable_tiling()
    pipe.set_progress_bar_config(disable=True)
    call.update(num_frames=settings["frames"], height=settings["height"], width=settings["width"], output_type="pt")
    return pipe, call, estimators
