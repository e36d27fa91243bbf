"""VGGT configuration: the architecture dataclasses of ``shared/specs/estimators.md`` section 5.1
(defaults are VGGT-1B) and their dict form.

The model lives in :mod:`geco_guide.estimators.vggt`, which re-exports :class:`VGGTConfig`.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import asdict, dataclass, field
from typing import Any

from ..types import is_integer, is_number, merge_dataclass

__all__ = ["AggregatorConfig", "CameraHeadConfig", "DepthHeadConfig", "DinoConfig", "VGGTConfig"]


# --------------------------------------------------------------------------------------------
# Configuration (spec 5.1)

#: The keys of the upstream model's ``config.json`` (its constructor arguments).
UPSTREAM_JSON_KEYS = ("img_size", "patch_size", "embed_dim", "enable_camera", "enable_point", "enable_depth",
                      "enable_track")


@dataclass
class DinoConfig:
    depth: int = 24
    num_heads: int = 16
    mlp_ratio: float = 4.0


@dataclass
class AggregatorConfig:
    depth: int = 24
    num_heads: int = 16
    mlp_ratio: float = 4.0
    qk_norm: bool = True
    rope_freq: float = 100.0


@dataclass
class CameraHeadConfig:
    trunk_depth: int = 4
    num_heads: int = 16
    mlp_ratio: float = 4.0
    num_iterations: int = 4


@dataclass
class DepthHeadConfig:
    features: int = 256
    out_channels: tuple[int, int, int, int] = (256, 512, 1024, 1024)
    intermediate_layer_idx: tuple[int, int, int, int] = (4, 11, 17, 23)


@dataclass
class VGGTConfig:
    """Architecture of a VGGT model; defaults are VGGT-1B. ``img_size`` is also the network
    input width used by :meth:`VGGT.estimate_geometry`."""

    patch_size: int = 14
    img_size: int = 518
    embed_dim: int = 1024
    num_register_tokens: int = 4
    dino: DinoConfig = field(default_factory=DinoConfig)
    aggregator: AggregatorConfig = field(default_factory=AggregatorConfig)
    camera_head: CameraHeadConfig = field(default_factory=CameraHeadConfig)
    depth_head: DepthHeadConfig = field(default_factory=DepthHeadConfig)

    @classmethod
    def from_dict(cls, d: Mapping[str, Any]) -> "VGGTConfig":
        """Build from the section-5.1 dict (nested sub-dicts; missing keys keep defaults), checked
        (:meth:`validate`)."""
        config = merge_dataclass(cls(), d)
        config.validate()
        return config

    @classmethod
    def from_json(cls, raw: Mapping[str, Any]) -> "VGGTConfig":
        """The architecture of a ``config.json``: ours (:meth:`to_dict`), or the upstream model's
        constructor arguments (``img_size``, ``patch_size``, ``embed_dim`` and ``enable_*`` head
        switches, written by its hub mixin), whose other sizes are fixed at VGGT-1B's."""
        if not set(raw) <= set(UPSTREAM_JSON_KEYS):
            return cls.from_dict(raw)
        missing_heads = [key for key in ("enable_camera", "enable_depth") if raw.get(key) is False]
        if missing_heads:
            raise ValueError(f"GeCo needs the camera and depth heads, but the config disables {missing_heads}")
        config = cls(**{key: raw[key] for key in ("img_size", "patch_size", "embed_dim") if key in raw})
        config.validate()
        return config

    def validate(self) -> None:
        """Raise ``ValueError`` naming the first field that no model can be built from (a
        ``config.json`` holding ``patch_size: "abc"`` or ``0`` would otherwise end in a
        traceback from inside the model)."""
        agg, dino, camera, head = self.aggregator, self.dino, self.camera_head, self.depth_head
        counts = {"patch_size": self.patch_size, "img_size": self.img_size, "embed_dim": self.embed_dim,
                  "dino.depth": dino.depth, "dino.num_heads": dino.num_heads, "aggregator.depth": agg.depth,
                  "aggregator.num_heads": agg.num_heads, "camera_head.trunk_depth": camera.trunk_depth,
                  "camera_head.num_heads": camera.num_heads, "camera_head.num_iterations": camera.num_iterations,
                  "depth_head.features": head.features}
        for name, value in counts.items():
            _check(is_integer(value) and value >= 1, name, value, "must be an integer >= 1")
        _check(is_integer(self.num_register_tokens) and self.num_register_tokens >= 0, "num_register_tokens",
               self.num_register_tokens, "must be an integer >= 0")
        for name, value in {"dino.mlp_ratio": dino.mlp_ratio, "aggregator.mlp_ratio": agg.mlp_ratio,
                            "camera_head.mlp_ratio": camera.mlp_ratio, "aggregator.rope_freq": agg.rope_freq}.items():
            _check(is_number(value) and math.isfinite(value) and value > 0, name, value, "must be a finite number > 0")
        _check(isinstance(agg.qk_norm, bool), "aggregator.qk_norm", agg.qk_norm, "must be true or false")
        _check(self.img_size % self.patch_size == 0, "img_size", self.img_size,
               f"must be a multiple of patch_size {self.patch_size}")
        for name, heads, width in (("dino.num_heads", dino.num_heads, self.embed_dim),
                                   ("aggregator.num_heads", agg.num_heads, self.embed_dim),
                                   ("camera_head.num_heads", camera.num_heads, 2 * self.embed_dim)):
            _check(width % heads == 0, name, heads, f"must divide the width {width}")
        _check((self.embed_dim // agg.num_heads) % 4 == 0, "aggregator.num_heads", agg.num_heads,
               "must leave a head width divisible by 4 (2D RoPE)")
        _check(head.features % 8 == 0, "depth_head.features", head.features,
               "must be a multiple of 8 (its half takes a position embedding)")
        for name, values in (("depth_head.out_channels", head.out_channels),
                             ("depth_head.intermediate_layer_idx", head.intermediate_layer_idx)):
            _check(isinstance(values, (list, tuple)) and len(values) == 4 and all(map(is_integer, values)), name,
                   values, "must be 4 integers")
        _check(all(c >= 4 and c % 4 == 0 for c in head.out_channels), "depth_head.out_channels", head.out_channels,
               "must be multiples of 4 (each takes a position embedding)")
        _check(all(0 <= i < agg.depth for i in head.intermediate_layer_idx), "depth_head.intermediate_layer_idx",
               head.intermediate_layer_idx, f"must index the aggregator's {agg.depth} layers (0 to {agg.depth - 1})")

    def to_dict(self) -> dict[str, Any]:
        """The section-5.1 dict (lists for sequences), inverse of :meth:`from_dict`."""
        d = asdict(self)
        for k in ("out_channels", "intermediate_layer_idx"):
            d["depth_head"][k] = list(d["depth_head"][k])
        return d

    @classmethod
    def tiny(cls) -> "VGGTConfig":
        """The public fixture's sizes: 1.1 M parameters, 70-pixel-wide network input."""
        return cls(
            img_size=70,
            embed_dim=64,
            num_register_tokens=4,
            dino=DinoConfig(depth=2, num_heads=4),
            aggregator=AggregatorConfig(depth=5, num_heads=4),
            camera_head=CameraHeadConfig(trunk_depth=1, num_heads=4),
            depth_head=DepthHeadConfig(features=32, out_channels=(16, 24, 32, 48),
                                       intermediate_layer_idx=(0, 2, 3, 4)),
        )


def _check(ok: bool, name: str, value: Any, requirement: str) -> None:
    if not ok:
        raise ValueError(f"VGGT config field {name} = {value!r}: {requirement}")
