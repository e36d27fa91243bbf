"""A tiny video autoencoder of the TAEHV architecture, checkpoint-compatible with the published
TAEHV weights (github.com/madebyollin/taehv: ``taecvx``, ``taew2_1``, ``taehv``, ``taew2_2``,
``taehv1_5``).

Our own implementation from ``shared/specs/tiny_decoder.md``. Its use here: decode latents to
frames cheaply *inside* the guidance gradient (about 10 M decoder parameters instead of the
full video VAE's hundreds of millions), so :meth:`TinyDecoder.decode` is differentiable with
respect to its latents and processes all time steps in one parallel pass.

Layouts: latents and frames are NTCHW (time before channels), frames are RGB in ``[0, 1]``.

Time: the decoder multiplies time by 4. A causal video VAE maps latent 0 to one frame and each
later latent to 4 frames, so ``T`` latents decode to ``4 T - 3`` frames (the first 3 decoded
frames are dropped) and the last decoded frame is the last frame of the last latent. The
published code keeps all ``4 T`` frames for CogVideoX when ``T`` is even; we do the same
(:meth:`TinyDecoder.num_frames`). The encoder divides time by 4 after repeating the last frame up
to a multiple of 4 (``T`` frames -> ``ceil(T / 4)`` latents).

Latent convention (what the decoder takes, derived from the diffusers pipelines' ``decode``
paths; :meth:`TinyDecoder.pipeline_latents`):

* CogVideoX: the pipeline divides its latents by ``vae.config.scaling_factor`` (0.7 for
  CogVideoX-5b and 1.5, 1.15258426 for CogVideoX-2b) before the VAE, and the tiny decoder was
  trained on that space, so the same division applies. The transformer's latents are NTCHW.
* Wan 2.1 / 2.2, HunyuanVideo (1 and 1.5): the tiny decoders take the diffusion model's latents
  as they are; the ``latents_mean`` / ``latents_std`` de-normalisation (Wan) or the division by
  ``scaling_factor`` (HunyuanVideo) that diffusers applies before its VAE is *not* applied. Those
  pipelines hold NCTHW latents.

Not supported: the ``taeltx*`` checkpoints (128 latent channels, patch 4, other time strides) and
the ``*_super`` checkpoints (a different decoder block).
"""

from __future__ import annotations

import math
import os
import zlib
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import torch
import torch.nn.functional as F
from torch import Tensor, nn

from ..families import (
    DEFAULT_MODEL,
    MODELS,
    TINY_DECODER_ALIASES,
    TINY_DECODERS,
    UNSUPPORTED_TINY_DECODERS,
    TinyDecoderVariant,
)
from ..types import check_frames
from .loading import (
    WeightsNotFoundError,
    fetch_checkpoint_file,
    load_state_dict_checked,
    load_weights,
)

__all__ = [
    "CONTEXT_LATENTS",
    "DEFAULT_DECODER_WIDTHS",
    "DEFAULT_VARIANT",
    "DEFAULT_ENCODER_WIDTH",
    "TINY_DECODER_WIDTHS",
    "TINY_ENCODER_WIDTH",
    "VARIANTS",
    "WEIGHTS_URL",
    "TinyDecoder",
    "TinyDecoderVariant",
    "resolve_variant",
    "seeded_tensor",
    "variant_from_filename",
]

MODEL_NAME = "TinyDecoder"
WEIGHTS_URL = "https://github.com/madebyollin/taehv"

DEFAULT_DECODER_WIDTHS = (256, 128, 64, 64)
DEFAULT_ENCODER_WIDTH = 64
# Widths of the offline tiny-random instances: same block graph (so the time alignment and the
# key names are the real ones) in under 0.2 M parameters.
# Latents a chunk needs for its last frame to equal the whole sequence's decode: each of the three
# MemBlock stages remembers 3 steps, at latent rates 1, 1 and 1/2 (the first TGrow has stride 1),
# so the memory reaches 3 + 3 + 1.5 latents back. Measured with random weights: the difference from
# the whole-sequence frame is 2e-5 with 7 latents and exactly 0 with 8.
CONTEXT_LATENTS = 8
TINY_DECODER_WIDTHS = (32, 16, 8, 8)
TINY_ENCODER_WIDTH = 8


#: The published variants (the registry's table, :data:`geco_guide.families.TINY_DECODERS`).
VARIANTS = TINY_DECODERS
#: The variant of the default model's latents: what a decoder built without a variant decodes.
DEFAULT_VARIANT = MODELS[DEFAULT_MODEL].tiny_decoder
# Other spellings users reach for; the checkpoint stems themselves are accepted too.
_ALIASES = {**TINY_DECODER_ALIASES, **{v.checkpoint: v.name for v in VARIANTS.values()}}
# Checked in this order because ``taehv`` is a prefix of ``taehv1_5``.
_FILENAME_ORDER = ("taehv1_5", "taew2_2", "taew2_1", "taecvx", "taehv")


def _refusal(name: str) -> str | None:
    """The reason a checkpoint / variant name is refused, or None."""
    lowered = name.lower()
    for word, reason in UNSUPPORTED_TINY_DECODERS.items():
        if word in lowered:
            return reason
    if "_super" in lowered or "-super" in lowered or lowered == "super":
        return "the '*_super' checkpoints use a different decoder block and are not supported"
    return None


def _known() -> str:
    return ", ".join(f"{v.name!r} ({v.checkpoint})" for v in VARIANTS.values())


def resolve_variant(variant: str | TinyDecoderVariant) -> TinyDecoderVariant:
    """Our variant name, an alias or a checkpoint stem (``"taecvx"``) -> its :class:`TinyDecoderVariant`.

    Raises:
        ValueError: one line, for taeltx / super names and unknown names (listing the known ones).
    """
    if isinstance(variant, TinyDecoderVariant):
        return variant
    key = str(variant).strip().lower()
    reason = _refusal(key)
    if reason:
        raise ValueError(f"{MODEL_NAME}: variant {variant!r}: {reason}; supported: {_known()}")
    key = _ALIASES.get(key, key)
    if key not in VARIANTS:
        raise ValueError(f"{MODEL_NAME}: unknown variant {variant!r}; supported: {_known()}")
    return VARIANTS[key]


def variant_from_filename(filename: str | os.PathLike) -> TinyDecoderVariant:
    """The variant a checkpoint file name names, the way the published code picks it
    (``taecvx`` anywhere in the name -> CogVideoX, ``taew2_2`` -> Wan 2.2 5B, ...).

    Unlike the published code, a name that names none of them is an error rather than a silent
    16-channel default: the CogVideoX time rule would otherwise depend on a guess.

    Raises:
        ValueError: one line, for taeltx / super names and names that tell no variant.
    """
    name = Path(filename).name.lower()
    reason = _refusal(name)
    if reason:
        raise ValueError(f"{MODEL_NAME}: checkpoint {Path(filename).name!r}: {reason}; supported: {_known()}")
    for stem in _FILENAME_ORDER:
        if stem in name:
            return VARIANTS[_ALIASES[stem]]
    raise ValueError(
        f"{MODEL_NAME}: cannot infer the variant from the file name {Path(filename).name!r} (it names "
        f"none of {', '.join(_FILENAME_ORDER)}); pass variant= one of {_known()}"
    )


def seeded_tensor(key: str, shape: tuple[int, ...], seed: int = 0) -> Tensor:
    """The fixture rule's tensor for state-dict key ``key``: N(0, 1) from a generator seeded with
    ``crc32(key) + seed``, divided by ``sqrt(numel / shape[0])`` (a fan-in scale) when it has more
    than one dimension, else multiplied by 0.1; float32. Independent of the global RNG and of the
    order in which keys are visited."""
    generator = torch.Generator().manual_seed(zlib.crc32(key.encode()) + seed)
    value = torch.randn(tuple(shape), generator=generator, dtype=torch.float32)
    if value.ndim > 1:
        return value / math.sqrt(value.numel() / shape[0])
    return value * 0.1


# ---- blocks ---------------------------------------------------------------------------------------


def _conv3x3(n_in: int, n_out: int, **kwargs: Any) -> nn.Conv2d:
    return nn.Conv2d(n_in, n_out, 3, padding=1, **kwargs)


class Clamp(nn.Module):
    """Soft clamp of the latents to about ``(-3, 3)``: ``tanh(x / 3) * 3``."""

    def forward(self, x: Tensor) -> Tensor:
        return torch.tanh(x / 3) * 3


class MemBlock(nn.Module):
    """Residual block with a memory of one time step.

    ``relu(conv(cat([x, past])) + skip(x))`` where ``past`` is this block's input at the previous
    time step (zeros at the first). Attribute names ``conv`` / ``skip`` are the checkpoint's.
    """

    def __init__(self, n_in: int, n_out: int):
        super().__init__()
        self.conv = nn.Sequential(
            _conv3x3(2 * n_in, n_out), nn.ReLU(inplace=True),
            _conv3x3(n_out, n_out), nn.ReLU(inplace=True),
            _conv3x3(n_out, n_out),
        )
        self.skip = nn.Conv2d(n_in, n_out, 1, bias=False) if n_in != n_out else nn.Identity()

    def forward(self, x: Tensor, past: Tensor) -> Tensor:
        """``x``, ``past``: ``[M, C_in, H, W]`` -> ``[M, C_out, H, W]``."""
        return torch.relu(self.conv(torch.cat([x, past], 1)) + self.skip(x))


class TGrow(nn.Module):
    """Time upsampling by ``stride``: a 1x1 conv to ``stride`` times the channels, whose channel
    groups become ``stride`` consecutive frames (``[M, C, H, W] -> [M * stride, C, H, W]``)."""

    def __init__(self, n: int, stride: int):
        super().__init__()
        self.stride = stride
        self.conv = nn.Conv2d(n, n * stride, 1, bias=False)

    def forward(self, x: Tensor) -> Tensor:
        m, c, h, w = x.shape
        return self.conv(x).reshape(m * self.stride, c, h, w)


class TPool(nn.Module):
    """Time downsampling by ``stride``: ``stride`` consecutive frames stacked along channels, then
    a 1x1 conv back to ``n`` channels (``[M, C, H, W] -> [M / stride, C, H, W]``)."""

    def __init__(self, n: int, stride: int):
        super().__init__()
        self.stride = stride
        self.conv = nn.Conv2d(n * stride, n, 1, bias=False)

    def forward(self, x: Tensor) -> Tensor:
        m, c, h, w = x.shape
        return self.conv(x.reshape(m // self.stride, self.stride * c, h, w))


def _run_parallel(blocks: nn.Sequential, x: Tensor) -> Tensor:
    """Apply ``blocks`` to ``x`` ``[N, T, C, H, W]`` with every time step at once.

    The batch and time axes are folded together for the 2-D convolutions; a MemBlock's memory is
    its own input shifted by one step along T, which is exactly what a frame-by-frame causal pass
    would feed it. Returns ``[N, T', C', H', W']`` (``T'`` changed by TGrow / TPool).
    """
    n = x.shape[0]
    x = x.flatten(0, 1)
    for block in blocks:
        if isinstance(block, MemBlock):
            steps = x.reshape(n, -1, *x.shape[1:])
            past = torch.cat([torch.zeros_like(steps[:, :1]), steps[:, :-1]], 1).flatten(0, 1)
            x = block(x, past)
        else:
            x = block(x)
    return x.reshape(n, -1, *x.shape[1:])


# ---- the autoencoder ------------------------------------------------------------------------------


class TinyDecoder(nn.Module):
    """TAEHV tiny video autoencoder (encoder and decoder) of one published variant.

    Args:
        variant: a name of :data:`VARIANTS` (the registry's published tiny decoders), an alias or
            a checkpoint stem such as ``"taecvx"``; default: the default model's.
        decoder_widths: channels of the three decoder stages and of the last conv; the published
            checkpoints use ``(256, 128, 64, 64)``.
        encoder_width: channels of the encoder; the published checkpoints use 64.

    The modules are ``encoder`` and ``decoder`` ``nn.Sequential`` s whose indices are the
    published state-dict keys (``encoder.N.*``, ``decoder.N.*``), so a published checkpoint loads
    with ``load_state_dict(sd, strict=True)``. A fresh instance holds PyTorch's default init;
    :meth:`from_pretrained` and :meth:`random` return frozen (no parameter gradients) eval-mode
    models, whose :meth:`decode` still passes gradients to the latents.

    Example:
        >>> vae = TinyDecoder.random(seed=0)  # the default model's variant (taecvx)
        >>> vae.decode(torch.randn(1, 3, 16, 4, 6)).shape
        torch.Size([1, 9, 3, 32, 48])
    """

    spatial_scale = 8  # three 2x upsamplings of the latent grid, before the pixel shuffle by patch_size

    def __init__(
        self,
        variant: str | TinyDecoderVariant = DEFAULT_VARIANT,
        *,
        decoder_widths: tuple[int, int, int, int] = DEFAULT_DECODER_WIDTHS,
        encoder_width: int = DEFAULT_ENCODER_WIDTH,
    ):
        super().__init__()
        spec = resolve_variant(variant)
        decoder_widths = tuple(int(w) for w in decoder_widths)
        if len(decoder_widths) != 4 or min(decoder_widths) < 1 or encoder_width < 1:
            raise ValueError(
                f"{MODEL_NAME}: decoder_widths must be 4 positive ints and encoder_width positive, got "
                f"{decoder_widths} / {encoder_width}"
            )
        self.variant = spec
        self.checkpoint_file: str | None = None  # set by from_pretrained
        self.latent_channels = spec.latent_channels
        self.patch_size = spec.patch_size
        self.decoder_widths = decoder_widths
        self.encoder_width = int(encoder_width)
        pixel_channels = 3 * spec.patch_size**2

        e = self.encoder_width
        encoder: list[nn.Module] = [_conv3x3(pixel_channels, e), nn.ReLU(inplace=True)]
        for time_stride in (2, 2, 1):
            encoder += [TPool(e, time_stride), _conv3x3(e, e, stride=2, bias=False)]
            encoder += [MemBlock(e, e) for _ in range(3)]
        encoder.append(_conv3x3(e, spec.latent_channels))
        self.encoder = nn.Sequential(*encoder)

        w = decoder_widths
        decoder: list[nn.Module] = [Clamp(), _conv3x3(spec.latent_channels, w[0]), nn.ReLU(inplace=True)]
        for stage, time_stride in enumerate((1, 2, 2)):
            decoder += [MemBlock(w[stage], w[stage]) for _ in range(3)]
            decoder += [nn.Upsample(scale_factor=2, mode="nearest"), TGrow(w[stage], time_stride),
                        _conv3x3(w[stage], w[stage + 1], bias=False)]
        decoder += [nn.ReLU(inplace=True), _conv3x3(w[3], pixel_channels)]
        self.decoder = nn.Sequential(*decoder)

        self.t_upscale = math.prod(b.stride for b in self.decoder if isinstance(b, TGrow))
        self.t_downscale = math.prod(b.stride for b in self.encoder if isinstance(b, TPool))

    def extra_repr(self) -> str:
        return f"variant={self.variant.name!r} ({self.variant.checkpoint}), widths={self.decoder_widths}"

    @property
    def dtype(self) -> torch.dtype:
        return self.decoder[1].weight.dtype

    @property
    def device(self) -> torch.device:
        return self.decoder[1].weight.device

    # ---- time alignment ---------------------------------------------------------------------------

    def frames_to_trim(self, num_latents: int) -> int:
        """Leading decoded frames dropped for ``num_latents`` latents: ``t_upscale - 1`` (3), but
        0 for CogVideoX with an even count (the published rule)."""
        if self.variant.even_count_untrimmed and num_latents % 2 == 0:
            return 0
        return self.t_upscale - 1

    def num_frames(self, num_latents: int) -> int:
        """Frames :meth:`decode` returns for ``num_latents`` latents (``4 T - 3``, or ``4 T``)."""
        return self.t_upscale * num_latents - self.frames_to_trim(num_latents)

    def num_latents(self, num_frames: int) -> int:
        """Latents :meth:`encode` returns for ``num_frames`` frames (``ceil(T / 4)``)."""
        return -(-num_frames // self.t_downscale)

    # ---- decode / encode --------------------------------------------------------------------------

    def _check_latents(self, latents: Tensor) -> None:
        if not isinstance(latents, torch.Tensor):
            raise ValueError(f"{MODEL_NAME}.decode: latents must be a torch.Tensor, got {type(latents).__name__}")
        if latents.ndim != 5 or latents.shape[1] == 0:
            raise ValueError(
                f"{MODEL_NAME}.decode: latents must be [N, T, C, h, w] (NTCHW) with T >= 1, got shape "
                f"{list(latents.shape)}"
            )
        if latents.shape[2] != self.latent_channels:
            hint = ""
            if latents.shape[1] == self.latent_channels:
                hint = " (these look NCTHW: permute(0, 2, 1, 3, 4), or use pipeline_latents)"
            raise ValueError(
                f"{MODEL_NAME}({self.variant.name}) expects {self.latent_channels} latent channels at dim 2, "
                f"got {latents.shape[2]} in latents of shape {list(latents.shape)}{hint}"
            )
        if not latents.is_floating_point():
            raise ValueError(f"{MODEL_NAME}.decode: latents must be floating, got dtype {latents.dtype}")

    def decode(self, latents: Tensor) -> Tensor:
        """Latents to frames, all time steps in one pass; differentiable in ``latents``.

        Args:
            latents: ``[N, T, C, h, w]`` (``C`` = :attr:`latent_channels`), in the convention of
                :meth:`pipeline_latents`; cast to the model's dtype.

        Returns:
            ``[N, T', 3, 8 h p, 8 w p]`` RGB in ``[0, 1]`` (``p`` = :attr:`patch_size`) in the
            model's dtype, ``T'`` = :meth:`num_frames` ``(T)``: frame ``-1`` is the last frame of
            latent ``T - 1``. The gradient is zero where the raw output lies outside ``[0, 1]``.

        Raises:
            ValueError: one line, for a wrong ndim or channel count (checked before any conv).
        """
        self._check_latents(latents)
        num_latents = latents.shape[1]
        frames = _run_parallel(self.decoder, latents.to(self.dtype))
        if self.patch_size > 1:
            frames = F.pixel_shuffle(frames, self.patch_size)  # acts on the last 3 dims of NTCHW
        frames = frames.clamp(0, 1)
        return frames[:, self.frames_to_trim(num_latents):]

    def encode(self, frames: Tensor) -> Tensor:
        """Frames to latents, all time steps in one pass.

        Args:
            frames: ``[N, T, 3, H, W]`` RGB in ``[0, 1]``; ``H``, ``W`` multiples of
                :attr:`patch_size`. The last frame is repeated up to a multiple of 4 frames.

        Returns:
            ``[N, ceil(T / 4), C, ceil(H / (8 p)), ceil(W / (8 p))]`` latents in the model's dtype.

        Raises:
            ValueError: one line, for a wrong shape.
        """
        check_frames(frames, f"{MODEL_NAME}.encode: frames")
        p = self.patch_size
        if frames.shape[-1] % p or frames.shape[-2] % p:
            raise ValueError(
                f"{MODEL_NAME}({self.variant.name}).encode: frame height and width must be multiples of the "
                f"patch size {p}, got {list(frames.shape[-2:])}"
            )
        x = frames.to(self.dtype)
        if p > 1:
            x = F.pixel_unshuffle(x, p)
        missing = -x.shape[1] % self.t_downscale
        if missing:
            x = torch.cat([x, x[:, -1:].expand(-1, missing, -1, -1, -1)], 1)
        return _run_parallel(self.encoder, x)

    def pipeline_latents(self, latents: Tensor, vae_config: Any = None, layout: str | None = None) -> Tensor:
        """A diffusers pipeline's latents (as its transformer produces them) -> :meth:`decode`'s input.

        Args:
            latents: the pipeline's latents, in ``layout``.
            vae_config: the pipeline's ``vae.config`` (a mapping or an object with attributes) or
                the ``scaling_factor`` as a number; needed for CogVideoX only, where the latents are
                divided by its ``scaling_factor`` as the pipeline does before its VAE.
            layout: ``"NTCHW"`` or ``"NCTHW"``; default the variant's pipeline layout (CogVideoX:
                NTCHW, Wan and HunyuanVideo: NCTHW).

        Returns:
            ``[N, T, C, h, w]`` latents.
        """
        layout = (layout or self.variant.pipeline_layout).upper()
        if layout not in ("NTCHW", "NCTHW"):
            raise ValueError(f"{MODEL_NAME}.pipeline_latents: layout must be 'NTCHW' or 'NCTHW', got {layout!r}")
        if layout == "NCTHW":
            if latents.ndim != 5:
                raise ValueError(f"{MODEL_NAME}.pipeline_latents: latents must be 5-d, got shape {list(latents.shape)}")
            latents = latents.transpose(1, 2)
        if not self.variant.scale_by_vae_scaling_factor:
            return latents
        if isinstance(vae_config, (int, float)):
            factor = vae_config
        elif isinstance(vae_config, Mapping):
            factor = vae_config.get("scaling_factor")
        else:
            factor = getattr(vae_config, "scaling_factor", None)
        if not isinstance(factor, (int, float)) or not math.isfinite(factor) or factor <= 0:
            raise ValueError(
                f"{MODEL_NAME}({self.variant.name}).pipeline_latents needs the VAE's scaling_factor "
                f"(pass vae.config; 0.7 for CogVideoX-5b), got {vae_config!r}"
            )
        return latents / factor

    # ---- construction -----------------------------------------------------------------------------

    def _frozen(self) -> TinyDecoder:
        return self.requires_grad_(False).eval()

    @classmethod
    def random(
        cls,
        variant: str | TinyDecoderVariant = DEFAULT_VARIANT,
        seed: int = 0,
        *,
        decoder_widths: tuple[int, int, int, int] = DEFAULT_DECODER_WIDTHS,
        encoder_width: int = DEFAULT_ENCODER_WIDTH,
    ) -> TinyDecoder:
        """A frozen model whose every tensor is :func:`seeded_tensor` ``(key, shape, seed)`` (the
        fixture's rule; the global RNG is untouched). Pass :data:`TINY_DECODER_WIDTHS` /
        :data:`TINY_ENCODER_WIDTH` for a tiny offline instance."""
        model = cls(variant, decoder_widths=decoder_widths, encoder_width=encoder_width)
        model.load_state_dict(
            {key: seeded_tensor(key, tuple(t.shape), seed) for key, t in model.state_dict().items()}, strict=True
        )
        return model._frozen()

    @classmethod
    def tiny(cls, variant: str | TinyDecoderVariant = DEFAULT_VARIANT, seed: int = 0) -> TinyDecoder:
        """:meth:`random` with :data:`TINY_DECODER_WIDTHS` / :data:`TINY_ENCODER_WIDTH`: the real
        block graph, time alignment and key names in under 0.2 M parameters (offline tests)."""
        return cls.random(variant, seed, decoder_widths=TINY_DECODER_WIDTHS, encoder_width=TINY_ENCODER_WIDTH)

    @classmethod
    def from_state_dict(cls, state_dict: Mapping[str, Tensor], variant: str | TinyDecoderVariant) -> TinyDecoder:
        """Build ``variant`` with the widths ``state_dict`` has and load it strictly; frozen.

        Raises:
            CheckpointMismatchError: one line listing the first missing / unexpected /
                mis-shaped keys.
        """
        model = cls(variant, **_widths_of(state_dict))
        load_state_dict_checked(model, state_dict, model_name=f"{MODEL_NAME}({model.variant.name})")
        return model._frozen()

    @classmethod
    def from_pretrained(
        cls,
        path_or_hub_id: str | os.PathLike,
        variant: str | TinyDecoderVariant | None = None,
        filename: str | None = None,
        *,
        dtype: torch.dtype = torch.float32,
        device: torch.device | str = "cpu",
        revision: str | None = None,
        cache_dir: str | os.PathLike | None = None,
    ) -> TinyDecoder:
        """Load published TAEHV weights (``.pth`` or ``.safetensors``); frozen, eval mode, with the
        resolved file in ``checkpoint_file``.

        Args:
            path_or_hub_id: a checkpoint file, a local folder, or a Hugging Face repo id. The
                published weights live on GitHub (``taecvx.pth`` has no known hub repo):
                download the file and pass its path.
            variant: see :class:`TinyDecoder`; default: inferred from the file name as the
                published code does (:func:`variant_from_filename`).
            filename: the file inside the folder / repo; default ``<checkpoint>.safetensors``,
                ``<checkpoint>.pth`` or ``safetensors/<checkpoint>.safetensors`` of the variant
                (of every variant when ``variant`` is None).

        Raises:
            WeightsNotFoundError: one line naming the missing file / folder / repo and how to pass
                a local path.
            ValueError: a variant that is unknown, refused, or not inferable from the file name.
            CheckpointMismatchError: the file's keys do not fit (the first few listed).
        """
        spec = resolve_variant(variant) if variant is not None else None
        weights = _locate(path_or_hub_id, spec, filename, revision=revision, cache_dir=cache_dir)
        if spec is None:
            spec = variant_from_filename(weights)
        model = cls.from_state_dict(load_weights(weights), spec)
        model.checkpoint_file = str(weights)  # what the run's record names (the file, not the folder)
        return model.to(device=device, dtype=dtype)


def _candidate_files(spec: TinyDecoderVariant | None) -> list[str]:
    specs = [spec] if spec is not None else list(VARIANTS.values())
    names: list[str] = []
    for s in specs:
        names += [f"{s.checkpoint}.safetensors", f"{s.checkpoint}.pth", f"safetensors/{s.checkpoint}.safetensors"]
    return names


def _locate(
    source: str | os.PathLike,
    spec: TinyDecoderVariant | None,
    filename: str | None,
    **fetch: Any,
) -> Path:
    """The checkpoint file of ``source`` (a file, a folder or a hub repo id)."""
    example = f"{spec.checkpoint if spec else 'taecvx'}.pth"
    how = (f"download {example} from {WEIGHTS_URL} and pass its local path, e.g. "
           f"TinyDecoder.from_pretrained('/path/to/{example}')")
    names = [filename] if filename else _candidate_files(spec)
    try:
        return fetch_checkpoint_file(source, names, model_name=MODEL_NAME, **fetch)
    except WeightsNotFoundError as err:
        raise WeightsNotFoundError(f"{err}; {how}") from None


def _widths_of(state_dict: Mapping[str, Tensor]) -> dict[str, Any]:
    """Constructor widths read off a state dict (the published ones when keys are absent, so a
    strict load reports what is wrong instead of this function)."""
    def out_channels(key: str, default: int) -> int:
        value = state_dict.get(key)
        return int(value.shape[0]) if isinstance(value, torch.Tensor) and value.ndim == 4 else default

    keys = ("decoder.1.weight", "decoder.8.weight", "decoder.14.weight", "decoder.20.weight")
    return {
        "decoder_widths": tuple(out_channels(k, d) for k, d in zip(keys, DEFAULT_DECODER_WIDTHS, strict=True)),
        "encoder_width": out_channels("encoder.0.weight", DEFAULT_ENCODER_WIDTH),
    }
