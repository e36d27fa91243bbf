import pytest
import torch

from geco_guide import geometry as geo
from geco_guide.bench.synthetic import default_intrinsics, look_at


def _camera_pair(dtype=torch.float64):
    K = default_intrinsics(12, 16, dtype=dtype)[None]
    extr_src = look_at(torch.tensor([0.0, 0.0, 0.0], dtype=dtype), torch.tensor([0.1, 0.0, 5.0], dtype=dtype))[None]
    extr_tgt = look_at(torch.tensor([0.3, -0.1, 0.2], dtype=dtype), torch.tensor([0.0, 0.1, 5.0], dtype=dtype))[None]
    depth = 3.0 + torch.rand(1, 12, 16, dtype=dtype, generator=torch.Generator().manual_seed(0))
    return depth, K, extr_src, extr_tgt


def test_relative_pose_maps_source_points_to_target_points():
    _, _, extr_src, extr_tgt = _camera_pair()
    world = torch.tensor([[0.5, -0.2, 4.0], [1.0, 1.0, 6.0]], dtype=torch.float64)
    in_src = world @ extr_src[0, :, :3].T + extr_src[0, :, 3]
    in_tgt = world @ extr_tgt[0, :, :3].T + extr_tgt[0, :, 3]
    moved = geo.transform_points(in_src[None], geo.relative_pose(extr_src, extr_tgt))[0]
    torch.testing.assert_close(moved, in_tgt)


def test_identity_pose_gives_zero_rigid_flow():
    depth, K, extr, _ = _camera_pair()
    flow, valid = geo.rigid_flow(depth, K, K, geo.relative_pose(extr, extr))
    assert valid.all()
    assert flow.abs().max() < 1e-10


def test_rigid_flow_matches_explicit_point_projection():
    depth, K, extr_src, extr_tgt = _camera_pair()
    flow, valid = geo.rigid_flow(depth, K, K, geo.relative_pose(extr_src, extr_tgt))
    k = K[0]
    for v, u in [(0, 0), (5, 7), (11, 15), (3, 12)]:
        z = depth[0, v, u]
        cam = torch.stack([(u - k[0, 2]) / k[0, 0] * z, (v - k[1, 2]) / k[1, 1] * z, z])
        world = extr_src[0, :, :3].T @ (cam - extr_src[0, :, 3])
        tgt = extr_tgt[0, :, :3] @ world + extr_tgt[0, :, 3]
        u_t = k[0, 0] * tgt[0] / tgt[2] + k[0, 2]
        v_t = k[1, 1] * tgt[1] / tgt[2] + k[1, 2]
        inside = 0 <= u_t <= 15 and 0 <= v_t <= 11
        assert bool(valid[0, v, u]) == inside
        if inside:
            torch.testing.assert_close(flow[0, :, v, u], torch.stack([u_t - u, v_t - v]))


def test_rigid_flow_validity_rules():
    depth, K, extr_src, extr_tgt = _camera_pair()
    depth = depth.clone()
    depth[0, 0, 0] = 0.0
    depth[0, 0, 1] = -2.0
    pose = geo.relative_pose(extr_src, extr_tgt)
    flow, valid = geo.rigid_flow(depth, K, K, pose)
    assert not valid[0, 0, 0] and not valid[0, 0, 1]
    assert (flow[:, :, ~valid[0]] == 0).all()
    # A target camera behind the scene sees nothing in front of it.
    behind = pose.clone()
    behind[0, 2, 3] -= 100.0
    _, valid = geo.rigid_flow(depth, K, K, behind)
    assert not valid.any()
    # A tiny target image contains almost no projection.
    _, valid_small = geo.rigid_flow(depth, K, K, pose, tgt_hw=(2, 2))
    assert valid_small.sum() < valid.numel() // 10


def test_sample_bilinear_puts_pixel_centres_at_integers():
    image = torch.arange(12, dtype=torch.float64).view(1, 1, 3, 4)
    uv = torch.tensor([[[0.0, 0.0], [3.0, 2.0], [1.5, 1.0], [2.0, 0.5]]], dtype=torch.float64)
    torch.testing.assert_close(geo.sample_bilinear(image, uv)[0, 0], torch.tensor([0.0, 11.0, 5.5, 4.0], dtype=torch.float64))


def test_depth_sampled_at_the_projection_of_a_consistent_plane_is_exact_where_valid():
    # A fronto-parallel plane: z is constant in both views after a pure sideways shift.
    K = default_intrinsics(12, 16)[None]
    depth = torch.full((1, 12, 16), 4.0, dtype=torch.float64)
    pose = torch.eye(4, dtype=torch.float64)[None]
    pose[0, 0, 3] = 0.2
    z_proj, samples, valid = geo.sample_at_projection(depth, K, K, pose, depth[:, None])
    assert valid.any() and not valid.all()
    torch.testing.assert_close(z_proj[valid], samples[:, 0][valid])


def test_resized_intrinsics_follow_pixel_centres():
    K = default_intrinsics(48, 64)[None]
    point = torch.tensor([[[0.3, -0.2, 2.0]]], dtype=torch.float64)
    uv, _ = geo.project(point, K)
    uv_small, _ = geo.project(point, geo.resize_intrinsics(K, (48, 64), (24, 16)))
    scale = torch.tensor([16 / 64, 24 / 48], dtype=torch.float64)
    torch.testing.assert_close(uv_small, scale * (uv + 0.5) - 0.5)
    uv_crop, _ = geo.project(point, geo.crop_intrinsics(K, top=5, left=7))
    torch.testing.assert_close(uv_crop, uv - torch.tensor([7.0, 5.0], dtype=torch.float64))
    torch.testing.assert_close(geo.crop_intrinsics(geo.crop_intrinsics(K, 5, 7), -5, -7), K)


def test_resize_flow_scales_vectors():
    flow = torch.ones(1, 2, 4, 6, dtype=torch.float64)
    resized = geo.resize_flow(flow, (8, 18))
    assert resized.shape == (1, 2, 8, 18)
    torch.testing.assert_close(resized[0, :, 0, 0], torch.tensor([3.0, 2.0], dtype=torch.float64))


def test_gradcheck_rigid_flow():
    depth, K, extr_src, extr_tgt = _camera_pair()
    depth = depth[:, :4, :5].clone().requires_grad_(True)
    pose = geo.relative_pose(extr_src, extr_tgt).clone().requires_grad_(True)
    K = K.clone().requires_grad_(True)
    assert torch.autograd.gradcheck(lambda d, k, p: geo.rigid_flow(d, k, k, p)[0], (depth, K, pose))


def test_gradcheck_sample_at_projection():
    depth, K, extr_src, extr_tgt = _camera_pair()
    src = depth[:, :4, :5].clone().requires_grad_(True)
    tgt = (depth + 0.1).clone().requires_grad_(True)
    pose = geo.relative_pose(extr_src, extr_tgt)
    assert torch.autograd.gradcheck(lambda s, t: geo.sample_at_projection(s, K, K, pose, t[:, None])[:2], (src, tgt))


@pytest.mark.parametrize(
    "call, name",
    [
        (lambda d, K, p: geo.rigid_flow(d[0], K, K, p), "depth_src"),
        (lambda d, K, p: geo.rigid_flow(d, K[0], K, p), "K_src"),
        (lambda d, K, p: geo.rigid_flow(d, K, K, p[:, :3]), "src_to_tgt"),
        (lambda d, K, p: geo.rigid_flow(d.long(), K, K, p), "depth_src"),
        (lambda d, K, p: geo.sample_at_projection(d, K, K, p, d), "target_maps"),
        (lambda d, K, p: geo.relative_pose(p[:, :3], p), "extr_tgt"),
    ],
)
def test_bad_shapes_and_dtypes_name_the_argument(call, name):
    depth, K, extr_src, extr_tgt = _camera_pair()
    with pytest.raises(ValueError, match=name):
        call(depth, K, geo.relative_pose(extr_src, extr_tgt))
