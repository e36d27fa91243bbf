"""WAFT (Warping-Alone Field Transforms): dense optical flow without a cost volume, our own
implementation, checkpoint-compatible with the published WAFT weights (``princeton-vl/WAFT``,
BSD-3-Clause; its feature network is Depth Anything V2 Small, Apache-2.0).

The network: a frozen Depth Anything V2 network (DINOv2 ViT + DPT head) gives per-pixel
features of each image; a ResNet-18 with a decoder turns them (and the image) into
half-resolution features; then, ``iters`` times, the target features are warped by the current
flow, a ViT with a DPT head reads both (and the recurrent state) and a small head adds a flow
update, convex-upsampled by 2. Module and key names follow the released state dict.

WAFT predicts flow only. Covisibility comes from forward-backward consistency: both directions
run as one batch, and a source pixel counts as covisible (1) where the backward flow at its
forward match cancels the forward flow within ``alpha1 (|f|^2 + |b|^2) + alpha2`` (the test of
Sundaram et al. 2010 and UnFlow) and the match lands in the image, else 0.

Everything runs in float32 by default and keeps gradients with respect to the frames.
``autocast_dtype`` runs the three trunks (feature, context and refinement networks) under
autocast; ``trunk_to(dtype)`` stores them in that dtype; the flow heads stay float32.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from typing import Any

import torch
import torch.nn.functional as F
from torch import Tensor, nn

from ..geometry import inside_image, pixel_grid, sample_bilinear
from ..types import Correspondences
from .base import FrozenEstimator, check_frame_pairs
from .dpt import FusionBlock, resample_layer
from .vit import Block, DinoV2, imagenet_normalise, init_weights_, resize_pos_embed, run_block
from .waft_config import ARCHITECTURE, DEFAULT_REPO_ID, WAFTConfig, WAFTViTConfig

__all__ = ["WAFT", "WAFTConfig", "WAFTViTConfig", "forward_backward_covisibility"]

# The DPT head resizes its output to 14 pixels per token whatever the ViT's patch size.
HEAD_OUTPUT_STRIDE = 14
# Random init (WAFT.reset_parameters): gain of the flow head's last layer. Flows of a tenth
# of a pixel keep the forward-backward test passing at most pixels (sqrt(alpha2) = 0.7 pixel).
FLOW_INIT_GAIN = 0.01


class DPTHead(nn.Module):
    """Depth Anything V2's DPT head up to ``output_conv1``: four token maps ``[N, h*w, C]`` ->
    ``[N, feature_dim / 2, 14 h, 14 w]``. ``output_conv2`` (the depth output) is kept for the
    checkpoint's keys and not run."""

    def __init__(self, in_dim: int, config: WAFTViTConfig) -> None:
        super().__init__()
        features = config.feature_dim
        self.projects = nn.ModuleList(nn.Conv2d(in_dim, c, kernel_size=1) for c in config.out_channels)
        self.resize_layers = nn.ModuleList(resample_layer(c, level) for level, c in enumerate(config.out_channels))
        self.scratch = nn.Module()
        for k, channels in enumerate(config.out_channels, start=1):
            self.scratch.add_module(f"layer{k}_rn", nn.Conv2d(channels, features, 3, padding=1, bias=False))
        for k in range(1, 5):  # refinenet4 has an unused skip branch in the checkpoint too
            self.scratch.add_module(f"refinenet{k}", FusionBlock(features, has_skip=True, rectify_skip=False))
        self.scratch.output_conv1 = nn.Conv2d(features, features // 2, 3, padding=1)
        self.scratch.output_conv2 = nn.Sequential(
            nn.Conv2d(features // 2, 32, 3, padding=1), nn.ReLU(), nn.Conv2d(32, 1, 1), nn.ReLU(), nn.Identity()
        )

    def forward(self, tokens: Sequence[Tensor], grid_hw: tuple[int, int]) -> Tensor:
        """``tokens``: four ``[N, h*w, C]`` maps of a ``grid_hw`` patch grid -> ``[N, F/2, 14h, 14w]``."""
        h, w = grid_hw
        levels = []
        for k, x in enumerate(tokens):
            x = x.transpose(1, 2).reshape(x.shape[0], x.shape[-1], h, w)
            x = self.resize_layers[k](self.projects[k](x))
            levels.append(getattr(self.scratch, f"layer{k + 1}_rn")(x))
        s = self.scratch
        path = s.refinenet4(levels[3], size=levels[2].shape[-2:])
        path = s.refinenet3(path, levels[2], size=levels[1].shape[-2:])
        path = s.refinenet2(path, levels[1], size=levels[0].shape[-2:])
        path = s.refinenet1(path, levels[0])
        out = s.output_conv1(path)
        size = (h * HEAD_OUTPUT_STRIDE, w * HEAD_OUTPUT_STRIDE)
        return F.interpolate(out, size, mode="bilinear", align_corners=True)


class DepthAnything(nn.Module):
    """Depth Anything V2 as a feature network (``pretrained`` DINOv2 + ``depth_head``)."""

    def __init__(self, config: WAFTConfig) -> None:
        super().__init__()
        vit = config.depth_encoder
        self.layers = tuple(vit.layers)
        self.pretrained = DinoV2(vit.embed_dim, vit.depth, vit.num_heads, img_size=config.img_size,
                                 patch_size=config.patch_size, with_mask_token=True)
        self.depth_head = DPTHead(vit.embed_dim, vit)

    def forward(self, images: Tensor) -> Tensor:
        """Normalised images ``[N, 3, H, W]`` (multiples of the patch) -> ``[N, F/2, H, W]``."""
        encoder = self.pretrained
        x = encoder.prepare_tokens(images)
        tokens = []
        for index, block in enumerate(encoder.blocks[: self.layers[-1] + 1]):
            x = run_block(block, x, None, encoder.gradient_checkpointing)
            if index in self.layers:
                tokens.append(encoder.norm(x)[:, 1:])
        grid = (images.shape[-2] // encoder.patch_size, images.shape[-1] // encoder.patch_size)
        return self.depth_head(tokens, grid)


class DepthAnythingFeature(nn.Module):
    """Holds :class:`DepthAnything` under the checkpoint's ``da_feature.depth_anything`` prefix."""

    def __init__(self, config: WAFTConfig) -> None:
        super().__init__()
        self.depth_anything = DepthAnything(config)

    def forward(self, images: Tensor) -> Tensor:
        return self.depth_anything(images)


class PatchProjection(nn.Module):
    """Patch embedding of a ``channels``-channel feature map: ``[N, C, H, W] -> [N, h*w, D]``."""

    def __init__(self, channels: int, patch_size: int, embed_dim: int) -> None:
        super().__init__()
        self.proj = nn.Conv2d(channels, embed_dim, kernel_size=patch_size, stride=patch_size)

    def forward(self, x: Tensor) -> Tensor:
        return self.proj(x).flatten(2).transpose(1, 2)


class RefineViT(nn.Module):
    """The refinement network: a ViT (no cls token, a square position table without a prefix)
    over ``patch_size`` patches of a feature map, then a DPT head; ``[N, C, H, W] ->
    [N, F/2, H, W]``."""

    def __init__(self, config: WAFTConfig) -> None:
        super().__init__()
        vit = config.refine
        self.layers = tuple(vit.layers)
        self.patch_size = config.refine_patch_size
        self.gradient_checkpointing = False
        self.blks = nn.ModuleList(Block(vit.embed_dim, vit.num_heads, layerscale=False) for _ in range(vit.depth))
        self.pos_embed = nn.Parameter(torch.zeros(1, config.refine_pos_grid ** 2, vit.embed_dim))
        self.patch_embed = PatchProjection(config.network_dim, self.patch_size, vit.embed_dim)
        self.dpt_head = DPTHead(vit.embed_dim, vit)

    def forward(self, x: Tensor) -> Tensor:
        height, width = x.shape[-2:]
        grid = (height // self.patch_size, width // self.patch_size)
        tokens = self.patch_embed(x)
        # scale factors n / M without an offset, no antialias: the "classic" resize with offset 0
        pos = resize_pos_embed(self.pos_embed, grid, "classic", interpolate_offset=0.0, num_prefix_tokens=0)
        tokens = tokens + pos.to(tokens.dtype)
        taken = []
        for index, block in enumerate(self.blks):
            tokens = run_block(block, tokens, None, self.gradient_checkpointing)
            if index in self.layers:
                taken.append(tokens)
        out = self.dpt_head(taken, grid)
        return F.interpolate(out, (height, width), mode="bilinear", align_corners=True)


class ResConv(nn.Module):
    """GELU -> conv(k, stride) -> GELU -> conv3x3, plus a 1x1 (strided) skip when the shape changes."""

    def __init__(self, inp: int, out: int, kernel: int = 3, stride: int = 1) -> None:
        super().__init__()
        self.conv = nn.Sequential(nn.GELU(), nn.Conv2d(inp, out, kernel, stride, kernel // 2),
                                  nn.GELU(), nn.Conv2d(out, out, 3, 1, 1))
        self.skip_conv = nn.Conv2d(inp, out, 1, stride) if inp != out or stride != 1 else nn.Identity()

    def forward(self, x: Tensor) -> Tensor:
        return self.conv(x) + self.skip_conv(x)


class BasicBlock(nn.Module):
    """ResNet basic block (timm's names): conv-bn-relu-conv-bn, plus the (downsampled) input, relu."""

    def __init__(self, inp: int, out: int, stride: int) -> None:
        super().__init__()
        self.conv1 = nn.Conv2d(inp, out, 3, stride, 1, bias=False)
        self.bn1 = nn.BatchNorm2d(out)
        self.conv2 = nn.Conv2d(out, out, 3, 1, 1, bias=False)
        self.bn2 = nn.BatchNorm2d(out)
        if stride != 1 or inp != out:
            self.downsample = nn.Sequential(nn.Conv2d(inp, out, 1, stride, bias=False), nn.BatchNorm2d(out))
        else:
            self.downsample = None

    def forward(self, x: Tensor) -> Tensor:
        y = self.bn2(self.conv2(F.relu(self.bn1(self.conv1(x)))))
        return F.relu(y + (x if self.downsample is None else self.downsample(x)))


class ContextNet(nn.Module):
    """ResNet-18 stages with a transposed-conv decoder: ``[N, C_in, H, W]`` -> half-resolution
    features ``[N, context_dim, H/2, W/2]`` (the decoder's finest level)."""

    def __init__(self, inp: int, channels: Sequence[int], out: int) -> None:
        super().__init__()
        c1, c2, c3, c4 = channels
        self.ds1 = ResConv(inp, c1, kernel=7, stride=2)
        for k, (cin, cout) in enumerate(zip((c1, c1, c2, c3), (c1, c2, c3, c4)), start=1):
            stride = 1 if k == 1 else 2
            self.add_module(f"conv{k}", nn.Sequential(BasicBlock(cin, cout, stride), BasicBlock(cout, cout, 1)))
        self.up_4 = nn.ConvTranspose2d(c4, c3, 2, 2)
        self.proj_3 = ResConv(c3, c3)
        self.up_3 = nn.ConvTranspose2d(c3, c2, 2, 2)
        self.proj_2 = ResConv(c2, c2)
        self.up_2 = nn.ConvTranspose2d(c2, c1, 2, 2)
        self.proj_1 = ResConv(c1, out)

    def forward(self, x: Tensor) -> Tensor:
        out_1 = self.conv1(self.ds1(x))
        out_2 = self.conv2(out_1)
        out_3 = self.conv3(out_2)
        out_4 = self.conv4(out_3)
        out_3 = self.proj_3(out_3 + self.up_4(out_4))
        out_2 = self.proj_2(out_2 + self.up_3(out_3))
        return self.proj_1(out_1 + self.up_2(out_2))


def pad_amounts(height: int, width: int, factor: int) -> tuple[int, int, int, int]:
    """``(left, right, top, bottom)`` zero padding that centres an ``H x W`` image in the next
    multiple of ``factor`` at least 8 pixels larger (WAFT's padder)."""
    pad_h = ((height + 8) // factor + 1) * factor - height
    pad_w = ((width + 8) // factor + 1) * factor - width
    return pad_w // 2, pad_w - pad_w // 2, pad_h // 2, pad_h - pad_h // 2


def convex_upsample(flow: Tensor, info: Tensor, weights: Tensor) -> tuple[Tensor, Tensor]:
    """Upsample ``flow [N, 2, h, w]`` (doubled) and ``info [N, C, h, w]`` by 2 as softmax-weighted
    combinations of 3x3 neighbourhoods (``weights [N, 36, h, w]``) -> ``[N, ., 2h, 2w]``."""
    n, c, h, w = info.shape
    mask = torch.softmax(weights.view(n, 1, 9, 2, 2, h, w), dim=2)

    def up(x: Tensor) -> Tensor:
        patches = F.unfold(x, [3, 3], padding=1).view(n, x.shape[1], 9, 1, 1, h, w)
        y = torch.sum(mask * patches, dim=2).permute(0, 1, 4, 2, 5, 3)
        return y.reshape(n, x.shape[1], 2 * h, 2 * w)

    return up(2 * flow), up(info)


def warp_features(features: Tensor, flow: Tensor) -> Tensor:
    """``features [N, C, h, w]`` bilinearly sampled at ``pixel + flow`` (``flow [N, 2, h, w]``,
    zero outside), ``[N, C, h, w]``."""
    n, _, h, w = features.shape
    coords = pixel_grid(h, w, device=flow.device, dtype=flow.dtype).permute(2, 0, 1) + flow
    scale = flow.new_tensor([2.0 / max(w - 1, 1), 2.0 / max(h - 1, 1)]).view(1, 2, 1, 1)
    grid = (coords * scale - 1.0).permute(0, 2, 3, 1)
    return F.grid_sample(features, grid, mode="bilinear", padding_mode="zeros", align_corners=True)


@torch.no_grad()
def forward_backward_covisibility(forward: Tensor, backward: Tensor, alpha1: float, alpha2: float) -> Tensor:
    """Covisibility of the source pixels: 1 where the forward match ``x + f`` lies in the image and
    ``|f + b(x + f)|^2 < alpha1 (|f|^2 + |b(x + f)|^2) + alpha2``, else 0.

    Args:
        forward: ``[N, 2, H, W]`` source -> target flow in pixels.
        backward: ``[N, 2, H, W]`` target -> source flow in pixels.
    Returns:
        ``[N, H, W]`` float in ``{0, 1}``.
    """
    n, _, h, w = forward.shape
    matches = pixel_grid(h, w, device=forward.device, dtype=forward.dtype) + forward.permute(0, 2, 3, 1)
    backward_there = sample_bilinear(backward, matches)  # [N, 2, H, W]
    residual = (forward + backward_there).square().sum(1)
    bound = alpha1 * (forward.square().sum(1) + backward_there.square().sum(1)) + alpha2
    return ((residual < bound) & inside_image(matches, h, w)).to(forward.dtype)


class WAFT(FrozenEstimator):
    """WAFT optical flow with forward-backward covisibility, behind the flow protocol.

    Parameters are frozen and the module is in eval mode; gradients flow to the frames.
    ``WAFT(config)`` draws a random initialisation from the global RNG (:meth:`random` for a
    seeded one) whose flows are a tenth of a pixel or so and depend on both images, so that most
    pixels are covisible (about 0.9), as with the tiny random UFM.
    """

    config_class = WAFTConfig
    model_name = "WAFT"
    default_repo_id = DEFAULT_REPO_ID
    checkpoint_files = ("model.safetensors", "LibreWAFTm-flow.pt", "tar-c-t.pth")
    trunk_modules = ("da_feature", "fnet", "refine_net")
    checkpointed_modules = ("refine_net", "da_feature.depth_anything.pretrained")

    def __init__(self, config: WAFTConfig | Mapping[str, Any] | None = None, *,
                 gradient_checkpointing: bool = False, autocast_dtype: torch.dtype | None = None) -> None:
        """``config``: a :class:`WAFTConfig` or its dict; None = the published architecture."""
        super().__init__()
        self.config = config = self.resolve_config(config)
        config.validate()
        da_dim, dim = config.depth_encoder.feature_dim // 2, config.network_dim
        self.da_feature = DepthAnythingFeature(config)
        self.refine_net = RefineViT(config)
        self.fnet = ContextNet(da_dim + 3, config.context_channels, config.context_dim)
        self.fmap_conv = nn.Conv2d(da_dim + config.context_dim, dim, 1)
        self.hidden_conv = nn.Conv2d(2 * dim, dim, 1)
        self.warp_linear = nn.Conv2d(3 * dim + 2, dim, 1)
        self.refine_transform = nn.Conv2d(config.refine.feature_dim // 2 + dim, dim, 1)
        self.upsample_weight = nn.Sequential(nn.Conv2d(dim, 2 * dim, 3, padding=1), nn.ReLU(),
                                             nn.Conv2d(2 * dim, 4 * 9, 1))
        # flow (2), then the mixture-of-Laplace uncertainty: weights (2) and log-scales (2)
        self.flow_head = nn.Sequential(nn.Conv2d(dim, 2 * dim, 3, padding=1), nn.ReLU(), nn.Conv2d(2 * dim, 6, 1))
        self._finish_init(gradient_checkpointing=gradient_checkpointing, autocast_dtype=autocast_dtype)

    @torch.no_grad()
    def reset_parameters(self, generator: torch.Generator | None = None) -> None:
        """Random weights (:func:`~.vit.init_weights_`, batch norms as identities) with a small
        last flow layer; also resets every buffer, so a meta-built model is complete."""
        init_weights_(self, generator)
        for module in self.modules():
            if isinstance(module, nn.BatchNorm2d):
                module.reset_parameters()
        last = self.flow_head[2]
        nn.init.normal_(last.weight, std=FLOW_INIT_GAIN * last.weight[0].numel() ** -0.5, generator=generator)

    @classmethod
    def config_from_json(cls, raw: Mapping[str, Any]) -> WAFTConfig:
        """A ``config.json`` of :meth:`save_pretrained`'s schema (``architecture: waft``)."""
        if raw.get("architecture") != ARCHITECTURE:
            raise ValueError(f"its architecture is {raw.get('architecture')!r}, not {ARCHITECTURE!r}")
        return WAFTConfig.from_dict(raw)

    # -- network -----------------------------------------------------------------------------

    def _trunk(self, module: nn.Module, x: Tensor) -> Tensor:
        """``module(x)`` in the module's storage dtype (under autocast if configured), returned in
        the dtype of ``x`` (the heads')."""
        dtype = next(module.parameters()).dtype
        if self.autocast_dtype is None:
            return module(x.to(dtype)).to(x.dtype)
        with torch.autocast(x.device.type, dtype=self.autocast_dtype):
            return module(x).to(x.dtype)

    def features(self, images: Tensor) -> Tensor:
        """Normalised padded images ``[N, 3, H, W]`` -> half-resolution features ``[N, D, H/2, W/2]``
        (context features and Depth Anything features, fused by a 1x1 conv)."""
        depth_features = self._trunk(self.da_feature, images)
        context = self._trunk(self.fnet, torch.cat([depth_features, images], dim=1))
        depth_half = F.interpolate(depth_features, scale_factor=0.5, mode="bilinear", align_corners=True)
        return self.fmap_conv(torch.cat([context, depth_half], dim=1))

    def network(self, image1: Tensor, image2: Tensor, iters: int) -> dict[str, Tensor]:
        """Normalised padded images ``[N, 3, H, W]`` -> ``flow [N, 2, H, W]`` (pixels) and ``info
        [N, 4, H, W]`` (the uncertainty channels) of the last of ``iters`` updates."""
        n, _, height, width = image1.shape
        fmap1, fmap2 = self.features(image1), self.features(image2)
        hidden = self.hidden_conv(torch.cat([fmap1, fmap2], dim=1))
        flow = fmap1.new_zeros(n, 2, height // 2, width // 2)
        for _ in range(iters):
            flow = flow.detach()  # each update sees the flow as a constant, as in training
            warped = warp_features(fmap2, flow)
            refined = self._trunk(self.refine_net, self.warp_linear(torch.cat([fmap1, warped, hidden, flow], dim=1)))
            hidden = self.refine_transform(torch.cat([refined, hidden], dim=1))
            update = self.flow_head(hidden)
            flow = flow + update[:, :2]
        up_flow, up_info = convex_upsample(flow, update[:, 2:], 0.25 * self.upsample_weight(hidden))
        return {"flow": up_flow, "info": up_info}

    def forward(self, source: Tensor, target: Tensor, iters: int | None = None) -> dict[str, Tensor]:
        """Frames ``[N, 3, H, W]`` in [0, 1] -> ``flow [N, 2, H, W]`` (pixels, ``target = source +
        flow``) and ``info [N, 4, H, W]``; padding is added and removed here."""
        height, width = source.shape[-2:]
        left, right, top, bottom = pad = pad_amounts(height, width, self.config.pad_factor)
        dtype = self.fmap_conv.weight.dtype  # the heads' dtype: float32 unless the whole model was cast
        image1 = F.pad(imagenet_normalise(source.to(dtype)), pad)
        image2 = F.pad(imagenet_normalise(target.to(dtype)), pad)
        out = self.network(image1, image2, self.config.iters if iters is None else iters)
        return {key: value[..., top: top + height, left: left + width] for key, value in out.items()}

    def estimate_flow(self, source: Tensor, target: Tensor) -> Correspondences:
        """:class:`FlowEstimator` protocol: pairs ``[N, 3, H, W]`` in [0, 1] -> flow ``[N, 2, H, W]``
        in pixels and covisibility ``[N, H, W]`` (forward-backward consistency); both directions
        run as one batch of ``2N`` pairs."""
        check_frame_pairs(source, target)
        flows = self(torch.cat([source, target]), torch.cat([target, source]))["flow"]
        forward, backward = flows.chunk(2)
        covisibility = forward_backward_covisibility(forward, backward.detach(), *self.config.consistency)
        return Correspondences(flow=forward, covisibility=covisibility)
