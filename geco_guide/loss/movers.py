"""Movers scored against their own rigid motion (``GeCoLossConfig.movers = "rigid"``).

With dynamic masks GeCo leaves moving content out (``movers = "drop"``, the default). With
``"rigid"`` it scores a mover for its own rigidity instead, as static pixels are scored for the
camera's:

1. **Movers.** Each frame's mask splits into 8-connected regions; a region's pixels carried by the
   flow onto a region of another frame (most of those that land on a mask) join it, so one mover
   is one object through the clip (:func:`link_movers`).
2. **Rigid fit** (:func:`fit_movers`, detached, on the CPU in float64). Per frame pair and mover,
   depth and cameras turn each flow correspondence into a 3-D match (the source pixel's world
   point and the world point at the target pixel its flow lands on, the target's inverse depth
   sampled bilinearly, so matches on a plane are exact); RANSAC + Kabsch fits one rigid motion. A
   match fits when its 3-D error is at most ``rigid_tolerance`` of its own 3-D displacement, or
   within :data:`FLOOR_PX` pixels at its depth (a mover that stands still fits the identity).
   A mover is **rigid** when its fits explain at least ``min_inliers`` of its matches over all its
   pairs; else it is **non-rigid** and its pixels stay masked, as with ``"drop"``.
3. **Scoring.** In a pair, each pixel of a rigid mover gets the motion cue against the flow that the
   camera and the mover's motion together predict, and the structure cue by reprojection with the
   mover's pose (the source-to-target transform ``E_j M E_i^-1`` with the fitted world motion
   ``M``), normalised as the static cues are and fused into the same map. A masked pixel that the
   camera explains better than its mover's motion (background inside a generous mask) is scored
   as static. A mover pixel's structure counts only where its reprojection lands wholly on the
   same mover in the target; static pixels landing on any mover are left out, as with ``"drop"``.

Detached fit, live gradient: the fit (:class:`MoverFit`: which pixels belong to which mover,
which matches its motion is solved on, the verdicts) carries no gradient, and the motions are
re-solved from it by a weighted Kabsch at every call, detached, from the call's own geometry and
flow (:func:`solve_motions`: closed form, no RANSAC, no host synchronisation). The gradient flows
through the frames into the movers' residuals (flow, depth and cameras), as for the static part.
A caller that refreshes the fit on its own rule (the guidance's mask refresh) holds a
:class:`RefreshedMovers`, or passes the :class:`MoverFit` of an earlier result back.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, field, replace
from typing import Any

import torch
from torch import Tensor

from ..geometry import (
    MIN_DEPTH,
    MIN_INLIERS,
    RANSAC_ITERATIONS,
    RIGID_TOLERANCE,
    homogeneous_pose,
    inside_image,
    invert_rigid,
    kabsch_from_moments,
    pixel_grid,
    project,
    ransac_rigid,
)
from ..io.masks import connected_regions
from ..types import Correspondences, SceneGeometry
from .cues import MASK_TOUCH_WEIGHT
from .modes import MOVER_MODES

__all__ = ["FLOOR_PX", "MIN_MATCHES", "MOVER_MODES", "TARGET_MARGIN", "MoverFit", "MoverScores", "RefreshedMovers", "fit_movers",
           "link_movers", "mover_scores", "point_matches", "solve_motions"]


#: Fewest valid matches a mover needs in a pair for a rigid fit there (fewer: left out in that pair).
MIN_MATCHES = 16

#: A match fits a motion whenever its 3-D error is within this many pixels at its depth, however
#: little it moves (a masked object standing still fits the identity).
FLOOR_PX = 0.5

#: Matches whose error exceeds this multiple of the inliers' median error are left out of the
#: motion that scores the mover: it is solved on the matches that fit best, so a deformation on
#: part of a mover biases it as little as possible.
TIGHT_MEDIANS = 3.0


@dataclass
class MoverFit:
    """What a refresh of the movers decides, detached: ``B`` clips, ``S`` frames, ``P`` pairs,
    ``K`` movers (the most of any clip).

    Attributes:
        labels: ``[B, S, H, W]`` int64, the mover (1..K) each masked pixel belongs to; 0 unmasked.
        assignment: ``[B, P, H, W]`` int64, per pair the motion that scores each source pixel: 0 the
            camera's (unmasked pixels, and masked ones the camera explains better), ``k`` mover
            ``k``'s, -1 none (left out: a non-rigid mover, or a pair its fit failed in).
        rigid: ``[B, K]`` bool, the verdict.
        inlier_fraction: ``[B, K]`` float64, the share of the mover's matches its fits explain over
            all its pairs (NaN: no pair held enough matches for a fit).
        pairs: the ``(source, target)`` pairs.
        entries: the ``(clip, pair, mover)`` triples a rigid motion scores.
        boxes: per entry, ``(top, bottom, left, right)`` of the source pixels it scores (the cues
            of a mover are computed in its box alone).
        target_boxes: per entry, the box of the mover in the target frame grown by
            :data:`TARGET_MARGIN` pixels (its structure cue samples the target there alone), or
            ``None`` where the target does not show it.
        solve_pixels: ``[M]`` int64, flat indices into ``[B*P, H, W]``: the matches the entries'
            motions are solved on (each fit's best inliers).
        solve_entry: ``[M]`` int64, the entry each of them belongs to.
    """

    labels: Tensor
    assignment: Tensor
    rigid: Tensor
    inlier_fraction: Tensor
    pairs: list[tuple[int, int]]
    entries: list[tuple[int, int, int]]
    boxes: list[tuple[int, int, int, int]]
    target_boxes: list[tuple[int, int, int, int] | None]
    solve_pixels: Tensor
    solve_entry: Tensor

    @property
    def num_movers(self) -> int:
        return self.rigid.shape[1]

    def fits(self, masks: Tensor, pairs: Sequence[tuple[int, int]]) -> bool:
        """Whether this fit can score clips of these masks ``[B, S, H, W]`` and pairs (no host sync)."""
        return tuple(self.labels.shape) == tuple(masks.shape) and list(pairs) == self.pairs

    def to(self, device: torch.device | str) -> MoverFit:
        """This fit with its maps on ``device`` (itself when they are there)."""
        if self.labels.device == torch.device(device):
            return self
        return replace(self, labels=self.labels.to(device), assignment=self.assignment.to(device),
                       solve_pixels=self.solve_pixels.to(device), solve_entry=self.solve_entry.to(device))


def link_movers(masks: Tensor, flow: Tensor, pairs: Sequence[tuple[int, int]]) -> Tensor:
    """One clip's movers: ``masks [S, H, W]`` bool and ``flow [P, 2, H, W]`` for ``pairs`` ->
    labels ``[S, H, W]`` int64 (1..K, 0 unmasked).

    Each frame's mask splits into 8-connected regions; a region joins the region of another frame
    on which most of its pixels that land on a mask (nearest pixel, along the flow) land, when
    they are at least half of those that land inside the image.
    """
    num_frames, height, width = masks.shape
    masks = masks.cpu()
    regions = torch.zeros(num_frames, height, width, dtype=torch.int64)
    count = 0
    for s in range(num_frames):
        if not bool(masks[s].any()):
            continue
        top, bottom, left, right = _box(masks[s], 0)
        box = (slice(top, bottom), slice(left, right))  # the labelling's cost follows the box
        raw = connected_regions(masks[s][box])
        ids, compact = raw[masks[s][box]].unique(return_inverse=True)
        regions[s][box][masks[s][box]] = compact + 1 + count
        count += len(ids)
    parent = list(range(count + 1))

    def root(node: int) -> int:
        while parent[node] != node:
            parent[node] = parent[parent[node]]
            node = parent[node]
        return node

    grid = pixel_grid(height, width, dtype=torch.float64)
    for p, (i, j) in enumerate(pairs):
        if not bool(masks[i].any()):
            continue
        landing = (grid + flow[p].detach().double().cpu().permute(1, 2, 0)).round()
        inside = inside_image(landing, height, width) & torch.isfinite(landing).all(-1) & masks[i]
        u = landing[..., 0].nan_to_num(0).long().clamp(0, width - 1)
        v = landing[..., 1].nan_to_num(0).long().clamp(0, height - 1)
        source, target = regions[i][inside], regions[j][v, u][inside]
        landed = torch.bincount(source, minlength=count + 1)
        on_mask = target > 0
        keys, hits = torch.unique(source[on_mask] * (count + 1) + target[on_mask], return_counts=True)
        best: dict[int, tuple[int, int]] = {}
        for key, hit in zip(keys.tolist(), hits.tolist()):
            a, b = divmod(key, count + 1)
            if hit > best.get(a, (0, 0))[0]:
                best[a] = (hit, b)
        for a, (hit, b) in best.items():
            if 2 * hit >= int(landed[a]):
                parent[root(a)] = root(b)
    roots = torch.tensor([root(n) for n in range(count + 1)])
    _, movers = roots[1:].unique(return_inverse=True)
    lookup = torch.cat((torch.zeros(1, dtype=torch.int64), movers + 1))
    return lookup[regions]


def point_matches(depth_src: Tensor, depth_tgt: Tensor, K_src: Tensor, K_tgt: Tensor, extr_src: Tensor, extr_tgt: Tensor,
                  flow: Tensor, pixels: Tensor) -> tuple[Tensor, Tensor, Tensor]:
    """3-D matches of some source pixels of pairs, in world coordinates.

    Args:
        depth_src, depth_tgt: ``[N, H, W]``; K_src, K_tgt: ``[N, 3, 3]``; extr_src, extr_tgt:
            ``[N, 3, 4]`` camera-from-world; flow: ``[N, 2, H, W]``: ``N`` pairs.
        pixels: ``[M]`` flat indices into ``[N, H, W]``: the source pixels.

    Returns:
        ``(X_src [M, 3], X_tgt [M, 3], valid [M])``: each pixel's world point, and the world point
        at the target pixel its flow lands on, the target's inverse depth sampled bilinearly there
        (exact on a plane); valid where both depths are positive and the landing is in the image.
    """
    height, width = depth_src.shape[-2:]
    pair, rest = pixels // (height * width), pixels % (height * width)
    row, col = (rest // width).to(depth_src.dtype), (rest % width).to(depth_src.dtype)
    depth = depth_src.flatten()[pixels]
    u = col + flow[:, 0].flatten()[pixels]
    v = row + flow[:, 1].flatten()[pixels]
    inverse = torch.where(depth_tgt > MIN_DEPTH, 1.0 / depth_tgt.clamp_min(MIN_DEPTH), torch.zeros_like(depth_tgt))
    inverse_at = _bilinear_at(inverse, pair, u, v)
    valid = (depth > MIN_DEPTH) & (inverse_at > 0) & inside_image(torch.stack((u, v), -1), height, width)
    depth_at = torch.where(valid, 1.0 / inverse_at.clamp_min(1e-30), torch.ones_like(inverse_at))
    x_src = _to_world(torch.stack((col, row), -1), depth, torch.linalg.inv(K_src)[pair], invert_rigid(extr_src)[pair])
    x_tgt = _to_world(torch.stack((u, v), -1), depth_at, torch.linalg.inv(K_tgt)[pair], invert_rigid(extr_tgt)[pair])
    return x_src, x_tgt, valid


def _bilinear_at(maps: Tensor, index: Tensor, u: Tensor, v: Tensor) -> Tensor:
    """``maps [N, H, W]`` sampled bilinearly at ``(u, v) [M]`` of map ``index [M]`` (clamped to the
    image; callers test the image bounds themselves)."""
    height, width = maps.shape[-2:]
    u = u.nan_to_num(0.0).clamp(0, width - 1)
    v = v.nan_to_num(0.0).clamp(0, height - 1)
    u0, v0 = u.floor().long().clamp(max=width - 2 if width > 1 else 0), v.floor().long().clamp(max=height - 2 if height > 1 else 0)
    fu, fv = u - u0, v - v0
    flat = maps.flatten()
    base = index * height * width

    def tap(dv: int, du: int) -> Tensor:
        return flat[base + (v0 + dv).clamp(max=height - 1) * width + (u0 + du).clamp(max=width - 1)]

    return (tap(0, 0) * (1 - fu) * (1 - fv) + tap(0, 1) * fu * (1 - fv) + tap(1, 0) * (1 - fu) * fv + tap(1, 1) * fu * fv)


def _to_world(uv: Tensor, depth: Tensor, K_inverse: Tensor, to_world: Tensor) -> Tensor:
    """World points ``[M, 3]`` of pixel positions ``uv [M, 2]`` at z-depth ``depth [M]`` seen by
    cameras of inverse intrinsics ``K_inverse [M, 3, 3]`` and world-from-camera ``to_world [M, 4, 4]``."""
    rays = torch.cat((uv, torch.ones_like(uv[:, :1])), dim=-1)
    camera = (K_inverse @ rays[:, :, None])[:, :, 0] * depth[:, None]
    return (to_world[:, :3, :3] @ camera[:, :, None])[:, :, 0] + to_world[:, :3, 3]


def _to_pixels(points: Tensor, K: Tensor, extrinsics: Tensor) -> Tensor:
    """Pixel positions ``[M, 2]`` of world ``points [M, 3]`` in cameras ``K [M, 3, 3]``,
    ``extrinsics [M, 3, 4]``."""
    camera = (extrinsics[:, :3, :3] @ points[:, :, None])[:, :, 0] + extrinsics[:, :3, 3]
    uv, _ = project(camera[:, None], K)
    return uv[:, 0]


#: Pixels by which a mover's box in the target frame grows: a bilinear sample's taps and the 3x3
#: depth-edge test around a landing point stay inside it.
TARGET_MARGIN = 2


def _box(mask: Tensor, margin: int) -> tuple[int, int, int, int] | None:
    """``(top, bottom, left, right)`` of ``mask [H, W]`` grown by ``margin`` (clipped), ``None`` if empty."""
    if not bool(mask.any()):
        return None
    rows, cols = mask.any(1).nonzero()[:, 0], mask.any(0).nonzero()[:, 0]
    height, width = mask.shape
    return (max(0, int(rows[0]) - margin), min(height, int(rows[-1]) + 1 + margin),
            max(0, int(cols[0]) - margin), min(width, int(cols[-1]) + 1 + margin))


def _floor(depth: Tensor, K: Tensor) -> Tensor:
    """``[M]`` the 3-D length of :data:`FLOOR_PX` pixels at depths ``depth [M]`` for ``K [M, 3, 3]``."""
    return FLOOR_PX * depth / (0.5 * (K[:, 0, 0] + K[:, 1, 1]))


@dataclass
class _FitRule:
    """How the movers' rigid motions are fitted: RANSAC's ``rigid_tolerance``, ``min_inliers`` and
    ``iterations`` (:func:`~geco_guide.geometry.ransac_rigid`), drawing from ``generator``."""

    rigid_tolerance: float
    min_inliers: float
    iterations: int
    generator: torch.Generator


@dataclass
class _Clip:
    """One clip's inputs to the fit, detached on the CPU: its ``index`` in the batch, ``flow [P, 2,
    H, W]`` (float64, non-finite values 0), ``covisible [P, H, W]``, ``masks [S, H, W]``, its
    movers' ``labels [S, H, W]`` (:func:`link_movers`) and ``depth [S, H, W]``, ``K [S, 3, 3]``,
    ``extrinsics [S, 3, 4]`` in float64."""

    index: int
    flow: Tensor
    covisible: Tensor
    masks: Tensor
    labels: Tensor
    depth: Tensor
    K: Tensor
    extrinsics: Tensor


@dataclass
class _Matches:
    """The masked source pixels of every pair of a clip, ``N`` of them, and their 3-D matches:
    ``pixels`` (flat over ``[P, H, W]``), ``pair``, ``grid [N, 2]`` (x, y), ``flow [N, 2]``,
    ``x_src`` / ``x_tgt [N, 3]``, ``valid`` (a covisible match landing wholly on a mask), ``limit``
    (the inlier distance), ``camera_flow [N, 2]`` (the flow the camera's motion alone gives) and
    ``mover`` (each pixel's mover)."""

    pixels: Tensor
    pair: Tensor
    grid: Tensor
    flow: Tensor
    x_src: Tensor
    x_tgt: Tensor
    valid: Tensor
    limit: Tensor
    camera_flow: Tensor
    mover: Tensor


@dataclass
class _Solved:
    """What the rigid movers leave to :func:`solve_motions`, clip after clip: the ``entries`` ``(b,
    p, k)``, their source ``boxes`` and ``target_boxes``, the ``pixels`` each is solved on (flat
    over ``[B, P, H, W]``) and the ``entry`` of each of those pixels."""

    entries: list[tuple[int, int, int]] = field(default_factory=list)
    boxes: list[tuple[int, int, int, int]] = field(default_factory=list)
    target_boxes: list[tuple[int, int, int, int] | None] = field(default_factory=list)
    pixels: list[Tensor] = field(default_factory=list)
    entry: list[Tensor] = field(default_factory=list)


def fit_movers(masks: Tensor, geometry: SceneGeometry, correspondences: Correspondences, pairs: Sequence[tuple[int, int]],
               *, covisibility_threshold: float = 0.5, rigid_tolerance: float = RIGID_TOLERANCE,
               min_inliers: float = MIN_INLIERS, iterations: int = RANSAC_ITERATIONS, seed: int = 0) -> MoverFit:
    """The movers of ``masks [B, S, H, W]`` and their rigid fits (see the module docstring).

    Args:
        masks: the dynamic masks.
        geometry: ``B`` clips' depth, intrinsics and extrinsics (finite).
        correspondences: flow ``[B*P, 2, H, W]`` and covisibility ``[B*P, H, W]``, batch-major.
        pairs: the ``P`` pairs.
        covisibility_threshold: matches count where the covisibility exceeds it.
        rigid_tolerance, min_inliers, iterations: the fit's thresholds
            (:func:`~geco_guide.geometry.ransac_rigid`); seed: seeds RANSAC (deterministic).

    Returns:
        :class:`MoverFit` (on the masks' device), computed without gradient.
    """
    pairs = list(pairs)
    rule = _FitRule(rigid_tolerance, min_inliers, iterations, torch.Generator().manual_seed(seed))
    solved = _Solved()
    with torch.no_grad():  # the clips in order: RANSAC draws from one generator
        clips = [_fit_clip(_clip_inputs(b, masks, geometry, correspondences, pairs, covisibility_threshold), pairs,
                           rule, solved) for b in range(masks.shape[0])]
    labels, assignments, verdicts, fractions = zip(*clips)
    width_k = max((len(v) for v in verdicts), default=0)

    def padded(rows: list[Tensor], fill: Any) -> Tensor:
        return torch.stack([torch.cat((r, torch.full((width_k - len(r),), fill, dtype=r.dtype))) for r in rows])

    def joined(parts: list[Tensor]) -> Tensor:
        return torch.cat(parts) if parts else torch.zeros(0, dtype=torch.int64)

    device = masks.device
    return MoverFit(labels=torch.stack(labels).to(device), assignment=torch.stack(assignments).to(device),
                    rigid=padded(verdicts, False), inlier_fraction=padded(fractions, math.nan), pairs=pairs,
                    entries=solved.entries, boxes=solved.boxes, target_boxes=solved.target_boxes,
                    solve_pixels=joined(solved.pixels).to(device), solve_entry=joined(solved.entry).to(device))


def _clip_inputs(b: int, masks: Tensor, geometry: SceneGeometry, correspondences: Correspondences,
                 pairs: list[tuple[int, int]], covisibility_threshold: float) -> _Clip:
    """Clip ``b``'s inputs to the fit (:class:`_Clip`), its movers linked over its pairs."""
    num_pairs = len(pairs)
    part = slice(b * num_pairs, (b + 1) * num_pairs)
    flow = correspondences.flow[part].detach().double().cpu()
    flow = torch.where(torch.isfinite(flow), flow, torch.zeros_like(flow))
    covisible = correspondences.covisibility[part].detach().cpu() > covisibility_threshold
    clip_masks = masks[b].cpu()
    return _Clip(b, flow, covisible, clip_masks, link_movers(clip_masks, flow, pairs),
                 geometry.depth[b].detach().double().cpu(), geometry.intrinsics[b].detach().double().cpu(),
                 geometry.extrinsics[b].detach().double().cpu())


def _fit_clip(clip: _Clip, pairs: list[tuple[int, int]], rule: _FitRule,
              solved: _Solved) -> tuple[Tensor, Tensor, Tensor, Tensor]:
    """One clip's fit: its mover ``labels [S, H, W]``, the ``assignment [P, H, W]`` of its pairs'
    source pixels (-1 left out, 0 the camera, ``k`` mover ``k``), each mover's ``rigid`` verdict and
    inlier ``fraction`` ``[movers]``; its rigid movers' solves are added to ``solved``."""
    num_movers = int(clip.labels.max())
    assignment = torch.where(clip.masks[[i for i, _ in pairs]], -1, 0).long()
    matches = _matches(clip, pairs, rule.rigid_tolerance)
    if matches is None:  # no mover is any pair's source
        return (clip.labels, assignment, torch.zeros(num_movers, dtype=torch.bool),
                torch.full((num_movers,), math.nan, dtype=torch.float64))
    explained, matched, passed = _rigid_motions(clip, matches, pairs, num_movers, rule)
    fraction = torch.where(matched > 0, explained / matched.clamp_min(1), torch.full_like(matched, math.nan))[1:]
    rigid = (matched[1:] > 0) & (fraction >= rule.min_inliers)
    _assign_rigid(clip, [entry for entry in passed if bool(rigid[entry[1] - 1])], pairs, assignment, solved)
    return clip.labels, assignment, rigid, fraction


def _matches(clip: _Clip, pairs: list[tuple[int, int]], rigid_tolerance: float) -> _Matches | None:
    """The masked source pixels of the clip's pairs and their 3-D matches (:class:`_Matches`),
    ``None`` where no pair's source holds a mover."""
    src = [i for i, _ in pairs]
    tgt = [j for _, j in pairs]
    height, width = clip.masks.shape[-2:]
    depth, K, extr, flow = clip.depth, clip.K, clip.extrinsics, clip.flow
    source_labels = clip.labels[src]  # [P, H, W]
    pixels = (source_labels > 0).flatten().nonzero()[:, 0]  # the masked source pixels of every pair
    if len(pixels) == 0:
        return None
    pair = pixels // (height * width)
    x_src, x_tgt, valid = point_matches(depth[src], depth[tgt], K[src], K[tgt], extr[src], extr[tgt], flow, pixels)
    flow_px = torch.stack((flow[:, 0].flatten()[pixels], flow[:, 1].flatten()[pixels]), -1)
    rest = pixels % (height * width)
    grid = torch.stack((rest % width, rest // width), -1).double()
    landing = grid + flow_px
    # landing wholly on a mask (no tap off it, as lands_on_mask tests): no blend with the background
    on_mask = _bilinear_at(clip.masks[tgt].double(), pair, landing[:, 0], landing[:, 1]) >= 1.0 - MASK_TOUCH_WEIGHT
    valid &= clip.covisible.flatten()[pixels] & on_mask
    displacement = (x_tgt - x_src).norm(dim=-1)
    limit = torch.maximum(rigid_tolerance * displacement, _floor(depth[src].flatten()[pixels], K[src][pair]))
    camera_flow = _to_pixels(x_src, K[tgt][pair], extr[tgt][pair]) - grid
    return _Matches(pixels, pair, grid, flow_px, x_src, x_tgt, valid, limit, camera_flow,
                    source_labels.flatten()[pixels])


def _rigid_motions(clip: _Clip, m: _Matches, pairs: list[tuple[int, int]], num_movers: int,
                   rule: _FitRule) -> tuple[Tensor, Tensor, list[tuple[int, int, Tensor, Tensor, Tensor]]]:
    """Each mover's rigid motion in each pair (RANSAC over its valid matches): the inliers each
    mover's fits ``explained`` and the matches they ``matched`` (``[movers + 1]``, 0 unused), and
    per fit that passed ``(p, k, its pixels, whether the camera explains each better, the pixels
    it is solved on)``."""
    tgt = [j for _, j in pairs]
    explained = torch.zeros(num_movers + 1, dtype=torch.float64)
    matched = torch.zeros(num_movers + 1, dtype=torch.float64)
    passed = []
    for p in range(len(pairs)):
        for k in range(1, num_movers + 1):
            mine = (m.pair == p) & (m.mover == k)
            usable = m.valid & mine
            count = int(usable.sum())
            if count < MIN_MATCHES:
                continue
            rotation, translation, inliers, sampled = ransac_rigid(
                m.x_src[usable], m.x_tgt[usable], m.limit[usable], rule.iterations, rule.generator)
            explained[k] += float(inliers.sum())
            matched[k] += count
            if sampled < rule.min_inliers or float(inliers.float().mean()) < rule.min_inliers:
                continue
            moved = m.x_src[mine] @ rotation.T + translation
            error = (moved - m.x_tgt[mine]).norm(dim=-1)[usable[mine]]
            best = torch.zeros_like(usable)
            best[usable] = inliers & (error <= TIGHT_MEDIANS * error[inliers].median())
            # a masked pixel whose flow the camera explains better is background caught by the mask
            own_flow = _to_pixels(moved, clip.K[tgt[p]].expand(len(moved), 3, 3),
                                  clip.extrinsics[tgt[p]].expand(len(moved), 3, 4)) - m.grid[mine]
            camera = clip.covisible.flatten()[m.pixels[mine]] & (
                (m.flow[mine] - m.camera_flow[mine]).norm(dim=-1) < (m.flow[mine] - own_flow).norm(dim=-1))
            passed.append((p, k, m.pixels[mine], camera, m.pixels[best]))
    return explained, matched, passed


def _assign_rigid(clip: _Clip, fits: list[tuple[int, int, Tensor, Tensor, Tensor]], pairs: list[tuple[int, int]],
                  assignment: Tensor, solved: _Solved) -> None:
    """Give the pixels of the rigid movers' ``fits`` to them in ``assignment`` (those the camera
    explains better to the camera) and add each fit with pixels of its own to ``solved``."""
    num_pairs = len(pairs)
    height, width = clip.masks.shape[-2:]
    flat_assignment = assignment.flatten()
    for p, k, mine, camera, solved_on in fits:
        own = mine[~camera]
        flat_assignment[own] = k
        flat_assignment[mine[camera]] = 0
        if len(own) == 0 or len(solved_on) < 3:
            continue  # the camera scores all its pixels
        rows, cols = (own % (height * width)) // width, own % width
        solved.boxes.append((int(rows.min()), int(rows.max()) + 1, int(cols.min()), int(cols.max()) + 1))
        solved.target_boxes.append(_box(clip.labels[pairs[p][1]] == k, TARGET_MARGIN))
        solved.pixels.append(solved_on + clip.index * num_pairs * height * width)
        solved.entry.append(torch.full((len(solved_on),), len(solved.entries)))
        solved.entries.append((clip.index, p, k))


def solve_motions(fit: MoverFit, depth_src: Tensor, depth_tgt: Tensor, K_src: Tensor, K_tgt: Tensor, extr_src: Tensor,
                  extr_tgt: Tensor, flow: Tensor) -> Tensor:
    """The world motions ``[E, 4, 4]`` of ``fit.entries``, solved detached by a weighted Kabsch on
    the fit's best matches of each, from this call's pairs (all ``[B*P, ...]``, as
    :func:`point_matches` takes them). No host synchronisation: the matches are fixed by the fit
    and their moments summed with one ``index_add``."""
    with torch.no_grad():
        args = [t.detach().double() for t in (depth_src, depth_tgt, K_src, K_tgt, extr_src, extr_tgt, flow)]
        s, t, valid = point_matches(*args, fit.solve_pixels)
        w = valid.double()[:, None]
        values = torch.cat((w, w * s, w * t, (w[:, :, None] * s[:, :, None] * t[:, None, :]).flatten(1)), dim=1)
        moments = torch.zeros(len(fit.entries), values.shape[1], dtype=values.dtype, device=values.device)
        moments.index_add_(0, fit.solve_entry, values)
        total = moments[:, :1].clamp_min(1e-12)
        mean_s, mean_t = moments[:, 1:4] / total, moments[:, 4:7] / total
        covariance = moments[:, 7:].reshape(-1, 3, 3) / total[..., None] - mean_s[:, :, None] * mean_t[:, None, :]
        rotation, translation = kabsch_from_moments(mean_s, mean_t, covariance)
        motion = homogeneous_pose(torch.cat((rotation, translation[..., None]), dim=-1))
        # no match left (this call's geometry invalidated them all): the world motion of the camera's, none
        lost = moments[:, 0] < 3
        return torch.where(lost[:, None, None], torch.eye(4, dtype=motion.dtype, device=motion.device), motion)


@dataclass
class MoverScores:
    """Per mover, what GeCo found (tensors; :meth:`records` turns one clip's into dicts).

    Attributes:
        fit: the :class:`MoverFit` scored (pass it back to score later frames with the same fit).
        pixels: ``[B, K]`` pixels labelled as the mover, over all frames.
        frames: ``[B, K, S]`` bool, the frames it is seen in.
        residual: ``[B, K]`` mean fused map over its valid pixels (NaN: none valid, e.g. non-rigid).
        contribution: ``[B, K]`` its part of the fused scalar: the fused scalar is the static
            part's plus every mover's.
        share: ``[B, K]`` contribution over the fused scalar.
        dropped: ``[B, S, H, W]`` bool, masked pixels left out (the non-rigid movers').
    """

    fit: MoverFit
    pixels: Tensor
    frames: Tensor
    residual: Tensor
    contribution: Tensor
    share: Tensor
    dropped: Tensor

    def records(self, clip: int = 0, frame_ids: Sequence[int] | None = None) -> list[dict[str, Any]]:
        """Clip ``clip``'s movers as JSON-ready dicts ``{id, frames, pixels, inlier_fraction,
        residual, verdict, share}`` (``frames`` named by ``frame_ids``, default their index; NaN
        -> None)."""
        def number(x: Tensor) -> float | None:
            value = float(x)
            return value if math.isfinite(value) else None

        out = []
        for k in range(self.fit.num_movers):
            seen = self.frames[clip, k].nonzero()[:, 0].tolist()
            if not seen:
                continue  # padding of a clip with fewer movers
            out.append({"id": k + 1, "frames": [frame_ids[s] if frame_ids is not None else s for s in seen],
                        "pixels": int(self.pixels[clip, k]), "inlier_fraction": number(self.fit.inlier_fraction[clip, k]),
                        "residual": number(self.residual[clip, k]),
                        "verdict": "rigid" if bool(self.fit.rigid[clip, k]) else "non-rigid",
                        "share": number(self.share[clip, k])})
        return out


def mover_scores(fit: MoverFit, fused: Tensor, fused_valid: Tensor, frame_counts: Tensor, scalar: Tensor) -> MoverScores:
    """The per-mover numbers of a scored clip batch.

    Args:
        fit: the movers' fit.
        fused, fused_valid: ``[B, S, H, W]`` the fused frame maps and their validity.
        frame_counts: ``[B, S]`` bool, the frames that count in the scalar.
        scalar: the fused scalar (mean of the counted frames' scores).
    """
    bins = fit.num_movers + 1
    labels = fit.labels.flatten(2)  # [B, S, HW]
    valid = fused_valid.flatten(2)
    values = torch.where(valid, fused.detach().flatten(2), torch.zeros_like(fused.flatten(2)))
    zeros = torch.zeros(*labels.shape[:2], bins, dtype=values.dtype, device=values.device)
    sums = zeros.scatter_add(2, labels, values)[..., 1:]  # [B, S, K]
    counts = zeros.scatter_add(2, labels, valid.to(values.dtype))[..., 1:]
    pixels = zeros.scatter_add(2, labels, torch.ones_like(values))[..., 1:]
    per_frame = valid.to(values.dtype).sum(-1).clamp_min(1.0)  # [B, S]
    counted = frame_counts.to(values.dtype)
    frames_counted = counted.sum().clamp_min(1.0)
    residual = sums.sum(1) / counts.sum(1).where(counts.sum(1) > 0, torch.full_like(counts.sum(1), math.nan))
    contribution = (sums / per_frame[..., None] * counted[..., None]).sum(1) / frames_counted
    share = contribution / scalar.detach().to(contribution.dtype)
    rigid_ids = torch.cat((torch.ones(fit.rigid.shape[0], 1, dtype=torch.bool), fit.rigid), dim=1).to(fit.labels.device)
    dropped = ~torch.gather(rigid_ids, 1, fit.labels.flatten(1)).reshape(fit.labels.shape)
    return MoverScores(fit=fit, pixels=pixels.sum(1), frames=(pixels > 0).permute(0, 2, 1), residual=residual,
                       contribution=contribution, share=share, dropped=dropped)


class RefreshedMovers:
    """The movers' fit under a caller's refresh rule: :meth:`fit` fits at its first call and after
    each :meth:`refresh`, and returns the last fit otherwise (new masks' shape or pairs refit too).

    Pass it as ``movers=`` to :class:`~geco_guide.loss.geco.GeCoLoss` with ``movers="rigid"``;
    call :meth:`refresh` whenever the masks are refreshed (e.g. with
    :class:`~geco_guide.sampler.algorithm.dynamic.RefreshedMasks`' refresh). The motions themselves are
    re-solved from the fit at every call (:func:`solve_motions`), so a reused fit follows the
    frames' geometry.

    Args:
        **options: the fit's thresholds (:func:`fit_movers`: ``rigid_tolerance``, ``min_inliers``,
            ``iterations``, ``seed``).
    """

    def __init__(self, **options: Any) -> None:
        unknown = set(options) - {"rigid_tolerance", "min_inliers", "iterations", "seed"}
        if unknown:
            raise ValueError(f"unknown mover fit option(s) {sorted(unknown)}; known: iterations, min_inliers, "
                             "rigid_tolerance, seed")
        self.options = options
        self.last: MoverFit | None = None
        self._due = True

    def refresh(self) -> None:
        """The next :meth:`fit` fits anew."""
        self._due = True

    def fit(self, masks: Tensor, geometry: SceneGeometry, correspondences: Correspondences,
            pairs: Sequence[tuple[int, int]], covisibility_threshold: float = 0.5) -> MoverFit:
        """:func:`fit_movers` when due, else the last fit."""
        if self._due or self.last is None or not self.last.fits(masks, pairs):
            self.last = fit_movers(masks, geometry, correspondences, pairs,
                                   covisibility_threshold=covisibility_threshold, **self.options)
            self._due = False
        return self.last
