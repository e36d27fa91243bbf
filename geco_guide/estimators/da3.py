"""Depth Anything 3 any-view geometry estimator, checkpoint-compatible with
``depth-anything/DA3-SMALL`` and ``depth-anything/DA3-BASE`` (Apache-2.0 weights).

A clean re-implementation of the published any-view network: a DINOv2 trunk whose later blocks
alternate per-view and all-view attention (a learned camera token replaces the class token where
they start), a dual DPT head (depth + confidence, and a ray map + confidence) and a camera
decoder (translation, quaternion and fields of view of a camera-to-world pose). The module tree
follows the checkpoints' key names (``model.backbone.pretrained.*``, ``model.head.*``,
``model.cam_dec.*``); the pose-conditioning encoder (``model.cam_enc.*``) and the ray head's
unused coarser output levels are not built.

Two entry points, as :class:`~geco_guide.estimators.vggt.VGGT`:

* :meth:`DA3.forward_raw` — network-size images ``[B, S, 3, H, W]`` in ``[0, 1]`` to the
  reference outputs (depth, confidences, pose encoding, K, camera-from-world extrinsics; the
  ray map on request).
* :meth:`DA3.estimate_geometry` — the :class:`~geco_guide.types.GeometryEstimator` protocol:
  frames of any size, differentiable resize to the network size (longest side
  ``process_res``, each side rounded to the patch grid), outputs mapped back to the input size.
"""

from __future__ import annotations

import contextlib
from collections.abc import Mapping, Sequence
from typing import Any

import torch
import torch.nn.functional as F
from torch import Tensor, nn

from ..geometry import invert_rigid, pose_encoding_to_cameras, resize_intrinsics
from ..types import SceneGeometry, check_frames
from .base import FrozenEstimator
from .da3_config import DA3Config
from .dpt import FusionBlock, add_position_embedding, resample_layer
from .loading import load_state_dict_checked
from .vit import (
    Block,
    PatchEmbed,
    RotaryEmbedding2D,
    grid_positions,
    imagenet_normalise,
    init_weights_,
    resize_pos_embed,
    run_block,
)

__all__ = ["DA3", "DA3Config", "network_size"]

CHECKPOINT_FILES = ("model.safetensors", "model.pt")
#: The ray head builds a prediction at each of 4 pyramid levels; only the finest is output.
RAY_LEVELS = 4
RAY_LEVEL = str(RAY_LEVELS - 1)
RAY_HEAD = "model.head.scratch.output_conv2_aux."
IGNORED_CHECKPOINT_PREFIXES = ("model.cam_enc.",) + tuple(
    f"model.head.scratch.output_conv{k}_aux.{level}." for k in (1, 2) for level in range(RAY_LEVELS - 1)
)
#: Views from which on the reference view is chosen by ``ref_view_strategy`` (fewer keep the first).
MIN_VIEWS_FOR_REF_SELECTION = 3
HEAD_NECK_CHANNELS = 32


def network_size(height: int, width: int, process_res: int, patch_size: int = 14) -> tuple[int, int]:
    """The network input size of an ``height x width`` frame: longest side ``process_res``
    (each side rounded half up), then each side to the nearest multiple of ``patch_size`` (a tie
    rounds up), at least one patch."""
    scale = process_res / max(height, width)

    def to_grid(side: int) -> int:
        resized = max(1, int(round(side * scale)))
        down = resized // patch_size * patch_size
        return max(patch_size, down + patch_size if resized - down >= down + patch_size - resized else down)

    return to_grid(height), to_grid(width)


# --------------------------------------------------------------------------------------------
# Trunk


class AnyViewTransformer(nn.Module):
    """DINOv2 trunk of DA3 (``model.backbone.pretrained``).

    ``forward(images [B, S, 3, H, W] in [0, 1])`` returns the patch features of ``out_layers``
    (each ``[B, S, P, 2C]``: the last per-view block's tokens, then the block's own tokens
    through the final norm) and the camera tokens of the last one (``[B, S, 2C]``, no norm).
    """

    def __init__(self, config: DA3Config) -> None:
        super().__init__()
        c, grid = config.embed_dim, config.img_size // config.patch_size
        self.config = config
        self.gradient_checkpointing = False
        self.patch_embed = PatchEmbed(config.patch_size, c)
        self.cls_token = nn.Parameter(torch.zeros(1, 1, c))
        self.camera_token = nn.Parameter(torch.zeros(1, 2, c))  # [reference view, other views]
        self.pos_embed = nn.Parameter(torch.zeros(1, 1 + grid * grid, c))
        self.blocks = nn.ModuleList(self._block(i) for i in range(config.depth))
        self.norm = nn.LayerNorm(c, eps=1e-5)
        self.rope = RotaryEmbedding2D(c // config.num_heads, base=config.rope_freq)

    def _block(self, index: int) -> Block:
        cfg = self.config
        block = Block(cfg.embed_dim, cfg.num_heads, cfg.mlp_ratio, qk_norm=index >= cfg.qknorm_start, norm_eps=1e-6)
        if block.attn.q_norm is not None:  # the q/k norms keep LayerNorm's default eps, unlike the block's
            block.attn.q_norm.eps = block.attn.k_norm.eps = 1e-5
        return block

    def is_global(self, index: int) -> bool:
        """Whether block ``index`` attends across all views (else within each view)."""
        return index >= self.config.alt_start and index % 2 == 1

    def forward(self, images: Tensor) -> tuple[list[Tensor], Tensor]:
        """See the class doc."""
        cfg = self.config
        b, s, _, h_img, w_img = images.shape
        gh, gw = h_img // cfg.patch_size, w_img // cfg.patch_size
        x = self.patch_embed(imagenet_normalise(images.reshape(b * s, 3, h_img, w_img)))  # [BS, P, C]
        x = torch.cat([self.cls_token.to(x.dtype).expand(b * s, -1, -1), x], dim=1)
        x = x + resize_pos_embed(self.pos_embed, (gh, gw), "classic", 0.1).to(x.dtype)
        t, c = x.shape[1:]
        x = x.reshape(b, s, t, c)
        local_rope, global_rope = self._ropes(gh, gw, s, x.device)
        ref_view, outputs, local_x = None, [], x
        for i, block in enumerate(self.blocks):
            if i == cfg.alt_start - 1 and s >= MIN_VIEWS_FOR_REF_SELECTION:
                ref_view = select_reference_view(x[:, :, 0], cfg.ref_view_strategy)
                x = reorder_views(x, ref_view)
            if i == cfg.alt_start:
                x = torch.cat([self._camera_tokens(b, s).unsqueeze(2).to(x.dtype), x[:, :, 1:]], dim=2)
            use_rope = i >= cfg.rope_start
            if self.is_global(i):
                rope = global_rope if use_rope else None
                x = run_block(block, x.reshape(b, s * t, c), rope, self.gradient_checkpointing).reshape(b, s, t, c)
            else:
                rope = local_rope if use_rope else None
                x = run_block(block, x.reshape(b * s, t, c), rope, self.gradient_checkpointing).reshape(b, s, t, c)
                local_x = x
            if i in cfg.out_layers:
                out = torch.cat([local_x, x], dim=-1)
                outputs.append(out if ref_view is None else restore_views(out, ref_view))
        features = [torch.cat([out[:, :, 1:, :c], self.norm(out[:, :, 1:, c:])], dim=-1) for out in outputs]
        return features, outputs[-1][:, :, 0]

    def _camera_tokens(self, b: int, s: int) -> Tensor:
        """``[B, S, C]``: the reference-view token for view 0, the other token for the rest."""
        token = self.camera_token
        return torch.cat([token[:, :1].expand(b, 1, -1), token[:, 1:].expand(b, s - 1, -1)], dim=1)

    def _ropes(self, gh: int, gw: int, s: int, device: torch.device) -> tuple[Any, Any]:
        """Per-view RoPE (1-based patch grid, class/camera token at 0) and all-view RoPE (every
        patch at (1, 1), so across views attention sees no position)."""
        patches = grid_positions(gh, gw, device, start=1)
        special = torch.zeros(1, 2, dtype=patches.dtype, device=device)
        local = torch.cat([special, patches]).unsqueeze(0)
        one_view = torch.cat([special, torch.ones_like(patches)])
        return (self.rope.bind(local, max(gh, gw)), self.rope.bind(one_view.repeat(s, 1).unsqueeze(0), 1))


def select_reference_view(tokens: Tensor, strategy: str) -> Tensor:
    """The index ``[B]`` of the reference view, from the class tokens ``[B, S, C]``.

    ``first`` / ``middle`` by position; ``saddle_balanced``: the view closest to the middle of
    the views' ranges of mean cosine similarity to the others, token norm and normalised-token
    variance; ``saddle_sim_range``: the view with the widest range of similarities to the others.
    """
    b, s = tokens.shape[:2]
    if strategy == "first":
        return torch.zeros(b, dtype=torch.long, device=tokens.device)
    if strategy == "middle":
        return torch.full((b,), s // 2, dtype=torch.long, device=tokens.device)
    unit = tokens / tokens.norm(dim=-1, keepdim=True)
    similarity = unit @ unit.transpose(1, 2) - torch.eye(s, device=tokens.device)  # [B, S, S], own similarity out
    if strategy == "saddle_sim_range":
        return (similarity.max(dim=-1).values - similarity.min(dim=-1).values).argmax(dim=1)
    scores = (similarity.sum(dim=-1) / (s - 1), tokens.norm(dim=-1), unit.var(dim=-1))
    balance = sum((_unit_range(score) - 0.5).abs() for score in scores)
    return balance.argmin(dim=1)


def _unit_range(score: Tensor) -> Tensor:
    """``[B, S]`` mapped to ``[0, 1]`` per batch row (min to 0, max to ~1)."""
    low, high = score.min(dim=1, keepdim=True).values, score.max(dim=1, keepdim=True).values
    return (score - low) / (high - low + 1e-8)


def _view_order(ref_view: Tensor, s: int) -> Tensor:
    """``[B, S]`` view order with ``ref_view`` first, the others in their order."""
    positions = torch.arange(s, device=ref_view.device).expand(ref_view.shape[0], -1)
    order = torch.where((positions > 0) & (positions <= ref_view[:, None]), positions - 1, positions)
    order[:, 0] = ref_view
    return order


def reorder_views(x: Tensor, ref_view: Tensor) -> Tensor:
    """``[B, S, ...]`` with each batch's reference view moved first."""
    order = _view_order(ref_view, x.shape[1])
    return x[torch.arange(x.shape[0], device=x.device)[:, None], order]


def restore_views(x: Tensor, ref_view: Tensor) -> Tensor:
    """Inverse of :func:`reorder_views`."""
    inverse = torch.argsort(_view_order(ref_view, x.shape[1]), dim=1)
    return x[torch.arange(x.shape[0], device=x.device)[:, None], inverse]


# --------------------------------------------------------------------------------------------
# Heads


class ChannelsLast(nn.Module):
    """``[N, C, H, W] -> [N, H, W, C]`` (so a LayerNorm can normalise channels)."""

    def forward(self, x: Tensor) -> Tensor:
        return x.permute(0, 2, 3, 1)


class ChannelsFirst(nn.Module):
    """``[N, H, W, C] -> [N, C, H, W]``."""

    def forward(self, x: Tensor) -> Tensor:
        return x.permute(0, 3, 1, 2)


class DualDPTHead(nn.Module):
    """DPT head with two fusion chains on one pyramid (``model.head``): depth + confidence at the
    input resolution, and a ray map (6 channels) + confidence at 8x the patch grid.

    ``forward(features [4 x [B, S, P, D]], image_hw, rays)`` returns ``depth [B, S, H, W]``
    (``exp``), ``depth_conf [B, S, H, W]`` (``1 + exp``) and, with ``rays``, ``ray
    [B, S, 8gh, 8gw, 6]`` and ``ray_conf [B, S, 8gh, 8gw]``.
    """

    def __init__(self, dim_in: int, patch_size: int, features: int, out_channels: Sequence[int]) -> None:
        super().__init__()
        self.patch_size = patch_size
        self.norm = nn.LayerNorm(dim_in, eps=1e-5)
        self.projects = nn.ModuleList(nn.Conv2d(dim_in, ch, kernel_size=1) for ch in out_channels)
        self.resize_layers = nn.ModuleList(resample_layer(ch, level) for level, ch in enumerate(out_channels))
        sc = self.scratch = nn.Module()
        half = features // 2
        for k, ch in enumerate(out_channels, start=1):
            setattr(sc, f"layer{k}_rn", nn.Conv2d(ch, features, kernel_size=3, padding=1, bias=False))
            for chain in ("", "_aux"):
                setattr(sc, f"refinenet{k}{chain}", FusionBlock(features, has_skip=k != 4, rectify_skip=False))
        sc.output_conv1 = nn.Conv2d(features, half, kernel_size=3, padding=1)
        sc.output_conv2 = nn.Sequential(nn.Conv2d(half, HEAD_NECK_CHANNELS, kernel_size=3, padding=1), nn.ReLU(),
                                        nn.Conv2d(HEAD_NECK_CHANNELS, 2, kernel_size=1))
        widths = (features, half, features, half, features, half)
        sc.output_conv1_aux = nn.ModuleDict({RAY_LEVEL: nn.Sequential(
            *(nn.Conv2d(a, b, kernel_size=3, padding=1) for a, b in zip(widths, widths[1:])))})
        sc.output_conv2_aux = nn.ModuleDict({RAY_LEVEL: nn.Sequential(
            nn.Conv2d(half, HEAD_NECK_CHANNELS, kernel_size=3, padding=1), ChannelsLast(),
            nn.LayerNorm(HEAD_NECK_CHANNELS, eps=1e-5), ChannelsFirst(), nn.ReLU(),
            nn.Conv2d(HEAD_NECK_CHANNELS, 7, kernel_size=1))})

    def forward(self, features: Sequence[Tensor], image_hw: tuple[int, int], rays: bool = False) -> dict[str, Tensor]:
        """See the class doc."""
        b, s = features[0].shape[:2]
        gh, gw = image_hw[0] // self.patch_size, image_hw[1] // self.patch_size
        sc = self.scratch
        levels = []
        for k, tokens in enumerate(features):
            x = self.norm(tokens).reshape(b * s, gh, gw, -1).permute(0, 3, 1, 2)  # [BS, D, gh, gw]
            x = self.resize_layers[k](add_position_embedding(self.projects[k](x), image_hw))
            levels.append(getattr(sc, f"layer{k + 1}_rn")(x))
        depth_logits = sc.output_conv1(self._fuse(levels, ""))
        depth_logits = F.interpolate(depth_logits, size=(gh * self.patch_size, gw * self.patch_size),
                                     mode="bilinear", align_corners=True)
        depth_logits = sc.output_conv2(add_position_embedding(depth_logits, image_hw))
        depth_logits = depth_logits.reshape(b, s, 2, *depth_logits.shape[-2:])
        out = {"depth": depth_logits[:, :, 0].exp(), "depth_conf": 1 + depth_logits[:, :, 1].exp()}
        if rays:
            ray = sc.output_conv1_aux[RAY_LEVEL](self._fuse(levels, "_aux"))
            ray = sc.output_conv2_aux[RAY_LEVEL](add_position_embedding(ray, image_hw))
            ray = ray.permute(0, 2, 3, 1).reshape(b, s, *ray.shape[-2:], 7)
            out["ray"], out["ray_conf"] = ray[..., :6], 1 + ray[..., 6].exp()
        return out

    def _fuse(self, levels: Sequence[Tensor], chain: str) -> Tensor:
        """Top-down fusion of the 4 levels through ``refinenet{4..1}{chain}``: ``[BS, F, 8gh, 8gw]``."""
        r1, r2, r3, r4 = levels
        sc = self.scratch
        y = getattr(sc, f"refinenet4{chain}")(r4, size=r3.shape[-2:])
        y = getattr(sc, f"refinenet3{chain}")(y, r3, size=r2.shape[-2:])
        y = getattr(sc, f"refinenet2{chain}")(y, r2, size=r1.shape[-2:])
        return getattr(sc, f"refinenet1{chain}")(y, r1)


class CameraDecoder(nn.Module):
    """Camera token ``[B, S, D]`` -> pose encoding ``[B, S, 9]`` (``model.cam_dec``): translation,
    quaternion (x, y, z, w) of the camera-to-world pose and the fields of view (h, w; ReLU)."""

    def __init__(self, dim: int) -> None:
        super().__init__()
        self.backbone = nn.Sequential(nn.Linear(dim, dim), nn.ReLU(), nn.Linear(dim, dim), nn.ReLU())
        self.fc_t = nn.Linear(dim, 3)
        self.fc_qvec = nn.Linear(dim, 4)
        self.fc_fov = nn.Sequential(nn.Linear(dim, 2), nn.ReLU())

    def forward(self, tokens: Tensor) -> Tensor:
        """``[B, S, D] -> [B, S, 9]``."""
        x = self.backbone(tokens)
        return torch.cat([self.fc_t(x), self.fc_qvec(x), self.fc_fov(x)], dim=-1)


def decode_pose(pose_enc: Tensor, image_hw: tuple[int, int]) -> tuple[Tensor, Tensor]:
    """DA3's pose encoding ``[B, S, 9]`` -> camera-from-world extrinsics ``[B, S, 3, 4]`` (the
    inverse of the encoded camera-to-world pose) and K ``[B, S, 3, 3]`` in pixels of the
    ``image_hw`` network input, principal point ``(W/2, H/2)`` (continuous pixel convention).

    The encoding is VGGT's (:func:`~geco_guide.geometry.pose_encoding_to_cameras`) of the other
    direction; fields of view below ``2e-6`` rad are raised to it, as the reference keeps
    ``tan(fov / 2) >= 1e-6``.
    """
    fov = pose_enc[..., 7:].clamp(min=2e-6)
    camera_to_world, intrinsics = pose_encoding_to_cameras(torch.cat([pose_enc[..., :7], fov], dim=-1), image_hw)
    return invert_rigid(camera_to_world)[..., :3, :], intrinsics


class DA3Network(nn.Module):
    """``model``: trunk (``backbone.pretrained``), dual DPT head and camera decoder."""

    def __init__(self, config: DA3Config) -> None:
        super().__init__()
        self.backbone = nn.Module()
        self.backbone.pretrained = AnyViewTransformer(config)
        self.head = DualDPTHead(2 * config.embed_dim, config.patch_size, config.head_features,
                                config.head_out_channels)
        self.cam_dec = CameraDecoder(2 * config.embed_dim)


# --------------------------------------------------------------------------------------------
# Estimator


class DA3(FrozenEstimator):
    """Depth Anything 3 any-view model; frozen, eval mode.

    ``DA3(config)`` draws a random initialisation from the global torch RNG (:meth:`random` for
    a seeded one) with sane outputs: depth ~1, confidence ~2, near-identity rotations, fields of
    view of ~1 rad. The trunk (:meth:`trunk_to`, :attr:`gradient_checkpointing`) is the DINOv2
    transformer; the heads run in float32.

    :meth:`from_pretrained` reads the architecture from the ``config.json`` beside the weights
    (ours, or the published one); the pose-conditioning encoder and the unused ray levels of a
    checkpoint are ignored, the ray head's LayerNorm (shared by its levels, so stored once) is
    read from whichever level holds it; any other missing, unexpected or mis-shaped key raises
    ``CheckpointMismatchError``.
    """

    config_class = DA3Config
    model_name = "DA3"
    default_repo_id = "depth-anything/DA3-SMALL"
    checkpoint_files = CHECKPOINT_FILES
    ignored_checkpoint_prefixes = IGNORED_CHECKPOINT_PREFIXES
    trunk_modules = ("model.backbone",)
    checkpointed_modules = ("model.backbone.pretrained",)

    @classmethod
    def config_from_json(cls, raw: Mapping[str, Any]) -> DA3Config:
        """A ``config.json`` in ours (:meth:`save_pretrained`'s) or the published schema."""
        return DA3Config.from_json(raw)

    def __init__(self, config: DA3Config | Mapping[str, Any] | None = None, *,
                 gradient_checkpointing: bool = False, autocast_dtype: torch.dtype | None = None) -> None:
        """``config``: a :class:`DA3Config` or its dict; None = DA3-SMALL."""
        super().__init__()
        self.config = config = self.resolve_config(config)
        config.validate()
        self.model = DA3Network(config)
        self._finish_init(gradient_checkpointing=gradient_checkpointing, autocast_dtype=autocast_dtype)

    @torch.no_grad()
    def reset_parameters(self, generator: torch.Generator | None = None) -> None:
        """Random weights that keep a random model's outputs in a sane range (see class doc)."""
        init_weights_(self, generator)
        # The camera decoder keeps its token's scale (ReLU gain) and ends in outputs that vary
        # by a few percent with the input around identity rotation and a field of view of 1 rad.
        cam = self.model.cam_dec
        dim = cam.fc_t.in_features
        for layer in (cam.backbone[0], cam.backbone[2]):
            nn.init.normal_(layer.weight, std=(2.0 / dim) ** 0.5, generator=generator)
        for layer in (cam.fc_t, cam.fc_qvec, cam.fc_fov[0]):
            nn.init.normal_(layer.weight, std=0.3 * dim**-0.5, generator=generator)
        cam.fc_qvec.bias.copy_(torch.tensor([0.0, 0.0, 0.0, 1.0]))
        cam.fc_fov[0].bias.fill_(1.0)
        nn.init.normal_(self.model.head.scratch.output_conv2[2].weight, std=0.02, generator=generator)

    def load_checkpoint(self, state_dict: Mapping[str, Tensor]) -> None:
        """Strict load of a published or saved checkpoint (see the class doc).

        Raises:
            CheckpointMismatchError: every missing, unexpected and mis-shaped key listed.
        """
        state = dict(state_dict)
        for suffix in ("weight", "bias"):
            ours = f"{RAY_HEAD}{RAY_LEVEL}.2.{suffix}"
            stored = sorted(k for k in state if k.startswith(RAY_HEAD) and k.endswith(f".2.{suffix}"))
            if ours not in state and stored:
                state[ours] = state[stored[0]]
        load_state_dict_checked(self, state, model_name=self.model_name, ignore_prefixes=self.ignored_checkpoint_prefixes)

    # ---- inference ----------------------------------------------------------------------------

    def forward_raw(self, images: Tensor, rays: bool = False) -> dict[str, Tensor]:
        """Reference outputs for network-size images.

        Args:
            images: ``[B, S, 3, H, W]`` (or ``[S, 3, H, W]``, taken as B = 1) in ``[0, 1]``,
                H and W multiples of the patch size.
            rays: also run the ray branch of the head (not needed for depth and cameras).
        Returns:
            ``depth [B, S, H, W]``, ``depth_conf [B, S, H, W]``, ``pose_enc [B, S, 9]``,
            ``extrinsic [B, S, 3, 4]`` (camera-from-world), ``intrinsic [B, S, 3, 3]`` (pixels of
            the ``H x W`` input, principal point ``(W/2, H/2)``) and, with ``rays``,
            ``ray [B, S, 8H/p, 8W/p, 6]`` and ``ray_conf [B, S, 8H/p, 8W/p]``; all float32.
        """
        if images.ndim == 4:
            images = images.unsqueeze(0)
        if images.ndim != 5 or images.shape[2] != 3:
            raise ValueError(f"images must be [B, S, 3, H, W], got {list(images.shape)}")
        image_hw = tuple(images.shape[-2:])
        patch = self.config.patch_size
        if image_hw[0] % patch or image_hw[1] % patch:
            raise ValueError(f"image size {image_hw} is not a multiple of the patch size {patch}")
        features, camera_tokens = self._trunk(images)
        with torch.autocast(images.device.type, enabled=False):
            out = self.model.head(features, image_hw, rays=rays)
            out["pose_enc"] = self.model.cam_dec(camera_tokens)
            out["extrinsic"], out["intrinsic"] = decode_pose(out["pose_enc"], image_hw)
        return out

    def _trunk(self, images: Tensor) -> tuple[list[Tensor], Tensor]:
        """The trunk in its storage dtype / under ``autocast_dtype``; outputs float32."""
        trunk_dtype = self.model.backbone.pretrained.cls_token.dtype
        if self.autocast_dtype is None:
            ctx: contextlib.AbstractContextManager = contextlib.nullcontext()
        else:
            ctx = torch.autocast(images.device.type, dtype=self.autocast_dtype)
        with ctx:
            features, camera_tokens = self.model.backbone.pretrained(images.to(trunk_dtype))
        return [f.float() for f in features], camera_tokens.float()

    def estimate_geometry(self, frames: Tensor) -> SceneGeometry:
        """Depth, K, extrinsics and confidence for frames of any size (differentiable).

        Frames ``[B, S, 3, H, W]`` in ``[0, 1]`` are resized to :func:`network_size` (bilinear,
        ``align_corners=False``, antialiased when shrinking, as the reference's area resize);
        depth and confidence are resized back bilinearly; K moves to integer pixel centres
        (``c - 0.5``) and is rescaled to ``H x W``; extrinsics are unchanged. The world frame is
        the reference view's camera (:attr:`DA3Config.ref_view_strategy`).
        """
        check_frames(frames)
        b, s, _, height, width = frames.shape
        net_hw = network_size(height, width, self.config.process_res, self.config.patch_size)
        images = frames.reshape(b * s, 3, height, width)
        if net_hw != (height, width):
            shrink = net_hw[0] < height or net_hw[1] < width
            images = F.interpolate(images, size=net_hw, mode="bilinear", align_corners=False, antialias=shrink)
        out = self.forward_raw(images.reshape(b, s, 3, *net_hw))
        depth, confidence = out["depth"], out["depth_conf"]
        if net_hw != (height, width):
            depth = F.interpolate(depth, size=(height, width), mode="bilinear", align_corners=False)
            confidence = F.interpolate(confidence, size=(height, width), mode="bilinear", align_corners=False)
        shift = out["intrinsic"].new_tensor([[0.0, 0.0, -0.5], [0.0, 0.0, -0.5], [0.0, 0.0, 0.0]])
        intrinsics = resize_intrinsics(out["intrinsic"] + shift, net_hw, (height, width))
        return SceneGeometry(depth=depth, intrinsics=intrinsics, extrinsics=out["extrinsic"], confidence=confidence)
