"""Automatic dynamic masks from what GeCo already computes: :class:`MotionMasks` (``"auto"``).

Training-free. Depth and cameras turn each flow correspondence into a 3-D to 3-D match: the
source pixel's world point and the world point its flow lands on in the target. On a static
scene both are the same point. Where they differ (the residual flow), two causes are possible:

- an object moving on its own: its matches are explained by one rigid motion of their own, a
  rotation and translation fitted with Kabsch inside RANSAC, up to a small residual;
- an inconsistency (a deformation, a surface that changes): no single rigid motion explains the
  region's matches, and the region stays in GeCo, which is what the metric is for.

For each frame, the pairs to its nearest frame before and after it are read
(:func:`nearest_pairs`: all ordered pairs would repeat the work ``n / 2`` times). Per pair, pixels
whose residual flow exceeds ``min_residual_px`` are grouped into connected regions; a region of
at least ``min_region_px`` pixels whose matches one rigid motion fits (a fraction
``min_inliers`` of them within ``rigid_tolerance``) is a mover, grown to the connected pixels
that the same motion explains better than the camera alone, and then to the pixels without a
match in the pair (leaving the image, hidden in the target) that continue its surfaces (no depth
step between neighbours). A mover masks its source pixels and, through the flow, the pixels its
matches land on in the target. Regions are unioned per frame
over pairs and dilated by ``dilation`` pixels. RANSAC draws from a seeded ``torch.Generator``, so
the masks are deterministic.

A non-rigid mover (a walking person, a waving flag, water) is several parts each moving its own
way, or none rigid: its limbs pass only where a part is large and rigid enough, the rest stays in
GeCo as if inconsistent. Name such subjects in text for a segmenter instead.
"""

from __future__ import annotations

from collections.abc import Sequence

import torch
import torch.nn.functional as F
from torch import Tensor

from ..geometry import (
    MIN_DEPTH,
    MIN_INLIERS,
    RANSAC_ITERATIONS,
    RIGID_TOLERANCE,
    inside_image,
    invert_rigid,
    pixel_grid,
    ransac_rigid,
    relative_pose,
    rigid_flow,
    sample_bilinear,
    transform_points,
    unproject,
)
from ..io.masks import connected_regions
from ..types import Correspondences, OptionError, SceneGeometry, is_integer, is_number

__all__ = ["MotionMasks", "depth_at", "dilate", "splat"]

#: Relative depth difference of two neighbouring pixels above which they lie on different surfaces
#: (an object's silhouette against what is behind it); a face seen at a grazing angle stays under it.
SURFACE_STEP = 0.1


def world_matches(geometry: SceneGeometry, flow: Tensor, source: int, target: int) -> tuple[Tensor, Tensor, Tensor]:
    """3-D matches of one pair: ``(X_src [H, W, 3], X_tgt [H, W, 3], valid [H, W])`` in world
    coordinates: each source pixel's point, and the target point at the pixel its ``flow
    [2, H, W]`` lands on (:func:`depth_at`)."""
    depth, K, extr = geometry.depth[0].double(), geometry.intrinsics[0].double(), geometry.extrinsics[0].double()
    height, width = depth.shape[-2:]
    to_world_src, to_world_tgt = invert_rigid(extr[source][None]), invert_rigid(extr[target][None])
    x_src = transform_points(unproject(depth[source][None], K[source][None]), to_world_src)[0]
    landing = pixel_grid(height, width, device=depth.device, dtype=depth.dtype) + flow.double().permute(1, 2, 0)
    depth_tgt = depth_at(depth[target], landing)
    x_tgt = transform_points(unproject_at(depth_tgt, landing, K[target])[None], to_world_tgt)[0]
    valid = (depth[source] > MIN_DEPTH) & (depth_tgt > MIN_DEPTH) & inside_image(landing, height, width)
    return x_src, x_tgt, valid


def depth_at(depth: Tensor, uv: Tensor, step: float = SURFACE_STEP) -> Tensor:
    """``depth [H, W]`` at positions ``uv [H, W, 2]``: the inverse depth interpolated bilinearly
    where the four pixels around a position lie on one surface (depths within ``step`` of each
    other; exact on a plane, so the matches of a face seen at a grazing angle keep the object's
    motion), the nearest pixel's depth across a silhouette (no blend of two surfaces)."""
    inverse = torch.where(depth > MIN_DEPTH, 1.0 / depth.clamp_min(MIN_DEPTH), torch.zeros_like(depth))
    smooth = sample_bilinear(inverse[None, None], uv[None])[0, 0]
    nearest = sample_bilinear(depth[None, None], uv.round()[None])[0, 0]
    padded = F.pad(depth[None, None], (0, 1, 0, 1), mode="replicate")
    highest, lowest = F.max_pool2d(padded, 2, stride=1), -F.max_pool2d(-padded, 2, stride=1)  # over each 2x2 block
    corner = uv.floor()[None]
    high, low = sample_bilinear(highest, corner)[0, 0], sample_bilinear(lowest, corner)[0, 0]
    one_surface = (low > MIN_DEPTH) & (high - low <= step * low)
    return torch.where(one_surface, 1.0 / smooth.clamp_min(1e-30), nearest)


def unproject_at(depth: Tensor, uv: Tensor, K: Tensor) -> Tensor:
    """Camera points ``[H, W, 3]`` of pixel positions ``uv [H, W, 2]`` at z-depth ``depth [H, W]``."""
    x = (uv[..., 0] - K[0, 2]) / K[0, 0]
    y = (uv[..., 1] - K[1, 2]) / K[1, 1]
    return torch.stack((x * depth, y * depth, depth), dim=-1)


def dilate(mask: Tensor, pixels: int) -> Tensor:
    """``mask [..., H, W]`` bool grown by ``pixels`` (square neighbourhood)."""
    if pixels <= 0:
        return mask
    flat = mask.reshape(-1, 1, *mask.shape[-2:]).float()
    return (F.max_pool2d(flat, 2 * pixels + 1, stride=1, padding=pixels) > 0).reshape(mask.shape)


class MotionMasks:
    """Automatic dynamic masks (a :class:`~geco_guide.types.DynamicMaskSource`): regions whose
    residual flow a rigid motion of their own explains.

    Args:
        min_residual_px: residual flow (measured minus camera-induced, in pixels) above which a
            pixel may belong to a mover; estimator noise must stay below it.
        min_region_px: smallest region (pixels) tested for a rigid motion of its own.
        rigid_tolerance: a match fits a rigid motion when its 3-D error is at most this fraction
            of its 3-D displacement (the motion explains the object's own motion to within it).
        min_inliers: fraction of a region's matches the fitted motion must explain.
        dilation: pixels by which the final masks grow (real estimators blur object edges).
        covisibility_threshold: matches count where the flow estimator's covisibility exceeds it.
        iterations: RANSAC hypotheses per region.
        seed: seeds the RANSAC draws.
    """

    source_name = "auto"

    def __init__(self, *, min_residual_px: float = 1.0, min_region_px: int = 16, rigid_tolerance: float = RIGID_TOLERANCE,
                 min_inliers: float = MIN_INLIERS, dilation: int = 0, covisibility_threshold: float = 0.5,
                 iterations: int = RANSAC_ITERATIONS, seed: int = 0) -> None:
        numbers = {"min_residual_px": min_residual_px, "rigid_tolerance": rigid_tolerance, "min_inliers": min_inliers,
                   "covisibility_threshold": covisibility_threshold}
        integers = {"min_region_px": min_region_px, "dilation": dilation, "iterations": iterations, "seed": seed}
        for key, value in numbers.items():
            if not is_number(value):
                raise OptionError(key, f"must be a number, got {value!r}")
        for key, value in integers.items():  # 1.5 RANSAC iterations would be truncated to 1, silently
            if not is_integer(value):
                raise OptionError(key, f"must be an integer, got {value!r}")
        checks = {
            "min_residual_px": (min_residual_px, min_residual_px > 0, "> 0"),
            "min_region_px": (min_region_px, min_region_px >= 3, ">= 3"),
            "rigid_tolerance": (rigid_tolerance, rigid_tolerance > 0, "> 0"),
            "min_inliers": (min_inliers, 0 < min_inliers <= 1, "in (0, 1]"),
            "dilation": (dilation, dilation >= 0, ">= 0"),
            "covisibility_threshold": (covisibility_threshold, 0 <= covisibility_threshold < 1, "in [0, 1)"),
            "iterations": (iterations, iterations >= 1, ">= 1"),
        }
        for key, (value, ok, wanted) in checks.items():
            if not ok:  # NaN fails every comparison
                raise OptionError(key, f"must be {wanted}, got {value!r}")
        self.min_residual_px = float(min_residual_px)
        self.min_region_px = int(min_region_px)
        self.rigid_tolerance = float(rigid_tolerance)
        self.min_inliers = float(min_inliers)
        self.dilation = int(dilation)
        self.covisibility_threshold = float(covisibility_threshold)
        self.iterations = int(iterations)
        self.seed = int(seed)

    def dynamic_masks(self, frames: Tensor, geometry: SceneGeometry | None = None,
                      flow: Correspondences | None = None,
                      pairs: Sequence[tuple[int, int]] | None = None) -> Tensor:
        """``frames [S, 3, H, W]`` with GeCo's ``geometry`` (batch 1) and ``flow`` (``[P, 2, H, W]``
        for ``pairs``) -> ``[S, H, W]`` bool masks of the movers."""
        if geometry is None or flow is None or pairs is None:
            raise ValueError("automatic dynamic masks need GeCo's geometry, flow and pairs (score through GeCoLoss or evaluate_video)")
        num_frames, _, height, width = frames.shape
        masks = torch.zeros(num_frames, height, width, dtype=torch.bool, device=frames.device)
        generator = torch.Generator().manual_seed(self.seed)
        for p in nearest_pairs(pairs):
            i, j = pairs[p]
            movers, continued = self.pair_movers(geometry, flow.flow[p], flow.covisibility[p], i, j, generator)
            masks[i] |= continued.to(masks.device)
            masks[j] |= splat(movers, flow.flow[p]).to(masks.device)  # the unmatched pixels land nowhere known
        return dilate(masks, self.dilation)

    def pair_movers(self, geometry: SceneGeometry, flow: Tensor, covisibility: Tensor, source: int, target: int,
                    generator: torch.Generator) -> tuple[Tensor, Tensor]:
        """``([H, W], [H, W])`` bool: the source pixels of the pair whose matches move rigidly on
        their own, and those with the unmatched pixels that continue their surfaces
        (:func:`continue_surface`)."""
        depth, K, extr = geometry.depth[0].double(), geometry.intrinsics[0].double(), geometry.extrinsics[0].double()
        flow = torch.where(torch.isfinite(flow), flow, torch.zeros_like(flow)).double().cpu()
        rel = relative_pose(extr[source][None], extr[target][None])
        camera_flow, camera_valid = rigid_flow(depth[source][None], K[source][None], K[target][None], rel)
        camera_flow, camera_valid = camera_flow[0].cpu(), camera_valid[0].cpu()
        x_src, x_tgt, valid = (t.cpu() for t in world_matches(geometry, flow, source, target))
        valid = valid & camera_valid & (covisibility.cpu() > self.covisibility_threshold)
        residual = (flow - camera_flow).norm(dim=0)
        candidates = valid & (residual > self.min_residual_px)
        movers, continued = torch.zeros_like(candidates), torch.zeros_like(candidates)
        if int(candidates.sum()) < self.min_region_px:
            return movers, continued
        labels = connected_regions(candidates)
        ids, counts = labels[candidates].unique(return_counts=True)
        static_error = (x_tgt - x_src).norm(dim=-1)
        for region in ids[counts >= self.min_region_px].tolist():
            inside = labels == region
            motion = self.fit_rigid(x_src[inside], x_tgt[inside], generator)
            if motion is None:
                continue
            # Grow within the region's box enlarged by half its size each way: the labelling's
            # cost follows the box, not the frame.
            rows, cols = inside.any(1).nonzero()[:, 0], inside.any(0).nonzero()[:, 0]
            pad_v, pad_u = (int(rows[-1] - rows[0]) + 2) // 2, (int(cols[-1] - cols[0]) + 2) // 2
            box = (slice(max(0, int(rows[0]) - pad_v), int(rows[-1]) + 1 + pad_v),
                   slice(max(0, int(cols[0]) - pad_u), int(cols[-1]) + 1 + pad_u))
            rotation, translation = motion
            error = (x_src[box] @ rotation.T + translation - x_tgt[box]).norm(dim=-1)
            explained = valid[box] & (error <= self.rigid_tolerance * static_error[box]) & (error < static_error[box])
            seed = inside[box]
            grown = connected_regions(explained | seed)
            grown = torch.isin(grown, grown[seed].unique()) & (explained | seed)
            movers[box] |= grown
            continued[box] |= continue_surface(grown, ~valid[box], depth[source][box].cpu())
        return movers, continued

    def fit_rigid(self, source: Tensor, target: Tensor, generator: torch.Generator) -> tuple[Tensor, Tensor] | None:
        """RANSAC + Kabsch on matches ``[N, 3]`` (:func:`~geco_guide.geometry.ransac_rigid`): the
        rigid motion explaining at least ``min_inliers`` of them (error <= ``rigid_tolerance`` of
        each match's displacement), refitted on its inliers; ``None`` when no hypothesis does."""
        limit = self.rigid_tolerance * (target - source).norm(dim=-1)
        rotation, translation, refit, sampled = ransac_rigid(source, target, limit, self.iterations, generator)
        if sampled < self.min_inliers:
            return None
        return (rotation, translation) if float(refit.float().mean()) >= self.min_inliers else None


def continue_surface(mover: Tensor, unmatched: Tensor, depth: Tensor, step: float = SURFACE_STEP) -> Tensor:
    """``mover [H, W]`` bool grown into the ``unmatched [H, W]`` pixels (no match in the pair: their
    landing leaves the image or is hidden) that continue its surfaces: reached from it through
    8-neighbours whose ``depth [H, W]`` differs by at most ``step`` of theirs.

    Such pixels of a mover carry no evidence of its motion in this pair (at the frame's border as
    it leaves the view, on a face that turns away), and in the first and last frame no other pair
    reads them: left unmasked, GeCo scores them against the camera's motion."""
    grown = mover.clone()
    height, width = mover.shape
    padded_depth = F.pad(depth[None, None], (1, 1, 1, 1), value=float("nan"))[0, 0]
    while True:
        frontier = unmatched & ~grown & dilate(grown, 1)
        if not bool(frontier.any()):
            return grown
        padded = F.pad(grown[None, None].float(), (1, 1, 1, 1))[0, 0] > 0
        reached = torch.zeros_like(grown)
        for dv in (0, 1, 2):
            for du in (0, 1, 2):
                near = padded[dv:dv + height, du:du + width]
                close = (padded_depth[dv:dv + height, du:du + width] - depth).abs() <= step * depth
                reached |= near & close
        added = frontier & reached
        if not bool(added.any()):
            return grown
        grown |= added


def nearest_pairs(pairs: Sequence[tuple[int, int]]) -> list[int]:
    """Indices of the pairs the detector reads: for each source frame, the first pair to its
    nearest target before it and after it. All ordered pairs of ``n`` frames (``n(n-1)``) come
    down to at most ``2n``; adjacent pairs stay as they are."""
    chosen: dict[tuple[int, bool], tuple[int, int]] = {}
    for p, (i, j) in enumerate(pairs):
        key = (i, j > i)
        if key not in chosen or abs(j - i) < chosen[key][0]:
            chosen[key] = (abs(j - i), p)
    return sorted(p for _, p in chosen.values())


def splat(mask: Tensor, flow: Tensor) -> Tensor:
    """``mask [H, W]`` carried along ``flow [2, H, W]`` (source -> target) to the target pixels
    its pixels land on (their 2x2 neighbours, so no holes open between landings)."""
    height, width = mask.shape
    out = torch.zeros(height * width, dtype=torch.bool)
    if not bool(mask.any()):
        return out.reshape(height, width)
    landing = pixel_grid(height, width, dtype=torch.float64)[mask.cpu()] + flow.detach().double().cpu().permute(1, 2, 0)[mask.cpu()]
    base = landing.floor().long()
    for du in (0, 1):
        for dv in (0, 1):
            u, v = base[:, 0] + du, base[:, 1] + dv
            keep = (u >= 0) & (u < width) & (v >= 0) & (v < height)
            out[(v * width + u)[keep]] = True
    return out.reshape(height, width)
