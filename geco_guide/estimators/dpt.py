"""DPT ("dense prediction transformer") building blocks shared by VGGT and UFM.

Spec: ``shared/specs/estimators.md`` section 2.4 (fusion units) and 3.4 (positional embedding).
Feature maps are ``[N, C, H, W]``.
"""

from __future__ import annotations

import math

import torch
import torch.nn.functional as F
from torch import Tensor, nn

__all__ = ["FusionBlock", "ResidualConvUnit", "add_position_embedding", "resample_layer"]


class ResidualConvUnit(nn.Module):
    """ReLU -> conv3x3 -> ReLU -> conv3x3, plus a skip; ``[N, F, H, W] -> [N, F, H, W]``.

    ``rectify_skip=True`` adds ``relu(x)`` (VGGT: its in-place ReLU rectifies the input before the
    skip add), ``False`` adds ``x`` (UFM).
    """

    def __init__(self, features: int, rectify_skip: bool) -> None:
        super().__init__()
        self.rectify_skip = rectify_skip
        self.conv1 = nn.Conv2d(features, features, kernel_size=3, padding=1)
        self.conv2 = nn.Conv2d(features, features, kernel_size=3, padding=1)

    def forward(self, x: Tensor) -> Tensor:
        """``[N, F, H, W] -> [N, F, H, W]``."""
        rectified = F.relu(x)
        out = self.conv2(F.relu(self.conv1(rectified)))
        return out + (rectified if self.rectify_skip else x)


class FusionBlock(nn.Module):
    """RefineNet fusion: ``y = x (+ RCU1(skip))``, ``y = RCU2(y)``, upsample, ``out_conv`` (1x1).

    Upsampling is bilinear with ``align_corners=True``, to ``size`` if given, else by 2.
    ``has_skip=False`` (the coarsest level) creates no ``resConfUnit1``.
    """

    def __init__(self, features: int, has_skip: bool, rectify_skip: bool) -> None:
        super().__init__()
        if has_skip:
            self.resConfUnit1 = ResidualConvUnit(features, rectify_skip)
        else:
            self.resConfUnit1 = None
        self.resConfUnit2 = ResidualConvUnit(features, rectify_skip)
        self.out_conv = nn.Conv2d(features, features, kernel_size=1)

    def forward(self, x: Tensor, skip: Tensor | None = None, size: tuple[int, int] | None = None) -> Tensor:
        """x, skip ``[N, F, h, w]`` -> ``[N, F, *size]`` (or ``[N, F, 2h, 2w]``)."""
        if skip is not None:
            if self.resConfUnit1 is None:
                raise ValueError("this FusionBlock was built without a skip branch")
            x = x + self.resConfUnit1(skip)
        y = self.resConfUnit2(x)
        if size is None:
            y = F.interpolate(y, scale_factor=2.0, mode="bilinear", align_corners=True)
        else:
            y = F.interpolate(y, size=tuple(size), mode="bilinear", align_corners=True)
        return self.out_conv(y)


def resample_layer(channels: int, level: int) -> nn.Module:
    """Resampling of DPT pyramid level ``level`` (0 = finest), ``[N, ch, h', w']`` in:
    x4 and x2 transposed convs (kernel = stride), identity, and a stride-2 3x3 conv (padding 1,
    ``ceil(h'/2) x ceil(w'/2)``) for levels 0-3 (spec 3.4, 4.4)."""
    if level == 0:
        return nn.ConvTranspose2d(channels, channels, kernel_size=4, stride=4)
    if level == 1:
        return nn.ConvTranspose2d(channels, channels, kernel_size=2, stride=2)
    if level == 2:
        return nn.Identity()
    if level == 3:
        return nn.Conv2d(channels, channels, kernel_size=3, stride=2, padding=1)
    raise ValueError(f"DPT pyramid level must be 0..3, got {level}")


def add_position_embedding(x: Tensor, image_hw: tuple[int, int], ratio: float = 0.1) -> Tensor:
    """Add VGGT's DPT sin/cos embedding of a normalised uv grid (spec 3.4) to ``x``.

    The grid spans ``[-a/d, a/d] x [-1/d, 1/d]`` (``a = W/H``, ``d = sqrt(a^2 + 1)``) at cell
    centres; channels ``[0, C/2)`` embed u (columns), ``[C/2, C)`` embed v (rows), each as all
    sines then all cosines with frequencies ``100^(-k/(C/4))``, evaluated in float64 like the
    reference and cast to float32 before scaling by ``ratio``. The two halves are added by
    broadcasting, so no full ``[C, gh, gw]`` table is materialised (it is 137 MB at 518 x 518).

    Args:
        x: ``[N, C, gh, gw]`` with ``C`` divisible by 4.
        image_hw: ``(H, W)`` of the network input image (sets the aspect ratio).
    Returns:
        ``[N, C, gh, gw]``.
    """
    channels, gh, gw = x.shape[-3:]
    if channels % 4:
        raise ValueError(f"DPT position embedding needs channels divisible by 4, got {channels}")
    aspect = image_hw[1] / image_hw[0]
    diag = math.sqrt(aspect * aspect + 1.0)
    half = channels // 2
    emb_u = _axis_embedding(gw, aspect / diag, half, x.device) * ratio  # [C/2, gw]
    emb_v = _axis_embedding(gh, 1.0 / diag, half, x.device) * ratio  # [C/2, gh]
    return torch.cat(
        [x[:, :half] + emb_u[:, None, :].to(x.dtype), x[:, half:] + emb_v[:, :, None].to(x.dtype)], dim=1
    )


def _axis_embedding(n: int, span: float, dim: int, device: torch.device) -> Tensor:
    """``[dim, n]`` float32: sines then cosines of ``n`` cell centres spread over ``[-span, span]``."""
    edge = span * (n - 1) / n
    p = torch.linspace(-edge, edge, n, dtype=torch.float32, device=device).double()
    omega = 1.0 / 100.0 ** (torch.arange(dim // 2, dtype=torch.float64, device=device) / (dim / 2.0))
    angles = torch.outer(p, omega)  # [n, dim/2]
    return torch.cat([angles.sin(), angles.cos()], dim=-1).float().t()
