"""Depth Anything 3 configuration: the architecture of the any-view models (DA3-SMALL, DA3-BASE)
and its two ``config.json`` schemas (ours, and the published checkpoints').

The model lives in :mod:`geco_guide.estimators.da3`, which re-exports :class:`DA3Config`.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import asdict, dataclass, replace
from typing import Any

from ..types import is_integer, is_number, merge_dataclass

__all__ = ["DA3Config", "REF_VIEW_STRATEGIES"]

#: How the reference view (whose camera is the world frame) is chosen among three or more views.
REF_VIEW_STRATEGIES = ("first", "middle", "saddle_balanced", "saddle_sim_range")

#: DINOv2 trunk sizes by the published configs' ``net.name``: (width, depth, heads).
NET_SIZES = {"vits": (384, 12, 6), "vitb": (768, 12, 12), "vitl": (1024, 24, 16)}


@dataclass
class DA3Config:
    """Architecture of a Depth Anything 3 any-view model; defaults are DA3-SMALL.

    The trunk is a DINOv2 ViT (``embed_dim``, ``depth``, ``num_heads``; position table for an
    ``img_size`` square) whose blocks from ``alt_start`` on alternate per-view (even index) and
    all-view (odd index) attention, with q/k-norm from ``qknorm_start`` and 2D RoPE from
    ``rope_start``; ``out_layers`` feed the dual DPT head (``head_features``,
    ``head_out_channels``) and the last one's camera token the camera decoder.
    ``process_res`` is the longest side of the network input :meth:`DA3.estimate_geometry`
    resizes frames to; ``ref_view_strategy`` picks the reference view of three or more.
    """

    patch_size: int = 14
    img_size: int = 518
    embed_dim: int = 384
    depth: int = 12
    num_heads: int = 6
    mlp_ratio: float = 4.0
    out_layers: tuple[int, int, int, int] = (5, 7, 9, 11)
    alt_start: int = 4
    qknorm_start: int = 4
    rope_start: int = 4
    rope_freq: float = 100.0
    head_features: int = 64
    head_out_channels: tuple[int, int, int, int] = (48, 96, 192, 384)
    process_res: int = 504
    ref_view_strategy: str = "saddle_balanced"

    @classmethod
    def small(cls) -> "DA3Config":
        """DA3-SMALL (``depth-anything/DA3-SMALL``)."""
        return cls()

    @classmethod
    def base(cls) -> "DA3Config":
        """DA3-BASE (``depth-anything/DA3-BASE``)."""
        return cls(embed_dim=768, num_heads=12, head_features=128, head_out_channels=(96, 192, 384, 768))

    @classmethod
    def tiny(cls) -> "DA3Config":
        """The parity fixture's sizes: 0.2 M parameters, a 56-pixel position table."""
        return cls(img_size=56, embed_dim=32, depth=6, num_heads=2, out_layers=(2, 3, 4, 5), alt_start=2,
                   qknorm_start=2, rope_start=3, head_features=16, head_out_channels=(8, 16, 24, 32),
                   process_res=70)

    @classmethod
    def from_dict(cls, d: Mapping[str, Any]) -> "DA3Config":
        """Build from :meth:`to_dict`'s dict (missing keys keep defaults), checked (:meth:`validate`)."""
        config = merge_dataclass(cls(), d)
        config.out_layers, config.head_out_channels = tuple(config.out_layers), tuple(config.head_out_channels)
        config.validate()
        return config

    @classmethod
    def from_json(cls, raw: Mapping[str, Any]) -> "DA3Config":
        """The architecture of a ``config.json``: ours (:meth:`to_dict`), or a published
        checkpoint's (``model_name`` and the model's ``config`` with its ``net`` and ``head``)."""
        if "config" not in raw and "model_name" not in raw:
            return cls.from_dict(raw)
        spec = raw.get("config")
        if not isinstance(spec, Mapping):
            named = {"da3-small": cls.small, "da3-base": cls.base}.get(str(raw.get("model_name")).lower())
            if named is None:
                raise ValueError(f"DA3 config.json names model {raw.get('model_name')!r} without its architecture")
            return named()
        return cls._from_published(spec)

    @classmethod
    def _from_published(cls, spec: Mapping[str, Any]) -> "DA3Config":
        net, head = spec.get("net") or {}, spec.get("head") or {}
        if net.get("name") not in NET_SIZES:
            raise ValueError(f"DA3 net {net.get('name')!r} is not supported (one of {sorted(NET_SIZES)})")
        if not net.get("cat_token", True) or head.get("output_dim", 2) != 2:
            raise ValueError("DA3 config: only the any-view models (cat_token, 2 head outputs) are supported")
        width, depth, heads = NET_SIZES[net["name"]]
        config = replace(cls(), embed_dim=width, depth=depth, num_heads=heads)
        for ours, theirs, section in (("out_layers", "out_layers", net), ("alt_start", "alt_start", net),
                                      ("qknorm_start", "qknorm_start", net), ("rope_start", "rope_start", net),
                                      ("head_features", "features", head),
                                      ("head_out_channels", "out_channels", head)):
            if theirs in section:
                value = section[theirs]
                setattr(config, ours, tuple(value) if isinstance(value, list) else value)
        config.validate()
        return config

    def validate(self) -> None:
        """Raise ``ValueError`` naming the first field no model can be built from."""
        counts = {"patch_size": self.patch_size, "img_size": self.img_size, "embed_dim": self.embed_dim,
                  "depth": self.depth, "num_heads": self.num_heads, "alt_start": self.alt_start,
                  "head_features": self.head_features, "process_res": self.process_res}
        for name, value in counts.items():
            _check(is_integer(value) and value >= 1, name, value, "must be an integer >= 1")
        for name, value in {"qknorm_start": self.qknorm_start, "rope_start": self.rope_start}.items():
            _check(is_integer(value) and 0 <= value < self.depth, name, value, f"must index a block (0 to {self.depth - 1})")
        for name, value in {"mlp_ratio": self.mlp_ratio, "rope_freq": self.rope_freq}.items():
            _check(is_number(value) and math.isfinite(value) and value > 0, name, value, "must be a finite number > 0")
        _check(self.img_size % self.patch_size == 0, "img_size", self.img_size,
               f"must be a multiple of patch_size {self.patch_size}")
        _check(self.embed_dim % self.num_heads == 0 and (self.embed_dim // self.num_heads) % 4 == 0, "num_heads",
               self.num_heads, f"must divide the width {self.embed_dim} into heads of a multiple of 4 (2D RoPE)")
        _check(self.alt_start < self.depth, "alt_start", self.alt_start, f"must be below depth {self.depth}")
        for name, values in (("out_layers", self.out_layers), ("head_out_channels", self.head_out_channels)):
            _check(isinstance(values, (list, tuple)) and len(values) == 4 and all(map(is_integer, values)), name,
                   values, "must be 4 integers")
        _check(all(0 <= i < self.depth for i in self.out_layers), "out_layers", self.out_layers,
               f"must index the blocks (0 to {self.depth - 1})")
        _check(all(c >= 4 and c % 4 == 0 for c in self.head_out_channels), "head_out_channels",
               self.head_out_channels, "must be multiples of 4 (each takes a position embedding)")
        _check(self.head_features % 8 == 0, "head_features", self.head_features,
               "must be a multiple of 8 (its half takes a position embedding)")
        _check(self.ref_view_strategy in REF_VIEW_STRATEGIES, "ref_view_strategy", self.ref_view_strategy,
               f"must be one of {', '.join(REF_VIEW_STRATEGIES)}")

    def to_dict(self) -> dict[str, Any]:
        """The dict :meth:`from_dict` reads (lists for sequences)."""
        d = asdict(self)
        d["out_layers"], d["head_out_channels"] = list(self.out_layers), list(self.head_out_channels)
        return d


def _check(ok: bool, name: str, value: Any, requirement: str) -> None:
    if not ok:
        raise ValueError(f"DA3 config field {name} = {value!r}: {requirement}")
