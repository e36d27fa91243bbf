"""The automatic dynamic masks: Kabsch, connected regions, movers found, deformations left in."""

from __future__ import annotations

import math

import pytest
import torch

from geco_guide.bench.synthetic import inject_deformation, moving_clip, rigid_clip
from geco_guide.estimators.motion_masks import MotionMasks, continue_surface, depth_at, dilate, splat
from geco_guide.geometry import kabsch
from geco_guide.io.masks import connected_regions
from geco_guide.loss.geco import frame_pairs
from geco_guide.types import DynamicMaskSource, OptionError


def _rotation(axis, angle):
    axis = torch.tensor(axis, dtype=torch.float64)
    axis = axis / axis.norm()
    k = torch.tensor([[0, -axis[2], axis[1]], [axis[2], 0, -axis[0]], [-axis[1], axis[0], 0]], dtype=torch.float64)
    return torch.eye(3, dtype=torch.float64) + math.sin(angle) * k + (1 - math.cos(angle)) * k @ k


def test_kabsch_recovers_a_rigid_motion_in_float64():
    generator = torch.Generator().manual_seed(0)
    points = torch.randn(50, 3, generator=generator, dtype=torch.float64)
    rotation, translation = _rotation((1.0, 2.0, -0.5), 0.7), torch.tensor([0.3, -1.0, 2.0], dtype=torch.float64)
    moved = points @ rotation.T + translation
    fitted_r, fitted_t = kabsch(points, moved)
    assert torch.allclose(fitted_r, rotation, atol=1e-12) and torch.allclose(fitted_t, translation, atol=1e-12)
    assert torch.linalg.det(fitted_r) == pytest.approx(1.0, abs=1e-12)
    # A mirror image is no rotation: Kabsch still returns one (det +1).
    mirrored = points * torch.tensor([1.0, 1.0, -1.0], dtype=torch.float64)
    assert torch.linalg.det(kabsch(points, mirrored)[0]) == pytest.approx(1.0, abs=1e-12)
    # Weights: outliers with weight 0 do not move the fit.
    noisy = moved.clone()
    noisy[:5] += 10.0
    weights = torch.ones(50, dtype=torch.float64)
    weights[:5] = 0
    assert torch.allclose(kabsch(points, noisy, weights)[0], rotation, atol=1e-12)


def test_connected_regions_dilate_and_splat():
    mask = torch.zeros(6, 7, dtype=torch.bool)
    mask[0:2, 0:2] = True
    mask[2, 2] = True  # diagonal neighbour: same region (8-connected)
    mask[4:6, 5:7] = True
    labels = connected_regions(mask)
    assert labels[0, 0] == labels[2, 2] != labels[5, 6]
    assert len(labels[mask].unique()) == 2 and (labels[~mask] == 0).all()
    assert int(dilate(mask[None], 1)[0].sum()) > int(mask.sum()) and torch.equal(dilate(mask, 0), mask)
    flow = torch.zeros(2, 6, 7, dtype=torch.float64)
    flow[0] = 1.0  # everything moves one pixel right
    carried = splat(mask, flow)
    assert carried[0, 1] and carried[0, 2] and not carried[0, 0]


@pytest.fixture(scope="module")
def moving():
    return moving_clip(5, 48, 64)


@pytest.mark.parametrize("mode", ["adjacent", "all"])
def test_auto_masks_find_the_moving_boxes(moving, mode):
    pairs = frame_pairs(5, mode)
    source = MotionMasks()
    assert isinstance(source, DynamicMaskSource)
    masks = source.dynamic_masks(moving.frames, moving.geometry(torch.float64), moving.pair_correspondences(pairs, torch.float64), pairs)
    truth = moving.dynamic_mask
    assert masks.shape == truth.shape and masks.dtype == torch.bool
    assert int((masks & truth).sum()) / int((masks | truth).sum()) >= 0.75
    again = MotionMasks().dynamic_masks(moving.frames, moving.geometry(torch.float64), moving.pair_correspondences(pairs, torch.float64), pairs)
    assert torch.equal(masks, again)  # seeded RANSAC


def test_auto_masks_leave_deformations_and_still_scenes_alone(moving):
    pairs = frame_pairs(5, "adjacent")
    still = rigid_clip(5, 48, 64)
    nothing = MotionMasks().dynamic_masks(still.frames, still.geometry(torch.float64), still.pair_correspondences(pairs, torch.float64), pairs)
    assert not nothing.any()
    warped = inject_deformation(still, amplitude=3.0, seed=1)
    assert warped.residual_displacement(0, 1).max() > 2.0  # the warp moves pixels well above the threshold
    masks = MotionMasks().dynamic_masks(warped.frames, warped.geometry(torch.float64), warped.pair_correspondences(pairs, torch.float64), pairs)
    assert int((masks & warped.mask).sum()) < 0.1 * int(warped.mask.sum())


def test_auto_masks_need_geometry_and_flow_and_check_options(moving):
    with pytest.raises(ValueError, match="need GeCo's geometry, flow and pairs"):
        MotionMasks().dynamic_masks(moving.frames)
    for key, value in (("min_residual_px", 0.0), ("min_inliers", 1.5), ("iterations", 0), ("dilation", -2),
                       ("rigid_tolerance", math.nan), ("iterations", 1.5), ("min_region_px", 16.5), ("dilation", True),
                       ("seed", "0"), ("min_inliers", "0.8")):
        with pytest.raises(OptionError, match=f"^{key} must be"):
            MotionMasks(**{key: value})
    assert MotionMasks(iterations=8, min_residual_px=2).iterations == 8  # integers are numbers too


def test_the_mask_source_factory_refuses_options_a_source_does_not_take():
    from geco_guide.estimators.dynamic_masks import mask_source

    with pytest.raises(ValueError, match=r"^the automatic mask source takes no option\(s\) \['bogus'\]; its options: "
                                         r"min_residual_px, .*, seed$"):
        mask_source("auto", bogus=1)
    with pytest.raises(ValueError, match=r"^a text segmenter takes no option\(s\) \['dilation'\]; its options: model, "):
        mask_source("a dog", dilation=2)  # refused before any segmenter loads


def test_a_mover_continues_into_its_unmatched_pixels_up_to_its_silhouette():
    """A box's pixels that leave the view in the pair have no match: the mask follows the box's
    surface into them, and stops at the depth step to the wall behind it."""
    depth = torch.full((8, 12), 6.0, dtype=torch.float64)
    depth[2:6, 3:10] = 3.0 + 0.05 * torch.arange(7, dtype=torch.float64)  # a slanted face, in front of the wall
    mover = torch.zeros(8, 12, dtype=torch.bool)
    mover[2:6, 3:6] = True  # the pixels whose matches fit
    unmatched = torch.zeros(8, 12, dtype=torch.bool)
    unmatched[:, 6:] = True  # leaving the view: the rest of the face and the wall beside it
    grown = continue_surface(mover, unmatched, depth)
    box = torch.zeros(8, 12, dtype=torch.bool)
    box[2:6, 3:10] = True
    assert torch.equal(grown, box)
    assert torch.equal(continue_surface(mover, torch.zeros_like(unmatched), depth), mover)  # every pixel matched: as it was


def test_depth_at_interpolates_on_a_surface_and_never_across_a_silhouette():
    rows, cols = torch.meshgrid(torch.arange(6, dtype=torch.float64), torch.arange(8, dtype=torch.float64), indexing="ij")
    plane = 1.0 / (0.2 + 0.004 * cols + 0.006 * rows)  # a plane: its inverse depth is affine in the pixel
    uv = torch.stack((cols + 0.3, rows + 0.4), -1)[:4, :6]
    exact = 1.0 / (0.2 + 0.004 * uv[..., 0] + 0.006 * uv[..., 1])
    assert torch.allclose(depth_at(plane, uv), exact, rtol=1e-12)  # nearest would be off by a pixel's slope
    step = torch.where(cols < 4, torch.full_like(cols, 3.0), torch.full_like(cols, 6.0))
    across = depth_at(step, torch.tensor([[[3.4, 2.0], [3.6, 2.0]]], dtype=torch.float64))
    assert across.tolist() == [[3.0, 6.0]]  # the nearest pixel's surface, no depth between the two
