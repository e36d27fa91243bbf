"""VGGT depth + camera estimator, checkpoint-compatible with ``facebook/VGGT-1B``.

Clean re-implementation of the aggregator, camera head and depth head from
``shared/specs/estimators.md`` (sections 1-3, 5.1, 6); the point and track heads are not built.

Two entry points:

* :meth:`VGGT.forward_raw` — network-size images ``[B, S, 3, H, W]`` in ``[0, 1]`` (H, W multiples
  of the patch size) to the reference outputs (depth, confidence, pose encoding, K, extrinsics).
* :meth:`VGGT.estimate_geometry` — the :class:`~geco_guide.types.GeometryEstimator`
  protocol: frames of any size, differentiable resize/crop to the network size, outputs mapped
  back to the input size in the project's integer-pixel-centre convention.

Precision knobs: ``autocast_dtype`` (e.g. ``torch.bfloat16``) runs the aggregator under autocast;
``trunk_to(dtype)`` (and ``from_pretrained(dtype=...)``) stores the aggregator in that dtype. The
camera and depth heads always run in float32, as upstream does. ``gradient_checkpointing``
recomputes the trunk's block activations in backward.

The configuration dataclasses live in :mod:`geco_guide.estimators.vggt_config`, the pose
decode in :mod:`geco_guide.geometry`, the lifecycle (construction, loading, ``trunk_to``,
checkpointing, freezing) in :class:`~geco_guide.estimators.base.FrozenEstimator`; their names
are importable from here too.
"""

from __future__ import annotations

import contextlib
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

import torch
import torch.nn.functional as F
from torch import Tensor, nn

from ..geometry import (
    crop_intrinsics,
    pose_encoding_to_cameras,
    quaternion_to_matrix,
    resize_intrinsics,
)
from ..types import SceneGeometry, check_frames
from .base import FrozenEstimator
from .dpt import FusionBlock, add_position_embedding, resample_layer
from .vggt_config import (
    AggregatorConfig,
    CameraHeadConfig,
    DepthHeadConfig,
    DinoConfig,
    VGGTConfig,
)
from .vit import (
    Block,
    DinoV2,
    Mlp,
    RotaryEmbedding2D,
    grid_positions,
    imagenet_normalise,
    init_weights_,
    run_block,
)

__all__ = [
    "VGGT",
    "VGGTConfig",
    "AggregatorConfig",
    "CameraHeadConfig",
    "DepthHeadConfig",
    "DinoConfig",
    "PreprocessPlan",
    "plan_preprocess",
    "pose_encoding_to_cameras",
    "quaternion_to_matrix",
    "unmap_intrinsics",
]

# Checkpoint parts we never build (spec 3.6 / 6); the DINO mask token is unused at inference.
IGNORED_CHECKPOINT_PREFIXES = ("point_head.", "track_head.", "aggregator.patch_embed.mask_token")
CHECKPOINT_FILES = ("model.safetensors", "model.pt")
POSE_ENCODING_DIM = 9


# --------------------------------------------------------------------------------------------
# Preprocessing geometry (spec 3.1); the pose encoding (spec 1.3) is decoded by
# geometry.pose_encoding_to_cameras


@dataclass(frozen=True)
class PreprocessPlan:
    """How an ``input_hw`` frame becomes the network input (resize, then centre row crop).

    ``resized_hw = (new_h, width)``; rows ``[crop_top, crop_top + network_hw[0])`` are kept.
    """

    input_hw: tuple[int, int]
    resized_hw: tuple[int, int]
    crop_top: int
    network_hw: tuple[int, int]


def plan_preprocess(height: int, width: int, target_width: int = 518, patch_size: int = 14) -> PreprocessPlan:
    """Reference "crop" geometry: width -> ``target_width``, height rounded to the patch grid.

    ``new_h = round(H * target_width / W / patch) * patch`` with Python's round-half-to-even
    (41x74 -> 20.5 -> 20 -> 280), at least one patch; rows are centre-cropped to
    ``target_width`` when taller.
    """
    new_h = max(patch_size, round(height * target_width / width / patch_size) * patch_size)
    crop_top = (new_h - target_width) // 2 if new_h > target_width else 0
    return PreprocessPlan(
        input_hw=(height, width),
        resized_hw=(new_h, target_width),
        crop_top=crop_top,
        network_hw=(min(new_h, target_width), target_width),
    )


# --------------------------------------------------------------------------------------------
# Network


class Aggregator(nn.Module):
    """DINOv2 patch embedding + alternating frame / global attention (spec 3.2).

    ``forward(images [B, S, 3, H, W] in [0, 1])`` returns ``{i: [B, S, T, 2C]}`` for the block
    indices in ``keep_layers`` only (``T = 1 + R + P``; patches start at ``patch_start_idx``).
    ``gradient_checkpointing`` here covers the frame/global blocks; the DINO embedder has its own
    flag (:attr:`VGGT.gradient_checkpointing` sets both).
    """

    def __init__(self, config: VGGTConfig, keep_layers: tuple[int, ...]) -> None:
        """``keep_layers``: block indices whose outputs the heads read (the rest are not kept)."""
        super().__init__()
        c, r, agg = config.embed_dim, config.num_register_tokens, config.aggregator
        self.patch_size = config.patch_size
        self.patch_start_idx = 1 + r
        self.keep_layers = frozenset(keep_layers)
        self.gradient_checkpointing = False
        self.patch_embed = DinoV2(
            c, config.dino.depth, config.dino.num_heads, config.dino.mlp_ratio,
            img_size=config.img_size, patch_size=config.patch_size, num_register_tokens=r,
            pos_embed_variant="registers",
        )
        self.camera_token = nn.Parameter(torch.zeros(1, 2, 1, c))
        self.register_token = nn.Parameter(torch.zeros(1, 2, r, c))

        def make_block() -> Block:
            return Block(c, agg.num_heads, agg.mlp_ratio, qk_norm=agg.qk_norm, norm_eps=1e-5)

        self.frame_blocks = nn.ModuleList(make_block() for _ in range(agg.depth))
        self.global_blocks = nn.ModuleList(make_block() for _ in range(agg.depth))
        self.rope = RotaryEmbedding2D(c // agg.num_heads, base=agg.rope_freq)

    def forward(self, images: Tensor) -> dict[int, Tensor]:
        """images ``[B, S, 3, H, W]`` in ``[0, 1]`` -> ``{i: [B, S, T, 2C]}`` (see class doc)."""
        b, s, _, h_img, w_img = images.shape
        patches = self.patch_embed(imagenet_normalise(images.reshape(b * s, 3, h_img, w_img)))  # [BS, P, C]
        special = torch.cat(
            [_per_frame_tokens(self.camera_token, b, s), _per_frame_tokens(self.register_token, b, s)], dim=2
        )  # [B, S, 1+R, C]
        x = torch.cat([special.reshape(b * s, -1, patches.shape[-1]).to(patches.dtype), patches], dim=1)
        t, c = x.shape[1:]
        gh, gw = h_img // self.patch_size, w_img // self.patch_size
        positions = _token_positions(gh, gw, self.patch_start_idx, x.device)  # [1, T, 2], 1-based patches
        frame_rope = self.rope.bind(positions, max(gh, gw))
        global_rope = self.rope.bind(positions.repeat(1, s, 1), max(gh, gw))  # no per-frame offset
        outputs: dict[int, Tensor] = {}
        for i, (frame_block, global_block) in enumerate(zip(self.frame_blocks, self.global_blocks)):
            x = run_block(frame_block, x.reshape(b * s, t, c), frame_rope, self.gradient_checkpointing)
            frame_out = x.reshape(b, s, t, c)
            x = run_block(global_block, x.reshape(b, s * t, c), global_rope, self.gradient_checkpointing)
            if i in self.keep_layers:
                outputs[i] = torch.cat([frame_out, x.reshape(b, s, t, c)], dim=-1)
        return outputs


def _per_frame_tokens(token: Tensor, b: int, s: int) -> Tensor:
    """``[1, 2, n, C]`` -> ``[B, S, n, C]``: index 0 for the first frame, index 1 for the rest."""
    first = token[:, :1].expand(b, 1, -1, -1)
    rest = token[:, 1:].expand(b, s - 1, -1, -1)
    return torch.cat([first, rest], dim=1)


def _token_positions(gh: int, gw: int, num_special: int, device: torch.device) -> Tensor:
    """RoPE positions ``[1, num_special + gh*gw, 2]`` (y, x): 0 for special tokens, 1-based patches."""
    patch = grid_positions(gh, gw, device, start=1)
    special = torch.zeros(num_special, 2, dtype=patch.dtype, device=device)
    return torch.cat([special, patch], dim=0).unsqueeze(0)


class CameraHead(nn.Module):
    """Iterative camera refinement from the camera tokens (spec 3.3).

    ``forward(tokens [B, S, D])`` (camera tokens of the last aggregator output, ``D = 2C``)
    returns the activated pose encoding ``[B, S, 9]`` of every iteration (the last one is the
    prediction).
    """

    def __init__(self, dim: int, cfg: CameraHeadConfig) -> None:
        super().__init__()
        self.num_iterations = cfg.num_iterations
        self.token_norm = nn.LayerNorm(dim, eps=1e-5)
        self.trunk = nn.ModuleList(
            Block(dim, cfg.num_heads, cfg.mlp_ratio, norm_eps=1e-5) for _ in range(cfg.trunk_depth)
        )
        self.trunk_norm = nn.LayerNorm(dim, eps=1e-5)
        self.empty_pose_tokens = nn.Parameter(torch.zeros(1, 1, POSE_ENCODING_DIM))
        self.embed_pose = nn.Linear(POSE_ENCODING_DIM, dim)
        self.poseLN_modulation = nn.Sequential(nn.SiLU(), nn.Linear(dim, 3 * dim))
        self.adaln_norm = nn.LayerNorm(dim, eps=1e-6, elementwise_affine=False)
        self.pose_branch = Mlp(dim, dim // 2, out_dim=POSE_ENCODING_DIM)

    def forward(self, tokens: Tensor) -> list[Tensor]:
        """tokens ``[B, S, 2C]`` -> ``num_iterations`` pose encodings ``[B, S, 9]``."""
        c = self.token_norm(tokens)
        normed_c = self.adaln_norm(c)
        raw: Tensor | None = None
        emitted = []
        for _ in range(self.num_iterations):
            if raw is None:
                e = self.embed_pose(self.empty_pose_tokens.expand(*tokens.shape[:2], -1))
            else:
                # The reference feeds back a detached estimate: no backprop through the loop.
                raw = raw.detach()
                e = self.embed_pose(raw)
            shift, scale, gate = self.poseLN_modulation(e).chunk(3, dim=-1)
            z = gate * (normed_c * (1 + scale) + shift) + c
            for block in self.trunk:
                z = block(z)
            delta = self.pose_branch(self.trunk_norm(z))
            raw = delta if raw is None else raw + delta
            emitted.append(_activate_pose(raw))
        return emitted


def _activate_pose(raw: Tensor) -> Tensor:
    """``[..., 9]``: translation and quaternion linear, both FoVs ReLU."""
    return torch.cat([raw[..., :7], F.relu(raw[..., 7:])], dim=-1)


class DepthHead(nn.Module):
    """DPT depth head (spec 3.4), VGGT flavour of the fusion blocks.

    ``forward(tokens {layer: [B, S, T, 2C]}, patch_start_idx, image_hw)`` returns
    ``depth [B, S, H, W, 1] = exp(.)`` and ``confidence [B, S, H, W] = 1 + exp(.)``.
    """

    def __init__(self, dim_in: int, patch_size: int, cfg: DepthHeadConfig) -> None:
        super().__init__()
        feats, oc = cfg.features, cfg.out_channels
        self.patch_size = patch_size
        self.layer_idx = tuple(cfg.intermediate_layer_idx)
        self.norm = nn.LayerNorm(dim_in, eps=1e-5)
        self.projects = nn.ModuleList(nn.Conv2d(dim_in, ch, kernel_size=1) for ch in oc)
        self.resize_layers = nn.ModuleList(resample_layer(ch, level) for level, ch in enumerate(oc))
        self.scratch = nn.Module()
        for k, ch in enumerate(oc, start=1):
            setattr(self.scratch, f"layer{k}_rn", nn.Conv2d(ch, feats, kernel_size=3, padding=1, bias=False))
            setattr(self.scratch, f"refinenet{k}", FusionBlock(feats, has_skip=k != 4, rectify_skip=True))
        self.scratch.output_conv1 = nn.Conv2d(feats, feats // 2, kernel_size=3, padding=1)
        self.scratch.output_conv2 = nn.Sequential(
            nn.Conv2d(feats // 2, 32, kernel_size=3, padding=1), nn.ReLU(), nn.Conv2d(32, 2, kernel_size=1)
        )

    def forward(self, tokens: Mapping[int, Tensor], patch_start_idx: int,
                image_hw: tuple[int, int]) -> tuple[Tensor, Tensor]:
        """tokens ``{layer: [B, S, T, 2C]}`` -> depth ``[B, S, H, W, 1]``, confidence ``[B, S, H, W]``."""
        b, s = tokens[self.layer_idx[0]].shape[:2]
        gh, gw = image_hw[0] // self.patch_size, image_hw[1] // self.patch_size
        sc = self.scratch
        levels = []
        for k, layer in enumerate(self.layer_idx):
            x = self.norm(tokens[layer][:, :, patch_start_idx:])  # [B, S, P, 2C]
            x = x.reshape(b * s, gh, gw, -1).permute(0, 3, 1, 2)  # [BS, 2C, gh, gw]
            x = add_position_embedding(self.projects[k](x), image_hw)
            x = self.resize_layers[k](x)
            levels.append(getattr(sc, f"layer{k + 1}_rn")(x))
        r1, r2, r3, r4 = levels
        y = sc.refinenet4(r4, size=r3.shape[-2:])
        y = sc.refinenet3(y, r3, size=r2.shape[-2:])
        y = sc.refinenet2(y, r2, size=r1.shape[-2:])
        y = sc.refinenet1(y, r1)
        y = F.interpolate(sc.output_conv1(y), size=image_hw, mode="bilinear", align_corners=True)
        y = sc.output_conv2(add_position_embedding(y, image_hw))  # [BS, 2, H, W]
        y = y.reshape(b, s, 2, *image_hw)
        return y[:, :, 0].exp().unsqueeze(-1), 1 + y[:, :, 1].exp()


class VGGT(FrozenEstimator):
    """VGGT aggregator + camera head + depth head; frozen, eval mode.

    ``VGGT(config)`` draws a random initialisation from the global torch RNG (use
    :meth:`random` for a seeded one) that gives sane outputs: depth ~1, confidence ~2, near
    identity rotations and a field of view of ~1 rad. The trunk (:meth:`trunk_to`,
    :attr:`gradient_checkpointing`) is the aggregator, DINO embedder included.

    The checkpoint carries no architecture, so :meth:`from_pretrained`'s ``config`` defaults to
    VGGT-1B; ``point_head.*``, ``track_head.*`` and the DINO ``mask_token`` are ignored when
    loading, any other missing, unexpected or mis-shaped key raises ``CheckpointMismatchError``.
    """

    config_class = VGGTConfig
    model_name = "VGGT"
    default_repo_id = "facebook/VGGT-1B"
    checkpoint_files = CHECKPOINT_FILES
    ignored_checkpoint_prefixes = IGNORED_CHECKPOINT_PREFIXES
    trunk_modules = ("aggregator",)
    checkpointed_modules = ("aggregator", "aggregator.patch_embed")

    @classmethod
    def config_from_json(cls, raw: Mapping[str, Any]) -> VGGTConfig:
        """A ``config.json`` in ours (:meth:`save_pretrained`'s) or the upstream schema
        (:meth:`VGGTConfig.from_json`)."""
        return VGGTConfig.from_json(raw)

    def __init__(self, config: VGGTConfig | Mapping[str, Any] | None = None, *,
                 gradient_checkpointing: bool = False, autocast_dtype: torch.dtype | None = None) -> None:
        """``config``: a :class:`VGGTConfig` or section-5.1 dict; None = VGGT-1B."""
        super().__init__()
        self.config = config = self.resolve_config(config)
        config.validate()
        depth = config.aggregator.depth
        layer_idx = tuple(config.depth_head.intermediate_layer_idx)
        self.aggregator = Aggregator(config, keep_layers=(*layer_idx, depth - 1))
        self.camera_head = CameraHead(2 * config.embed_dim, config.camera_head)
        self.depth_head = DepthHead(2 * config.embed_dim, config.patch_size, config.depth_head)
        self._finish_init(gradient_checkpointing=gradient_checkpointing, autocast_dtype=autocast_dtype)

    # ---- construction -----------------------------------------------------------------------

    @torch.no_grad()
    def reset_parameters(self, generator: torch.Generator | None = None) -> None:
        """Random weights that keep a random model's outputs in a sane range (see class doc)."""
        init_weights_(self, generator, exclude={"camera_head.empty_pose_tokens"})
        nn.init.zeros_(self.camera_head.empty_pose_tokens)
        # Small last layers: the accumulated pose starts at identity rotation, zero translation
        # and FoV ~1 rad; depth / confidence logits start near 0.
        fc2 = self.camera_head.pose_branch.fc2
        nn.init.normal_(fc2.weight, std=1e-3, generator=generator)
        fc2.bias.zero_()
        fc2.bias[6:9] = 1.0 / self.config.camera_head.num_iterations
        nn.init.normal_(self.depth_head.scratch.output_conv2[2].weight, std=0.02, generator=generator)

    # ---- inference ----------------------------------------------------------------------------

    def forward_raw(self, images: Tensor) -> dict[str, Tensor]:
        """Reference outputs for network-size images.

        Args:
            images: ``[B, S, 3, H, W]`` (or ``[S, 3, H, W]``, taken as B = 1) in ``[0, 1]``,
                H and W multiples of the patch size.
        Returns:
            ``depth [B, S, H, W, 1]``, ``depth_conf [B, S, H, W]``, ``pose_enc [B, S, 9]``,
            ``extrinsic [B, S, 3, 4]`` (camera-from-world), ``intrinsic [B, S, 3, 3]`` (pixels of
            the ``H x W`` input, principal point ``(W/2, H/2)``); all float32.
        """
        if images.ndim == 4:
            images = images.unsqueeze(0)
        if images.ndim != 5 or images.shape[2] != 3:
            raise ValueError(f"images must be [B, S, 3, H, W], got {list(images.shape)}")
        image_hw = tuple(images.shape[-2:])
        patch = self.config.patch_size
        if image_hw[0] % patch or image_hw[1] % patch:
            raise ValueError(f"image size {image_hw} is not a multiple of the patch size {patch}")
        tokens = self._aggregate(images)
        with torch.autocast(images.device.type, enabled=False):
            pose_enc = self.camera_head(tokens[self.config.aggregator.depth - 1][:, :, 0])[-1]
            depth, depth_conf = self.depth_head(tokens, self.aggregator.patch_start_idx, image_hw)
            extrinsic, intrinsic = pose_encoding_to_cameras(pose_enc, image_hw)
        return {"depth": depth, "depth_conf": depth_conf, "pose_enc": pose_enc,
                "extrinsic": extrinsic, "intrinsic": intrinsic}

    def _aggregate(self, images: Tensor) -> dict[int, Tensor]:
        """Aggregator in its storage dtype / under ``autocast_dtype``; outputs float32."""
        trunk_dtype = self.aggregator.camera_token.dtype
        if self.autocast_dtype is None:
            ctx: contextlib.AbstractContextManager = contextlib.nullcontext()
        else:
            ctx = torch.autocast(images.device.type, dtype=self.autocast_dtype)
        with ctx:
            tokens = self.aggregator(images.to(trunk_dtype))
        return {k: v.float() for k, v in tokens.items()}

    def estimate_geometry(self, frames: Tensor) -> SceneGeometry:
        """Depth, K, extrinsics and confidence for frames of any size (differentiable).

        Frames ``[B, S, 3, H, W]`` in ``[0, 1]`` are resized (bilinear, ``align_corners=False``,
        no antialias) to ``(new_h, img_size)`` and centre-cropped in rows to at most
        ``img_size`` (:func:`plan_preprocess`). Outputs at ``[B, S, H, W]``: depth and
        confidence are mapped back by padding the cropped rows (depth edge-replicated,
        confidence **0**, below VGGT's minimum of 1, so those rows never pass a confidence
        threshold) and bilinearly resizing. K is converted to integer pixel centres
        (``c - 0.5``), un-cropped and resized to ``H x W``; extrinsics are unchanged.
        """
        check_frames(frames)
        b, s, _, height, width = frames.shape
        plan = plan_preprocess(height, width, self.config.img_size, self.config.patch_size)
        images = preprocess_frames(frames, plan)
        out = self.forward_raw(images)
        depth = unmap_rows(out["depth"][..., 0], plan, fill=None)
        confidence = unmap_rows(out["depth_conf"], plan, fill=0.0)
        return SceneGeometry(
            depth=depth,
            intrinsics=unmap_intrinsics(out["intrinsic"], plan),
            extrinsics=out["extrinsic"],
            confidence=confidence,
        )


# --------------------------------------------------------------------------------------------
# Guidance-path pre- and post-processing (differentiable)


def preprocess_frames(frames: Tensor, plan: PreprocessPlan) -> Tensor:
    """``[B, S, 3, H, W] -> [B, S, 3, Hm, Wm]``: bilinear resize (no antialias), row crop."""
    b, s = frames.shape[:2]
    x = frames.reshape(b * s, *frames.shape[2:])
    if tuple(x.shape[-2:]) != plan.resized_hw:
        x = F.interpolate(x, size=plan.resized_hw, mode="bilinear", align_corners=False, antialias=False)
    x = x[:, :, plan.crop_top : plan.crop_top + plan.network_hw[0]]
    return x.reshape(b, s, 3, *plan.network_hw)


def unmap_rows(values: Tensor, plan: PreprocessPlan, fill: float | None) -> Tensor:
    """``[B, S, Hm, Wm] -> [B, S, H, W]``: re-insert cropped rows, bilinearly resize back.

    Cropped rows are filled with ``fill`` (``None`` = replicate the nearest predicted row).
    Resizing with ``align_corners=False`` inverts the input resize's pixel mapping exactly.
    """
    bottom = plan.resized_hw[0] - plan.crop_top - plan.network_hw[0]
    if plan.crop_top or bottom:
        pad = (0, 0, plan.crop_top, bottom)
        values = F.pad(values, pad, mode="replicate") if fill is None else F.pad(values, pad, value=fill)
    if tuple(values.shape[-2:]) != plan.input_hw:
        values = F.interpolate(values, size=plan.input_hw, mode="bilinear", align_corners=False)
    return values


def unmap_intrinsics(intrinsics: Tensor, plan: PreprocessPlan) -> Tensor:
    """Network K ``[..., 3, 3]`` (principal point ``(W/2, H/2)``) -> K of the input frames.

    Moves the principal point to the integer-centre convention (``-0.5``), undoes the row crop
    and the resize through the shared intrinsics helpers.
    """
    shift = intrinsics.new_tensor([[0.0, 0.0, -0.5], [0.0, 0.0, -0.5], [0.0, 0.0, 0.0]])
    k = intrinsics + shift
    k = crop_intrinsics(k, top=-plan.crop_top, left=0)
    return resize_intrinsics(k, plan.resized_hw, plan.input_hw)
