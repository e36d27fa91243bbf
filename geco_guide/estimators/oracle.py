"""Ground-truth estimators for synthetic clips: the metric with perfect geometry and flow.

They implement the :class:`GeometryEstimator` / :class:`FlowEstimator` protocols by looking the
given frames up in a :class:`~geco_guide.bench.synthetic.SyntheticClip` and returning its ground truth,
resized to the resolution they are asked about. A frame that is not (a resized copy of) one of
the clip's frames is an error, so an oracle can never silently answer for another video.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import Tensor

from ..geometry import resize_flow, resize_intrinsics
from ..types import Correspondences, SceneGeometry, check_frames

__all__ = ["OracleFlow", "OracleGeometry"]


class _ClipLookup:
    """Finds which frames of a reference clip an image batch shows."""

    def __init__(self, frames: Tensor, tolerance: float) -> None:
        self.frames = frames.float()  # [S, 3, H, W]
        self.tolerance = tolerance

    def indices(self, images: Tensor) -> list[int]:
        """``[N, 3, h, w]`` -> the index of the matching clip frame of each image."""
        reference = self.frames
        if tuple(images.shape[-2:]) != tuple(reference.shape[-2:]):
            reference = F.interpolate(reference, size=images.shape[-2:], mode="bilinear", align_corners=False)
        errors = (images.detach().float()[:, None] - reference[None]).abs().mean(dim=(2, 3, 4))  # [N, S]
        best, index = errors.min(dim=1)
        if (best > self.tolerance).any():
            raise ValueError(
                f"oracle: image does not match any frame of its clip (mean abs error {best.max():.3g} > "
                f"{self.tolerance}); an oracle only answers for the clip it was built from"
            )
        return index.tolist()


class OracleGeometry:
    """Ground-truth depth, intrinsics and extrinsics of a synthetic clip.

    Args:
        clip: a :class:`~geco_guide.bench.synthetic.SyntheticClip`.
        tolerance: largest mean absolute difference for a frame to count as a clip frame.
    """

    def __init__(self, clip, tolerance: float = 0.02) -> None:
        self.clip = clip
        self.lookup = _ClipLookup(clip.frames, tolerance)

    def estimate_geometry(self, frames: Tensor) -> SceneGeometry:
        """``frames [B, S, 3, h, w]`` -> ground truth at ``h x w`` (depth resized bilinearly)."""
        check_frames(frames)
        batch, num, _, height, width = frames.shape
        index = torch.tensor(self.lookup.indices(frames.flatten(0, 1))).view(batch, num)
        clip_hw = tuple(self.clip.depth.shape[-2:])
        depth = self.clip.depth[index].to(frames.dtype)
        if (height, width) != clip_hw:
            depth = F.interpolate(depth, size=(height, width), mode="bilinear", align_corners=False)
        intrinsics = resize_intrinsics(self.clip.intrinsics[index], clip_hw, (height, width))
        return SceneGeometry(
            depth=depth,
            intrinsics=intrinsics.to(frames.dtype),
            extrinsics=self.clip.extrinsics[index].to(frames.dtype),
        )


class OracleFlow:
    """Ground-truth flow and covisibility between frames of a synthetic clip."""

    def __init__(self, clip, tolerance: float = 0.02) -> None:
        self.clip = clip
        self.lookup = _ClipLookup(clip.frames, tolerance)

    def estimate_flow(self, source: Tensor, target: Tensor) -> Correspondences:
        """``[N, 3, h, w]`` pairs -> flow ``[N, 2, h, w]`` and covisibility ``[N, h, w]``."""
        if source.shape != target.shape:
            raise ValueError(f"source and target must have the same shape, got {list(source.shape)} and {list(target.shape)}")
        pairs = zip(self.lookup.indices(source), self.lookup.indices(target))
        flows, covis = zip(*(self.clip.correspondences(i, j) for i, j in pairs))
        size = tuple(source.shape[-2:])
        flow = resize_flow(torch.stack(flows), size).to(source.dtype)
        covisibility = torch.stack(covis)[:, None]
        if tuple(covisibility.shape[-2:]) != size:
            covisibility = F.interpolate(covisibility, size=size, mode="bilinear", align_corners=False)
        return Correspondences(flow=flow, covisibility=covisibility[:, 0].to(source.dtype))
