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

The configuration (dataclasses, validation, ``config.json`` translation) lives in
:mod:`geco_guide.estimators.ufm_config`; its public names are importable from here too. The
lifecycle (construction, loading, ``trunk_to``, checkpointing, freezing) is
:class:`~geco_guide.estimators.base.FrozenEstimator`'s.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from contextlib import nullcontext
from typing import Any

import numpy as np
import torch
import torch.nn.functional as F
from torch import Tensor, nn

from ..geometry import pixel_grid
from ..types import Correspondences
from .base import FrozenEstimator, check_frame_pairs
from .dpt import FusionBlock, resample_layer
from .loading import CheckpointMismatchError, load_state_dict_checked
from .ufm_config import (
    ADAPTOR_CHANNELS,
    COVISIBILITY_ADAPTOR,
    NORMALISATIONS,
    UFMAdaptorSpec,
    UFMConfig,
    UFMEncoderConfig,
    UFMFlowAdaptorConfig,
    UFMHeadConfig,
    UFMInfoSharingConfig,
    config_from_json,
    resolve_block_indices,
)
from .vit import (
    Block,
    DinoV2,
    RotaryEmbedding2D,
    grid_positions,
    init_weights_,
    run_block,
)

# The configuration's public names are importable from here too.
__all__ = ["UFM", "UFMConfig", "UFMEncoderConfig", "UFMInfoSharingConfig", "UFMHeadConfig",
           "UFMFlowAdaptorConfig", "UFMAdaptorSpec", "NORMALISATIONS", "COVISIBILITY_ADAPTOR",
           "choose_resolution", "config_from_json", "region_size", "sinusoid_view_table"]

# Random init (UFM.reset_parameters): output-layer gains and the covisibility bias, sigmoid ~0.8.
FLOW_INIT_GAIN = 0.5
UNCERTAINTY_INIT_GAIN = 0.3
COVISIBILITY_INIT_LOGIT = 1.4


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
        self.intermediate_blocks = resolve_block_indices(config.indices, config.depth)[:2]
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
    """``[1, 2, height, width]``: channel 0 = ``j + 0.5`` (x), channel 1 = ``i + 0.5`` (y).

    The reference's continuous convention (pixel centres at ``i + 0.5``) is
    :func:`~geco_guide.geometry.pixel_grid`'s integer centres shifted by half a pixel.
    """
    grid = pixel_grid(height, width, device=like.device, dtype=like.dtype) + 0.5  # [h, w, 2] (x, y)
    return grid.permute(2, 0, 1)[None]


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


class UFM(FrozenEstimator):
    """UniFlowMatchConfidence: dense flow and covisibility from an image pair (spec section 4).

    Parameters are frozen and the module is in eval mode; gradients still flow to the inputs.
    ``autocast_dtype`` (e.g. ``torch.bfloat16``) runs the encoder and info-sharing under autocast
    while the heads always run in their parameter dtype (fp32); ``gradient_checkpointing``
    recomputes transformer blocks in backward to save memory when differentiating.

    ``UFM(config)`` draws a random initialisation from the global torch RNG (use :meth:`random`
    for a seeded one) that gives sane outputs: flow of a pixel or so, covisibility ~0.8 (above
    GeCo's 0.5 threshold, not saturated), both depending on the images.
    """

    config_class = UFMConfig
    model_name = "UFM"
    default_repo_id = "infinity1096/UFM-Base"
    checkpoint_files = ("model.safetensors", "pytorch_model.bin")
    config_required = True  # the encoder size and adaptors are not knowable from the weights alone
    trunk_modules = ("encoder", "info_sharing")
    checkpointed_modules = ("info_sharing", "encoder.model")

    def __init__(
        self,
        config: UFMConfig | Mapping[str, Any] | None = None,
        *,
        gradient_checkpointing: bool = False,
        autocast_dtype: torch.dtype | None = None,
    ) -> None:
        """``config``: a :class:`UFMConfig` or section-5 dict; None = UFM-Base."""
        super().__init__()
        self.config = config = self.resolve_config(config)
        config.validate()
        self.encoder = UFMEncoder(config.encoder, config.patch_size)
        self.info_sharing = InfoSharing(config.info_sharing, config.encoder.embed_dim)
        dims = config.head_feature_dims
        self.head1 = UFMHead(config.flow_head, dims, 2, {"flow": FlowAdaptor(config.flow_adaptor)})
        self.uncertainty_head = UFMHead(config.uncertainty_head, dims, config.uncertainty_channels)
        self._finish_init(gradient_checkpointing=gradient_checkpointing, autocast_dtype=autocast_dtype)

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
    def config_from_json(cls, raw: Mapping[str, Any]) -> UFMConfig:
        """A ``config.json`` in the upstream schema (translated by :meth:`UFMConfig.from_config_json`)
        or ours (:meth:`save_pretrained`'s)."""
        return config_from_json(raw)

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
        check_frame_pairs(source, target)
        out = self.predict_correspondences(source, target, "identity")
        return Correspondences(flow=out["flow"], covisibility=out["covisibility"])
