"""What GeCo reads (and, in two places, writes) of diffusers' private attributes: here alone.

GeCo guides diffusers' own pipelines from outside their code, and a few facts it needs have no
public name: the device a pipeline runs its models on, whether accelerate's offload hooks hold
them, a denoiser's context-parallel plan, the cache a denoiser has switched on, ... Each function
below names the one attribute it touches and why GeCo needs it, so that a diffusers release that
renames one breaks in this module, and the functions say what broke. Nothing here imports
diffusers at module level: importing the package loads no diffusion code.

Attributes a pipeline subclass sets as diffusers' own ``__call__`` does (``GeCoCogVideoXPipeline``'s
``_guidance_scale``, ``_interrupt``, ...) are that class' state, not read here.
"""

from __future__ import annotations

from typing import Any

import torch
from torch import Tensor, nn

__all__ = ["active_attention_backend", "cache_config", "context_parallel_backends", "context_parallel_plan", "context_parallel_processes",
           "denormalize_ltx_latents", "dtype_keyword", "execution_device", "guidance_rescale", "hook_registry",
           "keeps_in_fp32", "offloads_models", "parallel_config", "remove_hook_registry", "rotary_embeddings",
           "set_parallel_config", "set_parallel_resolver", "sigma_to_alpha_sigma_t", "supports_gradient_checkpointing",
           "unpack_ltx_latents", "without_parallel_config"]


# --------------------------------------------------------------------------------------------
# pipelines


def execution_device(pipe: Any) -> torch.device:
    """``pipe._execution_device``: the device diffusers runs the pipeline's models on (the
    accelerator even while offloading keeps them on the CPU between calls): where guidance puts
    its masks and plans its memory."""
    return pipe._execution_device


def offloads_models(pipe: Any) -> bool:
    """Whether ``pipe._all_hooks`` holds accelerate's offload hooks
    (``enable_model_cpu_offload``): a memory plan then counts the models off the device."""
    return bool(getattr(pipe, "_all_hooks", None))


def guidance_rescale(pipe: Any) -> float:
    """``pipe._guidance_rescale``: the CFG rescale of an LTX pipeline's current call, which the
    LTX adapter applies again when it rebuilds the model output (``0.0``: none, or no call yet)."""
    return float(getattr(pipe, "_guidance_rescale", 0.0) or 0.0)


def unpack_ltx_latents(pipe: Any, tokens: Tensor, frames: int, height: int, width: int) -> Tensor:
    """``pipe._unpack_latents``: an LTX pipeline's tokens ``[B, S, C]`` back into latent frames
    ``[B, C, F, h, w]`` (``frames``, ``height``, ``width``: ``F, h, w``) by its transformer's
    patch sizes, as its own decode does."""
    return pipe._unpack_latents(tokens, frames, height, width, pipe.transformer_spatial_patch_size,
                                pipe.transformer_temporal_patch_size)


def denormalize_ltx_latents(pipe: Any, z: Tensor) -> Tensor:
    """``pipe._denormalize_latents``: an LTX pipeline's latents ``z`` de-normalised with its VAE's
    statistics and scaling factor, as its own decode does."""
    vae = pipe.vae
    return pipe._denormalize_latents(z, vae.latents_mean, vae.latents_std, vae.config.scaling_factor)


def rotary_embeddings(pipe: Any, *args: Any) -> Any:
    """``pipe._prepare_rotary_positional_embeddings(*args)``: CogVideoX's rotary position
    embeddings of a call's size, which ``GeCoCogVideoXPipeline``'s denoising loop passes its
    transformer as diffusers' loop does."""
    return pipe._prepare_rotary_positional_embeddings(*args)


def dtype_keyword() -> str:
    """The keyword ``from_pretrained`` reads the dtype by: ``dtype`` where diffusers has
    ``pipeline_utils._resolve_dtype`` (the release that renamed it), else ``torch_dtype``."""
    from diffusers.pipelines import pipeline_utils

    return "dtype" if hasattr(pipeline_utils, "_resolve_dtype") else "torch_dtype"


# --------------------------------------------------------------------------------------------
# models


def supports_gradient_checkpointing(model: Any) -> bool:
    """``model._supports_gradient_checkpointing``: whether a diffusers model can checkpoint its
    blocks, which a memory plan switches on while guidance differentiates it."""
    return bool(getattr(model, "_supports_gradient_checkpointing", False))


def keeps_in_fp32(model: Any) -> tuple[str, ...]:
    """``model._keep_in_fp32_modules``: the modules its class keeps in float32 when loaded in a
    lower precision (Wan's norms and time embedding, ...): a cast keeps them as loading does."""
    return tuple(getattr(model, "_keep_in_fp32_modules", None) or ())


def cache_config(module: Any) -> Any:
    """``module._cache_config``: the config of the denoiser cache ``enable_cache`` switched on
    (FirstBlockCache, FasterCache, ...), ``None`` without one; guidance refuses such caches."""
    return getattr(module, "_cache_config", None)


def hook_registry(module: nn.Module) -> Any:
    """``module._diffusers_hook``: the module's diffusers ``HookRegistry``, ``None`` where it has
    none (a module with one cannot be copied with its hooks working)."""
    return getattr(module, "_diffusers_hook", None)


def remove_hook_registry(module: nn.Module) -> None:
    """Delete ``module._diffusers_hook``, where ``HookRegistry.check_if_exists_or_initialize``
    keeps it: a module GeCo gave a registry is left as it was found."""
    del module._diffusers_hook


# --------------------------------------------------------------------------------------------
# schedulers


def sigma_to_alpha_sigma_t(scheduler: Any, sigma: Tensor) -> tuple[Tensor, Tensor]:
    """``scheduler._sigma_to_alpha_sigma_t(sigma)``: a multistep scheduler's ``(alpha_t,
    sigma_t)`` at ``sigma``, by its own rule: what its corrector's coefficient is made of."""
    return scheduler._sigma_to_alpha_sigma_t(sigma)


# --------------------------------------------------------------------------------------------
# context parallelism


def context_parallel_plan(denoiser: nn.Module) -> Any:
    """``denoiser._cp_plan``: how diffusers splits the denoiser's token sequence over processes
    and gathers it back (a ``ContextParallelModelPlan``; diffusers writes one for Wan, LTX-Video
    and LTX-2), ``None`` where it has none."""
    return getattr(denoiser, "_cp_plan", None)


def parallel_config(denoiser: nn.Module) -> Any:
    """``denoiser._parallel_config``: the ``ParallelConfig`` ``enable_parallelism`` gave it,
    ``None`` before: a denoiser split already is checked, not split again."""
    return getattr(denoiser, "_parallel_config", None)


def set_parallel_config(denoiser: nn.Module, parallel: Any) -> None:
    """Set ``denoiser._parallel_config``, as diffusers' resolver does, from GeCo's CPU resolver
    (:func:`set_parallel_resolver`)."""
    denoiser._parallel_config = parallel


def set_parallel_resolver(denoiser: nn.Module, resolve: Any) -> None:
    """Replace ``denoiser._resolve_parallel_config``, which picks a process' device among the
    accelerators, by ``resolve``: on a torch without an accelerator, a CPU mesh."""
    denoiser._resolve_parallel_config = resolve


def context_parallel_processes(split: Any) -> int:
    """``split._world_size``: the number of processes a ``ContextParallelConfig`` splits over."""
    return split._world_size


def without_parallel_config(processor: Any) -> None:
    """Clear an attention processor's ``_parallel_config``: it then attends on its process alone,
    without diffusers' all-to-all."""
    processor._parallel_config = None


def active_attention_backend() -> str:
    """The name of diffusers' active attention backend (``DIFFUSERS_ATTN_BACKEND``), from its
    private ``_AttentionBackendRegistry``."""
    from diffusers.models.attention_dispatch import _AttentionBackendRegistry

    return _AttentionBackendRegistry.get_active_backend()[0].value


def context_parallel_backends() -> Any:
    """``_AttentionBackendRegistry._supports_context_parallel``: the attention backends diffusers
    can split a sequence with."""
    from diffusers.models.attention_dispatch import _AttentionBackendRegistry

    return _AttentionBackendRegistry._supports_context_parallel
