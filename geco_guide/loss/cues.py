"""GeCo's per-pixel cues: motion residual, structure residual and their fusion, and :data:`CUES`,
the one table of the cues that the maps, the scalars, the validation and the reports read.

Both cues are scale invariant: the motion residual is measured in normalised image units
(pixels divided by the focal length) and the structure residual is a depth difference divided
by the source depth, so scaling all depths and camera translations by ``k > 0`` leaves them
unchanged.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import Tensor

from ..geometry import MIN_DEPTH, check_tensor, local_depth_ratio, pixel_grid, sample_at_projection, sample_bilinear

__all__ = ["CUES", "MAP_ORDER", "MASK_TOUCH_WEIGHT", "PAPER_ORDER", "Cue", "fuse_cues", "lands_on_mask",
           "masked_mean", "motion_residual", "safe_norm", "structure_residual"]


@dataclass(frozen=True)
class Cue:
    """One cue of :data:`CUES`: how it is named and drawn, and what its map is made from (its
    residual function is here, its map made in :func:`geco_guide.loss.geco.geco_from_geometry`,
    which averages every cue's maps per frame and the frames' means into its scalar alike).

    Attributes:
        symbol: the paper's name of its map and score (``M_geo``).
        title: its name at the head of a report's row (``Fused``).
        fuses: the cues whose maps its map combines (``()``: measured from the estimates), made
            before it (:data:`MAP_ORDER`).
        geometry_only: its map reaches the frames only through the geometry estimator, so as a
            guidance loss it needs ``geometry_grad`` (else there is no update).
        color: RGB of its lines and dots in the reports' plots.
        marker: the shape of its dots there (``square``, ``circle``, ``triangle``).
        line_width: its lines' width there: drawn widest first, a line that coincides with
            another still shows as the border of the one drawn over it.
    """

    symbol: str
    title: str
    fuses: tuple[str, ...] = ()
    geometry_only: bool = False
    color: tuple[int, int, int] = (0, 0, 0)
    marker: str = "circle"
    line_width: int = 1


def safe_norm(x: Tensor, dim: int) -> Tensor:
    """Euclidean norm along ``dim`` whose gradient is finite (zero) where the norm is 0.

    Computed as ``a * sqrt(sum((x / a)^2))`` with ``a = max |x|`` (held constant: the gradient
    is still ``x / norm``), so entries above ``sqrt(float max)`` (~1e19 in fp32) do not
    overflow to an infinite norm.
    """
    scale = x.detach().abs().amax(dim)
    positive = scale > 0
    # The double where keeps sqrt's infinite slope at 0 out of the backward pass.
    scale = torch.where(positive, scale, torch.ones_like(scale))
    unit = x / scale.unsqueeze(dim)
    squared = (unit * unit).sum(dim)
    safe = torch.where(positive, squared, torch.ones_like(squared))
    return torch.where(positive, scale * torch.sqrt(safe), torch.zeros_like(squared))


def motion_residual(flow: Tensor, rigid_flow: Tensor, K_src: Tensor) -> Tensor:
    """Residual motion between measured flow and camera-induced rigid flow.

    Args:
        flow: ``[B, 2, H, W]`` measured flow (du, dv) in pixels.
        rigid_flow: ``[B, 2, H, W]`` rigid flow in pixels.
        K_src: ``[B, 3, 3]`` source intrinsics (focal lengths normalise the residual).

    Returns:
        ``m [B, H, W] = sqrt(((du - du_r)/fx)^2 + ((dv - dv_r)/fy)^2)``.
    """
    check_tensor(flow, "flow", (None, 2, None, None))
    check_tensor(rigid_flow, "rigid_flow", tuple(flow.shape))
    check_tensor(K_src, "K_src", (flow.shape[0], 3, 3))
    focal = torch.stack((K_src[:, 0, 0], K_src[:, 1, 1]), dim=1)[:, :, None, None]
    return safe_norm((flow - rigid_flow) / focal, dim=1)


def structure_residual(
    depth_src: Tensor,
    depth_tgt: Tensor,
    K_src: Tensor,
    K_tgt: Tensor,
    src_to_tgt: Tensor,
    tau: float = 0.02,
    edge_tau: float | None = None,
    keep_occluded: Tensor | None = None,
) -> tuple[Tensor, Tensor]:
    """Depth reprojection error of the source depth against the target depth.

    Args:
        depth_src: ``[B, H, W]`` source z-depth.
        depth_tgt: ``[B, H_t, W_t]`` target z-depth.
        K_src, K_tgt: ``[B, 3, 3]`` intrinsics.
        src_to_tgt: ``[B, 4, 4]`` relative pose.
        tau: occlusion threshold: a pixel is hidden when the target surface at its projection
            is closer than its projected depth by more than ``tau * D_src``.
        edge_tau: if set, also drop pixels whose projection falls on a target depth edge (the
            depths a bilinear sample there mixes differ by more than a factor ``1 + edge_tau``):
            such a sample blends two surfaces and is comparable to neither. ``None`` (default)
            keeps them, as the paper does.
        keep_occluded: ``[B, H, W]`` bool, pixels to keep even where the occlusion test fails
            (the GeCo-Eval script keeps every pixel the flow estimator calls co-visible); ``None``
            lets the depth test alone decide.

    Returns:
        ``s [B, H, W] = |D_tgt(p') - z_proj| / D_src`` (0 where invalid) and ``valid [B, H, W]``
        excluding occluded, out-of-image and non-positive-depth pixels (and depth edges).
    """
    check_tensor(depth_tgt, "depth_tgt", (depth_src.shape[0], None, None))
    maps = depth_tgt[:, None]
    if edge_tau is not None:
        maps = torch.cat((maps, local_depth_ratio(depth_tgt)[:, None]), dim=1)
    z_proj, samples, valid = sample_at_projection(depth_src, K_src, K_tgt, src_to_tgt, maps)
    depth_at_proj = samples[:, 0]
    valid = valid & (depth_at_proj > MIN_DEPTH)
    if edge_tau is not None:
        valid = valid & (samples[:, 1] <= 1.0 + edge_tau)
    denom = torch.where(valid, depth_src, torch.ones_like(depth_src))
    occluded = (z_proj - depth_at_proj) / denom > tau
    if keep_occluded is not None:
        occluded = occluded & ~keep_occluded
    valid = valid & ~occluded
    s = torch.where(valid, (depth_at_proj - z_proj).abs() / denom, torch.zeros_like(depth_src))
    return s, valid


def fuse_cues(
    motion: Tensor, motion_valid: Tensor, structure: Tensor, structure_valid: Tensor
) -> tuple[Tensor, Tensor]:
    """The paper's fusion ``M_geo = sqrt((1_cov m)^2 + s^2)``.

    Args:
        motion: ``[B, H, W]`` motion residual ``m``.
        motion_valid: ``[B, H, W]`` where ``m`` counts: co-visible and rigid-flow valid (this is
            the ``1_cov`` indicator).
        structure: ``[B, H, W]`` structure residual ``s``.
        structure_valid: ``[B, H, W]`` where ``s`` counts.

    Returns:
        ``fused [B, H, W]`` and ``valid [B, H, W]`` (either cue valid).
    """
    m = torch.where(motion_valid, motion, torch.zeros_like(motion))
    s = torch.where(structure_valid, structure, torch.zeros_like(structure))
    return safe_norm(torch.stack((m, s), dim=0), dim=0), motion_valid | structure_valid


def masked_mean(values: Tensor, valid: Tensor, dims: tuple[int, ...]) -> Tensor:
    """Mean of ``values`` over ``dims`` where ``valid``; 0 (with zero gradient) where none is."""
    weights = valid.to(values.dtype)
    total = (torch.where(valid, values, torch.zeros_like(values)) * weights).sum(dims)
    count = weights.sum(dims)
    return total / count.clamp_min(1.0)


#: Bilinear weight above which a landing point touches a masked pixel: integer landings come out
#: of the sampler's coordinate normalisation with ~1e-7 weights on their neighbours, which are no blend.
MASK_TOUCH_WEIGHT = 1e-3


def lands_on_mask(target_mask: Tensor, displacement: Tensor) -> Tensor:
    """Which source pixels land on a masked target pixel.

    Args:
        target_mask: ``[B, H_t, W_t]`` bool, the target frame's dynamic mask.
        displacement: ``[B, 2, H, W]`` where each source pixel goes, in target pixels (the
            measured flow for the motion cue, the rigid flow, i.e. the reprojection, for the
            structure cue).

    Returns:
        ``[B, H, W]`` bool: the landing point touches a masked pixel (any of the four a bilinear
        sample there mixes with a weight above :data:`MASK_TOUCH_WEIGHT`), so content that moves
        on its own never reaches a cue through a neighbour's blend.
    """
    check_tensor(displacement, "displacement", (target_mask.shape[0], 2, None, None))
    height, width = displacement.shape[-2:]
    grid = pixel_grid(height, width, device=displacement.device, dtype=displacement.dtype)
    landing = grid + displacement.detach().permute(0, 2, 3, 1)
    return sample_bilinear(target_mask[:, None].to(displacement.dtype), landing)[:, 0] > MASK_TOUCH_WEIGHT


#: The cues, name -> :class:`Cue`, in the order of the scores (``fused`` first, the default loss).
CUES: dict[str, Cue] = {
    "fused": Cue("M_geo", "Fused", fuses=("motion", "structure"), color=(44, 160, 44),
                 marker="square", line_width=7),
    "motion": Cue("M_motion", "Motion", color=(255, 127, 14), marker="circle", line_width=4),
    "structure": Cue("M_struct", "Structure", geometry_only=True, color=(31, 119, 180),
                     marker="triangle", line_width=1),
}
#: The order the maps are made and stored in: the measured cues, then those fusing them.
MAP_ORDER = tuple(sorted(CUES, key=lambda name: bool(CUES[name].fuses)))
#: The paper's row order of its tables: structure, motion, fused.
PAPER_ORDER = tuple(reversed(CUES))
