"""UFM (UniFlowMatchConfidence): dense flow + covisibility, checkpoint-compatible with UFM-Base.

Our own implementation of ``infinity1096/UFM-Base`` written from ``shared/specs/estimators.md``
(sections 2 and 4): a DINOv2 encoder sees both images, a global-attention transformer lets the
two views exchange information, and two DPT heads read view 1 only: ``head1`` regresses flow,
``uncertainty_head`` a covisibility logit (and optionally a 2-D flow covariance). Module and key
names follow the released ``model.safetensors`` so the checkpoint loads by key.

Everything runs in float32 by default and keeps gradients, because GeCo differentiates its loss
through UFM back to the decoded frames. Precision knobs: ``autocast_dtype`` (e.g.
``torch.bfloat16``) runs the encoder and info-sharing under autocast; ``trunk_to(dtype)`` (and
``from_pretrained(dtype=...)``) stores them in that dtype. The heads always run in float32.
``gradient_checkpointing`` recomputes the encoder's and the info-sharing transformer's block
activations in backward.
"""

from __future__ import annotations

import json
import os
from collections.abc import Mapping, Sequence
from contextlib import nullcontext
from dataclasses import asdict, dataclass, field
from typing import Any

import numpy as np
import torch
import torch.nn.functional as F
from torch import Tensor, nn

from ..types import Correspondences, merge_dataclass
from .dpt import FusionBlock, resample_layer
from .loading import (
    CheckpointMismatchError,
    fetch_checkpoint_file,
    load_state_dict_checked,
    load_weights,
)
from .vit import (
    IMAGENET_MEAN,
    IMAGENET_STD,
    Block,
    DinoV2,
    RotaryEmbedding2D,
    grid_positions,
    init_weights_,
    run_block,
)

__all__ = [
    "UFM",
    "UFMConfig",
    "UFMEncoderConfig",
    "UFMInfoSharingConfig",
    "UFMHeadConfig",
    "UFMFlowAdaptorConfig",
    "UFMAdaptorSpec",
    "NORMALISATIONS",
]

# Input normalisations a caller may declare for float images: name -> (mean, std).
NORMALISATIONS: dict[str, tuple[tuple[float, float, float], tuple[float, float, float]]] = {
    "identity": ((0.0, 0.0, 0.0), (1.0, 1.0, 1.0)),
    "dinov2": (IMAGENET_MEAN, IMAGENET_STD),
    "imagenet": (IMAGENET_MEAN, IMAGENET_STD),
    "resnet": (IMAGENET_MEAN, IMAGENET_STD),
}

ADAPTOR_CHANNELS = {"mask": 1, "covariance2d": 3}
COVISIBILITY_ADAPTOR = "non_occluded_mask"
SCALE_STRATEGIES = ("none", "scale_width", "scale_height", "scale_both")
NUM_HEAD_FEATURES = 4  # encoder, two info-sharing intermediates, info-sharing final
# Random init (UFM.reset_parameters): output-layer gains and the covisibility bias, sigmoid ~0.8.
FLOW_INIT_GAIN = 0.5
UNCERTAINTY_INIT_GAIN = 0.3
COVISIBILITY_INIT_LOGIT = 1.4


# ---------------------------------------------------------------------------------------------
# Configuration (spec section 5.2)
# ---------------------------------------------------------------------------------------------


@dataclass
class UFMEncoderConfig:
    """DINOv2 encoder (``encoder.model``). ``feature_block`` -1 = last block."""

    embed_dim: int = 1024
    depth: int = 24
    num_heads: int = 16
    mlp_ratio: float = 4.0
    img_size: int = 518
    num_register_tokens: int = 0
    interpolate_antialias: bool = False
    interpolate_offset: float = 0.1
    ffn: str = "mlp"
    feature_block: int = -1
    norm_output: bool = True


@dataclass
class UFMInfoSharingConfig:
    """Global-attention transformer over both views (``info_sharing``)."""

    dim: int = 768
    depth: int = 12
    num_heads: int = 12
    mlp_ratio: float = 4.0
    qkv_bias: bool = True
    qk_norm: bool = False
    layerscale: bool = False
    max_num_views: int = 2
    indices: int | list[int] | None = field(default_factory=lambda: [5, 8])  # spec 4.3 step 5
    norm_intermediate: bool = True
    rope_freq: float | None = None


@dataclass
class UFMHeadConfig:
    """DPT feature pyramid + regression processor; ``hooks`` index [enc, inter0, inter1, final]."""

    hooks: list[int] = field(default_factory=lambda: [0, 1, 2, 3])
    layer_dims: list[int] = field(default_factory=lambda: [96, 192, 384, 768])
    feature_dim: int = 256
    hidden_dims: list[int] = field(default_factory=lambda: [128, 128])


@dataclass
class UFMFlowAdaptorConfig:
    """Flow de-normalisation; ``base_shape`` is ``[Hb, Wb]``. Mean/std are initial buffer values
    only (the checkpoint's buffers win); base_shape and scale_strategy are not in the checkpoint."""

    flow_mean: list[float] = field(default_factory=lambda: [0.0, 0.0])
    flow_std: list[float] = field(default_factory=lambda: [50.0, 50.0])
    base_shape: list[int] = field(default_factory=lambda: [420, 560])
    scale_strategy: str = "scale_both"


@dataclass
class UFMAdaptorSpec:
    """One uncertainty-head adaptor; ``type`` is ``"mask"`` (1 ch) or ``"covariance2d"`` (3 ch)."""

    name: str
    type: str


@dataclass
class UFMConfig:
    """Architecture of a UFM model (spec 5.2). Defaults are UFM-Base as far as known.

    ``inference_resolution`` lists ``[W, H]`` candidates (multiples of ``patch_size``); the
    uncertainty head's output channels are the sum of its adaptors' channels, in list order.
    """

    patch_size: int = 14
    inference_resolution: list[list[int]] = field(default_factory=lambda: [[560, 420]])
    data_norm: dict[str, list[float]] = field(
        default_factory=lambda: {"mean": list(IMAGENET_MEAN), "std": list(IMAGENET_STD)}
    )
    encoder: UFMEncoderConfig = field(default_factory=UFMEncoderConfig)
    info_sharing: UFMInfoSharingConfig = field(default_factory=UFMInfoSharingConfig)
    flow_head: UFMHeadConfig = field(default_factory=UFMHeadConfig)
    flow_adaptor: UFMFlowAdaptorConfig = field(default_factory=UFMFlowAdaptorConfig)
    uncertainty_head: UFMHeadConfig = field(default_factory=UFMHeadConfig)
    uncertainty_adaptors: list[UFMAdaptorSpec] = field(
        default_factory=lambda: [UFMAdaptorSpec(COVISIBILITY_ADAPTOR, "mask")]
    )

    # -- constructors ------------------------------------------------------------------------

    @classmethod
    def from_dict(cls, d: Mapping[str, Any]) -> UFMConfig:
        """Build from a section-5 dict (as in the fixtures' ``config``); absent keys keep the
        UFM-Base defaults, unknown keys raise ``ValueError`` naming them."""
        top = dict(d) if hasattr(d, "keys") else d
        if hasattr(top, "keys") and "inference_resolution" in top:
            top["inference_resolution"] = _resolution_list(top["inference_resolution"])
        config = merge_dataclass(cls(), top)
        config.validate()
        return config

    @classmethod
    def from_config_json(
        cls, d: Mapping[str, Any], encoder_override: Mapping[str, Any] | None = None
    ) -> UFMConfig:
        """Translate the upstream ``config.json`` (constructor kwargs of UniFlowMatchConfidence,
        spec 4.8) into a :class:`UFMConfig`.

        Args:
            d: the parsed ``config.json``.
            encoder_override: DINOv2 constructor arguments replacing the hub model named by
                ``encoder_kwargs.size`` (the upstream schema can only name small/base/large/giant).

        Raises:
            ValueError: naming the field, for values outside the supported architecture.
        """
        return _translate_config_json(d, encoder_override)

    @classmethod
    def tiny(cls) -> UFMConfig:
        """A ~0.6 M-parameter model for tests and the CPU demo (with :meth:`UFM.random` weights:
        flow of a pixel or so, covisibility ~0.8)."""
        return cls.from_dict(
            {
                "inference_resolution": [[98, 56], [70, 70], [56, 98]],
                "encoder": {"embed_dim": 48, "depth": 2, "num_heads": 3, "img_size": 70},
                "info_sharing": {"dim": 64, "depth": 4, "num_heads": 4, "indices": [0, 2]},
                "flow_head": {"layer_dims": [16, 24, 32, 48], "feature_dim": 32, "hidden_dims": [16, 16]},
                "flow_adaptor": {"flow_std": [1.0, 1.0], "base_shape": [56, 98]},
                "uncertainty_head": {
                    "layer_dims": [8, 16, 24, 32],
                    "feature_dim": 24,
                    "hidden_dims": [16, 8],
                },
            }
        )

    def to_dict(self) -> dict[str, Any]:
        """The section-5 dict (JSON-serialisable); ``from_dict(to_dict())`` round-trips."""
        return asdict(self)

    # -- derived quantities ------------------------------------------------------------------

    @property
    def head_feature_dims(self) -> list[int]:
        """Channels of ``[enc, inter0, inter1, final]``, the features the heads can hook."""
        dim = self.info_sharing.dim
        return [self.encoder.embed_dim, dim, dim, dim]

    @property
    def uncertainty_channels(self) -> int:
        """Output channels of the uncertainty head = sum over its adaptors."""
        return sum(ADAPTOR_CHANNELS[a.type] for a in self.uncertainty_adaptors)

    def validate(self) -> None:
        """Raise ``ValueError`` naming the first field that is outside the supported architecture."""
        p = self.patch_size
        _check(p > 0, "patch_size", p, "must be positive")
        _check(len(self.inference_resolution) > 0, "inference_resolution", [], "must not be empty")
        for wh in self.inference_resolution:
            ok = len(wh) == 2 and all(int(v) == v and v > 0 and v % p == 0 for v in wh)
            _check(ok, "inference_resolution", wh, f"must be [W, H] pairs of multiples of {p}")
        for key in ("mean", "std"):
            _check(
                len(self.data_norm.get(key, ())) == 3,
                f"data_norm.{key}",
                self.data_norm.get(key),
                "must have 3 values",
            )
        enc = self.encoder
        _check(enc.ffn == "mlp", "encoder.ffn", enc.ffn, "must be 'mlp' (SwiGLU encoders are out of scope)")
        _check(
            enc.embed_dim % enc.num_heads == 0, "encoder.embed_dim", enc.embed_dim, "must divide by num_heads"
        )
        _check(
            enc.img_size % p == 0, "encoder.img_size", enc.img_size, f"must be a multiple of patch_size {p}"
        )
        _check(
            -enc.depth <= enc.feature_block < enc.depth,
            "encoder.feature_block",
            enc.feature_block,
            f"must index one of {enc.depth} blocks",
        )
        _check(
            not (enc.interpolate_antialias and enc.interpolate_offset != 0),
            "encoder.interpolate_offset",
            enc.interpolate_offset,
            "must be 0 with interpolate_antialias (out of scope)",
        )
        info = self.info_sharing
        _check(info.dim % info.num_heads == 0, "info_sharing.dim", info.dim, "must divide by num_heads")
        if info.rope_freq is not None:
            _check(
                (info.dim // info.num_heads) % 4 == 0,
                "info_sharing.num_heads",
                info.num_heads,
                "head_dim must divide by 4 for RoPE",
            )
        _check(info.max_num_views >= 2, "info_sharing.max_num_views", info.max_num_views, "must be >= 2")
        blocks = _resolve_block_indices(info.indices, info.depth, "info_sharing.indices")
        _check(len(blocks) >= 2, "info_sharing.indices", info.indices, "must select at least 2 blocks")
        for name in ("flow_head", "uncertainty_head"):
            head: UFMHeadConfig = getattr(self, name)
            _check(
                len(head.hooks) == 4 and all(0 <= h < NUM_HEAD_FEATURES for h in head.hooks),
                f"{name}.hooks",
                head.hooks,
                "must be 4 indices into [enc, inter0, inter1, final] (0..3)",
            )
            _check(len(head.layer_dims) == 4, f"{name}.layer_dims", head.layer_dims, "must have 4 entries")
            _check(len(head.hidden_dims) == 2, f"{name}.hidden_dims", head.hidden_dims, "must have 2 entries")
        fa = self.flow_adaptor
        _check(
            fa.scale_strategy in SCALE_STRATEGIES,
            "flow_adaptor.scale_strategy",
            fa.scale_strategy,
            f"must be one of {SCALE_STRATEGIES}",
        )
        for key in ("flow_mean", "flow_std", "base_shape"):
            _check(len(getattr(fa, key)) == 2, f"flow_adaptor.{key}", getattr(fa, key), "must have 2 values")
        names = [a.name for a in self.uncertainty_adaptors]
        _check(len(set(names)) == len(names), "uncertainty_adaptors", names, "names must be unique")
        for a in self.uncertainty_adaptors:
            _check(
                a.type in ADAPTOR_CHANNELS,
                "uncertainty_adaptors.type",
                a.type,
                f"must be one of {sorted(ADAPTOR_CHANNELS)}",
            )
            _check(
                a.type != "mask" or a.name == COVISIBILITY_ADAPTOR,
                "uncertainty_adaptors.name",
                a.name,
                f"a mask adaptor must be named {COVISIBILITY_ADAPTOR!r}",
            )
        types = [a.type for a in self.uncertainty_adaptors]
        _check(
            types.count("mask") == 1,
            "uncertainty_adaptors",
            names,
            f"must contain exactly one {COVISIBILITY_ADAPTOR!r} mask",
        )
        _check(
            types.count("covariance2d") <= 1,
            "uncertainty_adaptors",
            names,
            "must contain at most one covariance2d",
        )


def _check(ok: bool, name: str, value: Any, requirement: str) -> None:
    if not ok:
        raise ValueError(f"UFM config field {name} = {value!r}: {requirement}")


def _resolution_list(value: Any) -> list[list[int]]:
    """``[W, H]`` or a list of them -> list of ``[W, H]``."""
    if isinstance(value, Sequence) and len(value) == 2 and all(isinstance(v, (int, float)) for v in value):
        value = [value]
    return [[int(w), int(h)] for w, h in value]


def _resolve_block_indices(
    indices: int | Sequence[int] | None, depth: int, name: str = "indices"
) -> list[int]:
    """Block selection semantics (spec 4.3 step 5): None = every block, int n = the last n blocks,
    a list = those blocks (negative from the end); increasing order, duplicates once."""
    if indices is None:
        return list(range(depth))
    if isinstance(indices, int):
        _check(0 < indices <= depth, name, indices, f"must select between 1 and {depth} blocks")
        return list(range(depth - indices, depth))
    resolved = sorted({i + depth if i < 0 else i for i in indices})
    _check(
        all(0 <= i < depth for i in resolved),
        name,
        list(indices),
        f"must index blocks of a depth-{depth} stack",
    )
    return resolved


# ---------------------------------------------------------------------------------------------
# config.json translation (spec 4.8 and 5.2 "Mapping from config.json")
# ---------------------------------------------------------------------------------------------

# DINOv2 hub sizes -> (embed_dim, depth, num_heads); giant uses a SwiGLU FFN (out of scope).
_DINO_SIZES = {"small": (384, 12, 6), "base": (768, 12, 12), "large": (1024, 24, 16)}
_OVERRIDE_DEFAULTS = {
    "img_size": 518,
    "patch_size": 14,
    "mlp_ratio": 4.0,
    "num_register_tokens": 0,
    "interpolate_antialias": False,
    "interpolate_offset": 0.1,
    "ffn_layer": "mlp",
    "init_values": 1.0,
    "block_chunks": 0,
}


def _must(value: Any, allowed: Sequence[Any], name: str) -> Any:
    if value not in allowed:
        raise ValueError(f"UFM config.json field {name} = {value!r}: must be one of {list(allowed)}")
    return value


def _require(d: Mapping[str, Any], key: str, where: str) -> Any:
    if key not in d:
        raise ValueError(f"UFM config.json field {where}.{key} is required but absent")
    return d[key]


def _translate_encoder(
    d: Mapping[str, Any], override: Mapping[str, Any] | None
) -> tuple[int, UFMEncoderConfig, dict]:
    """-> (patch_size, encoder config, data_norm) from ``encoder_str``/``encoder_kwargs``."""
    _must(d.get("encoder_str", "dinov2"), ["dinov2"], "encoder_str")
    ek = d.get("encoder_kwargs") or {}
    norm_type = _must(
        ek.get("data_norm_type", "dinov2"), list(NORMALISATIONS), "encoder_kwargs.data_norm_type"
    )
    mean, std = NORMALISATIONS[norm_type]
    patch = ek.get("patch_size", 14)
    if override is not None:
        unknown = sorted(set(override) - set(_OVERRIDE_DEFAULTS) - {"embed_dim", "depth", "num_heads"})
        if unknown:
            raise ValueError(f"UFM encoder override: unsupported DINOv2 argument(s) {unknown}")
        ov = {**_OVERRIDE_DEFAULTS, **override}
        _must(ov["patch_size"], [patch], "encoder override patch_size (vs encoder_kwargs.patch_size)")
        _must(ov["ffn_layer"], ["mlp"], "encoder override ffn_layer")
        _must(ov["block_chunks"], [0], "encoder override block_chunks")
        if ov["init_values"] is None:
            raise ValueError("UFM encoder override init_values = None: must be a number (LayerScale keys)")
        enc = UFMEncoderConfig(
            embed_dim=ov["embed_dim"],
            depth=ov["depth"],
            num_heads=ov["num_heads"],
            mlp_ratio=float(ov["mlp_ratio"]),
            img_size=ov["img_size"],
            num_register_tokens=ov["num_register_tokens"],
            interpolate_antialias=bool(ov["interpolate_antialias"]),
            interpolate_offset=float(ov["interpolate_offset"]),
        )
    else:
        _must(patch, [14], "encoder_kwargs.patch_size")
        size = _must(ek.get("size", "large"), list(_DINO_SIZES), "encoder_kwargs.size")
        embed_dim, depth, heads = _DINO_SIZES[size]
        registers = bool(ek.get("with_registers", False))
        enc = UFMEncoderConfig(
            embed_dim=embed_dim,
            depth=depth,
            num_heads=heads,
            img_size=518,
            num_register_tokens=4 if registers else 0,
            interpolate_antialias=registers,
            interpolate_offset=0.0 if registers else 0.1,
        )
    keep = ek.get("keep_first_n_layers")
    if keep is not None:
        _check(
            0 < keep <= enc.depth, "encoder_kwargs.keep_first_n_layers", keep, f"must be in 1..{enc.depth}"
        )
        enc.depth = keep
    feature = _resolve_block_indices(ek.get("indices", 1), enc.depth, "encoder_kwargs.indices")[-1]
    enc.feature_block = -1 if feature == enc.depth - 1 else feature
    enc.norm_output = bool(ek.get("norm_intermediate", True))
    return patch, enc, {"mean": list(mean), "std": list(std)}


def _translate_info_sharing(d: Mapping[str, Any], encoder_dim: int) -> UFMInfoSharingConfig:
    _must(
        d.get("info_sharing_and_head_structure", "dual+single"),
        ["dual+single"],
        "info_sharing_and_head_structure",
    )
    _must(d.get("info_sharing_str", "global_attention"), ["global_attention"], "info_sharing_str")
    ik = _require(d, "info_sharing_kwargs", "config")
    for key in ("name", "input_embed_dim", "max_num_views", "use_rand_idx_pe_for_non_reference_views"):
        _require(ik, key, "info_sharing_kwargs")
    _must(ik["input_embed_dim"], [encoder_dim], "info_sharing_kwargs.input_embed_dim (encoder width)")
    _must(
        ik["use_rand_idx_pe_for_non_reference_views"],
        [False],
        "info_sharing_kwargs.use_rand_idx_pe_for_non_reference_views",
    )
    _must(ik.get("intermediates_only", False), [False], "info_sharing_kwargs.intermediates_only")
    rope = _must(
        ik.get("custom_positional_encoding"), [None, "rope"], "info_sharing_kwargs.custom_positional_encoding"
    )
    return UFMInfoSharingConfig(
        dim=ik.get("dim", 768),
        depth=ik.get("depth", 12),
        num_heads=ik.get("num_heads", 12),
        mlp_ratio=float(ik.get("mlp_ratio", 4.0)),
        qkv_bias=bool(ik.get("qkv_bias", True)),
        qk_norm=bool(ik.get("qk_norm", False)),
        layerscale=ik.get("init_values") is not None,
        max_num_views=ik["max_num_views"],
        indices=ik.get("indices"),
        norm_intermediate=bool(ik.get("norm_intermediate", True)),
        rope_freq=100.0 if rope == "rope" else None,
    )


def _translate_head(
    hk: Mapping[str, Any], where: str, patch: int, feature_dims: list[int], output_dim: int
) -> UFMHeadConfig:
    feat = _require(hk, "dpt_feature", where)
    proc = hk.get("dpt_processor") or {}
    hooks = list(feat.get("hooks", [2, 5, 8, 11]))
    _check(
        all(0 <= h < NUM_HEAD_FEATURES for h in hooks),
        f"{where}.dpt_feature.hooks",
        hooks,
        "must index the 4 available features [enc, inter0, inter1, final]",
    )
    dims = feat.get("input_feature_dims", 768)
    dims = [dims] * len(hooks) if isinstance(dims, int) else list(dims)
    _must(dims, [[feature_dims[h] for h in hooks]], f"{where}.dpt_feature.input_feature_dims")
    _must(feat.get("patch_size", patch), [patch], f"{where}.dpt_feature.patch_size")
    _must(feat.get("use_bn", False), [False], f"{where}.dpt_feature.use_bn")
    _must(feat.get("output_width_ratio", 1), [1], f"{where}.dpt_feature.output_width_ratio")
    _must(feat.get("nonlinearity", "relu"), ["relu"], f"{where}.dpt_feature.nonlinearity")
    feature_dim = feat.get("feature_dim", 256)
    _must(
        proc.get("input_feature_dim", feature_dim), [feature_dim], f"{where}.dpt_processor.input_feature_dim"
    )
    _must(proc.get("output_dim", output_dim), [output_dim], f"{where}.dpt_processor.output_dim")
    hidden = proc.get("hidden_dims") or [feature_dim // 2, feature_dim // 2]
    return UFMHeadConfig(
        hooks=hooks,
        layer_dims=list(feat.get("layer_dims", [96, 192, 384, 768])),
        feature_dim=feature_dim,
        hidden_dims=list(hidden),
    )


def _translate_flow_adaptor(d: Mapping[str, Any]) -> UFMFlowAdaptorConfig:
    ak = _require(d, "adaptors_kwargs", "config")
    _must(sorted(ak), [["flow"]], "adaptors_kwargs (keys)")
    _must(ak["flow"].get("class", "FlowAdaptor"), ["FlowAdaptor"], "adaptors_kwargs.flow.class")
    kw = _require(ak["flow"], "kwargs", "adaptors_kwargs.flow")
    _must(
        kw.get("output_normalized_coordinate", False),
        [False],
        "adaptors_kwargs.flow.kwargs.output_normalized_coordinate",
    )
    where = "adaptors_kwargs.flow.kwargs"
    return UFMFlowAdaptorConfig(
        flow_mean=list(_require(kw, "flow_mean", where)),
        flow_std=list(_require(kw, "flow_std", where)),
        base_shape=list(_require(kw, "base_shape", where)),
        scale_strategy=_require(kw, "scale_strategy", where),
    )


def _translate_uncertainty_adaptors(d: Mapping[str, Any]) -> list[UFMAdaptorSpec]:
    specs = []
    for name, entry in _require(d, "uncertainty_adaptors_kwargs", "config").items():
        where = f"uncertainty_adaptors_kwargs.{name}"
        cls_name = _must(entry.get("class"), ["MaskAdaptor", "Covariance2DAdaptor"], f"{where}.class")
        if cls_name == "Covariance2DAdaptor":
            _must(
                (entry.get("kwargs") or {}).get("parametrization", "exp_tanh"),
                ["exp_tanh"],
                f"{where}.kwargs.parametrization",
            )
        specs.append(UFMAdaptorSpec(name, "mask" if cls_name == "MaskAdaptor" else "covariance2d"))
    return specs


def _translate_config_json(d: Mapping[str, Any], override: Mapping[str, Any] | None) -> UFMConfig:
    for key in ("pretrained_checkpoint_path", "pretrained_backbone_checkpoint_path"):
        _must(d.get(key), [None], key)
    _must(d.get("head_type", "dpt"), ["dpt"], "head_type")
    _must(d.get("uncertainty_head_type", "dpt"), ["dpt"], "uncertainty_head_type")
    patch, encoder, data_norm = _translate_encoder(d, override)
    info = _translate_info_sharing(d, encoder.embed_dim)
    feature_dims = [encoder.embed_dim, info.dim, info.dim, info.dim]
    adaptors = _translate_uncertainty_adaptors(d)
    config = UFMConfig(
        patch_size=patch,
        inference_resolution=_resolution_list(d.get("inference_resolution", [560, 420])),
        data_norm=data_norm,
        encoder=encoder,
        info_sharing=info,
        flow_head=_translate_head(
            _require(d, "feature_head_kwargs", "config"), "feature_head_kwargs", patch, feature_dims, 2
        ),
        flow_adaptor=_translate_flow_adaptor(d),
        uncertainty_head=_translate_head(
            _require(d, "uncertainty_head_kwargs", "config"),
            "uncertainty_head_kwargs",
            patch,
            feature_dims,
            sum(ADAPTOR_CHANNELS[a.type] for a in adaptors),
        ),
        uncertainty_adaptors=adaptors,
    )
    config.validate()
    return config


# ---------------------------------------------------------------------------------------------
# Network modules (spec 4.2 - 4.5); attribute names are the checkpoint's key names
# ---------------------------------------------------------------------------------------------


class UFMEncoder(nn.Module):
    """DINOv2 encoder (``encoder.model``): images ``[N, 3, h, w]`` -> features ``[N, C, h/p, w/p]``."""

    def __init__(self, config: UFMEncoderConfig, patch_size: int) -> None:
        super().__init__()
        self.feature_block = config.feature_block % config.depth
        self.norm_output = config.norm_output
        self.model = DinoV2(
            config.embed_dim,
            config.depth,
            config.num_heads,
            config.mlp_ratio,
            img_size=config.img_size,
            patch_size=patch_size,
            num_register_tokens=config.num_register_tokens,
            pos_embed_variant="registers" if config.interpolate_antialias else "classic",
            interpolate_offset=config.interpolate_offset,
        )

    def forward(self, images: Tensor) -> Tensor:
        """images ``[N, 3, h, w]`` (normalised) -> ``[N, C, h/p, w/p]`` (row-major tokens)."""
        tokens = self.model(images, block=self.feature_block, norm=self.norm_output)
        grid_hw = (images.shape[-2] // self.model.patch_size, images.shape[-1] // self.model.patch_size)
        return tokens.transpose(1, 2).reshape(tokens.shape[0], -1, *grid_hw)


def sinusoid_view_table(num_views: int, dim: int) -> Tensor:
    """``[num_views, dim]`` float32: ``sin(v / 10000^(2*floor(j/2)/dim))`` at even ``j``, cos at odd
    (spec 4.3 step 3; evaluated in float64). Only the initial value: the checkpoint stores it."""
    views = torch.arange(num_views, dtype=torch.float64)[:, None]
    j = torch.arange(dim)
    angles = views / torch.pow(10000.0, (2 * (j // 2)).double() / dim)[None, :]
    return torch.where(j % 2 == 0, angles.sin(), angles.cos()).float()


class InfoSharing(nn.Module):
    """Global self-attention over the tokens of both views (``info_sharing``)."""

    def __init__(self, config: UFMInfoSharingConfig, input_dim: int) -> None:
        super().__init__()
        dim = config.dim
        # Absent (identity) when the encoder width already equals the transformer width.
        self.proj_embed = nn.Linear(input_dim, dim) if input_dim != dim else None
        self.register_buffer("view_pos_table", sinusoid_view_table(config.max_num_views, dim))
        self.self_attention_blocks = nn.ModuleList(
            Block(
                dim,
                config.num_heads,
                config.mlp_ratio,
                qkv_bias=config.qkv_bias,
                qk_norm=config.qk_norm,
                layerscale=config.layerscale,
                norm_eps=1e-6,
            )
            for _ in range(config.depth)
        )
        self.norm = nn.LayerNorm(dim, eps=1e-6)
        self.intermediate_blocks = _resolve_block_indices(config.indices, config.depth)[:2]
        self.norm_intermediate = config.norm_intermediate
        self.rope = (
            None if config.rope_freq is None else RotaryEmbedding2D(dim // config.num_heads, config.rope_freq)
        )
        self.gradient_checkpointing = False

    def forward(self, view1: Tensor, view2: Tensor) -> list[tuple[Tensor, Tensor]]:
        """view1, view2 ``[B, C_in, h', w']`` -> ``[(inter0_1, inter0_2), (inter1_1, inter1_2),
        (final_1, final_2)]``, each ``[B, dim, h', w']``."""
        gh, gw = view1.shape[-2:]
        x = torch.cat([view1.flatten(2), view2.flatten(2)], dim=2).transpose(1, 2)  # [B, 2P, C_in]
        if self.proj_embed is not None:
            x = self.proj_embed(x)
        view_ids = torch.arange(2, device=x.device).repeat_interleave(gh * gw)  # [2P]
        x = x + self.view_pos_table[view_ids].to(x.dtype)
        rope = None if self.rope is None else self.rope.bind(_view_positions(gh, gw, x.device), max(gh, gw) - 1)
        outputs = []
        for i, block in enumerate(self.self_attention_blocks):
            x = run_block(block, x, rope, self.gradient_checkpointing)
            if i in self.intermediate_blocks:
                outputs.append(self.norm(x) if self.norm_intermediate else x)
        outputs.append(self.norm(x))
        return [_split_views(t, gh, gw) for t in outputs]


def _view_positions(grid_h: int, grid_w: int, device: torch.device) -> Tensor:
    """``[1, 2*h'*w', 2]`` 0-based ``(row, col)`` of every patch token, the same for both views."""
    return grid_positions(grid_h, grid_w, device).repeat(2, 1)[None]


def _split_views(tokens: Tensor, grid_h: int, grid_w: int) -> tuple[Tensor, Tensor]:
    """``[B, 2P, C]`` -> two ``[B, C, h', w']`` maps (view 1, view 2)."""
    maps = tokens.transpose(1, 2).unflatten(2, (2, grid_h, grid_w))  # [B, C, 2, h', w']
    return maps[:, :, 0], maps[:, :, 1]


def _level_input_process(in_dim: int, layer_dim: int, feature_dim: int, level: int) -> nn.Sequential:
    """Pyramid level ``level`` (0 = finest): ``[[1x1 conv, resample], layer_rn 3x3 conv]`` with
    resampling x4 (transposed conv), x2 (transposed conv), none, /2 (strided conv)."""
    project = nn.Sequential(nn.Conv2d(in_dim, layer_dim, kernel_size=1), resample_layer(layer_dim, level))
    # The no-bias 3x3 conv is the checkpoint's layer{k}_rn, stored as input_process.{k-1}.1.
    layer_rn = nn.Conv2d(layer_dim, feature_dim, kernel_size=3, padding=1, bias=False)
    return nn.Sequential(project, layer_rn)


class _Scratch(nn.Module):
    """Holds the four RefineNet fusion blocks (``scratch.refinenet{1..4}``)."""

    def __init__(self, feature_dim: int) -> None:
        super().__init__()
        self.refinenet1 = FusionBlock(feature_dim, has_skip=True, rectify_skip=False)
        self.refinenet2 = FusionBlock(feature_dim, has_skip=True, rectify_skip=False)
        self.refinenet3 = FusionBlock(feature_dim, has_skip=True, rectify_skip=False)
        self.refinenet4 = FusionBlock(feature_dim, has_skip=False, rectify_skip=False)


class DPTFeaturePyramid(nn.Module):
    """Four hooked ``[B, C_k, h', w']`` maps -> fused features ``[B, F, 8h', 8w']`` (spec 4.4)."""

    def __init__(self, config: UFMHeadConfig, feature_dims: Sequence[int]) -> None:
        super().__init__()
        self.hooks = list(config.hooks)
        self.input_process = nn.ModuleList(
            _level_input_process(feature_dims[hook], layer_dim, config.feature_dim, level)
            for level, (hook, layer_dim) in enumerate(zip(config.hooks, config.layer_dims, strict=True))
        )
        self.scratch = _Scratch(config.feature_dim)

    def forward(self, features: Sequence[Tensor]) -> Tensor:
        """features ``[enc, inter0, inter1, final]`` of one view, each ``[B, C_k, h', w']`` ->
        ``[B, F, 8h', 8w']``."""
        r1, r2, r3, r4 = (
            proc(features[hook]) for proc, hook in zip(self.input_process, self.hooks, strict=True)
        )
        s = self.scratch
        # x2 of the coarsest level can overshoot by one row/column (odd grids): crop, not resize.
        p4 = s.refinenet4(r4)[:, :, : r3.shape[-2], : r3.shape[-1]]
        p3 = s.refinenet3(p4, r3)
        p2 = s.refinenet2(p3, r2)
        return s.refinenet1(p2, r1)


class DPTRegressionProcessor(nn.Module):
    """``[B, F, 8h', 8w']`` -> ``[B, out, h, w]``: conv3x3, bilinear resize (align_corners=True)
    to the network input size, conv3x3 + ReLU + conv1x1."""

    def __init__(self, in_dim: int, hidden_dims: Sequence[int], out_dim: int) -> None:
        super().__init__()
        self.conv1 = nn.Conv2d(in_dim, hidden_dims[0], kernel_size=3, padding=1)
        self.conv2 = nn.Sequential(
            nn.Conv2d(hidden_dims[0], hidden_dims[1], kernel_size=3, padding=1),
            nn.ReLU(),
            nn.Conv2d(hidden_dims[1], out_dim, kernel_size=1),
        )

    def forward(self, x: Tensor, size: tuple[int, int]) -> Tensor:
        """x ``[B, F, H', W']`` -> ``[B, out, *size]``."""
        x = F.interpolate(self.conv1(x), size=size, mode="bilinear", align_corners=True)
        return self.conv2(x)


class FlowAdaptor(nn.Module):
    """Raw 2 channels -> flow in pixels of the network input (spec 4.5).

    ``flow_mean`` / ``flow_std`` ``[1, 2, 1, 1]`` are persistent buffers (the checkpoint wins).
    """

    def __init__(self, config: UFMFlowAdaptorConfig) -> None:
        super().__init__()
        self.register_buffer(
            "flow_mean", torch.tensor(config.flow_mean, dtype=torch.float32).view(1, 2, 1, 1)
        )
        self.register_buffer("flow_std", torch.tensor(config.flow_std, dtype=torch.float32).view(1, 2, 1, 1))
        self.base_shape = tuple(config.base_shape)
        self.scale_strategy = config.scale_strategy

    def forward(self, raw: Tensor) -> Tensor:
        """raw ``[B, 2, h, w]`` -> flow ``[B, 2, h, w]`` (x, y) in network-input pixels."""
        scale = flow_scale(raw.shape[-2:], self.base_shape, self.scale_strategy)
        scale = torch.tensor(scale, dtype=raw.dtype, device=raw.device).view(1, 2, 1, 1)
        return raw * self.flow_std * scale + self.flow_mean * scale


def flow_scale(size_hw: Sequence[int], base_hw: Sequence[int], strategy: str) -> tuple[float, float]:
    """``(sx, sy)`` multiplying the de-normalised flow of a ``size_hw`` network input."""
    (h, w), (hb, wb) = size_hw, base_hw
    return {
        "none": (1.0, 1.0),
        "scale_width": (w / wb, w / wb),
        "scale_height": (h / hb, h / hb),
        "scale_both": (w / wb, h / hb),
    }[strategy]


def covariance_from_exp_tanh(raw: Tensor) -> Tensor:
    """``[B, 3, h, w]`` parameters ``(c1, c2, s)`` -> ``[B, 3, h, w]`` covariance
    ``(sigma_x^2, sigma_y^2, sigma_xy) = (exp c1, exp c2, tanh(s) exp((c1 + c2)/2))``."""
    c1, c2, s = raw.unbind(1)
    return torch.stack([c1.exp(), c2.exp(), torch.tanh(s) * ((c1 + c2) / 2).exp()], dim=1)


class _Adaptors(nn.Module):
    """``X.1.adaptors.<name>`` (the checkpoint's layout for the flow adaptor's buffers)."""

    def __init__(self, adaptors: Mapping[str, nn.Module]) -> None:
        super().__init__()
        self.adaptors = nn.ModuleDict(adaptors)


class UFMHead(nn.ModuleList):
    """``X.0.0`` feature pyramid, ``X.0.1`` regression processor, ``X.1`` adaptors (if any)."""

    def __init__(
        self,
        config: UFMHeadConfig,
        feature_dims: Sequence[int],
        out_dim: int,
        adaptors: Mapping[str, nn.Module] | None = None,
    ) -> None:
        pyramid = DPTFeaturePyramid(config, feature_dims)
        processor = DPTRegressionProcessor(config.feature_dim, config.hidden_dims, out_dim)
        # Only the flow head has stateful adaptors; the uncertainty ones are plain functions.
        extra = [] if adaptors is None else [_Adaptors(adaptors)]
        super().__init__([nn.ModuleList([pyramid, processor]), *extra])

    def decode(self, features: Sequence[Tensor], size: tuple[int, int]) -> Tensor:
        """View-1 features ``[enc, inter0, inter1, final]`` -> raw channels ``[B, out, h, w]``."""
        pyramid, processor = self[0]
        return processor(pyramid(features), size)


# ---------------------------------------------------------------------------------------------
# Input handling and unmapping (spec 4.1 and 4.6)
# ---------------------------------------------------------------------------------------------


def to_channels_first(images: Tensor, name: str) -> Tensor:
    """``[B, 3, H, W]``, ``[B, H, W, 3]`` or the same without batch -> ``[B, 3, H, W]``.

    Channel-first wins when both readings are possible (``dim1 == 3``), as in the reference.
    """
    if not isinstance(images, Tensor):
        raise ValueError(f"{name} must be a torch.Tensor, got {type(images).__name__}")
    x = images.unsqueeze(0) if images.ndim == 3 else images
    if x.ndim == 4 and x.shape[1] == 3:
        return x
    if x.ndim == 4 and x.shape[-1] == 3:
        return x.permute(0, 3, 1, 2)
    raise ValueError(f"{name} must be [B, 3, H, W] or [B, H, W, 3] (or 3-D), got {list(images.shape)}")


def normalise_images(
    images: Tensor, data_norm_type: str, mean: Sequence[float], std: Sequence[float]
) -> Tensor:
    """Re-normalise ``[B, 3, H, W]`` images to the encoder's ``mean``/``std`` (float32).

    uint8 images are taken as ``x / 255``; float images must declare their current normalisation
    (``"identity"`` = plain [0, 1]). Conversion: ``x * std_prev/std + (mean_prev - mean)/std``.
    """
    if images.dtype == torch.uint8:
        x, data_norm_type = images.float() / 255.0, "identity"
    elif images.is_floating_point():
        x = images.float()
    else:
        raise ValueError(f"images must be uint8 or floating, got {images.dtype}")
    if data_norm_type not in NORMALISATIONS:
        raise ValueError(
            f"unknown data_norm_type {data_norm_type!r}; expected one of {sorted(NORMALISATIONS)}"
        )
    mean_prev, std_prev = NORMALISATIONS[data_norm_type]

    def column(values: Sequence[float]) -> Tensor:
        return torch.tensor(values, dtype=torch.float32, device=x.device).view(1, 3, 1, 1)

    mean_t, std_t = column(mean), column(std)
    return x * (column(std_prev) / std_t) + (column(mean_prev) - mean_t) / std_t


def choose_resolution(
    candidates: Sequence[Sequence[int]], source_hw: Sequence[int], target_hw: Sequence[int]
) -> tuple[int, int]:
    """Network size ``(h, w)``: the ``[W, H]`` candidate whose aspect ``h/w`` is closest to both
    images' (sum of absolute differences; the first wins ties)."""
    aspects = (source_hw[0] / source_hw[1], target_hw[0] / target_hw[1])
    w, h = min(candidates, key=lambda wh: sum(abs(wh[1] / wh[0] - a) for a in aspects))
    return int(h), int(w)


def region_size(network_hw: Sequence[int], source_hw: Sequence[int]) -> tuple[int, int]:
    """``(hr, wr)`` = ``trunc(f32(h/H0) * H0)``, ``trunc(f32(w/W0) * W0)`` in float32.

    The reference rounds the ratio to float32 and multiplies in float32, which lands one below
    ``h`` for some sizes (e.g. ``h = 56``, ``H0 = 92`` -> 55); the unmapping depends on it.
    """
    (h, w), (h0, w0) = network_hw, source_hw
    return _f32_truncated(h, h0), _f32_truncated(w, w0)


def _f32_truncated(n: int, n0: int) -> int:
    return int(np.float32(n / n0) * np.float32(n0))


def resize_images(images: Tensor, size: tuple[int, int]) -> Tensor:
    """Bilinear, ``align_corners=False``, antialiased resize ``[B, 3, H, W] -> [B, 3, *size]``."""
    if tuple(images.shape[-2:]) == tuple(size):
        return images
    return F.interpolate(images, size=size, mode="bilinear", align_corners=False, antialias=True)


def _pixel_centre_grid(height: int, width: int, like: Tensor) -> Tensor:
    """``[1, 2, height, width]``: channel 0 = ``j + 0.5`` (x), channel 1 = ``i + 0.5`` (y)."""
    ys = torch.arange(height, dtype=like.dtype, device=like.device) + 0.5
    xs = torch.arange(width, dtype=like.dtype, device=like.device) + 0.5
    grid_y, grid_x = torch.meshgrid(ys, xs, indexing="ij")
    return torch.stack([grid_x, grid_y])[None]


def _xy_column(x: float, y: float, like: Tensor) -> Tensor:
    return torch.tensor([x, y], dtype=like.dtype, device=like.device).view(1, 2, 1, 1)


def unmap_flow(
    flow: Tensor, region_hw: Sequence[int], source_hw: Sequence[int], target_hw: Sequence[int]
) -> Tensor:
    """Network-size flow ``[B, 2, h, w]`` -> flow in input pixels ``[B, 2, H0, W0]`` (spec 4.6).

    Source points are the bilinearly resized pixel-centre grid of the ``hr x wr`` region, target
    points that plus the nearest-resized flow; each is scaled by its own image's size ratio.
    """
    (hr, wr), (h0, w0), (h1, w1) = region_hw, source_hw, target_hw
    grid = _pixel_centre_grid(hr, wr, flow)
    source = F.interpolate(grid, size=(h0, w0), mode="bilinear", align_corners=False)
    target = F.interpolate(flow[:, :, :hr, :wr], size=(h0, w0), mode="nearest") + source
    return target * _xy_column(w1 / wr, h1 / hr, flow) - source * _xy_column(w0 / wr, h0 / hr, flow)


def unmap_nearest(maps: Tensor, region_hw: Sequence[int], source_hw: Sequence[int]) -> Tensor:
    """``[B, C, h, w]`` -> ``[B, C, H0, W0]``: crop the ``hr x wr`` region, nearest resize."""
    hr, wr = region_hw
    return F.interpolate(maps[:, :, :hr, :wr], size=tuple(source_hw), mode="nearest")


def unmap_covariance(
    cov: Tensor, region_hw: Sequence[int], network_hw: Sequence[int], source_hw: Sequence[int]
) -> Tensor:
    """Covariance ``[B, 3, h, w]`` (sxx, syy, sxy) -> ``[B, 3, H0, W0]`` in input pixels squared.

    The scale uses the full network size ``(h, w)``, not the region (reference behaviour).
    """
    (h, w), (h0, w0) = network_hw, source_hw
    sx, sy = w0 / w, h0 / h
    scale = torch.tensor([sx * sx, sy * sy, sx * sy], dtype=cov.dtype, device=cov.device).view(1, 3, 1, 1)
    return unmap_nearest(cov, region_hw, source_hw) * scale


# ---------------------------------------------------------------------------------------------
# The model
# ---------------------------------------------------------------------------------------------


class UFM(nn.Module):
    """UniFlowMatchConfidence: dense flow and covisibility from an image pair (spec section 4).

    Parameters are frozen and the module is in eval mode; gradients still flow to the inputs.
    ``autocast_dtype`` (e.g. ``torch.bfloat16``) runs the encoder and info-sharing under autocast
    while the heads always run in their parameter dtype (fp32); ``gradient_checkpointing``
    recomputes transformer blocks in backward to save memory when differentiating.

    ``UFM(config)`` draws a random initialisation from the global torch RNG (use :meth:`random`
    for a seeded one) that gives sane outputs: flow of a pixel or so, covisibility ~0.8 (above
    GeCo's 0.5 threshold, not saturated), both depending on the images.
    """

    def __init__(
        self,
        config: UFMConfig | Mapping[str, Any] | None = None,
        *,
        gradient_checkpointing: bool = False,
        autocast_dtype: torch.dtype | None = None,
    ) -> None:
        """``config``: a :class:`UFMConfig` or section-5 dict; None = UFM-Base."""
        super().__init__()
        if config is None:
            config = UFMConfig()
        elif not isinstance(config, UFMConfig):
            config = UFMConfig.from_dict(config)
        config.validate()
        self.config = config
        self.encoder = UFMEncoder(config.encoder, config.patch_size)
        self.info_sharing = InfoSharing(config.info_sharing, config.encoder.embed_dim)
        dims = config.head_feature_dims
        self.head1 = UFMHead(config.flow_head, dims, 2, {"flow": FlowAdaptor(config.flow_adaptor)})
        self.uncertainty_head = UFMHead(config.uncertainty_head, dims, config.uncertainty_channels)
        self.autocast_dtype = autocast_dtype
        self.gradient_checkpointing = gradient_checkpointing
        self.reset_parameters()
        self.requires_grad_(False)
        self.eval()

    @property
    def gradient_checkpointing(self) -> bool:
        """Recompute the encoder and info-sharing blocks' activations in backward."""
        return self.info_sharing.gradient_checkpointing

    @gradient_checkpointing.setter
    def gradient_checkpointing(self, value: bool) -> None:
        self.encoder.model.gradient_checkpointing = bool(value)
        self.info_sharing.gradient_checkpointing = bool(value)

    # -- construction ------------------------------------------------------------------------

    @torch.no_grad()
    def reset_parameters(self, generator: torch.Generator | None = None) -> None:
        """Random weights that keep a random model's outputs in a sane range (see class doc).

        Also resets the buffers to their initial values (``view_pos_table``, the flow
        adaptor's ``flow_mean`` / ``flow_std`` from the config), so a model built on the meta
        device and materialised with ``to_empty`` is complete.
        """
        init_weights_(self, generator)
        info, adaptor = self.info_sharing, self.head1[1].adaptors["flow"]
        # Variance-preserving info-sharing linears (not std 0.02): with near-uniform attention
        # the flow of a random model would hardly depend on the target image.
        for module in info.modules():
            if isinstance(module, nn.Linear):
                nn.init.normal_(module.weight, std=module.in_features**-0.5, generator=generator)
        info.view_pos_table.copy_(sinusoid_view_table(*info.view_pos_table.shape))
        flow_config = self.config.flow_adaptor
        adaptor.flow_mean.copy_(torch.tensor(flow_config.flow_mean).view_as(adaptor.flow_mean))
        adaptor.flow_std.copy_(torch.tensor(flow_config.flow_std).view_as(adaptor.flow_std))
        # Small last layers: flow of a pixel or so whatever the adaptor's scale, and a
        # covisibility logit near logit(0.8) with some spread (other channels start near 0).
        flow_out = self.head1[0][1].conv2[2]
        std = FLOW_INIT_GAIN / (max(flow_config.flow_std) * flow_out.weight[0].numel() ** 0.5)
        nn.init.normal_(flow_out.weight, std=std, generator=generator)
        uncertainty_out = self.uncertainty_head[0][1].conv2[2]
        std = UNCERTAINTY_INIT_GAIN * uncertainty_out.weight[0].numel() ** -0.5
        nn.init.normal_(uncertainty_out.weight, std=std, generator=generator)
        start = 0
        for spec in self.config.uncertainty_adaptors:
            if spec.type == "mask":
                uncertainty_out.bias[start] = COVISIBILITY_INIT_LOGIT
            start += ADAPTOR_CHANNELS[spec.type]

    @classmethod
    def random(
        cls, config: UFMConfig | Mapping[str, Any] | None = None, seed: int = 0, **kwargs: Any
    ) -> UFM:
        """A randomly initialised model whose weights depend only on ``seed`` (global RNG untouched)."""
        with torch.device("meta"):
            model = cls(config, **kwargs)
        model.to_empty(device="cpu")
        model.reset_parameters(torch.Generator().manual_seed(seed))
        return model

    # -- loading -----------------------------------------------------------------------------

    def checkpoint_aliases(self) -> dict[str, str]:
        """Alternative key -> our key for the ``layer{k}_rn`` convs (spec 4.7)."""
        aliases = {}
        for head in ("head1", "uncertainty_head"):
            for k in range(1, 5):
                ours = f"{head}.0.0.input_process.{k - 1}.1.weight"
                aliases[f"{head}.0.0.scratch.layer{k}_rn.weight"] = ours
                aliases[f"{head}.0.0.scratch.layer_rn.{k - 1}.weight"] = ours
        return aliases

    def load_checkpoint(self, state_dict: Mapping[str, Tensor]) -> None:
        """Strict, alias-aware load of a UFM state dict (spec 6).

        Raises:
            CheckpointMismatchError: missing / unexpected / mis-shaped keys, an uncertainty head
                whose channels do not fit the configured adaptors, absent flow buffers, or alias
                names of one conv holding different tensors.
        """
        channels_key = "uncertainty_head.0.1.conv2.2.weight"
        if (
            channels_key in state_dict
            and state_dict[channels_key].shape[0] != self.config.uncertainty_channels
        ):
            layout = [(a.name, ADAPTOR_CHANNELS[a.type]) for a in self.config.uncertainty_adaptors]
            raise CheckpointMismatchError(
                f"UFM checkpoint's uncertainty head has {state_dict[channels_key].shape[0]} output channels "
                f"but the configured adaptors {layout} need {self.config.uncertainty_channels}"
            )
        for buffer in ("flow_mean", "flow_std"):
            if f"head1.1.adaptors.flow.{buffer}" not in state_dict:
                raise CheckpointMismatchError(
                    f"UFM checkpoint lacks head1.1.adaptors.flow.{buffer}; the flow scale must come "
                    "from the checkpoint, not from the config's initial values"
                )
        aliases = self.checkpoint_aliases()
        seen: dict[str, Tensor] = {}
        for key, value in state_dict.items():
            ours = aliases.get(key, key)
            if ours in seen and not torch.equal(seen[ours], value):
                raise CheckpointMismatchError(
                    f"UFM checkpoint holds different tensors for the aliases of {ours}"
                )
            seen[ours] = value
        load_state_dict_checked(self, state_dict, model_name="UFM", aliases=aliases)

    @classmethod
    def from_state_dict(
        cls, config: UFMConfig | Mapping[str, Any] | None, state_dict: Mapping[str, Tensor], **kwargs: Any
    ) -> UFM:
        """Build from a config (section-5 dict or :class:`UFMConfig`; None = UFM-Base) and load
        ``state_dict`` with :meth:`load_checkpoint`; ``kwargs`` go to the constructor."""
        with torch.device("meta"):
            model = cls(config, **kwargs)
        model.to_empty(device="cpu")  # every parameter and buffer is overwritten by the strict load
        model.load_checkpoint(state_dict)
        return model

    @classmethod
    def from_pretrained(
        cls,
        repo_id_or_local_dir: str | os.PathLike = "infinity1096/UFM-Base",
        *,
        dtype: torch.dtype = torch.float32,
        device: str | torch.device = "cpu",
        revision: str | None = None,
        cache_dir: str | os.PathLike | None = None,
        **kwargs: Any,
    ) -> UFM:
        """Load ``config.json`` + ``model.safetensors`` from a hub repo or a local folder.

        ``config.json`` may be the upstream schema (translated by
        :meth:`UFMConfig.from_config_json`) or our section-5 schema. ``dtype`` applies to the
        trunk (:meth:`trunk_to`); ``kwargs`` (``gradient_checkpointing``, ``autocast_dtype``) go
        to the constructor.

        Raises:
            WeightsNotFoundError: the files are neither in the folder nor reachable / cached.
        """
        fetch = dict(model_name="UFM", revision=revision, cache_dir=cache_dir)
        config_path = fetch_checkpoint_file(repo_id_or_local_dir, ["config.json"], **fetch)
        weights_path = fetch_checkpoint_file(
            repo_id_or_local_dir, ["model.safetensors", "pytorch_model.bin"], **fetch
        )
        config = config_from_json(json.loads(config_path.read_text()))
        with torch.device("meta"):
            model = cls(config, **kwargs)
        model.to_empty(device=device)  # every parameter and buffer is overwritten by the strict load
        model.load_checkpoint(load_weights(weights_path))
        return model.trunk_to(dtype)

    def trunk_to(self, dtype: torch.dtype) -> UFM:
        """Store the encoder and info-sharing transformer (nearly all parameters and compute) in
        ``dtype``, e.g. bfloat16 on a GPU; the DPT heads stay float32 and so do the outputs.
        Returns ``self``."""
        self.encoder.to(dtype)
        self.info_sharing.to(dtype)
        return self

    # -- network -----------------------------------------------------------------------------

    def encode_views(self, source: Tensor, target: Tensor) -> tuple[list[Tensor], list[Tensor]]:
        """Normalised network-size images ``[B, 3, h, w]`` -> per view the four head features
        ``[enc [B, C_enc, h', w'], inter0, inter1, final [B, dim, h', w']]``.

        Both views go through the encoder as one batch ``[source; target]``.
        """
        param_dtype = self.encoder.model.patch_embed.proj.weight.dtype
        images = torch.cat([source, target])
        if self.autocast_dtype is None:
            context, images = nullcontext(), images.to(param_dtype)
        else:
            context = torch.autocast(images.device.type, dtype=self.autocast_dtype)
        with context:
            enc1, enc2 = self.encoder(images).chunk(2)
            (inter0_1, inter0_2), (inter1_1, inter1_2), (final1, final2) = self.info_sharing(enc1, enc2)
        return [enc1, inter0_1, inter1_1, final1], [enc2, inter0_2, inter1_2, final2]

    def decode(self, features: Sequence[Tensor], size: tuple[int, int]) -> dict[str, Tensor]:
        """View-1 features -> network-size outputs (float32), heads outside any autocast.

        Returns:
            ``flow_raw [B, 2, h, w]`` (pixels of the network input), ``covisibility_raw [B, h, w]``,
            ``flow_covariance_raw [B, 3, h, w]`` if a covariance adaptor is configured, and the
            pre-adaptor channels ``flow_head_decoded [B, 2, h, w]``,
            ``uncertainty_head_decoded [B, K, h, w]``.
        """
        head_dtype = self.head1[0][1].conv1.weight.dtype
        with torch.autocast(features[0].device.type, enabled=False):
            features = [f.to(head_dtype) for f in features]
            flow_decoded = self.head1.decode(features, size).float()
            uncertainty_decoded = self.uncertainty_head.decode(features, size).float()
        out = {
            "flow_raw": self.head1[1].adaptors["flow"](flow_decoded),
            "flow_head_decoded": flow_decoded,
            "uncertainty_head_decoded": uncertainty_decoded,
        }
        channels = [ADAPTOR_CHANNELS[a.type] for a in self.config.uncertainty_adaptors]
        for spec, raw in zip(
            self.config.uncertainty_adaptors, uncertainty_decoded.split(channels, dim=1), strict=True
        ):
            if spec.type == "mask":
                out["covisibility_raw"] = torch.sigmoid(raw[:, 0])
            else:
                out["flow_covariance_raw"] = covariance_from_exp_tanh(raw)
        return out

    def forward(self, source: Tensor, target: Tensor) -> dict[str, Tensor]:
        """Normalised network-size images ``[B, 3, h, w]`` -> :meth:`decode` outputs."""
        features, _ = self.encode_views(source, target)
        return self.decode(features, tuple(source.shape[-2:]))

    # -- public entry points -----------------------------------------------------------------

    def preprocess(
        self, source: Tensor, target: Tensor, data_norm_type: str = "identity"
    ) -> tuple[Tensor, Tensor]:
        """Images in any accepted layout -> normalised network inputs ``[B, 3, h, w]`` (spec 4.1).

        Normalisation happens before the antialiased resize; both images get the same ``(h, w)``.
        """
        source, target = to_channels_first(source, "source"), to_channels_first(target, "target")
        if source.dtype != target.dtype:
            raise ValueError(f"source and target must share a dtype, got {source.dtype} and {target.dtype}")
        if source.shape[0] != target.shape[0]:
            raise ValueError(f"source and target batch sizes differ: {source.shape[0]} vs {target.shape[0]}")
        size = choose_resolution(self.config.inference_resolution, source.shape[-2:], target.shape[-2:])
        mean, std = self.config.data_norm["mean"], self.config.data_norm["std"]
        source = resize_images(normalise_images(source, data_norm_type, mean, std), size)
        target = resize_images(normalise_images(target, data_norm_type, mean, std), size)
        return source, target

    def predict_correspondences(
        self, source: Tensor, target: Tensor, data_norm_type: str = "identity"
    ) -> dict[str, Tensor]:
        """Flow and covisibility of ``source`` -> ``target`` at the source's input resolution.

        Args:
            source, target: ``[B, 3, H, W]`` / ``[B, H, W, 3]`` (3-D: B = 1), uint8 or float in
                the normalisation named by ``data_norm_type`` (``"identity"`` = [0, 1]).
        Returns:
            ``flow [B, 2, H0, W0]`` in pixels (x, y), ``covisibility [B, H0, W0]`` in [0, 1],
            ``flow_covariance [B, 3, H0, W0]`` if configured, plus the :meth:`decode` outputs.
            Differentiable with respect to float inputs.
        """
        source, target = to_channels_first(source, "source"), to_channels_first(target, "target")
        source_hw, target_hw = tuple(source.shape[-2:]), tuple(target.shape[-2:])
        net_source, net_target = self.preprocess(source, target, data_norm_type)
        network_hw = tuple(net_source.shape[-2:])
        out = self(net_source, net_target)
        region = region_size(network_hw, source_hw)
        out["flow"] = unmap_flow(out["flow_raw"], region, source_hw, target_hw)
        out["covisibility"] = unmap_nearest(out["covisibility_raw"][:, None], region, source_hw)[:, 0]
        if "flow_covariance_raw" in out:
            out["flow_covariance"] = unmap_covariance(
                out["flow_covariance_raw"], region, network_hw, source_hw
            )
        return out

    def estimate_flow(self, source: Tensor, target: Tensor) -> Correspondences:
        """:class:`FlowEstimator` protocol: pairs ``[N, 3, H, W]`` in [0, 1] -> flow ``[N, 2, H, W]``
        in pixels and covisibility ``[N, H, W]``, all pairs in one forward pass."""
        for name, x in (("source", source), ("target", target)):
            if not isinstance(x, Tensor) or x.ndim != 4 or x.shape[1] != 3 or not x.is_floating_point():
                raise ValueError(
                    f"{name} must be a floating [N, 3, H, W] tensor in [0, 1], got "
                    f"{getattr(x, 'dtype', type(x).__name__)} {list(getattr(x, 'shape', []))}"
                )
        if source.shape != target.shape:
            raise ValueError(f"source and target shapes differ: {list(source.shape)} vs {list(target.shape)}")
        out = self.predict_correspondences(source, target, "identity")
        return Correspondences(flow=out["flow"], covisibility=out["covisibility"])


def config_from_json(raw: Mapping[str, Any]) -> UFMConfig:
    """A ``config.json`` in either the upstream schema (``encoder_kwargs`` ...) or ours."""
    if "encoder_kwargs" in raw or "encoder_str" in raw:
        return UFMConfig.from_config_json(raw)
    return UFMConfig.from_dict(raw)
