import pytest
import torch

from geco_guide.bench.synthetic import inject_deformation, rigid_clip
from geco_guide.geometry import relative_pose, rigid_flow
from geco_guide.loss.cues import (
    fuse_cues,
    masked_mean,
    motion_residual,
    structure_residual,
)
from geco_guide.loss.geco import GeCoLossConfig, frame_pairs, geco_from_geometry
from geco_guide.types import Correspondences, SceneGeometry


def _pair_inputs(dtype=torch.float64):
    clip = rigid_clip(num_frames=2, height=10, width=14)
    depth = clip.depth.to(dtype)
    K = clip.intrinsics.to(dtype)
    pose = relative_pose(clip.extrinsics[:1].to(dtype), clip.extrinsics[1:].to(dtype))
    return depth[:1], depth[1:], K[:1], K[1:], pose


def test_motion_residual_formula():
    K = torch.tensor([[[100.0, 0, 5], [0, 50.0, 5], [0, 0, 1]]], dtype=torch.float64)
    flow = torch.zeros(1, 2, 2, 3, dtype=torch.float64)
    rigid = flow.clone()
    flow[0, 0, 1, 2] = 3.0
    flow[0, 1, 1, 2] = 2.0
    m = motion_residual(flow, rigid, K)
    assert m[0, 1, 2].item() == pytest.approx(((3 / 100) ** 2 + (2 / 50) ** 2) ** 0.5)
    assert m.flatten().tolist().count(0.0) == 5


def test_structure_residual_flags_a_depth_mismatch_and_masks_occlusion():
    d_src, d_tgt, K_src, K_tgt, pose = _pair_inputs()
    s, valid = structure_residual(d_src, d_tgt, K_src, K_tgt, pose)
    assert valid.float().mean() > 0.8
    assert s[valid].mean() < 1e-3  # bilinear depth sampling on a 10x14 image: creases only
    # The target sees every surface 10% farther: about 10% relative residual everywhere.
    s_far, valid_far = structure_residual(d_src, d_tgt * 1.1, K_src, K_tgt, pose)
    assert valid_far.equal(valid)
    assert s_far[valid_far].min() > 0.08 and s_far[valid_far].max() < 0.12
    # A target surface 10% closer hides the source points: all excluded as occluded.
    _, valid_near = structure_residual(d_src, d_tgt * 0.9, K_src, K_tgt, pose)
    assert not valid_near.any()


def test_script_occlusion_rule_keeps_covisible_pixels_the_depth_test_calls_occluded():
    d_src, d_tgt, K_src, K_tgt, pose = _pair_inputs()
    _, valid = structure_residual(d_src, d_tgt, K_src, K_tgt, pose)
    near = d_tgt * 0.9  # every source point hidden by a closer target surface
    covisible = torch.zeros_like(valid)
    covisible[..., :7] = True  # the flow estimator calls the left half co-visible
    s, kept = structure_residual(d_src, near, K_src, K_tgt, pose, keep_occluded=covisible)
    assert kept.equal(valid & covisible)  # occluded by depth, kept where co-visible only
    assert s[kept].min() > 0.08  # and scored against the closer surface, as the script does
    # through the metric: the config's structure_occlusion selects the rule
    clip = rigid_clip(num_frames=2, height=10, width=14)
    depth = torch.cat((clip.depth[:1], clip.depth[1:] * 0.9))[None]
    geometry = SceneGeometry(depth=depth, intrinsics=clip.intrinsics[None], extrinsics=clip.extrinsics[None])
    corr = Correspondences(flow=torch.zeros(1, 2, 10, 14), covisibility=torch.ones(1, 10, 14))
    for rule, any_valid in (("depth", False), ("covisibility", True)):
        config = GeCoLossConfig(structure_occlusion=rule, confidence_percentile=None, depth_edge_tau=None)
        result = geco_from_geometry(geometry, corr, [(0, 1)], config)
        assert bool(result.pair_maps.structure_valid.any()) == any_valid
    with pytest.raises(ValueError, match="structure_occlusion"):
        GeCoLossConfig(structure_occlusion="both")


def test_structure_residual_edge_test_drops_samples_that_straddle_a_depth_edge():
    d_src, d_tgt, K_src, K_tgt, pose = _pair_inputs()
    stepped = d_tgt.clone()
    stepped[..., 7:] *= 2.0  # a hard depth edge down the middle of the target
    s, valid = structure_residual(d_src, stepped, K_src, K_tgt, pose)
    _, valid_edge = structure_residual(d_src, stepped, K_src, K_tgt, pose, edge_tau=0.1)
    assert (valid_edge <= valid).all() and valid_edge.sum() < valid.sum()
    dropped = valid & ~valid_edge
    assert s[dropped].min() > 0  # what the edge test removes are blended, wrong samples


def test_fusion_follows_the_paper_equation():
    m = torch.tensor([[[0.3, 0.3, 0.3, 0.0]]])
    s = torch.tensor([[[0.4, 0.4, 0.0, 0.0]]])
    m_valid = torch.tensor([[[True, False, True, False]]])
    s_valid = torch.tensor([[[True, True, False, False]]])
    fused, valid = fuse_cues(m, m_valid, s, s_valid)
    torch.testing.assert_close(fused, torch.tensor([[[0.5, 0.4, 0.3, 0.0]]]))
    assert valid.tolist() == [[[True, True, True, False]]]


def test_gradcheck_motion_and_structure_residual():
    d_src, d_tgt, K_src, K_tgt, pose = _pair_inputs()
    d_src = d_src[:, 3:6, 4:8].contiguous().requires_grad_(True)
    # Keep the crop's own intrinsics consistent: shift the principal point.
    K_crop = K_src.clone()
    K_crop[:, 0, 2] -= 4
    K_crop[:, 1, 2] -= 3
    d_tgt = d_tgt.clone().requires_grad_(True)
    flow = torch.randn(1, 2, 3, 4, dtype=torch.float64, requires_grad=True)

    def motion(depth, observed):
        rigid, _ = rigid_flow(depth, K_crop, K_tgt, pose)
        return motion_residual(observed, rigid, K_crop)

    assert torch.autograd.gradcheck(motion, (d_src, flow))
    assert torch.autograd.gradcheck(lambda a, b: structure_residual(a, b, K_crop, K_tgt, pose)[0], (d_src, d_tgt))


def _geco(clip, pairs_mode="adjacent", depth_scale=1.0, translation_scale=1.0, dtype=torch.float64):
    geometry = clip.geometry(dtype)
    extrinsics = geometry.extrinsics.clone()
    extrinsics[..., 3] *= translation_scale
    geometry = SceneGeometry(depth=geometry.depth * depth_scale, intrinsics=geometry.intrinsics, extrinsics=extrinsics)
    pairs = frame_pairs(clip.num_frames, pairs_mode)
    return geco_from_geometry(geometry, clip.pair_correspondences(pairs, dtype), pairs, GeCoLossConfig(pairs=pairs_mode))


@pytest.mark.parametrize("k", [0.01, 0.37, 5.0, 1000.0])
def test_scale_invariance(k):
    # A deformed clip so that both cues are non-trivial.
    clip = inject_deformation(rigid_clip(num_frames=3, height=24, width=32), amplitude=2.0)
    base = _geco(clip)
    scaled = _geco(clip, depth_scale=k, translation_scale=k)
    assert base.fused > 1e-4
    for name in ("motion", "structure", "fused"):
        torch.testing.assert_close(getattr(base.pair_maps, name), getattr(scaled.pair_maps, name), atol=1e-5, rtol=0)
        assert getattr(base.pair_maps, f"{name}_valid").equal(getattr(scaled.pair_maps, f"{name}_valid"))
        assert abs(float(getattr(base, name)) - float(getattr(scaled, name))) < 1e-5


def _degenerate_geometry(kind: str, dtype=torch.float32):
    g = torch.Generator().manual_seed(0)
    depth = 1.0 + torch.rand(1, 2, 6, 8, generator=g, dtype=dtype)
    K = torch.tensor([[20.0, 0, 3.5], [0, 20.0, 2.5], [0, 0, 1]], dtype=dtype).expand(1, 2, 3, 3).clone()
    extrinsics = torch.eye(3, 4, dtype=dtype).expand(1, 2, 3, 4).clone()
    extrinsics[0, 1, 0, 3] = 0.05
    covisibility = torch.ones(1, 6, 8, dtype=dtype)
    if kind == "zero_depth":
        depth = torch.zeros_like(depth)
    elif kind == "negative_depth":
        depth = -depth
    elif kind == "behind_camera":
        extrinsics[0, 1, 2, 3] = -50.0
    elif kind == "outside_image":
        extrinsics[0, 1, 0, 3] = 1e4
    elif kind == "not_covisible":
        covisibility = torch.zeros_like(covisibility)
    return depth, K, extrinsics, covisibility


@pytest.mark.parametrize("kind", ["zero_depth", "negative_depth", "behind_camera", "outside_image", "not_covisible"])
def test_degenerate_inputs_give_finite_results_and_zero_gradient(kind):
    depth, K, extrinsics, covisibility = _degenerate_geometry(kind)
    depth.requires_grad_(True)
    flow = torch.randn(1, 2, 6, 8, generator=torch.Generator().manual_seed(1), requires_grad=True)
    geometry = SceneGeometry(depth=depth, intrinsics=K, extrinsics=extrinsics)
    config = GeCoLossConfig(cue="motion" if kind == "not_covisible" else "fused")
    result = geco_from_geometry(geometry, Correspondences(flow, covisibility), [(0, 1)], config)
    result.loss.backward()
    for tensor in (result.motion, result.structure, result.fused, result.pair_maps.fused):
        assert torch.isfinite(tensor).all()
    assert result.loss.item() == 0.0
    assert torch.isfinite(depth.grad).all() and depth.grad.abs().max() == 0
    assert torch.isfinite(flow.grad).all() and flow.grad.abs().max() == 0


def test_masked_mean_of_nothing_is_zero_with_zero_gradient():
    values = torch.randn(3, 4, requires_grad=True)
    mean = masked_mean(values, torch.zeros(3, 4, dtype=torch.bool), dims=(0, 1))
    mean.backward()
    assert mean.item() == 0.0 and values.grad.abs().max() == 0


@pytest.mark.parametrize(
    "call, name",
    [
        (lambda f, K: motion_residual(f[:, :1], f[:, :1], K), "flow"),
        (lambda f, K: motion_residual(f, f[..., :-1], K), "rigid_flow"),
        (lambda f, K: motion_residual(f, f, K[:, :2]), "K_src"),
        (lambda f, K: motion_residual(f.int(), f, K), "flow"),
    ],
)
def test_bad_inputs_name_the_argument(call, name):
    flow = torch.zeros(1, 2, 4, 5)
    K = torch.eye(3)[None]
    with pytest.raises(ValueError, match=name):
        call(flow, K)
