"""VGGT configuration: the architecture dataclasses of ``shared/specs/estimators.md`` section 5.1
(defaults are VGGT-1B) and their dict form.

The model lives in :mod:`geco_guide.estimators.vggt`, which re-exports :class:`VGGTConfig`.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import asdict, dataclass, field
from typing import Any

from ..types import merge_dataclass

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
        """Build from the section-5.1 dict (nested sub-dicts; missing keys keep defaults)."""
        return merge_dataclass(cls(), d)

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
        return cls(**{key: raw[key] for key in ("img_size", "patch_size", "embed_dim") if key in raw})

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
