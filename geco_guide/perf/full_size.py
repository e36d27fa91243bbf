"""Full-size models without weights: every traced registry model's denoiser(s), VAE and scheduler
built from its published configs (:mod:`geco_guide.families.published`), random-initialised cheaply
or left on the meta device, and fake-tensor copies of any model.

Nothing is downloaded. On the meta device nothing is allocated (for tests and the cost model);
:func:`to_fake` then gives a model fake CPU tensors of the same shapes and dtypes, so a
``FakeTensorMode`` can run it.
"""

from __future__ import annotations

import inspect
from typing import Any

import torch
from torch import Tensor

from ..estimators.bundle import Estimators
from ..estimators.tiny_decoder import TinyDecoder
from ..estimators.ufm import UFM, UFMConfig
from ..estimators.vggt import VGGT, VGGTConfig
from ..families import DEFAULT_MODEL, model_named
from ..families.published import published_configs
from ..sampler.diffusers_private import keeps_in_fp32
from ..sampler.pipelines.loading import cast_model

__all__ = ["CALIBRATION_MODEL", "build_cost_pipeline", "build_full_size_components", "cast_as_loaded",
           "cast_components", "full_size_vae", "materialise", "model_bytes", "model_video", "stock_pipeline",
           "text_embed_shape", "text_encoder_stand_in", "to_fake"]

#: The model whose measured H200 step calibrates the cost model: the paper's CogVideoX-5B, the default.
CALIBRATION_MODEL = DEFAULT_MODEL


def model_video(name: str) -> dict[str, int]:
    """``frames``, ``height``, ``width`` of registry model ``name``'s default call (the paper's 49
    frames of 480x720 for CogVideoX-5B)."""
    call = model_named(name).call
    return {"frames": call["num_frames"], "height": call["height"], "width": call["width"]}


def text_embed_shape(name: str) -> tuple[int, int, int]:
    """``[1, tokens, dim]`` of one prompt's text embeddings as registry model ``name``'s pipeline
    hands them to its denoiser: the prompt length it pads to, the width its denoiser takes
    (CogVideoX's T5 embeddings are ``[1, 226, 4096]``)."""
    published = published_configs(name)
    config = published.transformer
    dim = next(config[key] for key in ("text_embed_dim", "text_dim", "caption_channels") if key in config)
    return 1, published.prompt_tokens, dim


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


def cast_as_loaded(model: torch.nn.Module, dtype: torch.dtype) -> torch.nn.Module:
    """``model`` cast to ``dtype`` as ``from_pretrained(torch_dtype=dtype)`` loads it: the modules
    its class keeps in float32 (``_keep_in_fp32_modules``: Wan's norms and time embedding, ...) stay
    float32. Returns ``model``."""
    torch.nn.Module.to(model, dtype)
    keep = keeps_in_fp32(model)
    for name, module in model.named_modules():
        if any(part in keep for part in name.split(".")):
            torch.nn.Module.to(module, torch.float32)
    return model


def materialise(config: dict[str, Any], device: str | torch.device, dtype: torch.dtype, seed: int) -> Any:
    """The diffusers model of a published ``config`` (its ``_class_name`` and keys, read by the
    class's ``from_config`` as ``from_pretrained`` reads a config.json: the keys this version of the
    class does not know are left out) built on the meta device, then allocated in ``dtype``
    (:func:`cast_as_loaded`) on ``device`` with :func:`init_weights_` (left on meta when ``device``
    is meta), in eval mode."""
    import diffusers

    cls = getattr(diffusers, config["_class_name"])
    with torch.device("meta"):
        model = cls.from_config({key: value for key, value in config.items()})
    cast_as_loaded(model, dtype)
    if torch.device(device).type != "meta":
        model.to_empty(device=device)
        init_weights_(model, seed)
    return model.eval()


def full_size_vae(device: str | torch.device, dtype: torch.dtype, seed: int, model: str = CALIBRATION_MODEL) -> Any:
    """Registry model ``model``'s VAE with random weights (:func:`materialise`)."""
    return materialise(published_configs(model).vae, device, dtype, seed)


def build_full_size_components(model: str, device: str | torch.device, dtype: torch.dtype,
                               seed: int = 0) -> dict[str, Any]:
    """Registry model ``model``'s denoiser(s) (Wan 2.2 A14B: ``transformer`` and
    ``transformer_2``) and VAE (random weights, ``dtype``, on ``device``) and its scheduler, from its
    published configs, and its pipeline's own settings (``boundary_ratio``, ...). The CogVideoX
    models get the DDIM scheduler the GeCo pipeline samples with.

    Built on the meta device and materialised with ``to_empty`` directly in ``dtype``; with
    ``device="meta"`` nothing is allocated (for tests). No tokenizer or text encoder.
    """
    import diffusers

    published = published_configs(model)
    components = {"vae": materialise(published.vae, device, dtype, seed + 1),
                  "transformer": materialise(published.transformer, device, dtype, seed),
                  "scheduler": getattr(diffusers, published.scheduler["_class_name"]).from_config(published.scheduler)}
    if published.transformer_2 is not None:
        components["transformer_2"] = materialise(published.transformer_2, device, dtype, seed + 2)
    return {**components, **published.pipeline}


def text_encoder_stand_in(model: str, seed: int = 0) -> dict[str, Any]:
    """``tokenizer`` and ``text_encoder`` for registry model ``model``'s pipeline with random
    weights: a one-layer T5 of the width its denoiser takes (T5-XXL's 4096 for CogVideoX), over
    the tiny preset's small word-level tokenizer padding to the model's prompt length. The random
    models make noise of any prompt; the full-size text encoder would add its weights and one
    forward per call that the harness does not time."""
    from transformers import T5Config, T5EncoderModel

    from ..tiny.components import seeded, tiny_tokenizer

    _, tokens, width = text_embed_shape(model)
    tokenizer = tiny_tokenizer(max_length=tokens)
    state = seeded(seed)
    try:
        encoder = T5EncoderModel(T5Config(vocab_size=len(tokenizer), d_model=width, d_kv=64, d_ff=64, num_layers=1,
                                          num_heads=width // 64, dropout_rate=0.0, pad_token_id=tokenizer.pad_token_id,
                                          eos_token_id=tokenizer.eos_token_id))
    finally:
        torch.random.set_rng_state(state)
    return {"tokenizer": tokenizer, "text_encoder": encoder.eval()}


def stock_pipeline(model: str, components: dict[str, Any]) -> Any:
    """Registry model ``model``'s diffusers pipeline class holding ``components`` (its other
    components, the text encoders and tokenizers, ``None``)."""
    import diffusers

    cls = getattr(diffusers, model_named(model).pipeline)
    accepted = inspect.signature(cls.__init__).parameters
    given = {name: components.get(name) for name in accepted if name != "self"
             and accepted[name].kind is inspect.Parameter.POSITIONAL_OR_KEYWORD}
    return cls(**{name: value for name, value in given.items() if name in components or
                  accepted[name].default is inspect.Parameter.empty})


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
    estimators. Full size: ``settings["model"]``'s denoiser(s) and VAE from its published configs
    (in the GeCo pipeline for the models it guides, in the stock pipeline otherwise), VGGT-1B and
    UFM-Base (trunks in ``dtype``, heads float32) and, with ``decoder="tiny"``, the model's tiny
    decoder, built on the meta device: nothing is allocated."""
    dtype = getattr(torch, settings["dtype"])
    decoder = None
    if settings["preset"] == "tiny":
        from ..tiny import TINY_MAX_SEQUENCE_LENGTH, tiny_estimators, tiny_guidance_decoder, tiny_pipeline

        pipe = tiny_pipeline(settings["seed"])
        tiny = tiny_estimators(settings["seed"])
        geometry, flow = tiny.geometry, tiny.flow
        decoder = tiny_guidance_decoder(seed=settings["seed"]) if settings.get("decoder") == "tiny" else None
        cast_components(pipe, dtype)
        call = {"prompt": "a red cube on a table", "max_sequence_length": TINY_MAX_SEQUENCE_LENGTH}
    else:
        name, ckpt = settings["model"], settings["estimator_checkpointing"]
        with torch.device("meta"):
            geometry = VGGT(VGGTConfig(), gradient_checkpointing=ckpt)
            flow = UFM(UFMConfig(), gradient_checkpointing=ckpt)
        geometry.trunk_to(dtype).eval()
        flow.trunk_to(dtype).eval()
        if settings.get("decoder") == "tiny":
            with torch.device("meta"):
                decoder = TinyDecoder(model_named(name).tiny_decoder).to(dtype).requires_grad_(False)
        components = build_full_size_components(name, "meta", dtype, settings["seed"])
        if model_named(name).guided_by == "pipeline":
            from ..sampler.pipelines.pipeline_cogvideox import GeCoCogVideoXPipeline

            pipe = GeCoCogVideoXPipeline(tokenizer=None, text_encoder=None, **components)
        else:
            pipe = stock_pipeline(name, components)
        call = {"max_sequence_length": text_embed_shape(name)[1]}
    estimators = Estimators(geometry, flow, tiny_decoder=decoder)
    for model in (*pipe.components.values(), *estimators.modules()):
        if isinstance(model, torch.nn.Module):
            to_fake(model, fake_mode)
    if settings["vae_tiling"]:
        pipe.vae.enable_tiling()
    pipe.set_progress_bar_config(disable=True)
    call.update(num_frames=settings["frames"], height=settings["height"], width=settings["width"], output_type="pt")
    return pipe, call, estimators
