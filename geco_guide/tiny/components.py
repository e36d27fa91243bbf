"""The tiny random CogVideoX parts every tiny stand-in starts from: a word-level T5-style tokenizer
made with the ``tokenizers`` library, a tiny ``T5EncoderModel``, ``CogVideoXTransformer3DModel`` and
``AutoencoderKLCogVideoX`` (temporal compression 4, spatial 8, so the real frame <-> latent mapping
is exercised) and the DDIM scheduler with the CogVideoX-5b scheduler settings, each seeded."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import torch
from transformers import PreTrainedTokenizerFast

__all__ = ["TINY_ANCHORS", "TINY_HEIGHT", "TINY_MAX_SEQUENCE_LENGTH", "TINY_NUM_FRAMES", "TINY_WIDTH", "TinySizes",
           "TinyTokenizer", "seeded", "tiny_cogvideox_components", "tiny_cogvideox_transformer", "tiny_tokenizer"]

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


def seeded(seed: int):
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
    state = seeded(seed)
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
