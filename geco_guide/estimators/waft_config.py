"""WAFT configuration: the architecture dataclasses, their validation and the ``config.json``
schema that :meth:`~geco_guide.estimators.waft.WAFT.save_pretrained` writes.

The defaults are the published WAFT checkpoints (a Depth Anything V2 Small feature network, a
ViT-S refinement network with 8-pixel patches, a ResNet-18 context network, 5 iterations). The
model itself lives in :mod:`geco_guide.estimators.waft`.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import asdict, dataclass, field
from typing import Any

from ..types import OptionError, merge_dataclass

__all__ = ["ARCHITECTURE", "DEFAULT_REPO_ID", "WAFTConfig", "WAFTViTConfig"]

#: The ``architecture`` entry of a WAFT ``config.json``.
ARCHITECTURE = "waft"
#: The hub repository of the default WAFT weights (the authors' zero-shot ``tar-c-t`` checkpoint,
#: repackaged on the Hugging Face hub; the authors publish theirs on Google Drive).
DEFAULT_REPO_ID = "LibreYOLO/LibreWAFTm-flow"


@dataclass
class WAFTViTConfig:
    """One ViT with a Depth Anything V2 DPT head: ``layers`` are the blocks whose outputs the
    head reads (0-based), ``feature_dim`` the head's fusion width (its output has half of it),
    ``out_channels`` the head's four projection widths."""

    embed_dim: int = 384
    depth: int = 12
    num_heads: int = 6
    layers: tuple[int, ...] = (2, 5, 8, 11)
    feature_dim: int = 64
    out_channels: tuple[int, ...] = (48, 96, 192, 384)

    def validate(self, key: str) -> None:
        if self.embed_dim % self.num_heads:
            raise OptionError(f"{key}.embed_dim", f"{self.embed_dim} is not divisible by num_heads {self.num_heads}")
        if len(self.layers) != 4 or len(self.out_channels) != 4:
            raise OptionError(f"{key}.layers", "the DPT head reads exactly four blocks and has four out_channels")
        if sorted(set(self.layers)) != list(self.layers) or not 0 <= self.layers[0] <= self.layers[-1] < self.depth:
            raise OptionError(f"{key}.layers", f"must be increasing block indices below depth {self.depth}, "
                                               f"got {list(self.layers)}")
        if self.feature_dim % 2:
            raise OptionError(f"{key}.feature_dim", f"must be even, got {self.feature_dim}")


@dataclass
class WAFTConfig:
    """Architecture of a WAFT model.

    ``depth_encoder`` is the frozen Depth Anything V2 network (patch 14, a ``img_size`` square
    position table); ``refine`` the ViT that updates the flow (patch ``refine_patch_size`` on
    half-resolution features, a ``refine_pos_grid`` square position table); ``context_channels``
    the four ResNet-18 stage widths of the context network and ``context_dim`` its output.
    Images are padded to multiples of ``pad_factor``. ``consistency`` holds the two constants of
    the forward-backward check that gives covisibility: a pixel is covisible where
    ``|f + b|^2 < alpha1 (|f|^2 + |b|^2) + alpha2``.
    """

    depth_encoder: WAFTViTConfig = field(default_factory=WAFTViTConfig)
    refine: WAFTViTConfig = field(default_factory=WAFTViTConfig)
    img_size: int = 518
    patch_size: int = 14
    refine_patch_size: int = 8
    refine_pos_grid: int = 8
    context_channels: tuple[int, ...] = (64, 128, 256, 512)
    context_dim: int = 64
    iters: int = 5
    pad_factor: int = 112
    consistency: tuple[float, float] = (0.01, 0.5)

    @classmethod
    def from_dict(cls, d: Mapping[str, Any]) -> WAFTConfig:
        """Build from :meth:`to_dict`'s schema; absent keys keep the published defaults, unknown
        keys raise ``ValueError`` naming them."""
        raw = dict(d)
        architecture = raw.pop("architecture", ARCHITECTURE)
        if architecture != ARCHITECTURE:
            raise OptionError("architecture", f"is {architecture!r}, not a WAFT config ({ARCHITECTURE!r})")
        config = merge_dataclass(cls(), raw)
        config.validate()
        return config

    @classmethod
    def tiny(cls) -> WAFTConfig:
        """A ~0.8 M-parameter model of the same structure for tests and the CPU demo (with
        :meth:`WAFT.random` weights: flows of a tenth of a pixel or so, most pixels covisible)."""
        small = {"embed_dim": 32, "num_heads": 2, "feature_dim": 16, "out_channels": (8, 16, 24, 32)}
        # a 32-channel state: CPU bfloat16 convolutions with 8-pixel patches go wrong on 16 channels
        return cls.from_dict({"depth_encoder": small, "refine": {**small, "feature_dim": 32},
                              "context_channels": (8, 16, 24, 32), "context_dim": 8, "iters": 3})

    def to_dict(self) -> dict[str, Any]:
        """JSON-serialisable, with ``architecture: waft``; ``from_dict(to_dict())`` round-trips."""
        return {"architecture": ARCHITECTURE, **asdict(self)}

    def validate(self) -> None:
        """Raises :class:`OptionError` naming the first field outside the supported architecture."""
        self.depth_encoder.validate("depth_encoder")
        self.refine.validate("refine")
        if len(self.context_channels) != 4:
            raise OptionError("context_channels", f"needs the four ResNet stage widths, got {self.context_channels}")
        if self.iters < 1:
            raise OptionError("iters", f"must be >= 1, got {self.iters}")
        # padded images must split into DINOv2 patches and into the ResNet's 1/16 grid, whose
        # half-resolution input must split into refinement patches
        for name, unit in (("patch_size", self.patch_size), ("16", 16), ("2 x refine_patch_size",
                                                                          2 * self.refine_patch_size)):
            if self.pad_factor % unit:
                raise OptionError("pad_factor", f"{self.pad_factor} is not a multiple of {name} ({unit})")
        if self.img_size % self.patch_size:
            raise OptionError("img_size", f"{self.img_size} is not a multiple of patch_size {self.patch_size}")
        alpha1, alpha2 = self.consistency
        if alpha1 < 0 or alpha2 <= 0:
            raise OptionError("consistency", f"needs alpha1 >= 0 and alpha2 > 0, got {self.consistency}")

    @property
    def network_dim(self) -> int:
        """Channels of the recurrent state and the warped features (the refinement head's width)."""
        return self.refine.feature_dim
