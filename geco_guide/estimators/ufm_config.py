"""UFM configuration: the architecture dataclasses (spec section 5.2), their validation, and the
translation of the upstream ``config.json`` (spec 4.8).

The model itself (modules, pre/post-processing, the :class:`~geco_guide.estimators.ufm.UFM`
wrapper) lives in :mod:`geco_guide.estimators.ufm`, which re-exports the names defined here.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import asdict, dataclass, field
from typing import Any

from ..types import merge_dataclass
from .vit import IMAGENET_MEAN, IMAGENET_STD

__all__ = [
    "UFMConfig",
    "UFMEncoderConfig",
    "UFMInfoSharingConfig",
    "UFMHeadConfig",
    "UFMFlowAdaptorConfig",
    "UFMAdaptorSpec",
    "NORMALISATIONS",
    "ADAPTOR_CHANNELS",
    "COVISIBILITY_ADAPTOR",
    "config_from_json",
    "resolve_block_indices",
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
        blocks = resolve_block_indices(info.indices, info.depth, "info_sharing.indices")
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


def resolve_block_indices(
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
    feature = resolve_block_indices(ek.get("indices", 1), enc.depth, "encoder_kwargs.indices")[-1]
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


def config_from_json(raw: Mapping[str, Any]) -> UFMConfig:
    """A ``config.json`` in either the upstream schema (``encoder_kwargs`` ...) or ours."""
    if "encoder_kwargs" in raw or "encoder_str" in raw:
        return UFMConfig.from_config_json(raw)
    return UFMConfig.from_dict(raw)
