import torch

from geco_guide.bench.synthetic import (
    inject_deformation,
    occlusion_swap_clip,
    rigid_clip,
    thin_plate_spline,
)
from geco_guide.geometry import pixel_grid, sample_bilinear


def _photometric_error(clip, i, j):
    """Mean |frame_j(p + flow) - frame_i(p)| over covisible pixels."""
    flow, covisible = clip.correspondences(i, j)
    height, width = flow.shape[-2:]
    target = pixel_grid(height, width, dtype=flow.dtype) + flow.permute(1, 2, 0)
    warped = sample_bilinear(clip.frames[j][None].to(flow.dtype), target[None])[0]
    error = (warped - clip.frames[i].to(flow.dtype)).abs().mean(0)
    return error[covisible > 0.5].mean().item(), (covisible > 0.5).float().mean().item()


def test_ground_truth_flow_explains_the_rendered_frames():
    clip = rigid_clip(num_frames=3, height=48, width=64)
    error, covisible = _photometric_error(clip, 0, 2)
    assert covisible > 0.85
    assert error < 0.01
    # The same check with zero flow shows the test has teeth: the camera really moves.
    still = (clip.frames[2] - clip.frames[0]).abs().mean().item()
    assert still > 5 * error


def test_covisibility_sees_the_pillar_hide_the_wall():
    clip = occlusion_swap_clip(num_frames=5, height=48, width=64)
    _, covisible = clip.rigid_correspondences(0, 4)
    flow_only = clip.rigid_correspondences(0, 4)[0]
    assert covisible.mean() < 0.9  # parallax behind the pillar and the image border
    assert flow_only.abs().max() > 5


def test_deformation_stays_inside_its_region_and_ground_truth_flow_follows_it():
    base = rigid_clip(num_frames=4, height=48, width=64)
    clip = inject_deformation(base, amplitude=3.0, seed=3)
    changed = (clip.frames - base.frames).abs().amax(1) > 1e-6
    assert changed.any()
    assert not (changed & ~(clip.warp.norm(dim=-1) > 0)).any()
    assert clip.mask.any() and clip.mask.float().mean() < 0.3
    rigid_error, _ = _photometric_error(base, 1, 2)
    warped_error, _ = _photometric_error(clip, 1, 2)
    assert warped_error < 2 * rigid_error + 0.005
    again = inject_deformation(base, amplitude=3.0, seed=3)
    assert torch.equal(again.frames, clip.frames)


def test_thin_plate_spline_interpolates_its_controls_and_reproduces_affine_maps():
    controls = torch.tensor([[0.0, 0.0], [1.0, 0.0], [0.0, 1.0], [1.0, 1.0], [0.5, 0.3]], dtype=torch.float64)
    values = torch.randn(5, 2, dtype=torch.float64, generator=torch.Generator().manual_seed(0))
    torch.testing.assert_close(thin_plate_spline(controls, values, controls), values)
    affine = controls @ torch.tensor([[2.0, 0.5], [-1.0, 1.0]], dtype=torch.float64) + 0.25
    points = torch.rand(7, 2, dtype=torch.float64)
    expected = points @ torch.tensor([[2.0, 0.5], [-1.0, 1.0]], dtype=torch.float64) + 0.25
    torch.testing.assert_close(thin_plate_spline(controls, affine, points), expected)


def test_occlusion_clip_marks_only_the_re_revealed_object():
    clip = occlusion_swap_clip(num_frames=9, height=48, width=64)
    swap = 9 // 4
    assert not clip.mask[:swap].any()
    assert clip.mask[swap:].any()
    assert clip.scenes[0] is not clip.scenes[-1]
