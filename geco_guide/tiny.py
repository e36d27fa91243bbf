"""Tiny, randomly initialised, offline stand-ins for the real models: the ``tiny`` preset and the
``tiny-random`` ids, GeCo-Eval's ``--preset tiny``, the tests and the runnable examples.

:func:`tiny_pipeline` returns a ready :class:`GeCoCogVideoXPipeline` whose every component is
built here from a seed: a word-level T5-style tokenizer made with the ``tokenizers`` library, a
tiny ``T5EncoderModel``, ``CogVideoXTransformer3DModel`` and ``AutoencoderKLCogVideoX`` (temporal
compression 4, spatial 8, so the real frame <-> latent mapping is exercised), the DDIM scheduler
with the CogVideoX-5b scheduler settings; :func:`tiny_estimators` the tiny random VGGT / UFM.
Every family of the model registry (:mod:`geco_guide.families`) has its builder here, which the
registry names (:func:`tiny_video_components`). Nothing is downloaded. The outputs are noise-like
videos; only the mechanics are real.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import torch
from transformers import PreTrainedTokenizerFast

from .estimators import Estimators, tiny_estimators, tiny_random_decoder
from .families import VideoModel

__all__ = ["HUNYUAN15_LATENT_CHANNELS", "TINY_ANCHORS", "TINY_CALL_KWARGS", "TINY_HEIGHT",
           "TINY_MAX_SEQUENCE_LENGTH", "TINY_NUM_FRAMES", "TINY_WIDTH", "TinySizes", "TinyTokenizer",
           "WAN22_LATENT_CHANNELS", "tiny_bundle", "tiny_call_extras", "tiny_call_kwargs", "tiny_cogvideox15_pipeline",
           "tiny_cogvideox_components", "tiny_cogvideox_i2v_pipeline", "tiny_cogvideox_pipeline",
           "tiny_cogvideox_transformer", "tiny_estimators", "tiny_guidance_config", "tiny_guidance_decoder",
           "tiny_hunyuan15_i2v_pipeline", "tiny_hunyuan15_pipeline", "tiny_hunyuan_pipeline", "tiny_ltx2_pipeline",
           "tiny_ltx_pipeline", "tiny_pipeline", "tiny_run_options", "tiny_sampling", "tiny_tokenizer",
           "tiny_video_components", "tiny_wan22_a14b_pipeline", "tiny_wan22_ti2v_pipeline", "tiny_wan_modular_pipeline",
           "tiny_wan_pipeline"]

# Tiny sampling settings that fit the tiny models (17 frames = 5 latents, 32x48 pixels).
TINY_NUM_FRAMES = 17
TINY_HEIGHT = 32
TINY_WIDTH = 48
TINY_ANCHORS = (4, 8, 12, 16)
TINY_MAX_SEQUENCE_LENGTH = 16

_SPECIAL = ["<pad>", "</s>", "<unk>"]
_WORDS = (
    "a an the of on in at with and to from by for is are over under near its this that "
    "marble bust statue head face man woman person child dog cat horse bird car train boat ship "
    "house building city street road bridge tower castle church room table chair kitchen garden "
    "tree forest mountain hill river lake sea ocean beach sky cloud sun moon star snow rain "
    "red green blue white black golden silver old new small big tall wooden stone glass "
    "walking running flying turning rotating moving standing sitting camera orbit pan zoom slow "
    "fast view shot close wide aerial scene video light night day sunset morning . ,"
).split()


class TinyTokenizer(PreTrainedTokenizerFast):
    """Truncates at ``model_max_length`` unless a call says otherwise. The pipelines tokenize
    each prompt twice, truncated at ``max_sequence_length`` and once more untruncated to warn
    about what was cut; at the tiny preset's 16 tokens nearly every prompt is cut, and that
    second pass printed transformers' "longer than the specified maximum" line and a line of
    the cut words (mostly ``<unk>``: the vocabulary is small) on every call. A module-level
    class, so that a saved tiny pipeline loads again (``model_index.json`` names it)."""

    def __call__(self, *args: Any, truncation: Any = True, **kwargs: Any) -> Any:
        return super().__call__(*args, truncation=truncation, **kwargs)


def tiny_tokenizer(max_length: int = TINY_MAX_SEQUENCE_LENGTH):
    """A T5-compatible fast tokenizer over a small fixed word list (lower-cased, ``</s>`` appended)
    that truncates at ``max_length`` by default (so long prompts are cut quietly, as the
    pipelines cut them at ``max_sequence_length``)."""
    from tokenizers import Tokenizer, normalizers, pre_tokenizers, processors
    from tokenizers.models import WordLevel

    vocab = {tok: i for i, tok in enumerate(_SPECIAL + list(dict.fromkeys(_WORDS)))}
    tok = Tokenizer(WordLevel(vocab=vocab, unk_token="<unk>"))
    tok.normalizer = normalizers.Sequence([normalizers.NFKC(), normalizers.Lowercase()])
    tok.pre_tokenizer = pre_tokenizers.Whitespace()
    tok.post_processor = processors.TemplateProcessing(
        single="$A </s>", pair="$A </s> $B </s>", special_tokens=[("</s>", vocab["</s>"])]
    )
    return TinyTokenizer(
        tokenizer_object=tok,
        pad_token="<pad>",
        eos_token="</s>",
        unk_token="<unk>",
        model_max_length=max_length,
        padding_side="right",
    )


def _seeded(seed: int):
    gen_state = torch.random.get_rng_state()
    torch.manual_seed(seed)
    return gen_state


@dataclass
class TinySizes:
    """Sizes of the tiny CogVideoX parts."""

    text_dim: int = 16
    heads: int = 2
    head_dim: int = 16  # rotary 3-D embeddings need head_dim divisible by 8 (t/h/w split)
    layers: int = 1
    latent_channels: int = 4
    vae_channels: tuple[int, ...] = field(default_factory=lambda: (8, 8, 8, 8))


def tiny_cogvideox_transformer(sizes: TinySizes, **changes: Any):
    """A tiny ``CogVideoXTransformer3DModel`` (1.0 layout unless ``changes`` say otherwise),
    initialised from the global RNG: callers seed it."""
    from diffusers import CogVideoXTransformer3DModel

    kwargs = dict(
        num_attention_heads=sizes.heads,
        attention_head_dim=sizes.head_dim,
        in_channels=sizes.latent_channels,
        out_channels=sizes.latent_channels,
        time_embed_dim=8,
        text_embed_dim=sizes.text_dim,
        num_layers=sizes.layers,
        sample_width=TINY_WIDTH // 8,
        sample_height=TINY_HEIGHT // 8,
        sample_frames=TINY_NUM_FRAMES,
        patch_size=2,
        temporal_compression_ratio=4,
        max_text_seq_length=TINY_MAX_SEQUENCE_LENGTH,
        use_rotary_positional_embeddings=True,
        use_learned_positional_embeddings=False,
    )
    return CogVideoXTransformer3DModel(**{**kwargs, **changes})


def tiny_cogvideox_components(seed: int = 0, sizes: TinySizes | None = None) -> dict[str, Any]:
    """Tokenizer, text encoder, VAE, transformer and DDIM scheduler, randomly initialised from ``seed``."""
    from diffusers import AutoencoderKLCogVideoX, CogVideoXDDIMScheduler
    from transformers import T5Config, T5EncoderModel

    sizes = sizes or TinySizes()
    tokenizer = tiny_tokenizer()
    state = _seeded(seed)
    try:
        text_encoder = T5EncoderModel(
            T5Config(
                vocab_size=len(tokenizer),
                d_model=sizes.text_dim,
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
        vae = AutoencoderKLCogVideoX(
            in_channels=3,
            out_channels=3,
            down_block_types=("CogVideoXDownBlock3D",) * len(sizes.vae_channels),
            up_block_types=("CogVideoXUpBlock3D",) * len(sizes.vae_channels),
            block_out_channels=sizes.vae_channels,
            latent_channels=sizes.latent_channels,
            layers_per_block=1,
            norm_num_groups=2,
            temporal_compression_ratio=4,
        )
        transformer = tiny_cogvideox_transformer(sizes)
    finally:
        torch.random.set_rng_state(state)
    # The CogVideoX-5b scheduler settings (v-prediction, zero terminal SNR, trailing spacing).
    scheduler = CogVideoXDDIMScheduler(
        beta_start=0.00085,
        beta_end=0.012,
        beta_schedule="scaled_linear",
        clip_sample=False,
        prediction_type="v_prediction",
        rescale_betas_zero_snr=True,
        set_alpha_to_one=True,
        snr_shift_scale=1.0,
        steps_offset=0,
        timestep_spacing="trailing",
    )
    for model in (text_encoder, vae, transformer):
        model.eval()
    return {
        "tokenizer": tokenizer,
        "text_encoder": text_encoder,
        "vae": vae,
        "transformer": transformer,
        "scheduler": scheduler,
    }


def tiny_video_components(model: VideoModel, seed: int = 0) -> dict[str, Any]:
    """What ``model``'s tiny random stand-in (the builder its registry entry names), seeded with
    ``seed``, is built from: its components and the settings of its config that its class takes
    (Wan 2.2's ``boundary_ratio``, ``expand_timesteps``): what ``model.id=tiny-random`` loads."""
    import inspect

    if model.tiny is None:
        raise ValueError(f"{model.name} has no tiny random stand-in")
    pipe = globals()[model.tiny](seed)
    accepted = inspect.signature(type(pipe).__init__).parameters
    settings = {key: value for key, value in pipe.config.items() if key in accepted and key not in pipe.components}
    return {**pipe.components, **settings}


def tiny_sampling(model: VideoModel) -> dict[str, int]:
    """The ``sampling`` of a tiny stand-in of ``model``'s family: 17 frames of 32x48 pixels (the
    width of 64 where the model wants sizes in multiples of 32)."""
    width = TINY_WIDTH if TINY_WIDTH % model.size_multiple == 0 else -(-TINY_WIDTH // model.size_multiple) * model.size_multiple
    height = TINY_HEIGHT if TINY_HEIGHT % model.size_multiple == 0 else -(-TINY_HEIGHT // model.size_multiple) * model.size_multiple
    return {"num_frames": TINY_NUM_FRAMES, "height": height, "width": width}


def tiny_bundle(seed: int = 0, **more: Any) -> Estimators:
    """The tiny random VGGT and UFM (:func:`tiny_estimators`) as one
    :class:`~geco_guide.estimators.Estimators`, with ``more`` of its fields (``segmenter``,
    ``tiny_decoder``)."""
    return Estimators(*tiny_estimators(seed), **more)


def tiny_guidance_decoder(variant: str = "cogvideox", seed: int = 0, latent_channels: int = TinySizes.latent_channels):
    """A tiny random :class:`~geco_guide.estimators.tiny_decoder.TinyDecoder` of ``variant`` for the
    tiny models' latents (their channel count; the published variants take 16 or more)."""
    return tiny_random_decoder(variant, seed, latent_channels)


def tiny_guidance_config(**changes: Any):
    """A short guidance schedule for the tiny models and a few steps (default: 4 steps), with the
    fused loss (the cues all get gradients, so the tests see every path)."""
    from dataclasses import replace

    from .loss.presets import fused_guidance_loss
    from .sampler.config import GuidanceConfig

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
    from .sampler.run_options import RunOptions

    return RunOptions(**{"memory_plan": "explicit", "gradient_checkpointing": False, "vae_checkpointing": False,
                         **changes})


def tiny_pipeline(seed: int = 0, *, guidance_config: Any = None):
    """A ready tiny :class:`GeCoCogVideoXPipeline` (CPU, fp32); guide its calls with
    :func:`tiny_bundle`'s estimators.

    Call it with ``num_frames=TINY_NUM_FRAMES, height=TINY_HEIGHT, width=TINY_WIDTH,
    num_inference_steps=4, max_sequence_length=TINY_MAX_SEQUENCE_LENGTH`` (the guidance default
    is :func:`tiny_guidance_config`, a 4-step schedule) and ``run_options=tiny_run_options()``.
    """
    from .sampler.pipeline_cogvideox import GeCoCogVideoXPipeline

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
        state = _seeded(seed + 1)
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
    state = _seeded(seed + 2)
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
    state = _seeded(seed)
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
    :class:`~geco_guide.sampler.modular.GeCoWanDenoiseStep` (``GeCoWan22DenoiseStep`` for 2.2).
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
    state = _seeded(seed)
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
    state = _seeded(seed)
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


def tiny_call_extras(pipe: Any) -> dict[str, Any]:
    """What the tiny stand-ins' calls need beyond the config's sampling: HunyuanVideo's prompt
    template, bare (``"{}"``: the tiny tokenizer cannot crop the real template's system text)."""
    name = type(pipe).__name__
    if name.startswith("HunyuanVideo") and not name.startswith("HunyuanVideo15"):
        return {"prompt_template": {"template": "{}", "crop_start": 0}}
    return {}


#: Latent channels of the Wan 2.2 VAE (TI2V-5B) and of the HunyuanVideo 1.5 VAE: the tiny
#: builders keep the real counts, which the tiny decoders ``wan2.2-5b`` / ``hunyuanvideo1.5`` take.
WAN22_LATENT_CHANNELS = 48
HUNYUAN15_LATENT_CHANNELS = 32


def tiny_wan22_ti2v_pipeline(seed: int = 0):
    """A stock tiny ``WanPipeline`` in the Wan 2.2 TI2V-5B layout: :func:`tiny_wan_pipeline`'s text
    encoder, ``AutoencoderKLWan`` as the Wan 2.2 VAE (48 latent channels, residual blocks, 2x2 pixel
    patches: 16x spatial, 4x temporal; its own ``latents_mean/std``), ``expand_timesteps=True`` (a
    timestep per latent token) and the flow UniPC scheduler (shift 5). Latents ``[B, 48, F, h, w]``;
    :func:`tiny_call_kwargs` makes 32x64 frames (16x VAE and 2x2 transformer patches)."""
    from diffusers import AutoencoderKLWan, UniPCMultistepScheduler, WanPipeline, WanTransformer3DModel

    wan, channels = tiny_wan_pipeline(seed), WAN22_LATENT_CHANNELS
    state = _seeded(seed + 1)
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
    state = _seeded(seed)
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
    state = _seeded(seed + 1)
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
    state = _seeded(seed)
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
        vocoder = LTX2Vocoder(in_channels=audio_vae.config.output_channels * audio_vae.config.mel_bins, hidden_channels=8,
                              upsample_kernel_sizes=[4, 4], upsample_factors=[2, 2], resnet_kernel_sizes=[3],
                              resnet_dilations=[[1, 3, 5]], output_sampling_rate=16000)
    finally:
        torch.random.set_rng_state(state)
    scheduler = FlowMatchEulerDiscreteScheduler(base_image_seq_len=1024, base_shift=0.95, max_image_seq_len=4096,
                                                max_shift=2.05, shift_terminal=0.1, use_dynamic_shifting=True)
    return _finish(LTX2Pipeline(scheduler=scheduler, vae=vae, audio_vae=audio_vae, text_encoder=text_encoder,
                                tokenizer=tokenizer, connectors=connectors, transformer=transformer, vocoder=vocoder))


def tiny_call_kwargs(pipe, **changes: Any) -> dict[str, Any]:
    """Call arguments that fit the tiny pipelines: 17 frames of 32x48, 4 steps, short prompts
    (32x64 for LTX and LTX-2, which want multiples of 32, and for a Wan with the Wan 2.2 16x VAE;
    plus the conditioning image for image-to-video, the bare ``"{}"`` prompt template for Hunyuan,
    HunyuanVideo 1.5's calls without ``max_sequence_length`` (and without a size for its
    image-to-video pipeline, which takes it from the image), and spatio-temporal guidance on the
    tiny LTX-2 transformer's last block, which its default block list does not name)."""
    kwargs: dict[str, Any] = dict(
        num_frames=TINY_NUM_FRAMES,
        height=TINY_HEIGHT,
        width=TINY_WIDTH,
        num_inference_steps=4,
        max_sequence_length=TINY_MAX_SEQUENCE_LENGTH,
    )
    name = type(pipe).__name__
    if "ImageToVideo" in name:
        kwargs["image"] = tiny_image(0)
    if name.startswith("HunyuanVideo15"):
        del kwargs["max_sequence_length"]  # it pads its prompts to its own lengths
        if "ImageToVideo" in name:  # the size comes from the image
            del kwargs["height"], kwargs["width"]
    kwargs.update(tiny_call_extras(pipe))
    if name.startswith("LTX"):
        kwargs["width"] = 64  # LTXPipeline wants multiples of 32
    if name.startswith("LTX2"):
        kwargs["spatio_temporal_guidance_blocks"] = [pipe.transformer.config.num_layers - 1]
    if name.startswith("Wan") and pipe.vae_scale_factor_spatial == 16:
        kwargs["width"] = 64  # 16x VAE and 2x2 patches: multiples of 32
    kwargs.update(changes)
    return kwargs
