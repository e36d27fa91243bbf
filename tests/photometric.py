"""A check of synthetic scenes shared by the tests of their ground truth: the exact flow must carry
each pixel to where the next frame shows it."""

from __future__ import annotations

from geco_guide.geometry import pixel_grid, sample_bilinear


def photometric_error(clip, i, j, where):
    """Mean |frame_j(p + flow) - frame_i(p)| over covisible pixels of ``where`` ``[H, W]`` bool and
    their count: ``(error, pixels)``."""
    flow, covisible = clip.correspondences(i, j)
    height, width = flow.shape[-2:]
    target = pixel_grid(height, width, dtype=flow.dtype) + flow.permute(1, 2, 0)
    warped = sample_bilinear(clip.frames[j][None].to(flow.dtype), target[None])[0]
    error = (warped - clip.frames[i].to(flow.dtype)).abs().mean(0)
    keep = (covisible > 0.5) & where
    return error[keep].mean().item(), int(keep.sum())
