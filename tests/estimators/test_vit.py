"""Shared ViT / DPT building blocks against the formulas of specs/estimators.md section 2."""

from __future__ import annotations

import math

import pytest
import torch
import torch.nn.functional as F

from geco_guide.estimators.dpt import (
    FusionBlock,
    ResidualConvUnit,
    add_position_embedding,
)
from geco_guide.estimators.vit import (
    Attention,
    Block,
    DinoV2,
    RotaryEmbedding2D,
    grid_positions,
    imagenet_normalise,
    resize_pos_embed,
)


def _randomise(module: torch.nn.Module, seed: int = 0) -> None:
    gen = torch.Generator().manual_seed(seed)
    with torch.no_grad():
        for p in module.parameters():
            p.copy_(torch.randn(p.shape, generator=gen) * 0.3)


def _rope_reference(t: torch.Tensor, pos: torch.Tensor, base: float) -> torch.Tensor:
    """Element-wise spec 2.3: y on the first half, x on the second, pairs (i, i + D/2)."""
    out = t.clone()
    head_dim = t.shape[-1]
    d = head_dim // 2
    for axis in range(2):
        for i in range(d // 2):
            omega = base ** (-2.0 * i / d)
            theta = pos[..., axis].double() * omega  # [N, T]
            cos, sin = theta.cos()[:, None], theta.sin()[:, None]
            a, b = axis * d + i, axis * d + i + d // 2
            out[..., a] = (t[..., a] * cos - t[..., b] * sin).to(t.dtype)
            out[..., b] = (t[..., b] * cos + t[..., a] * sin).to(t.dtype)
    return out


def test_rope_matches_spec_formula_and_is_relative() -> None:
    torch.manual_seed(0)
    rope = RotaryEmbedding2D(head_dim=16, base=100.0)
    pos = torch.randint(0, 9, (2, 5, 2))
    t = torch.randn(2, 3, 5, 16)
    torch.testing.assert_close(rope.bind(pos, 8)(t), _rope_reference(t, pos, 100.0), atol=1e-5, rtol=0)
    # q.k depends only on the position difference.
    q, k = torch.randn(1, 1, 1, 16), torch.randn(1, 1, 1, 16)

    def score(pq: list[int], pk: list[int]) -> torch.Tensor:
        rq = rope.bind(torch.tensor([[pq]]), 10)(q)
        rk = rope.bind(torch.tensor([[pk]]), 10)(k)
        return (rq * rk).sum()

    torch.testing.assert_close(score([1, 2], [3, 7]), score([4, 5], [6, 10]), atol=1e-5, rtol=0)


def test_attention_layout_qk_norm_and_rope_match_explicit_softmax() -> None:
    torch.manual_seed(0)
    dim, heads = 32, 4
    attn = Attention(dim, heads, qk_norm=True, norm_eps=1e-5)
    _randomise(attn)
    x = torch.randn(2, 6, dim)
    pos = torch.randint(0, 4, (1, 6, 2))
    rope = RotaryEmbedding2D(dim // heads).bind(pos, 3)
    # Explicit computation from the spec: qkv features are [3][heads][head_dim].
    qkv = attn.qkv(x).view(2, 6, 3, heads, dim // heads)
    q, k, v = (qkv[:, :, i].transpose(1, 2) for i in range(3))
    q = F.layer_norm(q, (dim // heads,), attn.q_norm.weight, attn.q_norm.bias, 1e-5)
    k = F.layer_norm(k, (dim // heads,), attn.k_norm.weight, attn.k_norm.bias, 1e-5)
    q, k = rope(q), rope(k)
    weights = torch.softmax(q @ k.transpose(-1, -2) / math.sqrt(dim // heads), dim=-1)
    expected = attn.proj((weights @ v).transpose(1, 2).reshape(2, 6, dim))
    torch.testing.assert_close(attn(x, rope), expected, atol=1e-5, rtol=1e-5)


def test_block_keys_follow_checkpoint_names() -> None:
    keys = set(Block(32, 4, qk_norm=True).state_dict())
    assert {"norm1.weight", "attn.qkv.weight", "attn.q_norm.weight", "attn.k_norm.bias", "attn.proj.bias",
            "ls1.gamma", "norm2.bias", "mlp.fc1.weight", "mlp.fc2.bias", "ls2.gamma"} <= keys
    plain = set(Block(32, 4, layerscale=False).state_dict())
    assert not any(k.startswith(("ls1", "ls2", "attn.q_norm")) for k in plain)


def test_resize_pos_embed_variants() -> None:
    torch.manual_seed(0)
    pos = torch.randn(1, 1 + 25, 8)
    assert resize_pos_embed(pos, (5, 5), "registers") is pos
    grid = pos[:, 1:].reshape(1, 5, 5, 8).permute(0, 3, 1, 2)
    reg = resize_pos_embed(pos, (4, 7), "registers")
    expected = F.interpolate(grid, size=(4, 7), mode="bicubic", antialias=True)
    torch.testing.assert_close(reg[:, 1:], expected.permute(0, 2, 3, 1).reshape(1, 28, 8))
    torch.testing.assert_close(reg[:, :1], pos[:, :1])
    classic = resize_pos_embed(pos, (4, 7), "classic", interpolate_offset=0.1)
    expected = F.interpolate(grid, scale_factor=(4.1 / 5, 7.1 / 5), mode="bicubic")
    torch.testing.assert_close(classic[:, 1:], expected.permute(0, 2, 3, 1).reshape(1, 28, 8))
    assert (classic - reg).abs().max() > 1e-3  # the two variants really differ


def test_dinov2_matches_vggt_fixture_tokens(vggt_fixture) -> None:
    fx = vggt_fixture
    cfg = fx["config"]
    dino = DinoV2(cfg["embed_dim"], cfg["dino"]["depth"], cfg["dino"]["num_heads"], cfg["dino"]["mlp_ratio"],
                  img_size=cfg["img_size"], patch_size=cfg["patch_size"],
                  num_register_tokens=cfg["num_register_tokens"], pos_embed_variant="registers",
                  with_mask_token=True)
    prefix = "aggregator.patch_embed."
    dino.load_state_dict({k[len(prefix):]: v for k, v in fx["state_dict"].items() if k.startswith(prefix)})
    images = fx["inputs"]["images"].flatten(0, 1)
    with torch.no_grad():
        tokens = dino(imagenet_normalise(images))
    ref = fx["debug"]["dino_patch_tokens"]
    assert tokens.shape == ref.shape
    assert (tokens - ref).abs().max() <= 1e-4 * ref.abs().max()


def test_dinov2_gradient_checkpointing_is_transparent() -> None:
    torch.manual_seed(0)
    dino = DinoV2(16, 2, 2, img_size=28, patch_size=14, num_register_tokens=2, pos_embed_variant="registers")
    _randomise(dino)
    x = torch.randn(2, 3, 28, 42, requires_grad=True)
    plain = dino(x)
    (g_plain,) = torch.autograd.grad(plain.square().sum(), x)
    dino.gradient_checkpointing = True
    ckpt = dino(x)
    (g_ckpt,) = torch.autograd.grad(ckpt.square().sum(), x)
    assert plain.shape == (2, 6, 16)
    torch.testing.assert_close(ckpt, plain)
    torch.testing.assert_close(g_ckpt, g_plain)


def test_dinov2_earlier_block_with_and_without_norm() -> None:
    torch.manual_seed(0)
    dino = DinoV2(16, 3, 2, img_size=28, patch_size=14, num_register_tokens=2, pos_embed_variant="registers")
    _randomise(dino)
    x = torch.randn(2, 3, 28, 42)
    with torch.no_grad():
        tokens = dino.prepare_tokens(x)
        assert tokens.shape == (2, 1 + 2 + 6, 16)
        after_block1 = dino.blocks[1](dino.blocks[0](tokens))
        torch.testing.assert_close(dino(x, block=1, norm=False), after_block1[:, 3:])
        torch.testing.assert_close(dino(x, block=-2), dino.norm(after_block1)[:, 3:])
        torch.testing.assert_close(dino(x), dino(x, block=2, norm=True))
    with pytest.raises(ValueError, match="out of range"):
        dino(x, block=3)


def test_imagenet_normalise_and_grid_positions() -> None:
    x = torch.rand(2, 3, 4, 5)
    mean = torch.tensor([0.485, 0.456, 0.406]).view(1, 3, 1, 1)
    std = torch.tensor([0.229, 0.224, 0.225]).view(1, 3, 1, 1)
    torch.testing.assert_close(imagenet_normalise(x), (x - mean) / std)
    assert grid_positions(2, 3, torch.device("cpu"), start=1).tolist() == [
        [1, 1], [1, 2], [1, 3], [2, 1], [2, 2], [2, 3]
    ]


def test_residual_conv_unit_flavours() -> None:
    torch.manual_seed(0)
    x = torch.randn(1, 4, 5, 6)
    vggt_rcu = ResidualConvUnit(4, rectify_skip=True)
    ufm_rcu = ResidualConvUnit(4, rectify_skip=False)
    ufm_rcu.load_state_dict(vggt_rcu.state_dict())
    branch = vggt_rcu.conv2(F.relu(vggt_rcu.conv1(F.relu(x))))
    torch.testing.assert_close(vggt_rcu(x), branch + F.relu(x))
    torch.testing.assert_close(ufm_rcu(x), branch + x)


def test_fusion_block_keys_and_sizes() -> None:
    torch.manual_seed(0)
    top = FusionBlock(8, has_skip=False, rectify_skip=True)
    assert not any(k.startswith("resConfUnit1") for k in top.state_dict())
    fuse = FusionBlock(8, has_skip=True, rectify_skip=False)
    assert {"resConfUnit1.conv1.weight", "resConfUnit2.conv2.bias", "out_conv.weight"} <= set(fuse.state_dict())
    x, skip = torch.randn(1, 8, 3, 5), torch.randn(1, 8, 3, 5)
    assert top(x).shape == (1, 8, 6, 10)
    assert fuse(x, skip, size=(4, 7)).shape == (1, 8, 4, 7)
    y = fuse.resConfUnit2(x + fuse.resConfUnit1(skip))
    expected = fuse.out_conv(F.interpolate(y, size=(4, 7), mode="bilinear", align_corners=True))
    torch.testing.assert_close(fuse(x, skip, size=(4, 7)), expected)


def test_dpt_position_embedding_matches_spec_formula() -> None:
    channels, (gh, gw), (height, width) = 8, (3, 5), (42, 70)
    x = torch.zeros(1, channels, gh, gw)
    got = add_position_embedding(x, (height, width), ratio=0.1)
    a = width / height
    d = math.sqrt(a * a + 1)
    half = channels // 2
    for i in range(gh):
        for j in range(gw):
            u = -a / d * (gw - 1) / gw + j * 2 * a / d * (gw - 1) / gw / (gw - 1)
            v = -1 / d * (gh - 1) / gh + i * 2 / d * (gh - 1) / gh / (gh - 1)
            for p, offset in ((u, 0), (v, half)):
                for k in range(half // 2):
                    omega = 100.0 ** (-k / (half / 2))
                    assert got[0, offset + k, i, j] == pytest.approx(0.1 * math.sin(p * omega), abs=1e-6)
                    assert got[0, offset + half // 2 + k, i, j] == pytest.approx(0.1 * math.cos(p * omega), abs=1e-6)
