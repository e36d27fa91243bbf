"""Anchor frame <-> latent chunk mapping and the chunked anchor decode."""

from __future__ import annotations

from functools import partial

import pytest
import torch

from geco_guide.sampler.algorithm.slicing import (
    anchor_latent_chunks,
    check_latents,
    check_num_frames,
    decode_anchor_frames,
    decode_chunk,
    latent_to_pixels,
    pixel_to_latent,
)


def test_frame_latent_mapping_is_causal_with_compression_4():
    assert pixel_to_latent(0, 4) == 0
    assert [pixel_to_latent(p, 4) for p in range(1, 9)] == [1, 1, 1, 1, 2, 2, 2, 2]
    assert list(latent_to_pixels(0, 4)) == [0]
    assert list(latent_to_pixels(3, 4)) == [9, 10, 11, 12]
    for k in range(1, 13):
        assert all(pixel_to_latent(p, 4) == k for p in latent_to_pixels(k, 4))
    assert check_num_frames(49, 4) == 13
    assert check_num_frames(17, 4) == 5
    assert check_num_frames(13, 2) == 7  # derived from r, not hard-coded


def test_paper_anchors_map_to_latents_3_6_9_12_with_3_latent_chunks():
    chunks = anchor_latent_chunks((12, 24, 36, 48), 49, 4, 3)
    assert [c.latent for c in chunks] == [3, 6, 9, 12]
    assert [(c.start, c.stop) for c in chunks] == [(1, 4), (4, 7), (7, 10), (10, 13)]
    # 3 latents decode causally to 1 + 4 * 2 = 9 frames; the anchor is the last one.
    assert all(c.index_in_chunk == 8 and c.from_end == 0 for c in chunks)


def test_chunks_clip_at_latent_zero_and_pick_frames_inside_a_group():
    chunks = anchor_latent_chunks((2, 8, 11), 17, 4, 3)
    assert [(c.start, c.stop) for c in chunks] == [(0, 2), (0, 3), (1, 4)]
    # frame 2 is the 2nd of latent 1's frames 1..4 -> 2 from the end; frame 11 is the 3rd of 9..12.
    assert [c.from_end for c in chunks] == [2, 0, 1]
    assert chunks[0].index_in_chunk == 2


@pytest.mark.parametrize(
    "anchors, num_frames, chunk, match",
    [
        ((4, 49), 49, 3, "out of range"),
        ((-1, 4), 49, 3, "out of range"),
        ((12,), 49, 3, "at least two"),
        ((0, 12), 49, 3, "latent 0"),
        ((12, 12), 49, 3, "strictly increasing"),
        ((12, 24), 48, 3, "num_frames=48"),
        ((12, 24), 49, 1, "chunk_latents"),
    ],
)
def test_invalid_anchor_settings_raise_naming_the_problem(anchors, num_frames, chunk, match):
    with pytest.raises(ValueError, match=match):
        anchor_latent_chunks(anchors, num_frames, 4, chunk)


class CountingVAE(torch.nn.Module):
    """Fake causal VAE: latent k -> r frames whose value encodes (k, frame-in-group)."""

    def __init__(self, r: int = 4):
        super().__init__()
        self.r = r
        self.scale = torch.nn.Parameter(torch.ones(()))
        self.calls: list[tuple[int, int]] = []  # (batch, latents) of each decode

    def decode(self, z):  # z [B, C, F, h, w]
        self.calls.append((z.shape[0], z.shape[2]))
        frames = []
        for i in range(z.shape[2]):
            n = 1 if i == 0 else self.r
            for j in range(n):
                frames.append(z[:, :1, i] * self.scale + 0.01 * j)
        video = torch.stack(frames, dim=2).expand(-1, 3, -1, -1, -1) * 2 - 1  # to [-1, 1]
        return type("Out", (), {"sample": video})()


def test_decode_anchor_frames_decodes_only_the_chunks_and_picks_the_anchor():
    vae = CountingVAE()
    # latent k of video b has value k/10 + b/2 (two videos: the batched decode must keep them apart)
    latents = torch.arange(5.0).view(1, 5, 1, 1, 1).expand(2, 5, 2, 2, 3) / 10 + torch.tensor([0.0, 0.5]).view(2, 1, 1, 1, 1)
    latents = latents.clone().requires_grad_(True)
    chunks = anchor_latent_chunks((2, 8, 12, 16), 17, 4, 3)
    frames = decode_anchor_frames(partial(decode_chunk, vae, scaling_factor=1.0), latents, chunks)
    assert frames.shape == (2, 4, 3, 2, 3)
    # short chunks only, never the 5-latent video; the three 3-latent chunks of both videos in one call
    assert vae.calls == [(2, 2), (6, 3)]
    # anchor 2 = latent 1, frame 1 of its group; anchors 8/12/16 = last frame of latents 2/3/4
    expected = torch.tensor([0.1 + 0.01, 0.2 + 0.03, 0.3 + 0.03, 0.4 + 0.03])
    torch.testing.assert_close(frames[0, :, 0, 0, 0], expected)
    torch.testing.assert_close(frames[1, :, 0, 0, 0], expected + 0.5)
    frames.sum().backward()
    assert latents.grad[:, 0].abs().sum() == 0  # latent 0 feeds no anchor
    assert latents.grad[:, 4].abs().sum() > 0


def test_shared_chunks_are_decoded_once():
    vae = CountingVAE()
    latents = torch.zeros(1, 5, 2, 2, 2)
    chunks = anchor_latent_chunks((13, 14, 16), 17, 4, 3)  # 13 and 14 share latent 4
    decode_anchor_frames(partial(decode_chunk, vae, scaling_factor=1.0), latents, chunks)
    assert vae.calls == [(1, 3)]


def test_chunk_decode_of_the_whole_video_matches_a_full_decode():
    from geco_guide.tiny import tiny_cogvideox_components

    vae = tiny_cogvideox_components(0)["vae"]
    latents = torch.randn(1, 3, 4, 4, 6, generator=torch.Generator().manual_seed(0))
    with torch.no_grad():
        full = decode_chunk(vae, latents, vae.config.scaling_factor)
        chunks = anchor_latent_chunks((4, 8), 9, 4, 3)
        frames = decode_anchor_frames(partial(decode_chunk, vae, scaling_factor=vae.config.scaling_factor), latents, chunks)
    assert full.shape[1] == 9
    torch.testing.assert_close(frames[:, 1], full[:, 8])  # chunk [0, 3) is the whole video
    assert 0 <= frames.min() and frames.max() <= 1


@pytest.mark.slow
def test_batched_chunk_decode_matches_decoding_each_chunk_alone():
    from geco_guide.tiny import tiny_cogvideox_components

    vae = tiny_cogvideox_components(0)["vae"].double()
    latents = torch.randn(2, 5, 4, 4, 6, generator=torch.Generator().manual_seed(1), dtype=torch.float64)
    chunks = anchor_latent_chunks((4, 8, 12, 16), 17, 4, 3)
    with torch.no_grad():
        frames = decode_anchor_frames(partial(decode_chunk, vae, scaling_factor=vae.config.scaling_factor), latents, chunks)
        for k, chunk in enumerate(chunks):
            alone = decode_chunk(vae, latents[:, chunk.start : chunk.stop], vae.config.scaling_factor)
            torch.testing.assert_close(frames[:, k], alone[:, alone.shape[1] - 1 - chunk.from_end])


@pytest.mark.slow
def test_checkpointed_chunks_give_the_same_frames_and_gradient():
    from geco_guide.tiny import tiny_cogvideox_components

    vae = tiny_cogvideox_components(0)["vae"].double().requires_grad_(False)
    latents = torch.randn(1, 5, 4, 4, 6, generator=torch.Generator().manual_seed(2), dtype=torch.float64)
    weights = torch.randn(1, 4, 3, 32, 48, generator=torch.Generator().manual_seed(3), dtype=torch.float64)
    chunks = anchor_latent_chunks((4, 8, 12, 16), 17, 4, 3)
    results = []
    for checkpoint_chunks in (False, True):
        z = latents.clone().requires_grad_(True)
        frames = decode_anchor_frames(partial(decode_chunk, vae, scaling_factor=vae.config.scaling_factor), z, chunks,
                                      checkpoint_chunks=checkpoint_chunks)
        (grad,) = torch.autograd.grad((frames * weights).sum(), z)
        results.append((frames.detach(), grad))
    torch.testing.assert_close(results[1][0], results[0][0])
    torch.testing.assert_close(results[1][1], results[0][1])
    assert results[0][1].abs().sum() > 0


def test_check_latents_takes_none_and_the_right_shape_and_refuses_the_rest():
    check_latents(None, (1, 2), "a call")
    check_latents(torch.zeros(1, 2), (1, 2), "a call")
    check_latents(torch.zeros(3), None, "a call")  # shape unknown: values only
    with pytest.raises(ValueError, match=r"^latents must have shape \[1, 2\] \(those of a call\), got \[2, 1\]$"):
        check_latents(torch.zeros(2, 1), (1, 2), "a call")
    with pytest.raises(ValueError, match=r"^latents hold 2 NaN or infinite value\(s\) of 3"):
        check_latents(torch.tensor([1.0, float("-inf"), float("nan")]), None, "a call")
    with pytest.raises(TypeError, match="must be a torch.Tensor, got list"):
        check_latents([[0.0, 0.0]], (1, 2), "a call")
