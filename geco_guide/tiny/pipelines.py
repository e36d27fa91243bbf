"""Tiny stock diffusers pipelines of every family of the model registry (for the pipeline hooks,
the Modular Diffusers block, ``model.id=tiny-random`` and the tests): each built from ``seed`` with
the real diffusers and transformers classes at a few pixels, eval mode, progress bar off."""

from __future__ import annotations

from typing import Any

import torch

from .components import (
    TINY_HEIGHT,
    TINY_WIDTH,
    TinySizes,
    seeded,
    tiny_cogvideox_components,
    tiny_cogvideox_transformer,
    tiny_tokenizer,
)

__all__ = ["HUNYUAN15_LATENT_CHANNELS", "WAN22_LATENT_CHANNELS", "tiny_cogvideox15_pipeline",
           "tiny_cogvideox_i2v_pipeline", "tiny_cogvideox_pipeline", "tiny_hunyuan15_i2v_pipeline",
           "tiny_hunyuan15_pipeline", "tiny_hunyuan_pipeline", "tiny_image", "tiny_ltx2_pipeline", "tiny_ltx_pipeline",
           "tiny_wan22_a14b_pipeline", "tiny_wan22_ti2v_pipeline", "tiny_wan_modular_pipeline", "tiny_wan_pipeline"]

#: Latent channels of the Wan 2.2 VAE (TI2V-5B) and of the HunyuanVideo 1.5 VAE: the tiny
#: builders keep the real counts, which the tiny decoders ``wan2.2-5b`` / ``hunyuanvideo1.5`` take.
WAN22_LATENT_CHANNELS = 48
HUNYUAN15_LATENT_CHANNELS = 32


# ---- tiny pipelines of the other families (for the pipeline hooks) -----------------------------
#
# Every builder returns a stock diffusers pipeline (not a GeCo subclass) with all parts randomly
# initialised from ``seed``, eval mode, progress bar off. Call them with
# ``pipe(prompt, generator=..., **tiny_call_kwargs(pipe))``: 17 frames of 32x48 pixels, 4 steps.


def _tiny_t5(tokenizer, d_model: int = 16):
    from transformers import T5Config, T5EncoderModel

    return T5EncoderModel(
        T5Config(
            vocab_size=len(tokenizer),
            d_model=d_model,
            d_kv=8,
            d_ff=32,
            num_layers=1,
            num_heads=2,
            relative_attention_num_buckets=8,
            dropout_rate=0.0,
            pad_token_id=tokenizer.pad_token_id,
            eos_token_id=tokenizer.eos_token_id,
        )
    )


def _finish(pipe):
    for component in pipe.components.values():
        if isinstance(component, torch.nn.Module):
            component.eval()
    pipe.set_progress_bar_config(disable=True)
    return pipe


def tiny_cogvideox_pipeline(seed: int = 0, *, version: str = "1.0", scheduler: str = "ddim"):
    """A stock tiny ``CogVideoXPipeline``.

    ``version="1.5"`` builds the CogVideoX 1.5 layout: ``patch_size_t=2`` (so the pipeline pads
    the 5 latent frames of a 17-frame video to 6 at the front) and no patch bias.
    ``scheduler="dpm"`` swaps in ``CogVideoXDPMScheduler`` (the scheduler the checkpoints ship).
    """
    from diffusers import CogVideoXDPMScheduler, CogVideoXPipeline

    components = tiny_cogvideox_components(seed)
    if version == "1.5":
        sizes = TinySizes()
        state = seeded(seed + 1)
        try:
            components["transformer"] = tiny_cogvideox_transformer(sizes, patch_size_t=2, patch_bias=False).eval()
        finally:
            torch.random.set_rng_state(state)
    elif version != "1.0":
        raise ValueError(f"version must be '1.0' or '1.5', got {version!r}")
    if scheduler == "dpm":
        components["scheduler"] = CogVideoXDPMScheduler.from_config(components["scheduler"].config)
    elif scheduler != "ddim":
        raise ValueError(f"scheduler must be 'ddim' or 'dpm', got {scheduler!r}")
    return _finish(CogVideoXPipeline(**components))


def tiny_cogvideox15_pipeline(seed: int = 0):
    """A stock tiny ``CogVideoXPipeline`` of the CogVideoX 1.5 layout (:func:`tiny_cogvideox_pipeline`)."""
    return tiny_cogvideox_pipeline(seed, version="1.5")


def tiny_cogvideox_i2v_pipeline(seed: int = 0):
    """A stock tiny ``CogVideoXImageToVideoPipeline`` (the transformer sees latents + image latents)."""
    from diffusers import CogVideoXImageToVideoPipeline

    components = tiny_cogvideox_components(seed)
    sizes = TinySizes()
    state = seeded(seed + 2)
    try:
        # The image-to-video transformer sees the noisy latents and the image latents.
        components["transformer"] = tiny_cogvideox_transformer(sizes, in_channels=2 * sizes.latent_channels).eval()
    finally:
        torch.random.set_rng_state(state)
    return _finish(CogVideoXImageToVideoPipeline(**components))


def tiny_image(seed: int = 0, height: int = TINY_HEIGHT, width: int = TINY_WIDTH):
    """A seeded random RGB ``PIL.Image`` (the conditioning image of the image-to-video pipelines)."""
    import numpy as np
    from PIL import Image

    rng = np.random.default_rng(seed)
    return Image.fromarray(rng.integers(0, 256, size=(height, width, 3), dtype=np.uint8))


def tiny_wan_pipeline(seed: int = 0, *, scheduler: str = "unipc", version: str = "2.1"):
    """A stock tiny ``WanPipeline`` (Wan 2.1 layout): UMT5 text encoder, ``AutoencoderKLWan`` with
    per-channel ``latents_mean/std`` (r=4, 8x spatial), ``WanTransformer3DModel``.

    ``scheduler="unipc"`` (default, as the Wan 2.1 diffusers checkpoints: UniPC multistep with flow
    sigmas, a corrector that reads ``last_sample``) or ``"euler"`` (``FlowMatchEulerDiscreteScheduler``).
    ``version="2.2"`` adds Wan 2.2's second expert, ``transformer_2``, for the steps below
    ``boundary_ratio=0.875`` (of 4 UniPC steps: the last two); the other components stay those of 2.1.
    """
    from diffusers import (
        AutoencoderKLWan,
        FlowMatchEulerDiscreteScheduler,
        UniPCMultistepScheduler,
        WanPipeline,
        WanTransformer3DModel,
    )
    from transformers import UMT5Config, UMT5EncoderModel

    if version not in ("2.1", "2.2"):
        raise ValueError(f"version must be '2.1' or '2.2', got {version!r}")
    tokenizer = tiny_tokenizer()
    z_dim = 4
    state = seeded(seed)
    try:
        text_encoder = UMT5EncoderModel(
            UMT5Config(
                vocab_size=len(tokenizer),
                d_model=16,
                d_kv=8,
                d_ff=32,
                num_layers=1,
                num_heads=2,
                relative_attention_num_buckets=8,
                dropout_rate=0.0,
                pad_token_id=tokenizer.pad_token_id,
                eos_token_id=tokenizer.eos_token_id,
            )
        )
        vae = AutoencoderKLWan(
            base_dim=8,
            z_dim=z_dim,
            dim_mult=[1, 1, 1, 1],
            num_res_blocks=1,
            temperal_downsample=[False, True, True],
            latents_mean=[0.1, -0.2, 0.3, -0.1],
            latents_std=[1.5, 0.8, 1.2, 2.0],
        )
        transformer = WanTransformer3DModel(
            patch_size=(1, 2, 2),
            num_attention_heads=2,
            attention_head_dim=12,
            in_channels=z_dim,
            out_channels=z_dim,
            text_dim=16,
            freq_dim=32,
            ffn_dim=32,
            num_layers=1,
            cross_attn_norm=True,
            qk_norm="rms_norm_across_heads",
            rope_max_seq_len=32,
        )
        # drawn last, so that the components of 2.1 keep their weights
        transformer_2 = WanTransformer3DModel.from_config(transformer.config) if version == "2.2" else None
    finally:
        torch.random.set_rng_state(state)
    if scheduler == "unipc":
        sched = UniPCMultistepScheduler(
            prediction_type="flow_prediction", use_flow_sigmas=True, num_train_timesteps=1000, flow_shift=3.0
        )
    elif scheduler == "euler":
        sched = FlowMatchEulerDiscreteScheduler(shift=3.0)
    else:
        raise ValueError(f"scheduler must be 'unipc' or 'euler', got {scheduler!r}")
    pipe = WanPipeline(tokenizer=tokenizer, text_encoder=text_encoder, vae=vae, transformer=transformer, scheduler=sched,
                       transformer_2=transformer_2, boundary_ratio=0.875 if transformer_2 is not None else None)
    return _finish(pipe)


def tiny_wan_modular_pipeline(seed: int = 0, *, version: str = "2.1", denoise_loop: Any = None,
                              guidance_scale: float = 5.0, guidance_scale_2: float | None = None):
    """A tiny ``WanModularPipeline`` (``Wan22ModularPipeline`` for ``version="2.2"``) of diffusers'
    Wan blocks, with the components of :func:`tiny_wan_pipeline` of the same ``seed`` and
    ``version`` (the same weights) and CFG guiders of scale ``guidance_scale`` (the second expert's:
    ``guidance_scale_2``, by default the same), as ``WanPipeline`` calls them.

    Its blocks leave out diffusers' text encoder step (it needs the optional ``ftfy``): calls take
    ``prompt_embeds`` / ``negative_prompt_embeds`` (e.g. ``tiny_wan_pipeline(seed).encode_prompt``).
    ``denoise_loop``: a block in place of diffusers' denoise loop, e.g. the GeCo-guided
    :class:`~geco_guide.sampler.pipelines.modular.GeCoWanDenoiseStep` (``GeCoWan22DenoiseStep`` for 2.2).
    """
    from diffusers import ClassifierFreeGuidance
    from diffusers.modular_pipelines import Wan22Blocks, WanBlocks

    stock = tiny_wan_pipeline(seed, version=version)
    wan22 = version == "2.2"
    blocks = Wan22Blocks() if wan22 else WanBlocks()
    blocks.sub_blocks.pop("text_encoder")
    core = blocks.sub_blocks["denoise"]
    if denoise_loop is not None:
        core.sub_blocks["denoise"] = denoise_loop
    # (the pipeline's set_progress_bar_config reaches its top-level blocks only, not this loop)
    core.sub_blocks["denoise"].set_progress_bar_config(disable=True)
    pipe = blocks.init_pipeline()
    guiders = {"guider": ClassifierFreeGuidance(guidance_scale=guidance_scale)}
    if wan22:
        second = guidance_scale if guidance_scale_2 is None else guidance_scale_2
        guiders["guider_2"] = ClassifierFreeGuidance(guidance_scale=second)
        guiders["boundary_ratio"] = stock.config.boundary_ratio
    components = {name: stock.components[name] for name in blocks.component_names if stock.components.get(name) is not None}
    pipe.update_components(**components, **guiders)
    return pipe


def tiny_ltx_pipeline(seed: int = 0):
    """A stock tiny ``LTXPipeline``: packed latent tokens, ``AutoencoderKLLTXVideo`` with 8x temporal
    and 8x spatial compression (as LTX-Video's 8 x 32 x 32, scaled down), per-channel latent
    mean/std, a non-causal decoder, and the LTX-Video scheduler settings (dynamic shifting)."""
    from diffusers import (
        AutoencoderKLLTXVideo,
        FlowMatchEulerDiscreteScheduler,
        LTXPipeline,
        LTXVideoTransformer3DModel,
    )

    tokenizer = tiny_tokenizer()
    channels = 8
    state = seeded(seed)
    try:
        text_encoder = _tiny_t5(tokenizer)
        vae = AutoencoderKLLTXVideo(
            latent_channels=channels,
            block_out_channels=(8, 8, 8, 8),
            decoder_block_out_channels=(8, 8, 8, 8),
            layers_per_block=(1, 1, 1, 1, 1),
            decoder_layers_per_block=(1, 1, 1, 1, 1),
            spatio_temporal_scaling=(True, True, True, False),
            decoder_spatio_temporal_scaling=(True, True, True, False),
            patch_size=1,
            patch_size_t=1,
            encoder_causal=True,
            decoder_causal=False,
        )
        vae.use_framewise_encoding = False
        vae.use_framewise_decoding = False
        # non-trivial latent statistics, so that the de-normalisation before decoding matters
        vae.latents_mean.copy_(torch.linspace(-0.2, 0.2, channels))
        vae.latents_std.copy_(torch.linspace(0.8, 1.5, channels))
        transformer = LTXVideoTransformer3DModel(
            in_channels=channels,
            out_channels=channels,
            patch_size=1,
            patch_size_t=1,
            num_attention_heads=2,
            attention_head_dim=8,
            cross_attention_dim=16,
            num_layers=1,
            caption_channels=16,
        )
    finally:
        torch.random.set_rng_state(state)
    scheduler = FlowMatchEulerDiscreteScheduler(
        base_image_seq_len=1024,
        base_shift=0.95,
        max_image_seq_len=4096,
        max_shift=2.05,
        shift_terminal=0.1,
        use_dynamic_shifting=True,
    )
    pipe = LTXPipeline(scheduler=scheduler, vae=vae, text_encoder=text_encoder, tokenizer=tokenizer, transformer=transformer)
    return _finish(pipe)


def tiny_hunyuan_pipeline(seed: int = 0):
    """A stock tiny ``HunyuanVideoPipeline``: a tiny Llama (hidden states) + CLIP text encoder pair,
    ``AutoencoderKLHunyuanVideo`` (r=4, 8x spatial), ``HunyuanVideoTransformer3DModel`` with the
    distilled guidance embedding, and the flow-matching Euler scheduler (shift 7)."""
    from diffusers import (
        AutoencoderKLHunyuanVideo,
        FlowMatchEulerDiscreteScheduler,
        HunyuanVideoPipeline,
        HunyuanVideoTransformer3DModel,
    )
    from transformers import CLIPTextConfig, CLIPTextModel, LlamaConfig, LlamaModel

    tokenizer = tiny_tokenizer(max_length=128)
    tokenizer_2 = tiny_tokenizer(max_length=77)
    state = seeded(seed)
    try:
        text_encoder = LlamaModel(
            LlamaConfig(
                vocab_size=len(tokenizer),
                hidden_size=16,
                intermediate_size=32,
                num_attention_heads=2,
                num_key_value_heads=2,
                num_hidden_layers=3,
                max_position_embeddings=256,
                pad_token_id=tokenizer.pad_token_id,
                bos_token_id=tokenizer.eos_token_id,
                eos_token_id=tokenizer.eos_token_id,
            )
        )
        text_encoder_2 = CLIPTextModel(
            CLIPTextConfig(
                vocab_size=len(tokenizer_2),
                hidden_size=8,
                intermediate_size=16,
                num_attention_heads=2,
                num_hidden_layers=1,
                max_position_embeddings=77,
                projection_dim=8,
                pad_token_id=tokenizer_2.pad_token_id,
                bos_token_id=tokenizer_2.eos_token_id,
                eos_token_id=tokenizer_2.eos_token_id,
            )
        )
        vae = AutoencoderKLHunyuanVideo(
            latent_channels=4,
            block_out_channels=(8, 8, 8, 8),
            layers_per_block=1,
            norm_num_groups=4,
            spatial_compression_ratio=8,
            temporal_compression_ratio=4,
            mid_block_add_attention=True,
        )
        transformer = HunyuanVideoTransformer3DModel(
            in_channels=4,
            out_channels=4,
            num_attention_heads=2,
            attention_head_dim=10,
            num_layers=1,
            num_single_layers=1,
            num_refiner_layers=1,
            patch_size=1,
            patch_size_t=1,
            guidance_embeds=True,
            text_embed_dim=16,
            pooled_projection_dim=8,
            rope_axes_dim=(2, 4, 4),
        )
    finally:
        torch.random.set_rng_state(state)
    pipe = HunyuanVideoPipeline(
        text_encoder=text_encoder,
        tokenizer=tokenizer,
        transformer=transformer,
        vae=vae,
        scheduler=FlowMatchEulerDiscreteScheduler(shift=7.0),
        text_encoder_2=text_encoder_2,
        tokenizer_2=tokenizer_2,
    )
    return _finish(pipe)


def tiny_wan22_ti2v_pipeline(seed: int = 0):
    """A stock tiny ``WanPipeline`` in the Wan 2.2 TI2V-5B layout: :func:`tiny_wan_pipeline`'s text
    encoder, ``AutoencoderKLWan`` as the Wan 2.2 VAE (48 latent channels, residual blocks, 2x2 pixel
    patches: 16x spatial, 4x temporal; its own ``latents_mean/std``), ``expand_timesteps=True`` (a
    timestep per latent token) and the flow UniPC scheduler (shift 5). Latents ``[B, 48, F, h, w]``;
    :func:`tiny_call_kwargs` makes 32x64 frames (16x VAE and 2x2 transformer patches)."""
    from diffusers import AutoencoderKLWan, UniPCMultistepScheduler, WanPipeline, WanTransformer3DModel

    wan, channels = tiny_wan_pipeline(seed), WAN22_LATENT_CHANNELS
    state = seeded(seed + 1)
    try:
        vae = AutoencoderKLWan(
            base_dim=8, z_dim=channels, dim_mult=[1, 1, 1, 1], num_res_blocks=1, temperal_downsample=[False, True, True],
            is_residual=True, in_channels=12, out_channels=12, patch_size=2,  # 12 = 3 colours x the 2x2 patch
            scale_factor_spatial=16, scale_factor_temporal=4,
            latents_mean=torch.linspace(-0.3, 0.3, channels).tolist(), latents_std=torch.linspace(0.6, 1.8, channels).tolist(),
        )
        transformer = WanTransformer3DModel.from_config(wan.transformer.config, in_channels=channels, out_channels=channels)
    finally:
        torch.random.set_rng_state(state)
    scheduler = UniPCMultistepScheduler(prediction_type="flow_prediction", use_flow_sigmas=True, flow_shift=5.0)
    return _finish(WanPipeline(tokenizer=wan.tokenizer, text_encoder=wan.text_encoder, vae=vae, transformer=transformer,
                               scheduler=scheduler, expand_timesteps=True))


def tiny_wan22_a14b_pipeline(seed: int = 0):
    """A stock tiny ``WanPipeline`` of the Wan 2.2 T2V-A14B layout: :func:`tiny_wan_pipeline` of
    ``version="2.2"`` (two experts, each with its own CFG scale: ``guidance_scale``,
    ``guidance_scale_2``)."""
    return tiny_wan_pipeline(seed, version="2.2")


_HUNYUAN15_TEXT_TOKENS, _HUNYUAN15_IMAGE_DIM = 16, 12


def _tiny_hunyuan15_components(seed: int, task: str, guidance_scale: float, guidance_rescale: float) -> dict[str, Any]:
    """The parts of the tiny HunyuanVideo 1.5 pipelines (``task``: the transformer's, ``"t2v"`` or
    ``"i2v"``), randomly initialised from ``seed``."""
    from diffusers import AutoencoderKLHunyuanVideo15, FlowMatchEulerDiscreteScheduler, HunyuanVideo15Transformer3DModel
    from diffusers.guiders import ClassifierFreeGuidance
    from transformers import ByT5Tokenizer, Qwen2_5_VLTextConfig, Qwen2_5_VLTextModel, T5Config, T5EncoderModel

    channels = HUNYUAN15_LATENT_CHANNELS
    # prompts are chats (the role contents in turn), padded to tokenizer_max_length + 108 tokens; the
    # pipeline drops the first 108 (the system message's)
    tokenizer = tiny_tokenizer(max_length=_HUNYUAN15_TEXT_TOKENS + 108)
    tokenizer.chat_template = "{% for message in messages %}{{ message['content'] }} {% endfor %}"
    tokenizer_2 = ByT5Tokenizer()
    state = seeded(seed)
    try:
        text_encoder = Qwen2_5_VLTextModel(Qwen2_5_VLTextConfig(
            vocab_size=len(tokenizer), hidden_size=16, intermediate_size=32, num_hidden_layers=3, num_attention_heads=2,
            num_key_value_heads=2, rope_scaling={"mrope_section": [1, 1, 2], "rope_type": "default", "type": "default"},
            pad_token_id=tokenizer.pad_token_id, bos_token_id=tokenizer.eos_token_id, eos_token_id=tokenizer.eos_token_id,
        ))
        text_encoder_2 = T5EncoderModel(T5Config(
            vocab_size=len(tokenizer_2), d_model=8, d_kv=4, d_ff=16, num_layers=1, num_heads=2,
            relative_attention_num_buckets=8, dropout_rate=0.0, pad_token_id=tokenizer_2.pad_token_id,
            eos_token_id=tokenizer_2.eos_token_id,
        ))
        vae = AutoencoderKLHunyuanVideo15(  # the encoder's last width: a multiple of 2 x the latent channels
            latent_channels=channels, block_out_channels=(4, 8, 16, 32, 64), layers_per_block=1,
            spatial_compression_ratio=16, temporal_compression_ratio=4, scaling_factor=1.03682,
        )
        transformer = HunyuanVideo15Transformer3DModel(
            in_channels=2 * channels + 1, out_channels=channels, num_attention_heads=2, attention_head_dim=8,
            num_layers=1, num_refiner_layers=1, mlp_ratio=2.0, text_embed_dim=16, text_embed_2_dim=8,
            image_embed_dim=_HUNYUAN15_IMAGE_DIM, rope_axes_dim=(2, 2, 4), target_size=32, task_type=task,
        )
    finally:
        torch.random.set_rng_state(state)
    return dict(text_encoder=text_encoder, tokenizer=tokenizer, transformer=transformer, vae=vae,
                scheduler=FlowMatchEulerDiscreteScheduler(shift=5.0), text_encoder_2=text_encoder_2,
                tokenizer_2=tokenizer_2,
                guider=ClassifierFreeGuidance(guidance_scale=guidance_scale, guidance_rescale=guidance_rescale))


def _shorter_hunyuan15_sequences(pipe):
    """Shorter text and image-token sequences than the real 1000 + 256 + 729: instance attributes
    the pipeline sets in ``__init__``, so a saved and reloaded tiny pipeline gets the real lengths
    back (and runs as well, only slower)."""
    pipe.tokenizer_max_length = pipe.tokenizer_2_max_length = _HUNYUAN15_TEXT_TOKENS
    pipe.vision_num_semantic_tokens = 4
    return _finish(pipe)


def tiny_hunyuan15_pipeline(seed: int = 0, *, guidance_scale: float = 6.0, guidance_rescale: float = 0.0):
    """A stock tiny ``HunyuanVideo15Pipeline``: a tiny Qwen2.5-VL text model (chat prompts) + ByT5
    glyph encoder, ``AutoencoderKLHunyuanVideo15`` (32 latent channels as the real one, 16x spatial
    and 4x temporal compression, causal), ``HunyuanVideo15Transformer3DModel`` (its input: the
    latents, the image-condition latents and a mask, along channels), CFG by diffusers'
    ``ClassifierFreeGuidance`` guider (``guidance_scale``, ``guidance_rescale``), the flow-matching
    Euler scheduler (shift 5)."""
    from diffusers import HunyuanVideo15Pipeline

    components = _tiny_hunyuan15_components(seed, "t2v", guidance_scale, guidance_rescale)
    return _shorter_hunyuan15_sequences(HunyuanVideo15Pipeline(**components))


def tiny_hunyuan15_i2v_pipeline(seed: int = 0, *, guidance_scale: float = 6.0):
    """A stock tiny ``HunyuanVideo15ImageToVideoPipeline``: :func:`tiny_hunyuan15_pipeline`'s parts
    with an image-to-video transformer, a tiny SigLIP vision encoder and its image processor. The
    pipeline takes the video size from the image (the transformer's ``target_size`` bucket), puts
    the image's latent first in the condition channels, and generates every latent."""
    from diffusers import HunyuanVideo15ImageToVideoPipeline
    from transformers import SiglipImageProcessor, SiglipVisionConfig, SiglipVisionModel

    components = _tiny_hunyuan15_components(seed, "i2v", guidance_scale, 0.0)
    state = seeded(seed + 1)
    try:
        image_encoder = SiglipVisionModel(SiglipVisionConfig(
            hidden_size=_HUNYUAN15_IMAGE_DIM, intermediate_size=16, num_hidden_layers=1, num_attention_heads=2,
            image_size=16, patch_size=8))
    finally:
        torch.random.set_rng_state(state)
    return _shorter_hunyuan15_sequences(HunyuanVideo15ImageToVideoPipeline(
        **components, image_encoder=image_encoder, feature_extractor=SiglipImageProcessor(size={"height": 16, "width": 16})))


def tiny_ltx2_pipeline(seed: int = 0):
    """A stock tiny ``LTX2Pipeline`` (video and audio from one joint transformer): a tiny Gemma 3
    text encoder, ``LTX2TextConnectors``, ``LTX2VideoTransformer3DModel`` (video and audio streams
    with cross-attention between them), ``AutoencoderKLLTX2Video`` (8x temporal compression and a
    non-causal decoder as LTX-2's; 8x spatial instead of 32x, so that 32-pixel frames keep a few
    latents; per-channel latent mean/std), ``AutoencoderKLLTX2Audio``, ``LTX2Vocoder`` and the
    flow-matching Euler scheduler with dynamic shifting. Video latents: packed tokens ``[B, S, C]``."""
    from diffusers import (AutoencoderKLLTX2Audio, AutoencoderKLLTX2Video, FlowMatchEulerDiscreteScheduler,
                           LTX2Pipeline, LTX2VideoTransformer3DModel)
    from diffusers.pipelines.ltx2 import LTX2TextConnectors
    from diffusers.pipelines.ltx2.vocoder import LTX2Vocoder
    from transformers import Gemma3Config, Gemma3ForConditionalGeneration, Gemma3TextConfig, SiglipVisionConfig

    tokenizer, channels, text_dim, text_layers = tiny_tokenizer(), 8, 16, 2
    state = seeded(seed)
    try:
        text_encoder = Gemma3ForConditionalGeneration(Gemma3Config(
            text_config=Gemma3TextConfig(
                vocab_size=len(tokenizer), hidden_size=text_dim, intermediate_size=32, num_hidden_layers=text_layers,
                num_attention_heads=2, num_key_value_heads=1, head_dim=8, sliding_window=16,
                pad_token_id=tokenizer.pad_token_id, eos_token_id=tokenizer.eos_token_id,
                bos_token_id=tokenizer.eos_token_id).to_dict(),
            vision_config=SiglipVisionConfig(hidden_size=8, intermediate_size=16, num_hidden_layers=1,
                                             num_attention_heads=2, image_size=16, patch_size=8).to_dict(),
            mm_tokens_per_image=4))
        connector = dict(num_attention_heads=2, attention_head_dim=8, num_layers=1, num_learnable_registers=None)
        connectors = LTX2TextConnectors(  # projects the stacked hidden states of every text layer
            caption_channels=text_dim, text_proj_in_factor=text_layers + 1, connector_rope_base_seq_len=32,
            rope_double_precision=False, rope_type="split",
            **{f"{stream}_connector_{key}": value for stream in ("video", "audio") for key, value in connector.items()})
        transformer = LTX2VideoTransformer3DModel(
            in_channels=channels, out_channels=channels, num_attention_heads=2, attention_head_dim=8,
            cross_attention_dim=16, vae_scale_factors=(8, 8, 8), audio_in_channels=4, audio_out_channels=4,
            audio_num_attention_heads=2, audio_attention_head_dim=4, audio_cross_attention_dim=8, num_layers=2,
            caption_channels=text_dim, rope_double_precision=False, rope_type="split")
        vae = AutoencoderKLLTX2Video(
            latent_channels=channels, block_out_channels=(8, 8, 8, 8), decoder_block_out_channels=(8, 16, 32),
            layers_per_block=(1, 1, 1, 1, 1), decoder_layers_per_block=(1, 1, 1, 1),
            downsample_type=("spatial", "temporal", "spatiotemporal", "spatiotemporal"), patch_size=1,
            decoder_causal=False, spatial_compression_ratio=8, temporal_compression_ratio=8)
        # non-trivial latent statistics, so that the de-normalisation before decoding matters
        vae.latents_mean.copy_(torch.linspace(-0.2, 0.2, channels))
        vae.latents_std.copy_(torch.linspace(0.8, 1.5, channels))
        audio_vae = AutoencoderKLLTX2Audio(base_channels=4, ch_mult=(1,), num_res_blocks=1, resolution=32,
                                           latent_channels=2, mel_bins=8)
        # 160x upsampling, the mel hop: a waveform as long as the video at 16 kHz, as LTX-2's (240x to 24 kHz)
        vocoder = LTX2Vocoder(in_channels=audio_vae.config.output_channels * audio_vae.config.mel_bins, hidden_channels=8,
                              upsample_kernel_sizes=[8, 8, 20], upsample_factors=[4, 4, 10], resnet_kernel_sizes=[3],
                              resnet_dilations=[[1, 3, 5]], output_sampling_rate=audio_vae.config.sample_rate)
    finally:
        torch.random.set_rng_state(state)
    scheduler = FlowMatchEulerDiscreteScheduler(base_image_seq_len=1024, base_shift=0.95, max_image_seq_len=4096,
                                                max_shift=2.05, shift_terminal=0.1, use_dynamic_shifting=True)
    return _finish(LTX2Pipeline(scheduler=scheduler, vae=vae, audio_vae=audio_vae, text_encoder=text_encoder,
                                tokenizer=tokenizer, connectors=connectors, transformer=transformer, vocoder=vocoder))
