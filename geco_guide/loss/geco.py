"""GeCoLoss: frames -> estimators -> frame pairs -> cues -> per-pixel maps -> scalars.

The same computation is the evaluation metric and the guidance loss. :func:`geco_from_geometry`
does the math from given geometry and correspondences (tests, evaluation with ground truth);
:class:`GeCoLoss` obtains them from an estimator bundle (``.geometry``, a :class:`GeometryEstimator`;
``.flow``, a :class:`FlowEstimator`: :class:`geco_guide.estimators.Estimators`).

Aggregation: per pair, each cue is a map with a validity mask; a frame's map is the pixel-wise
mean over the pairs whose source it is (where valid); a frame's score is the mean of its map over
valid pixels; a scalar is the mean of the frame scores over frames with any valid pixel. With
adjacent pairs this is the mean over pairs of the per-pair means.
"""

from __future__ import annotations

import math
import os
from collections.abc import Sequence
from dataclasses import asdict, dataclass, fields, replace
from functools import partial
from typing import TYPE_CHECKING, Any

import torch
import torch.nn.functional as F
from torch import Tensor, nn

from ..geometry import (
    check_tensor,
    crop_intrinsics,
    homogeneous_pose,
    invert_rigid,
    relative_pose,
    resize_flow,
    rigid_flow,
)
from ..io.masks import MaskReadError, check_masks, fit_masks, read_masks
from ..types import (
    NAMED_MASK_SOURCES,
    Correspondences,
    DynamicMaskSource,
    OptionError,
    SceneGeometry,
    check_estimator_bundle,
    refuses_earlier_keywords,
    check_frame_values,
    check_frames,
    non_finite_fields,
)
from .cues import CUES, MAP_ORDER, fuse_cues, lands_on_mask, masked_mean, motion_residual, structure_residual
from .movers import MOVER_MODES, MoverFit, MoverScores, RefreshedMovers, mover_scores, solve_motions

if TYPE_CHECKING:  # the bundle's room is beside the loss', on its floor
    from ..estimators.bundle import Estimators

__all__ = ["CUES", "MIN_UNMASKED_FRACTION", "MOVER_MODES", "PAIR_MODES", "GeCoLoss", "GeCoLossConfig", "GeCoMaps",
           "GeCoResult", "check_movers", "frame_pairs", "geco_from_geometry", "movers_problem",
           "no_valid_pixels_reason", "resolve_dynamic_masks"]

#: adjacent: (i, i+1), n-1 pairs; center: every frame with the middle one, 2(n-1); all: every
#: ordered pair, n(n-1) (the paper's evaluation script).
PAIR_MODES = ("adjacent", "center", "all")

STRUCTURE_OCCLUSION = ("depth", "covisibility")

#: With dynamic masks, a frame counts in a cue only where that cue's valid (unmasked) pixels cover
#: at least this fraction of the frame: a score over a sliver left between masked objects is
#: noise. Without masks every frame with any valid pixel counts, as in the paper.
MIN_UNMASKED_FRACTION = 0.05


def no_valid_pixels_reason(masked: bool) -> str:
    """Why a score over no valid pixel is NaN, in a user's words (``masked``: dynamic masks were
    used, and a frame counts only where :data:`MIN_UNMASKED_FRACTION` of it stays valid)."""
    if masked:
        return f"no frame kept {MIN_UNMASKED_FRACTION:.0%} of its pixels valid outside the dynamic mask"
    return "no pixel was valid (co-visible, confidently estimated and seen by both frames of a pair)"


@dataclass
class GeCoLossConfig:
    """Options of the GeCo metric / loss.

    Attributes:
        pairs: ``adjacent`` (k -> k+1), ``center`` (centre frame against every other frame, both
            directions) or ``all`` (every ordered pair).
        cue: which scalar is the loss: ``fused``, ``motion`` or ``structure``.
        covisibility_threshold: motion counts where the flow estimator's covisibility exceeds it.
        confidence_percentile: drop source pixels below this percentile of the frame's depth
            confidence (VGGT-style); ``None`` keeps all pixels.
        flow_downscale: run the flow estimator on frames resized by this factor and bring flow
            and covisibility back to full resolution (0.5 for guidance).
        occlusion_tau: relative depth margin of the occlusion test of the structure cue.
        depth_edge_tau: drop structure pixels whose projection lands on a target depth edge
            (bilinear sample mixing depths that differ by more than ``1 + depth_edge_tau``);
            ``None`` keeps them as the paper does. See :func:`structure_residual`.
        geometry_grad: let gradients flow through the geometry estimator. Without it the
            structure cue gives no gradient at all and the motion cue only through the flow.
        structure_occlusion: which pixels the structure cue drops as occluded: ``depth`` (the
            paper: where the reprojected point lies behind the target surface by more than
            ``occlusion_tau``) or ``covisibility`` (the GeCo-Eval script: the depth test only for
            pixels the flow estimator does not call co-visible; co-visible pixels always count).
        movers: what dynamic masks do to what they cover: ``drop`` (the default: left out) or
            ``rigid`` (each mover scored against its own fitted rigid motion, a non-rigid one left
            out: :mod:`geco_guide.loss.movers`). Only with dynamic masks.
    """

    pairs: str = "adjacent"
    cue: str = "fused"
    covisibility_threshold: float = 0.5
    confidence_percentile: float | None = 20.0
    flow_downscale: float = 1.0
    occlusion_tau: float = 0.02
    depth_edge_tau: float | None = 0.1
    geometry_grad: bool = True
    structure_occlusion: str = "depth"
    movers: str = "drop"

    def __post_init__(self) -> None:
        for key, value in non_finite_fields(self):  # the first one
            raise OptionError(key, f"must be a finite number, got {value}")
        if self.pairs not in PAIR_MODES:
            raise OptionError("pairs", f"must be one of {PAIR_MODES}, got {self.pairs!r}")
        if self.cue not in CUES:
            raise OptionError("cue", f"must be one of {tuple(CUES)}, got {self.cue!r}")
        if not 0.0 <= self.covisibility_threshold < 1.0:
            raise OptionError("covisibility_threshold", f"must be in [0, 1), got {self.covisibility_threshold}")
        if self.confidence_percentile is not None and not 0.0 <= self.confidence_percentile < 100.0:
            raise OptionError("confidence_percentile", f"must be in [0, 100) or None, got {self.confidence_percentile}")
        if not 0.0 < self.flow_downscale <= 1.0:
            raise OptionError("flow_downscale", f"must be in (0, 1], got {self.flow_downscale}")
        if self.occlusion_tau <= 0.0:
            raise OptionError("occlusion_tau", f"must be > 0, got {self.occlusion_tau}")
        if self.structure_occlusion not in STRUCTURE_OCCLUSION:
            raise OptionError("structure_occlusion", f"must be one of {STRUCTURE_OCCLUSION}, got {self.structure_occlusion!r}")
        if self.depth_edge_tau is not None and self.depth_edge_tau <= 0.0:
            raise OptionError("depth_edge_tau", f"must be > 0 or None, got {self.depth_edge_tau}")
        if self.movers not in MOVER_MODES:
            raise OptionError("movers", f"must be one of {MOVER_MODES}, got {self.movers!r}")


def frame_pairs(num_frames: int, mode: str) -> list[tuple[int, int]]:
    """Ordered ``(source, target)`` frame pairs of a clip of ``num_frames`` frames."""
    if num_frames < 2:
        raise ValueError(f"GeCo needs at least 2 frames, got {num_frames}")
    if mode == "adjacent":
        return [(k, k + 1) for k in range(num_frames - 1)]
    if mode == "center":
        c = num_frames // 2
        others = [k for k in range(num_frames) if k != c]
        return [(k, c) for k in others] + [(c, k) for k in others]
    if mode == "all":
        return [(i, j) for i in range(num_frames) for j in range(num_frames) if i != j]
    raise ValueError(f"pairs must be one of {PAIR_MODES}, got {mode!r}")


@dataclass
class GeCoMaps:
    """Per-pixel cue maps with their validity masks, all ``[B, N, H, W]``.

    ``N`` indexes pairs (pair maps) or frames (frame maps).
    """

    motion: Tensor
    motion_valid: Tensor
    structure: Tensor
    structure_valid: Tensor
    fused: Tensor
    fused_valid: Tensor

    def cue(self, name: str) -> tuple[Tensor, Tensor]:
        """``(map, valid)`` of cue ``name`` (fused | motion | structure)."""
        return getattr(self, name), getattr(self, f"{name}_valid")


@dataclass
class GeCoResult:
    """Everything GeCo computes for a clip.

    Attributes:
        loss: scalar of the configured cue (differentiable, fp32 or the geometry's dtype).
        motion, structure, fused: scalars M_motion, M_struct, M_geo.
        pairs: the ``(source, target)`` frame pairs.
        pair_maps: :class:`GeCoMaps` ``[B, P, H, W]``.
        frame_maps: :class:`GeCoMaps` ``[B, S, H, W]`` (frames that are no pair's source are
            all-invalid).
        frame_scores: cue name -> ``[B, S]`` mean over the frame's valid pixels.
        frame_has_valid: cue name -> ``[B, S]`` bool, frames that count in the scalars (with
            dynamic masks: valid pixels cover at least :data:`MIN_UNMASKED_FRACTION` of it).
        dynamic_masks: ``[B, S, H, W]`` bool, the pixels left out as moving on their own, or
            ``None`` (no masks: the paper's metric).
        masked_fraction: ``[B, S]`` fraction of each frame's pixels masked, or ``None``.
        mask_source: where the masks came from (``"given: masks.npz"``, ``"auto"``, ...), or ``None``.
        movers: with ``movers="rigid"``, each mover's numbers and the fit
            (:class:`~geco_guide.loss.movers.MoverScores`); ``None`` otherwise.
        cue: the configured cue, the one :attr:`loss` is.

    :attr:`valid_pixels` says how many pixels each scalar measured: with none, the scalars are 0
    with a zero gradient (the loss convention: an update with nothing to measure moves nothing);
    a score shown to a user is NaN with :func:`no_valid_pixels_reason` instead (:meth:`scalars`).
    """

    loss: Tensor
    motion: Tensor
    structure: Tensor
    fused: Tensor
    pairs: list[tuple[int, int]]
    pair_maps: GeCoMaps
    frame_maps: GeCoMaps
    frame_scores: dict[str, Tensor]
    frame_has_valid: dict[str, Tensor]
    dynamic_masks: Tensor | None = None
    masked_fraction: Tensor | None = None
    mask_source: str | None = None
    movers: MoverScores | None = None
    cue: str = "fused"

    @property
    def valid_pixels(self) -> dict[str, Tensor]:
        """Cue name -> ``[B]`` int64: the valid pixels of the frames that count in its scalar (0:
        the scalar is over nothing). Computed when asked, on the maps' device."""
        return {name: (self.frame_maps.cue(name)[1].flatten(2).sum(-1) * self.frame_has_valid[name]).sum(-1)
                for name in CUES}

    def scalars(self) -> dict[str, float]:
        """Plain floats: ``motion``, ``structure``, ``fused`` and ``loss``; a cue over no valid
        pixel is NaN (:meth:`empty_cues`), never the 0 the loss holds (``loss`` keeps its value)."""
        empty = set(self.empty_cues())
        return {name: math.nan if name in empty else float(getattr(self, name).detach())
                for name in (*MAP_ORDER, "loss")}

    def valid_fraction(self) -> Tensor:
        """0-dim: the fraction of the frames' pixels :attr:`loss` measured (0: the loss is 0 with a
        zero gradient, having nothing to measure); no host sync."""
        counts = self.valid_pixels[self.cue].sum()
        return counts / self.frame_maps.cue(self.cue)[1].numel()

    def empty_cues(self) -> list[str]:
        """The cues whose scalar is over no valid pixel (a host sync); why:
        :func:`no_valid_pixels_reason` of ``dynamic_masks is not None``."""
        counts = self.valid_pixels
        return [name for name in CUES if int(counts[name].sum()) == 0]


def confidence_mask(confidence: Tensor, percentile: float) -> Tensor:
    """``[B, S, H, W]`` -> bool mask of pixels at or above the frame's ``percentile``.

    Non-positive confidence marks pixels without a prediction (e.g. rows VGGT cropped away)
    and never passes, even when they make up more than ``percentile`` % of the frame.
    """
    confidence = confidence.detach()
    threshold = torch.quantile(confidence.flatten(2).float(), percentile / 100.0, dim=-1)
    return (confidence >= threshold[..., None, None].to(confidence.dtype)) & (confidence > 0)


def _check_geometry(geometry: SceneGeometry) -> tuple[int, int, int, int]:
    check_tensor(geometry.depth, "depth", (None, None, None, None))
    batch, frames, height, width = geometry.depth.shape
    check_tensor(geometry.intrinsics, "intrinsics", (batch, frames, 3, 3))
    check_tensor(geometry.extrinsics, "extrinsics", (batch, frames, 3, 4))
    if geometry.confidence is not None:
        check_tensor(geometry.confidence, "confidence", (batch, frames, height, width))
    return batch, frames, height, width


def _without_non_finite(x: Tensor) -> Tensor:
    """``x`` with NaN/inf entries set to 0 (zero gradient there), same shape."""
    return torch.where(torch.isfinite(x), x, torch.zeros_like(x))


# Largest |R R^T - I| entry of a rotation: fp32/bf16 rounding passes, non-rotations do not.
ROTATION_TOLERANCE = 1e-2


def _usable_cameras(intrinsics: Tensor, extrinsics: Tensor) -> tuple[Tensor, Tensor, Tensor]:
    """Cameras safe to compute with, and which of them are real.

    Args:
        intrinsics: ``[B, S, 3, 3]``.
        extrinsics: ``[B, S, 3, 4]``.

    Returns:
        ``(K [B, S, 3, 3], extrinsics [B, S, 3, 4], usable [B, S])``: a camera with a NaN/inf
        entry, a singular K (which ``unproject`` could not invert) or an ``R`` that is not a
        rotation (``invert_rigid`` assumes one; huge entries overflow) is replaced by the identity
        camera and marked unusable, so its pairs are invalid instead of NaN (zero gradient).
    """
    eye = torch.eye(3, 4, dtype=extrinsics.dtype, device=extrinsics.device)
    finite = torch.isfinite(intrinsics).flatten(-2).all(-1) & torch.isfinite(extrinsics).flatten(-2).all(-1)
    K = torch.where(finite[..., None, None], intrinsics, eye[:, :3]).detach()
    rotation = torch.where(finite[..., None, None], extrinsics, eye)[..., :3].detach()
    gram_error = (rotation @ rotation.transpose(-1, -2) - eye[:, :3]).abs().flatten(-2).amax(-1)
    # "<=" is False for NaN (inf - inf in an overflowing product).
    usable = finite & (torch.linalg.det(K) != 0) & (gram_error <= ROTATION_TOLERANCE)
    ok = usable[..., None, None]
    return torch.where(ok, intrinsics, eye[:, :3]), torch.where(ok, extrinsics, eye), usable


def _frame_average(pair_map: Tensor, pair_valid: Tensor, sources: Tensor, num_frames: int) -> tuple[Tensor, Tensor]:
    """Pixel-wise mean over the pairs of each source frame: ``[B, P, H, W]`` -> ``[B, S, H, W]``."""
    batch, _, height, width = pair_map.shape
    weights = pair_valid.to(pair_map.dtype)
    total = pair_map.new_zeros(batch, num_frames, height, width)
    total = total.index_add(1, sources, torch.where(pair_valid, pair_map, torch.zeros_like(pair_map)))
    count = weights.new_zeros(batch, num_frames, height, width).index_add(1, sources, weights)
    return total / count.clamp_min(1.0), count > 0


def geco_from_geometry(
    geometry: SceneGeometry,
    correspondences: Correspondences,
    pairs: list[tuple[int, int]],
    config: GeCoLossConfig | None = None,
    dynamic_masks: Tensor | str | os.PathLike | None = None,
    mask_source: str | None = None,
    movers: MoverFit | RefreshedMovers | None = None,
) -> GeCoResult:
    """GeCo maps and scores from known geometry and correspondences (no estimator).

    Args:
        geometry: per-frame depth ``[B, S, H, W]``, K ``[B, S, 3, 3]``, extrinsics
            ``[B, S, 3, 4]`` and optional confidence ``[B, S, H, W]``.
        correspondences: flow ``[B*P, 2, H, W]`` and covisibility ``[B*P, H, W]`` of the pairs,
            batch-major (all pairs of batch element 0 first).
        pairs: ``P`` ordered ``(source, target)`` frame indices.
        config: the options (defaults if ``None``).
        dynamic_masks: ``[B, S, H, W]`` or ``[S, H, W]`` (every clip alike) bool, true where
            content may move on its own, any size of the frames' aspect ratio (resized, nearest),
            or a mask file (:func:`~geco_guide.io.masks.read_masks`). A pixel drops out of the
            motion cue when it is masked or its flow lands on a masked pixel of the target, and
            out of the structure cue when it is masked or its reprojection lands on one; a frame
            counts only where :data:`MIN_UNMASKED_FRACTION` of it stays valid. ``None``: the
            paper's metric, unchanged.
        mask_source: what to record as the masks' source (default: ``"given"`` or the path).
        movers: with ``config.movers == "rigid"``, the movers' fit to score with: a
            :class:`~geco_guide.loss.movers.MoverFit` (reused as it is, e.g. an earlier result's
            ``movers.fit``), a :class:`~geco_guide.loss.movers.RefreshedMovers` (the caller's
            refresh rule), or ``None`` (fitted now). See :mod:`geco_guide.loss.movers`.

    Returns:
        :class:`GeCoResult`.
    """
    config = config or GeCoLossConfig()
    check_movers(config, dynamic_masks is not None, movers)
    batch, num_frames, height, width = _check_geometry(geometry)
    num_pairs = len(pairs)
    if num_pairs == 0:
        raise ValueError("pairs must not be empty")
    if any(not (0 <= i < num_frames and 0 <= j < num_frames) or i == j for i, j in pairs):
        raise ValueError(f"pairs must hold distinct frame indices in [0, {num_frames}), got {pairs}")
    check_tensor(correspondences.flow, "flow", (batch * num_pairs, 2, height, width))
    check_tensor(correspondences.covisibility, "covisibility", (batch * num_pairs, height, width))
    masks = None
    if dynamic_masks is not None:
        masks, name = _given_masks(dynamic_masks, batch, num_frames, (height, width))
        masks, mask_source = masks.to(geometry.depth.device), mask_source or name
    view = _PairView.of(geometry, correspondences, pairs, config)
    cues = _camera_cues(view, config)
    fit = None
    if masks is not None:
        fit, cues = _masked_cues(view, cues, masks, movers, config)
    return _result(view, cues, config, masks, mask_source, fit)


@dataclass
class _PairView:
    """The clips' geometry and correspondences as the cues see them, per pair: ``B*P`` rows,
    batch-major. Estimator outputs may hold NaN/inf (e.g. an overflow): such pixels and cameras
    count as invalid (depth, flow and covisibility 0, cameras unusable), so they neither turn the
    scores into NaN nor reach grid_sample or the gradient.

    Attributes:
        pairs, num_frames: the ``P`` pairs and the clips' ``S`` frames; src, tgt: ``[P]`` their
            source and target frames (on the depth's device).
        depth: ``[B, S, H, W]``; intrinsics, extrinsics: ``[B, S, 3, 3]`` / ``[B, S, 3, 4]``
            (finite); usable: ``[B, S]`` the finite cameras.
        depth_src, depth_tgt: ``[B*P, H, W]``; K_src, K_tgt: ``[B*P, 3, 3]``; extr_src,
            extr_tgt: ``[B*P, 3, 4]``; src_to_tgt: ``[B*P, 4, 4]`` the relative pose.
        pair_usable: ``[B*P, 1, 1]`` both cameras usable.
        flow: ``[B*P, 2, H, W]`` (in the depth's dtype); flow_finite: ``[B*P, H, W]``;
            covisibility: ``[B*P, H, W]``; covisible: above ``covisibility_threshold``.
        rigid, rigid_valid: ``[B*P, 2, H, W]`` / ``[B*P, H, W]`` where the source pixels land
            with the camera's motion alone.
        trusted: ``[B*P, H, W]`` the source depth confidence passes ``confidence_percentile``;
            ``None`` without confidence or percentile.
    """

    pairs: list[tuple[int, int]]
    num_frames: int
    src: Tensor
    tgt: Tensor
    depth: Tensor
    intrinsics: Tensor
    extrinsics: Tensor
    depth_src: Tensor
    depth_tgt: Tensor
    K_src: Tensor
    K_tgt: Tensor
    extr_src: Tensor
    extr_tgt: Tensor
    src_to_tgt: Tensor
    pair_usable: Tensor
    flow: Tensor
    flow_finite: Tensor
    covisibility: Tensor
    covisible: Tensor
    rigid: Tensor
    rigid_valid: Tensor
    trusted: Tensor | None

    @classmethod
    def of(cls, geometry: SceneGeometry, correspondences: Correspondences, pairs: Sequence[tuple[int, int]],
           config: GeCoLossConfig) -> _PairView:
        device = geometry.depth.device
        src = torch.tensor([i for i, _ in pairs], device=device)
        tgt = torch.tensor([j for _, j in pairs], device=device)
        gather = partial(_gather_pairs, num_pairs=len(pairs))
        depth = _without_non_finite(geometry.depth)  # 0: no depth, never valid
        intrinsics, extrinsics, usable = _usable_cameras(geometry.intrinsics, geometry.extrinsics)
        depth_src, K_src, K_tgt = gather(depth, src), gather(intrinsics, src), gather(intrinsics, tgt)
        extr_src, extr_tgt = gather(extrinsics, src), gather(extrinsics, tgt)
        src_to_tgt = relative_pose(extr_src, extr_tgt)
        flow = correspondences.flow.to(depth_src.dtype)
        covisibility = _without_non_finite(correspondences.covisibility)
        trusted = None
        if geometry.confidence is not None and config.confidence_percentile is not None:
            confidence = _without_non_finite(geometry.confidence)  # 0: no prediction, never trusted
            trusted = gather(confidence_mask(confidence, config.confidence_percentile), src)
        return cls(list(pairs), geometry.depth.shape[1], src, tgt, depth, intrinsics, extrinsics, depth_src,
                   gather(depth, tgt), K_src, K_tgt, extr_src, extr_tgt, src_to_tgt,
                   (gather(usable, src) & gather(usable, tgt))[:, None, None], _without_non_finite(flow),
                   torch.isfinite(flow).all(dim=1), covisibility, covisibility > config.covisibility_threshold,
                   *rigid_flow(depth_src, K_src, K_tgt, src_to_tgt), trusted)

    def gather(self, x: Tensor, index: Tensor) -> Tensor:
        """``x [B, S, ...]`` at the frames ``index [P]``: ``[B*P, ...]``."""
        return _gather_pairs(x, index, num_pairs=len(self.pairs))


def _gather_pairs(x: Tensor, index: Tensor, *, num_pairs: int) -> Tensor:
    """``x [B, S, ...]`` at the frames ``index [P]``: ``[B*P, ...]``, batch-major."""
    return x[:, index].reshape(x.shape[0] * num_pairs, *x.shape[2:])


def _camera_cues(view: _PairView, config: GeCoLossConfig) -> tuple[Tensor, Tensor, Tensor, Tensor]:
    """The pair maps ``(motion, motion_valid, structure, structure_valid)`` ``[B*P, H, W]`` of the
    camera's motion alone: every pixel scored as static."""
    motion = motion_residual(view.flow, view.rigid, view.K_src)
    structure, structure_valid = structure_residual(
        view.depth_src, view.depth_tgt, view.K_src, view.K_tgt, view.src_to_tgt, tau=config.occlusion_tau,
        edge_tau=config.depth_edge_tau,
        keep_occluded=view.covisible if config.structure_occlusion == "covisibility" else None,
    )
    motion_valid = view.rigid_valid & view.covisible & view.flow_finite & view.pair_usable
    structure_valid = structure_valid & view.pair_usable
    if view.trusted is not None:
        motion_valid = motion_valid & view.trusted
        structure_valid = structure_valid & view.trusted
    return motion, motion_valid, structure, structure_valid


def _masked_cues(view: _PairView, cues: tuple[Tensor, Tensor, Tensor, Tensor], masks: Tensor,
                 movers: MoverFit | RefreshedMovers | None,
                 config: GeCoLossConfig) -> tuple[MoverFit | None, tuple[Tensor, Tensor, Tensor, Tensor]]:
    """The camera's ``cues`` with the dynamic ``masks [B, S, H, W]``: a masked source pixel, or
    one whose flow or reprojection lands on a masked target pixel, left out; with
    ``movers="rigid"``, the movers' fit (``movers``: reused or refreshed, fitted otherwise) and each
    rigid mover's pixels scored against its own motion. Returns the fit (``None`` with ``drop``)
    and the cues."""
    motion, motion_valid, structure, structure_valid = cues
    masked_source, masked_target = view.gather(masks, view.src), view.gather(masks, view.tgt)
    fit = None
    if config.movers == "rigid":
        clean = SceneGeometry(depth=view.depth, intrinsics=view.intrinsics, extrinsics=view.extrinsics)
        fit = movers if isinstance(movers, MoverFit) else (movers or RefreshedMovers()).fit(
            masks, clean, Correspondences(view.flow, view.covisibility), view.pairs, config.covisibility_threshold)
        fit = fit.to(view.depth.device)
        # a pixel scored by a mover's motion is left to it; the camera scores the others
        masked_source = fit.assignment.flatten(0, 1) != 0
    motion_valid = motion_valid & ~masked_source & ~lands_on_mask(masked_target, view.flow)
    structure_valid = structure_valid & ~masked_source & ~lands_on_mask(masked_target, view.rigid)
    cues = (motion, motion_valid, structure, structure_valid)
    if fit is not None and fit.entries:
        motion_ok, structure_ok = view.covisible & view.flow_finite & view.pair_usable, view.pair_usable.expand_as(view.covisible)
        if view.trusted is not None:
            motion_ok, structure_ok = motion_ok & view.trusted, structure_ok & view.trusted
        cues = _with_mover_cues(fit, cues, (motion_ok, structure_ok), config, view)
    return fit, cues


def _result(view: _PairView, cues: tuple[Tensor, Tensor, Tensor, Tensor], config: GeCoLossConfig, masks: Tensor | None,
            mask_source: str | None, fit: MoverFit | None) -> GeCoResult:
    """The :class:`GeCoResult` of the pair maps ``cues``: fused, averaged per frame, scored per
    frame (a frame counts where :data:`MIN_UNMASKED_FRACTION` of it stays valid under ``masks``)
    and over the clips, with the movers' scores of ``fit``."""
    fused, fused_valid = fuse_cues(*cues)
    batch, num_pairs = view.depth.shape[0], len(view.pairs)
    height, width = view.depth.shape[-2:]

    def per_pair(x: Tensor) -> Tensor:
        return x.reshape(batch, num_pairs, height, width)

    pair_maps = GeCoMaps(*(per_pair(x) for x in (*cues, fused, fused_valid)))
    frame_fields = []
    for name in MAP_ORDER:  # GeCoMaps field order
        frame_fields.extend(_frame_average(*pair_maps.cue(name), view.src, view.num_frames))
    frame_maps = GeCoMaps(*frame_fields)

    frame_scores, frame_has_valid, scalars = {}, {}, {}
    for name in CUES:
        values, valid = frame_maps.cue(name)
        frame_scores[name] = masked_mean(values, valid, dims=(-2, -1))
        if masks is None:
            frame_has_valid[name] = valid.flatten(2).any(-1)
        else:
            frame_has_valid[name] = valid.flatten(2).float().mean(-1) >= MIN_UNMASKED_FRACTION
        scalars[name] = masked_mean(frame_scores[name], frame_has_valid[name], dims=(0, 1))
    scores = None
    if fit is not None:
        scores = mover_scores(fit, *frame_maps.cue("fused"), frame_has_valid["fused"], scalars["fused"])
    return GeCoResult(
        loss=scalars[config.cue],
        **{name: scalars[name] for name in CUES},
        pairs=list(view.pairs),
        pair_maps=pair_maps,
        frame_maps=frame_maps,
        frame_scores=frame_scores,
        frame_has_valid=frame_has_valid,
        dynamic_masks=masks,
        masked_fraction=None if masks is None else masks.flatten(2).float().mean(-1),
        mask_source=mask_source,
        movers=scores,
        cue=config.cue,
    )


def movers_problem(movers: str, has_masks: bool,
                   masks: str = "dynamic masks (a file, 'auto' or subjects)") -> str | None:
    """Why ``movers`` cannot act, the value first (``'rigid' scores ...``: it scores the movers of
    dynamic masks, and there are none; ``masks`` says how to give them), or ``None``: the one
    check of this rule, wherever ``loss.movers`` is set."""
    if movers == "rigid" and not has_masks:
        return f"{movers!r} scores the movers of dynamic masks: give {masks}, or leave movers at 'drop'"
    return None


def check_movers(config: GeCoLossConfig, has_masks: bool, movers: Any = None) -> None:
    """One-line ValueError for movers options that would do nothing: ``movers="rigid"`` without
    dynamic masks, or a fit given with ``movers="drop"``."""
    problem = movers_problem(config.movers, has_masks)
    if problem is not None:
        raise ValueError(f"movers={problem}")
    if movers is not None and config.movers != "rigid":
        raise ValueError(f"a movers fit was given but movers={config.movers!r}: set movers='rigid' to score with it")
    if movers is not None and not isinstance(movers, (MoverFit, RefreshedMovers)):
        raise ValueError(f"movers must be a MoverFit or a RefreshedMovers, got {type(movers).__name__}")


def _with_mover_cues(fit: MoverFit, cues: tuple[Tensor, Tensor, Tensor, Tensor], usable: tuple[Tensor, Tensor],
                     config: GeCoLossConfig, view: _PairView) -> tuple[Tensor, Tensor, Tensor, Tensor]:
    """The pair maps ``(motion, motion_valid, structure, structure_valid)`` ``[B*P, H, W]`` with
    each rigid mover's pixels scored against its own motion (:mod:`geco_guide.loss.movers`),
    computed in the mover's box of each pair alone.

    ``usable``: ``[B*P, H, W]`` where the motion cue may count (co-visible, finite flow, usable
    pair, trusted depth) and where the structure cue may (usable pair, trusted depth), as for the
    static part; ``view``: the pairs' geometry and flow (:class:`_PairView`).
    """
    motion_ok, structure_ok = usable
    depth_src, depth_tgt, K_src, K_tgt = view.depth_src, view.depth_tgt, view.K_src, view.K_tgt
    extr_src, extr_tgt, flow, covisible = view.extr_src, view.extr_tgt, view.flow, view.covisible
    target_labels = view.gather(fit.labels, view.tgt)  # [B*P, H, W] the target frame's mover labels
    motion, motion_valid, structure, structure_valid = (x.clone() for x in cues)
    world = solve_motions(fit, depth_src, depth_tgt, K_src, K_tgt, extr_src, extr_tgt, flow).to(depth_src.dtype)
    num_pairs = len(fit.pairs)
    height, width = depth_src.shape[-2:]
    assignment = fit.assignment.flatten(0, 1)
    for e, ((b, p, k), (top, bottom, left, right), target_box) in enumerate(zip(fit.entries, fit.boxes, fit.target_boxes)):
        n = b * num_pairs + p
        box = (n, slice(top, bottom), slice(left, right))
        K_box = crop_intrinsics(K_src[n:n + 1], top, left)
        # source camera -> world -> moved with the mover -> target camera; the cameras keep their gradient
        pose = homogeneous_pose(extr_tgt[n:n + 1]) @ world[e:e + 1] @ invert_rigid(extr_src[n:n + 1])
        depth_box = depth_src[box][None]
        landing, rigid_valid = rigid_flow(depth_box, K_box, K_tgt[n:n + 1], pose, tgt_hw=(height, width))
        offset = landing.new_tensor([float(left), float(top)])[None, :, None, None]
        own_motion = motion_residual(flow[n, :, top:bottom, left:right][None], landing - offset, K_box)
        scored = assignment[box] == k
        motion[box] = torch.where(scored, own_motion[0].to(motion.dtype), motion[box])
        motion_valid[box] |= scored & rigid_valid[0] & motion_ok[box]
        if target_box is None:
            continue  # the target does not show the mover: no depth of it to compare with
        # the reprojection must land wholly on the same mover (a blend with what lies around it is
        # no depth of it), so the target is read in the mover's box alone
        t_top, t_bottom, t_left, t_right = target_box
        own_structure, own_structure_valid = structure_residual(
            depth_box, depth_tgt[n:n + 1, t_top:t_bottom, t_left:t_right], K_box,
            crop_intrinsics(K_tgt[n:n + 1], t_top, t_left), pose, tau=config.occlusion_tau, edge_tau=config.depth_edge_tau,
            keep_occluded=covisible[box][None] if config.structure_occlusion == "covisibility" else None,
        )
        off_mover = (target_labels[n] != k)[None]
        structure[box] = torch.where(scored, own_structure[0].to(structure.dtype), structure[box])
        structure_valid[box] |= scored & own_structure_valid[0] & structure_ok[box] & ~lands_on_mask(off_mover, landing)[0]
    return motion, motion_valid, structure, structure_valid


def _given_masks(masks: Any, batch: int, num_frames: int, size: tuple[int, int]) -> tuple[Tensor, str]:
    """A mask tensor or file -> ``([B, S, H, W] bool, source name)``, checked and resized."""
    name = "given"
    if isinstance(masks, (str, os.PathLike)):
        masks, name = read_masks(masks)[0], f"given: {os.fspath(masks)}"
    masks = fit_masks(check_masks(masks, batched=True), num_frames, size)
    if masks.ndim == 3:
        return masks[None].expand(batch, -1, -1, -1), name
    if masks.shape[0] != batch:
        raise MaskReadError(f"dynamic_masks hold {masks.shape[0]} clip(s), the frames {batch}")
    return masks, name


def resolve_dynamic_masks(
    dynamic_masks: Any,
    frames: Tensor,
    geometry: SceneGeometry,
    correspondences: Correspondences,
    pairs: Sequence[tuple[int, int]],
) -> tuple[Tensor | None, str | None]:
    """The dynamic masks of ``frames [B, S, 3, H, W]`` and their source's name.

    Args:
        dynamic_masks: ``None``; a tensor ``[B, S, H, W]`` / ``[S, H, W]`` or a mask file (see
            :func:`geco_from_geometry`); or a :class:`~geco_guide.types.DynamicMaskSource`, asked
            once per clip with the clip's detached frames, geometry and correspondences.
        frames, geometry, correspondences, pairs: what GeCo computed on the clips.

    Returns:
        ``(masks [B, S, H, W] bool | None, source name | None)``; masks carry no gradient.
    """
    if dynamic_masks is None:
        return None, None
    batch, num_frames, _, height, width = frames.shape
    if not isinstance(dynamic_masks, DynamicMaskSource):
        return _given_masks(dynamic_masks, batch, num_frames, (height, width))
    num_pairs = len(pairs)
    clips = []
    with torch.no_grad():
        for b in range(batch):
            scene = SceneGeometry(**{f.name: None if getattr(geometry, f.name) is None else getattr(geometry, f.name)[b : b + 1].detach()
                                     for f in fields(SceneGeometry)})
            part = slice(b * num_pairs, (b + 1) * num_pairs)
            flow = Correspondences(correspondences.flow[part].detach(), correspondences.covisibility[part].detach())
            masks = dynamic_masks.dynamic_masks(frames[b].detach(), scene, flow, list(pairs))
            name = f"dynamic masks ({dynamic_masks.source_name})"
            clips.append(fit_masks(check_masks(masks, name), num_frames, (height, width), name).to(frames.device))
    return torch.stack(clips), dynamic_masks.source_name


def _resize_images(images: Tensor, size: tuple[int, int]) -> Tensor:
    if tuple(images.shape[-2:]) == size:
        return images
    return F.interpolate(images, size=size, mode="bilinear", align_corners=False)


class GeCoLoss(nn.Module):
    """The GeCo metric as a differentiable module.

    Args:
        estimators: the models as one bundle (:class:`geco_guide.estimators.Estimators`): its
            ``geometry`` (a :class:`GeometryEstimator`, e.g. VGGT: depth, K, extrinsics as a
            :class:`~geco_guide.types.SceneGeometry`) and its ``flow`` (a :class:`FlowEstimator`,
            e.g. UFM: flow and covisibility per pair).
        config: :class:`GeCoLossConfig` (or a dict of its fields); defaults if ``None``: the
            fused map on ADJACENT pairs (k -> k+1), the guidance loss' pairs, cheap enough to
            differentiate at every update. ``evaluate_video`` defaults to all ordered pairs of a
            window instead (:func:`~geco_guide.loss.presets.evaluation_loss`), because the
            benchmark reproduces the published evaluation script; docs/metric.md says more.
        check_values: refuse frames that are not finite (:class:`NonFiniteFramesError`) or not in
            ``[0, 1]`` with a ValueError naming them, at the cost of one device-to-host copy per
            call. The samplers pass ``False``: their updates must not wait for the device, and a
            non-finite decode then makes the scalars NaN (never a score of 0.0); its gradient is
            zero or non-finite, and ``guided_step`` moves nothing with either.

    ``forward(frames [B, S, 3, H, W] in [0, 1], dynamic_masks=None, movers=None) -> GeCoResult``;
    dynamic masks (a tensor, a mask file, ``"auto"`` (the automatic detector, as in
    ``evaluate_video``) or a :class:`~geco_guide.types.DynamicMaskSource`, see
    :func:`resolve_dynamic_masks`) leave moving content out, or, with ``config.movers="rigid"``,
    score each rigid mover against its own motion (fitted detached; ``movers`` reuses a fit or
    holds the caller's refresh rule: :mod:`geco_guide.loss.movers`). In the loss an all-masked
    clip is ``0`` with a zero gradient, as any clip without valid pixels;
    ``GeCoResult.valid_pixels`` says so, and its ``scalars()`` are NaN.
    """

    @refuses_earlier_keywords("GeCoLoss")
    def __init__(
        self,
        estimators: Estimators | None = None,
        config: GeCoLossConfig | dict | None = None,
        *,
        check_values: bool = True,
    ) -> None:
        super().__init__()
        check_estimator_bundle(estimators, "GeCoLoss")
        if isinstance(config, dict):
            known = {f.name for f in fields(GeCoLossConfig)}
            unknown = sorted(set(config) - known)
            if unknown:
                raise ValueError(f"unknown GeCo loss option(s) {unknown}; known: {sorted(known)}")
            config = GeCoLossConfig(**config)
        self.config = config or GeCoLossConfig()
        self.check_values = check_values
        # Registered as attributes (modules when they are modules) so .to() moves them.
        self.geometry_estimator = estimators.geometry
        self.flow_estimator = estimators.flow

    def extra_repr(self) -> str:
        return ", ".join(f"{k}={v!r}" for k, v in asdict(self.config).items())

    def estimate_correspondences(self, frames: Tensor, pairs: list[tuple[int, int]]) -> Correspondences:
        """Flow and covisibility for ``pairs`` of ``frames [B, S, 3, H, W]``, batched in one call.

        Returns ``Correspondences`` at full resolution: flow ``[B*P, 2, H, W]``, covisibility
        ``[B*P, H, W]``, batch-major.
        """
        height, width = frames.shape[-2:]
        src = frames[:, [i for i, _ in pairs]].flatten(0, 1)
        tgt = frames[:, [j for _, j in pairs]].flatten(0, 1)
        scale = self.config.flow_downscale
        small = (max(2, round(height * scale)), max(2, round(width * scale)))
        result = self.flow_estimator.estimate_flow(_resize_images(src, small), _resize_images(tgt, small))
        flow = resize_flow(result.flow, (height, width))
        covisibility = _resize_images(result.covisibility[:, None], (height, width))[:, 0]
        return Correspondences(flow=flow, covisibility=covisibility)

    def forward(self, frames: Tensor, dynamic_masks: Any = None, movers: MoverFit | RefreshedMovers | None = None) -> GeCoResult:
        """Raises ValueError for frames that are not finite or not in [0, 1] (see ``check_values``)
        and MaskReadError (a ValueError) for dynamic masks of the wrong shape or not binary.
        ``movers``: with ``config.movers == "rigid"``, the movers' fit to reuse or its refresh rule
        (see :func:`geco_from_geometry`); ``None`` fits the movers now."""
        check_frames(frames)
        check_movers(self.config, dynamic_masks is not None, movers)
        if frames.shape[1] < 2:
            raise ValueError(f"frames must hold at least 2 frames, got {frames.shape[1]}")
        if self.check_values:
            check_frame_values(frames)
        if isinstance(dynamic_masks, str) and dynamic_masks.strip() in NAMED_MASK_SOURCES:
            dynamic_masks = NAMED_MASK_SOURCES[dynamic_masks.strip()]()
        given = None
        if dynamic_masks is not None and not isinstance(dynamic_masks, DynamicMaskSource):
            given = _given_masks(dynamic_masks, frames.shape[0], frames.shape[1], tuple(frames.shape[-2:]))  # before any estimator
        frames = frames.float()
        with torch.set_grad_enabled(torch.is_grad_enabled() and self.config.geometry_grad):
            geometry = self.geometry_estimator.estimate_geometry(frames)
        if not self.config.geometry_grad:
            # Depth and cameras are constants of the update (the paper's experiment): detached even
            # if the estimator enabled gradients inside, so the rigid flow of the motion cue depends
            # on the frames only through the flow estimator's input.
            geometry = replace(geometry, **{f.name: getattr(geometry, f.name).detach() for f in fields(geometry)
                                            if isinstance(getattr(geometry, f.name), Tensor)})
        pairs = frame_pairs(frames.shape[1], self.config.pairs)
        correspondences = self.estimate_correspondences(frames, pairs)
        masks, source = given or resolve_dynamic_masks(dynamic_masks, frames, geometry, correspondences, pairs)
        result = geco_from_geometry(geometry, correspondences, pairs, self.config, masks, source, movers)
        if not self.check_values:
            _nan_unless_finite(result, frames)
        return result


def _nan_unless_finite(result: GeCoResult, frames: Tensor) -> None:
    """Set the scalars of ``result`` to NaN if ``frames`` hold NaN/inf, without a host sync.

    Non-finite depth and flow are masked as invalid pixels, so a NaN decode would otherwise score
    as consistent as can be.
    """
    finite = torch.isfinite(frames.detach()).all()
    for name in ("loss", *MAP_ORDER):
        value = getattr(result, name)
        setattr(result, name, torch.where(finite, value, torch.full_like(value, float("nan"))))
