import pytest
import torch

from geco_guide.bench.ranking import average_precision, spearman
from geco_guide.estimators import Estimators
from geco_guide.bench.synthetic import (
    inject_deformation,
    occlusion_swap_clip,
    rigid_clip,
)
from geco_guide.estimators.oracle import OracleFlow, OracleGeometry
from geco_guide.estimators.ufm import UFM, UFMConfig
from geco_guide.estimators.vggt import VGGT, VGGTConfig
from geco_guide.loss.geco import (
    GeCoLoss,
    GeCoLossConfig,
    frame_pairs,
    geco_from_geometry,
)
from geco_guide.loss.motion_stats import motion_statistics
from geco_guide.types import Correspondences, SceneGeometry


@pytest.fixture(scope="module")
def rigid():
    return rigid_clip(num_frames=5, height=48, width=64)


def test_frame_pairs():
    assert frame_pairs(4, "adjacent") == [(0, 1), (1, 2), (2, 3)]
    assert frame_pairs(3, "center") == [(0, 1), (2, 1), (1, 0), (1, 2)]
    assert len(frame_pairs(4, "all")) == 12
    with pytest.raises(ValueError, match="at least 2"):
        frame_pairs(1, "adjacent")


@pytest.mark.parametrize("mode", ["adjacent", "center", "all"])
def test_rigid_scene_with_ground_truth_scores_zero(rigid, mode):
    loss = GeCoLoss(Estimators(OracleGeometry(rigid), OracleFlow(rigid)), GeCoLossConfig(pairs=mode))
    result = loss(rigid.frames[None])
    assert result.fused.item() < 1e-4
    assert result.motion.item() < 1e-4 and result.structure.item() < 1e-4
    assert result.pair_maps.fused_valid.float().mean() > 0.8  # scored on most of the image, not masked away


def test_frame_maps_average_the_pairs_of_each_source_frame(rigid):
    clip = inject_deformation(rigid, amplitude=2.0)
    pairs = frame_pairs(clip.num_frames, "all")
    result = geco_from_geometry(clip.geometry(torch.float64), clip.pair_correspondences(pairs, torch.float64), pairs)
    frame = 2
    index = [p for p, (i, _) in enumerate(pairs) if i == frame]
    maps, valid = result.pair_maps.motion[0, index], result.pair_maps.motion_valid[0, index]
    expected = (maps * valid).sum(0) / valid.sum(0).clamp_min(1)
    torch.testing.assert_close(result.frame_maps.motion[0, frame], expected)
    scores = result.frame_scores["motion"][0]
    torch.testing.assert_close(result.motion, scores.mean())


def test_deformation_is_localised_by_the_motion_map(rigid):
    clip = inject_deformation(rigid, amplitude=3.0, smoothing=0.5, seed=0)
    pairs = frame_pairs(clip.num_frames, "adjacent")
    result = geco_from_geometry(clip.geometry(torch.float64), clip.pair_correspondences(pairs, torch.float64), pairs)
    motion = torch.where(result.pair_maps.motion_valid, result.pair_maps.motion, 0.0)[0]
    truth = clip.mask[: len(pairs)]  # the warped region of each pair's source frame
    assert average_precision(motion, truth) >= 0.9
    displacement = torch.stack([clip.residual_displacement(i, j) for i, j in pairs])
    inside = truth & result.pair_maps.motion_valid[0]
    assert spearman(motion[inside], displacement[inside]) > 0.5
    assert result.fused > 10 * rigid_scores(rigid)


def rigid_scores(clip):
    pairs = frame_pairs(clip.num_frames, "adjacent")
    return geco_from_geometry(clip.geometry(torch.float64), clip.pair_correspondences(pairs, torch.float64), pairs).fused


def test_occlusion_inconsistency_is_localised_by_the_structure_map():
    clip = occlusion_swap_clip(num_frames=9, height=48, width=64)
    pairs = frame_pairs(clip.num_frames, "all")
    config = GeCoLossConfig(pairs="all")
    result = geco_from_geometry(clip.geometry(torch.float64), clip.pair_correspondences(pairs, torch.float64), pairs, config)
    assert clip.mask.any()
    for cue in ("structure", "fused"):
        values, valid = result.frame_maps.cue(cue)
        assert average_precision(torch.where(valid, values, 0.0), clip.mask[None]) >= 0.9, cue


def test_gradients_reach_geometry_and_flow():
    clip = inject_deformation(rigid_clip(num_frames=3, height=16, width=20), amplitude=2.0)
    geometry = clip.geometry(torch.float64)
    depth = geometry.depth.clone().requires_grad_(True)
    pairs = frame_pairs(3, "adjacent")
    corr = clip.pair_correspondences(pairs, torch.float64)
    flow = corr.flow.clone().requires_grad_(True)
    result = geco_from_geometry(
        SceneGeometry(depth, geometry.intrinsics, geometry.extrinsics), Correspondences(flow, corr.covisibility), pairs
    )
    result.loss.backward()
    assert depth.grad.abs().sum() > 0 and flow.grad.abs().sum() > 0


def test_geco_loss_runs_end_to_end_with_tiny_vggt_and_ufm():
    estimators = Estimators(VGGT.random(VGGTConfig.tiny(), seed=0), UFM.random(UFMConfig.tiny(), seed=0))
    loss = GeCoLoss(estimators, GeCoLossConfig(flow_downscale=0.5))
    frames = rigid_clip(num_frames=3, height=28, width=42).frames[None].float().requires_grad_(True)
    result = loss(frames)
    assert set(result.scalars()) == {"motion", "structure", "fused", "loss"}
    assert all(torch.isfinite(torch.tensor(v)) for v in result.scalars().values())
    assert result.pair_maps.fused.shape == (1, 2, 28, 42)
    result.loss.backward()
    assert frames.grad is not None and frames.grad.abs().sum() > 0
    # Without gradients through the geometry estimator, the structure cue alone gives none.
    frames.grad = None
    no_geometry_grad = GeCoLoss(estimators, GeCoLossConfig(cue="structure", geometry_grad=False))
    out = no_geometry_grad(frames)
    assert not out.loss.requires_grad


def test_confidence_percentile_drops_low_confidence_pixels(rigid):
    geometry = rigid.geometry(torch.float64)
    confidence = torch.linspace(1, 2, 48 * 64, dtype=torch.float64).view(1, 1, 48, 64).expand(1, 5, 48, 64)
    confidence = confidence.clone()
    confidence[:, :, :5] = 0.0  # rows without a prediction
    pairs = frame_pairs(5, "adjacent")
    corr = rigid.pair_correspondences(pairs, torch.float64)
    plain = geco_from_geometry(geometry, corr, pairs, GeCoLossConfig(confidence_percentile=None))
    masked = geco_from_geometry(
        SceneGeometry(geometry.depth, geometry.intrinsics, geometry.extrinsics, confidence), corr, pairs, GeCoLossConfig()
    )
    kept = masked.pair_maps.fused_valid.float().sum() / plain.pair_maps.fused_valid.float().sum()
    assert 0.7 < kept < 0.85
    assert not masked.pair_maps.fused_valid[..., :5, :].any()


def test_oracle_refuses_frames_of_another_clip(rigid):
    other = inject_deformation(rigid, amplitude=10.0)
    with pytest.raises(ValueError, match="does not match"):
        OracleGeometry(rigid).estimate_geometry(torch.rand(1, 2, 3, 48, 64))
    assert OracleFlow(other).estimate_flow(other.frames[:1], other.frames[1:2]).flow.shape == (1, 2, 48, 64)


@pytest.mark.parametrize(
    "kwargs, name",
    [
        ({"pairs": "random"}, "pairs"),
        ({"cue": "depth"}, "cue"),
        ({"covisibility_threshold": 1.5}, "covisibility_threshold"),
        ({"confidence_percentile": 100}, "confidence_percentile"),
        ({"flow_downscale": 0}, "flow_downscale"),
        ({"occlusion_tau": -1}, "occlusion_tau"),
        ({"depth_edge_tau": 0}, "depth_edge_tau"),
    ],
)
def test_bad_config_values_name_the_option(kwargs, name):
    with pytest.raises(ValueError, match=name):
        GeCoLossConfig(**kwargs)


def test_bad_inputs_to_geco_loss(rigid):
    loss = GeCoLoss(Estimators(OracleGeometry(rigid), OracleFlow(rigid)))
    with pytest.raises(ValueError, match="frames"):
        loss(rigid.frames)  # missing batch dimension
    with pytest.raises(ValueError, match="at least 2"):
        loss(rigid.frames[None, :1])
    with pytest.raises(ValueError, match="unknown GeCo loss option"):
        GeCoLoss(Estimators(OracleGeometry(rigid), OracleFlow(rigid)), {"pair": "adjacent"})
    with pytest.raises(ValueError, match="geometry"):
        GeCoLoss(Estimators(object(), OracleFlow(rigid)))
    pairs = frame_pairs(5, "adjacent")
    corr = rigid.pair_correspondences(pairs)
    with pytest.raises(ValueError, match="flow"):
        geco_from_geometry(rigid.geometry(), Correspondences(corr.flow[:2], corr.covisibility), pairs)
    with pytest.raises(ValueError, match="pairs"):
        geco_from_geometry(rigid.geometry(), corr, [(0, 7)] * 4)


def test_the_estimators_enter_as_one_bundle_and_the_earlier_spellings_are_refused_naming_it(rigid):
    geometry, flow = OracleGeometry(rigid), OracleFlow(rigid)
    loss = GeCoLoss(Estimators(geometry, flow))
    assert loss.geometry_estimator is geometry and loss.flow_estimator is flow
    assert float(loss(rigid.frames[None]).fused) == float(GeCoLoss(estimators=Estimators(geometry, flow))(
        rigid.frames[None]).fused)
    new = r"pass the models as one estimators=Estimators\(geometry, flow\) \(geco_guide.Estimators\)$"
    for earlier, first in (({"geometry_estimator": geometry, "flow_estimator": flow}, "flow_estimator"),
                           ({"geometry": geometry, "flow": flow}, "flow"), ({"geometry": geometry}, "geometry")):
        with pytest.raises(TypeError, match=rf"^GeCoLoss\({first}=...\) is the earlier spelling: {new}"):
            GeCoLoss(**earlier)
    # the pair is no bundle, positionally or as a tuple (its order could be swapped without an error)
    refused = r"^GeCoLoss takes the estimators as one Estimators\(geometry, flow\) \(geco_guide.Estimators\), got "
    for args, name in ((((geometry, flow),), "tuple"), ((geometry, flow), "OracleGeometry"), ((None,), "NoneType")):
        with pytest.raises(TypeError, match=refused + name + "$"):
            GeCoLoss(*args)
    with pytest.raises(TypeError, match="^Estimators is not a \\(geometry, flow\\) pair"):
        first, second = Estimators(geometry, flow)
    with pytest.raises(ValueError, match=r"^GeCoLoss: estimators.geometry must implement estimate_geometry\(frames\), "
                                         r"got object$"):
        GeCoLoss(Estimators(object(), flow))
    with pytest.raises(ValueError, match=r"^GeCoLoss: estimators.flow must implement estimate_flow"):
        GeCoLoss(Estimators(geometry, object()))


def test_motion_statistics():
    flow = torch.zeros(4, 2, 30, 40)
    flow[:, 0] = 5.0  # 5 px per step on a 30x40 image (diagonal 50)
    stats = motion_statistics(flow, None, duration_s=5 / 8)  # 5 frames at 8 fps: S = 0.625 s
    assert stats.per_step.tolist() == pytest.approx([0.1] * 4)
    assert stats.total_motion == pytest.approx(40.0)
    assert stats.mean_motion == pytest.approx(40.0 / 0.625)
    valid = torch.zeros(4, 30, 40, dtype=torch.bool)
    valid[:, :10] = True
    flow[:, 0, 10:] = 100.0  # ignored outside the valid pixels
    assert motion_statistics(flow, valid, duration_s=0.625).total_motion == pytest.approx(40.0)
    for bad in (0.0, float("inf"), float("nan")):
        with pytest.raises(ValueError, match="duration_s"):
            motion_statistics(flow, None, duration_s=bad)
