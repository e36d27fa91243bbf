"""Vision-transformer building blocks shared by the VGGT and UFM re-implementations.

Everything here follows ``shared/specs/estimators.md`` section 2: pre-norm blocks with optional
LayerScale and q/k-norm, the fused ``qkv`` layout ``[3][heads][head_dim]``, 2D rotary position
embedding, and a DINOv2 ViT whose parameter names match the public checkpoints. Also the
ImageNet normalisation both encoders expect (spec 1.4) and the random initialisation both models'
``reset_parameters`` start from.

Token tensors are ``[N, T, C]`` (batch, tokens, channels) throughout.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Collection
from typing import Literal

import torch
import torch.nn.functional as F
from torch import Tensor, nn
from torch.utils.checkpoint import checkpoint

__all__ = ["IMAGENET_MEAN", "IMAGENET_STD", "Attention", "Block", "DinoV2", "Mlp", "RotaryEmbedding2D",
           "grid_positions", "imagenet_normalise", "init_weights_", "resize_pos_embed", "run_block"]

RopeFn = Callable[[Tensor], Tensor]
PosEmbedVariant = Literal["classic", "registers"]

# ImageNet / "dinov2" / "resnet" statistics of both encoders (spec 1.4), per RGB channel.
IMAGENET_MEAN = (0.485, 0.456, 0.406)
IMAGENET_STD = (0.229, 0.224, 0.225)


def imagenet_normalise(images: Tensor) -> Tensor:
    """``(images - mean) / std`` for images ``[N, 3, H, W]`` in ``[0, 1]``; same shape and dtype."""
    mean = images.new_tensor(IMAGENET_MEAN).view(1, 3, 1, 1)
    std = images.new_tensor(IMAGENET_STD).view(1, 3, 1, 1)
    return (images - mean) / std


class Mlp(nn.Module):
    """Linear -> exact (erf) GELU -> Linear; ``[..., dim] -> [..., out_dim or dim]``."""

    def __init__(self, dim: int, hidden_dim: int, out_dim: int | None = None) -> None:
        super().__init__()
        self.fc1 = nn.Linear(dim, hidden_dim)
        self.fc2 = nn.Linear(hidden_dim, dim if out_dim is None else out_dim)

    def forward(self, x: Tensor) -> Tensor:
        return self.fc2(F.gelu(self.fc1(x)))


class LayerScale(nn.Module):
    """Per-channel scaling ``x * gamma`` with ``gamma [dim]``."""

    def __init__(self, dim: int, init_value: float = 1e-5) -> None:
        super().__init__()
        self.gamma = nn.Parameter(torch.full((dim,), float(init_value)))

    def forward(self, x: Tensor) -> Tensor:
        return x * self.gamma


class Attention(nn.Module):
    """Multi-head self-attention ``[N, T, C] -> [N, T, C]`` with optional q/k-norm and RoPE.

    ``qkv`` output features are ordered ``[3][heads][head_dim]`` (Q block, K block, V block).
    ``q_norm`` / ``k_norm`` are one LayerNorm over ``head_dim`` shared by all heads.
    """

    def __init__(
        self,
        dim: int,
        num_heads: int,
        qkv_bias: bool = True,
        qk_norm: bool = False,
        norm_eps: float = 1e-6,
    ) -> None:
        super().__init__()
        if dim % num_heads:
            raise ValueError(f"dim {dim} is not divisible by num_heads {num_heads}")
        self.num_heads = num_heads
        self.head_dim = dim // num_heads
        self.qkv = nn.Linear(dim, 3 * dim, bias=qkv_bias)
        if qk_norm:
            self.q_norm = nn.LayerNorm(self.head_dim, eps=norm_eps)
            self.k_norm = nn.LayerNorm(self.head_dim, eps=norm_eps)
        else:
            self.q_norm = self.k_norm = None
        self.proj = nn.Linear(dim, dim)

    def forward(self, x: Tensor, rope: RopeFn | None = None) -> Tensor:
        """x ``[N, T, C]``; ``rope`` maps ``[N, heads, T, head_dim]`` to the same shape."""
        n, t, c = x.shape
        qkv = self.qkv(x).reshape(n, t, 3, self.num_heads, self.head_dim).permute(2, 0, 3, 1, 4)
        q, k, v = qkv.unbind(0)  # each [N, heads, T, head_dim]
        if self.q_norm is not None:
            q, k = self.q_norm(q), self.k_norm(k)
        if rope is not None:
            q, k = rope(q), rope(k)
        # Under autocast LayerNorm returns fp32 while v stays low precision; SDPA wants one dtype.
        out = F.scaled_dot_product_attention(q.to(v.dtype), k.to(v.dtype), v)
        return self.proj(out.transpose(1, 2).reshape(n, t, c))


class Block(nn.Module):
    """Pre-norm transformer block: ``x + ls1(attn(norm1 x))``, ``x + ls2(mlp(norm2 x))``."""

    def __init__(
        self,
        dim: int,
        num_heads: int,
        mlp_ratio: float = 4.0,
        qkv_bias: bool = True,
        qk_norm: bool = False,
        layerscale: bool = True,
        norm_eps: float = 1e-6,
    ) -> None:
        super().__init__()
        self.norm1 = nn.LayerNorm(dim, eps=norm_eps)
        self.attn = Attention(dim, num_heads, qkv_bias=qkv_bias, qk_norm=qk_norm, norm_eps=norm_eps)
        self.ls1 = LayerScale(dim) if layerscale else nn.Identity()
        self.norm2 = nn.LayerNorm(dim, eps=norm_eps)
        self.mlp = Mlp(dim, int(dim * mlp_ratio))
        self.ls2 = LayerScale(dim) if layerscale else nn.Identity()

    def forward(self, x: Tensor, rope: RopeFn | None = None) -> Tensor:
        """x ``[N, T, C] -> [N, T, C]``."""
        x = x + self.ls1(self.attn(self.norm1(x), rope))
        return x + self.ls2(self.mlp(self.norm2(x)))


def run_blocks(blocks: nn.ModuleList, x: Tensor, rope: RopeFn | None, checkpointed: bool) -> Tensor:
    """Apply ``blocks`` to ``x [N, T, C]`` in order; with ``checkpointed`` and grad enabled,
    recompute their activations in backward."""
    for block in blocks:
        x = run_block(block, x, rope, checkpointed)
    return x


def run_block(block: nn.Module, x: Tensor, rope: RopeFn | None, checkpointed: bool) -> Tensor:
    """One block call ``[N, T, C] -> [N, T, C]``, optionally checkpointed (only useful with grad)."""
    if checkpointed and torch.is_grad_enabled():
        return checkpoint(block, x, rope, use_reentrant=False)
    return block(x, rope)


class RotaryEmbedding2D:
    """2D rotary position embedding (spec 2.3), no parameters.

    The first half of each head's channels is rotated by the row (y) position, the second half
    by the column (x) position; within a half of size ``D`` element ``i`` pairs with ``i + D/2``
    and has frequency ``base^(-2i/D)``. Angles are computed in float32.

    Usage: ``rope = RotaryEmbedding2D(head_dim).bind(positions, max_position)`` with integer
    positions ``[N or 1, T, 2]`` as ``(y, x)``, then ``rope(q)`` for ``q [N, heads, T, head_dim]``.
    """

    def __init__(self, head_dim: int, base: float = 100.0) -> None:
        if head_dim % 4:
            raise ValueError(f"2D RoPE needs head_dim divisible by 4, got {head_dim}")
        self.head_dim = head_dim
        self.base = float(base)
        self._tables: dict[tuple[int, torch.device], tuple[Tensor, Tensor]] = {}

    def _table(self, max_pos: int, device: torch.device) -> tuple[Tensor, Tensor]:
        """cos, sin ``[max_pos + 1, D]`` (D = head_dim/2, frequencies repeated twice), float32.

        Cached per (size, device): positions are small integers, so one table serves every
        forward pass; the cache is rebuilt only when a larger grid appears.
        """
        key = (max_pos, device)
        if key not in self._tables:
            half = self.head_dim // 2
            exponents = torch.arange(0, half, 2, dtype=torch.float32, device=device) / half
            freqs = 1.0 / self.base**exponents  # [D/2]
            pos = torch.arange(max_pos + 1, dtype=torch.float32, device=device)
            angles = torch.outer(pos, freqs)  # [max_pos+1, D/2]
            angles = torch.cat([angles, angles], dim=-1)  # [max_pos+1, D]
            self._tables = {k: v for k, v in self._tables.items() if k[1] != device}
            self._tables[key] = (angles.cos(), angles.sin())
        return self._tables[key]

    def bind(self, positions: Tensor, max_position: int) -> RopeFn:
        """Return ``rope(t)`` rotating ``t [N, heads, T, head_dim]`` by ``positions [N|1, T, 2]``.

        ``max_position`` bounds the largest coordinate in ``positions``; the caller knows it from
        the patch grid, and reading it from the tensor would wait for the GPU on every forward.
        """
        if positions.ndim != 3 or positions.shape[-1] != 2:
            raise ValueError(f"positions must be [N, T, 2], got {list(positions.shape)}")
        positions = positions.long()
        cos_t, sin_t = self._table(int(max_position), positions.device)
        # [N, 1, T, D] per axis, broadcast over heads.
        cos_y, sin_y = cos_t[positions[..., 0]].unsqueeze(1), sin_t[positions[..., 0]].unsqueeze(1)
        cos_x, sin_x = cos_t[positions[..., 1]].unsqueeze(1), sin_t[positions[..., 1]].unsqueeze(1)

        def rope(t: Tensor) -> Tensor:
            t_y, t_x = t.chunk(2, dim=-1)
            return torch.cat(
                [_rotate(t_y, cos_y, sin_y), _rotate(t_x, cos_x, sin_x)], dim=-1
            )

        return rope


def _rotate(t: Tensor, cos: Tensor, sin: Tensor) -> Tensor:
    """Rotate-half rotation of ``t [..., D]`` pairing ``(i, i + D/2)``; cos/sin ``[..., D]``."""
    first, second = t.chunk(2, dim=-1)
    rotated = torch.cat([-second, first], dim=-1)
    return t * cos.to(t.dtype) + rotated * sin.to(t.dtype)


def grid_positions(grid_h: int, grid_w: int, device: torch.device, start: int = 0) -> Tensor:
    """Integer ``(y, x)`` of a row-major ``grid_h x grid_w`` patch grid: ``[grid_h*grid_w, 2]``,
    counting from ``start`` (RoPE positions; VGGT is 1-based, UFM 0-based)."""
    ys, xs = torch.meshgrid(
        torch.arange(start, start + grid_h, device=device),
        torch.arange(start, start + grid_w, device=device),
        indexing="ij",
    )
    return torch.stack([ys.flatten(), xs.flatten()], dim=-1)


def resize_pos_embed(
    pos_embed: Tensor,
    grid_hw: tuple[int, int],
    variant: PosEmbedVariant,
    interpolate_offset: float = 0.1,
    num_prefix_tokens: int = 1,
) -> Tensor:
    """Resize a square DINOv2 position table to a ``h x w`` patch grid (spec 2.1).

    Args:
        pos_embed: ``[1, num_prefix_tokens + M*M, C]`` (prefix = cls row, never resized).
        grid_hw: target patch grid ``(h, w)``.
        variant: ``"registers"`` = bicubic with antialias to the explicit size (VGGT);
            ``"classic"`` = bicubic without antialias by scale factors ``(n + offset) / M`` (UFM).
        interpolate_offset: the ``+offset`` of the classic variant.
    Returns:
        ``[1, num_prefix_tokens + h*w, C]`` in the dtype of ``pos_embed`` (computed in float32).
    """
    h, w = grid_hw
    prefix, patch = pos_embed[:, :num_prefix_tokens], pos_embed[:, num_prefix_tokens:]
    m = math.isqrt(patch.shape[1])
    if m * m != patch.shape[1]:
        raise ValueError(f"pos_embed has {patch.shape[1]} patch rows, not a square grid")
    if (h, w) == (m, m):
        return pos_embed
    c = patch.shape[-1]
    grid = patch.float().reshape(1, m, m, c).permute(0, 3, 1, 2)  # [1, C, M, M], row = y
    if variant == "registers":
        grid = F.interpolate(grid, size=(h, w), mode="bicubic", align_corners=False, antialias=True)
    elif variant == "classic":
        scale = ((h + interpolate_offset) / m, (w + interpolate_offset) / m)
        grid = F.interpolate(grid, scale_factor=scale, mode="bicubic", align_corners=False)
        if grid.shape[-2:] != (h, w):
            raise ValueError(f"classic pos-embed resize gave {tuple(grid.shape[-2:])}, not {(h, w)}")
    else:
        raise ValueError(f"unknown pos-embed variant {variant!r}")
    patch = grid.permute(0, 2, 3, 1).reshape(1, h * w, c).to(pos_embed.dtype)
    return torch.cat([prefix, patch], dim=1)


class PatchEmbed(nn.Module):
    """Non-overlapping patch projection ``[N, 3, H, W] -> [N, (H/p)*(W/p), C]`` (row-major)."""

    def __init__(self, patch_size: int, embed_dim: int) -> None:
        super().__init__()
        self.proj = nn.Conv2d(3, embed_dim, kernel_size=patch_size, stride=patch_size)

    def forward(self, x: Tensor) -> Tensor:
        return self.proj(x).flatten(2).transpose(1, 2)


class DinoV2(nn.Module):
    """DINOv2 ViT with the public checkpoints' parameter names (spec 2.1).

    ``forward(images [N, 3, H, W], already normalised, H and W multiples of patch_size)``
    returns the final-normed patch tokens ``[N, h*w, C]`` (cls and registers dropped); ``block``
    and ``norm`` select an earlier block's output and whether the final norm is applied.
    Set ``gradient_checkpointing = True`` to recompute block activations in backward.
    """

    def __init__(
        self,
        embed_dim: int,
        depth: int,
        num_heads: int,
        mlp_ratio: float = 4.0,
        img_size: int = 518,
        patch_size: int = 14,
        num_register_tokens: int = 0,
        pos_embed_variant: PosEmbedVariant = "classic",
        interpolate_offset: float = 0.1,
        with_mask_token: bool = False,
    ) -> None:
        super().__init__()
        if img_size % patch_size:
            raise ValueError(f"img_size {img_size} is not a multiple of patch_size {patch_size}")
        self.patch_size = patch_size
        self.num_register_tokens = num_register_tokens
        self.pos_embed_variant: PosEmbedVariant = pos_embed_variant
        self.interpolate_offset = interpolate_offset
        self.gradient_checkpointing = False
        grid = img_size // patch_size
        self.patch_embed = PatchEmbed(patch_size, embed_dim)
        self.cls_token = nn.Parameter(torch.zeros(1, 1, embed_dim))
        self.pos_embed = nn.Parameter(torch.zeros(1, 1 + grid * grid, embed_dim))
        if num_register_tokens > 0:
            self.register_tokens = nn.Parameter(torch.zeros(1, num_register_tokens, embed_dim))
        else:
            self.register_tokens = None
        if with_mask_token:
            self.mask_token = nn.Parameter(torch.zeros(1, embed_dim))
        self.blocks = nn.ModuleList(
            Block(embed_dim, num_heads, mlp_ratio, norm_eps=1e-6) for _ in range(depth)
        )
        self.norm = nn.LayerNorm(embed_dim, eps=1e-6)

    def prepare_tokens(self, images: Tensor) -> Tensor:
        """images ``[N, 3, H, W]`` -> block input ``[N, 1 + R + h*w, C]`` = ``[cls, registers,
        patches]`` with the resized position embedding added to cls and patches (spec 2.1 1-4)."""
        n, _, h_img, w_img = images.shape
        if h_img % self.patch_size or w_img % self.patch_size:
            raise ValueError(f"image size {(h_img, w_img)} is not a multiple of {self.patch_size}")
        x = self.patch_embed(images)  # [N, h*w, C]
        cls = self.cls_token.to(x.dtype).expand(n, -1, -1)
        x = torch.cat([cls, x], dim=1)
        grid_hw = (h_img // self.patch_size, w_img // self.patch_size)
        pos = resize_pos_embed(self.pos_embed, grid_hw, self.pos_embed_variant, self.interpolate_offset)
        x = x + pos.to(x.dtype)
        if self.register_tokens is not None:
            # Registers carry no position: inserted after the cls token, after the add.
            reg = self.register_tokens.to(x.dtype).expand(n, -1, -1)
            x = torch.cat([x[:, :1], reg, x[:, 1:]], dim=1)
        return x

    def forward(self, images: Tensor, block: int = -1, norm: bool = True) -> Tensor:
        """images ``[N, 3, H, W]`` -> patch tokens ``[N, (H/p)*(W/p), C]`` after block ``block``
        (negative counts from the end; later blocks are not run), final-normed if ``norm``."""
        depth = len(self.blocks)
        if not -depth <= block < depth:
            raise ValueError(f"block {block} is out of range for a depth-{depth} DINOv2")
        x = self.prepare_tokens(images)
        x = run_blocks(self.blocks[: block % depth + 1], x, None, self.gradient_checkpointing)
        if norm:
            x = self.norm(x)
        return x[:, 1 + self.num_register_tokens :]


@torch.no_grad()
def init_weights_(
    module: nn.Module, generator: torch.Generator | None = None, *, exclude: Collection[str] = ()
) -> None:
    """Random init of ``module`` that keeps a deep random stack's activations in range.

    Linear: truncated normal (std 0.02), zero bias. Conv / transposed conv: variance-preserving
    normal (std ``fan_in^-0.5``; a stride == kernel transposed conv sees ``in_channels`` inputs),
    zero bias. LayerNorm: identity. LayerScale: 0.1. Then, in parameter order, every
    ``*_token``, ``*_tokens`` and ``*pos_embed`` parameter not named in ``exclude``: normal,
    std 0.02. Buffers are not touched. Draws come from ``generator`` (global RNG if None).
    """
    for m in module.modules():
        if isinstance(m, nn.Linear):
            nn.init.trunc_normal_(m.weight, std=0.02, generator=generator)
            if m.bias is not None:
                nn.init.zeros_(m.bias)
        elif isinstance(m, (nn.Conv2d, nn.ConvTranspose2d)):
            fan_in = m.weight[0].numel() if isinstance(m, nn.Conv2d) else m.weight.shape[0]
            nn.init.normal_(m.weight, std=fan_in**-0.5, generator=generator)
            if m.bias is not None:
                nn.init.zeros_(m.bias)
        elif isinstance(m, nn.LayerNorm) and m.elementwise_affine:
            nn.init.ones_(m.weight)
            nn.init.zeros_(m.bias)
        elif isinstance(m, LayerScale):
            m.gamma.fill_(0.1)
    for name, param in module.named_parameters():
        if name.endswith(("_token", "_tokens", "pos_embed")) and name not in exclude:
            nn.init.normal_(param, std=0.02, generator=generator)
