"""Dynamic masks in the loss and the metric: the drop rule, None unchanged, NaN with a reason, mask
files and every bad mask input as one line."""

from __future__ import annotations

import json
import math
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
import torch
from PIL import Image

from geco_guide.bench.synthetic import inject_deformation, moving_clip, rigid_clip
from geco_guide.cli.evaluate import main as evaluate_main
from geco_guide.estimators import Estimators
from geco_guide.estimators.dynamic_masks import GivenMasks, mask_source
from geco_guide.estimators.motion_masks import MotionMasks
from geco_guide.estimators.oracle import OracleFlow, OracleGeometry
from geco_guide.estimators.ufm import UFM, UFMConfig
from geco_guide.estimators.vggt import VGGT, VGGTConfig
from geco_guide.io.masks import MaskReadError, fit_masks, read_masks
from geco_guide.io.video import write_video
from geco_guide.loss.cues import lands_on_mask
from geco_guide.loss.geco import MIN_UNMASKED_FRACTION, GeCoLoss, GeCoLossConfig, frame_pairs, geco_from_geometry
from geco_guide.metric.detection import detection_maps, frame_scores, render_detection
from geco_guide.metric.evaluate import evaluate_video, render_maps
from geco_guide.metric.render import INVALID_COLOR, hatch
from geco_guide.types import Correspondences, DynamicMaskSource, SceneGeometry


@pytest.fixture(scope="module")
def moving():
    return moving_clip(5, 24, 32)


def _score(clip, masks=None, mode="adjacent", **kwargs):
    pairs = frame_pairs(clip.num_frames, mode)
    return geco_from_geometry(clip.geometry(torch.float64), clip.pair_correspondences(pairs, torch.float64), pairs,
                              GeCoLossConfig(pairs=mode, **kwargs), dynamic_masks=masks)


# --- None is the paper's metric -----------------------------------------------------------------

# Computed by the code before dynamic masks existed, on the same input (float64, exact hex). A CPU
# of another vector width sums in another order, so the last bits may differ from machine to
# machine: the check allows a few units in the last place, far below any change of the metric.
BEFORE_MASKS = {
    "adjacent": (["0x1.d54d70e3bd7fcp-9", "0x1.35b2986de279fp-13", "0x1.e8a202d11bf21p-9"],
                 ["0x1.d36d19e114f88p-9", "0x1.22728225ee069p-8", "0x1.a193ea4662d0bp-9", "0x0.0p+0"]),
    "all": (["0x1.cd88842586648p-9", "0x1.e531ce6d0825fp-14", "0x1.dca8f46efb3afp-9"],
            ["0x1.e693098a95c24p-9", "0x1.e769fe15895cbp-9", "0x1.f333e4586eb04p-9", "0x1.b172e5c35f1c8p-9"]),
}


@pytest.mark.parametrize("mode", ["adjacent", "all"])
def test_no_masks_keep_the_numbers_of_before(mode):
    clip = inject_deformation(rigid_clip(4, 24, 32), amplitude=2.0, seed=1)
    pairs = frame_pairs(4, mode)
    geometry = clip.geometry(torch.float64)
    geometry.confidence = torch.linspace(0.1, 1, 4 * 24 * 32, dtype=torch.float64).reshape(1, 4, 24, 32)
    result = geco_from_geometry(geometry, clip.pair_correspondences(pairs, torch.float64), pairs, GeCoLossConfig(pairs=mode),
                                dynamic_masks=None)
    scalars, frames = BEFORE_MASKS[mode]
    before = [float.fromhex(x) for x in scalars]
    assert [float(getattr(result, n)) for n in ("motion", "structure", "fused")] == pytest.approx(before, rel=1e-14)
    before_frames = [float.fromhex(x) for x in frames]
    assert result.frame_scores["fused"][0].tolist() == pytest.approx(before_frames, rel=1e-14, abs=0)
    assert result.dynamic_masks is None and result.masked_fraction is None and result.mask_source is None


# --- the drop rule -----------------------------------------------------------------------------


def test_lands_on_mask_touches_the_four_pixels_a_bilinear_sample_mixes():
    mask = torch.zeros(1, 4, 5, dtype=torch.bool)
    mask[0, 2, 3] = True
    flow = torch.zeros(1, 2, 4, 5, dtype=torch.float64)
    flow[0, 0, 1, 1] = 1.5  # (u=1, v=1) -> (2.5, 1.5): mixes (2|3, 1|2), touching (3, 2)
    flow[0, 1, 1, 1] = 0.5
    flow[0, 0, 0, 0] = 1.0  # (0, 0) -> (1, 0): far from the mask
    hit = lands_on_mask(mask, flow)
    assert hit[0, 1, 1] and not hit[0, 0, 0]
    assert hit[0, 2, 3]  # zero flow: the masked pixel lands on itself
    assert int(hit.sum()) == 2


def test_drop_rule_on_a_hand_made_pair():
    """Two frames of a plane; source pixel A is masked, B's flow lands on the target's masked
    pixel, C's reprojection does; D is untouched. Only the cues the rule names drop."""
    height, width = 6, 8
    K = torch.tensor([[10.0, 0, 3.5], [0, 10.0, 2.5], [0, 0, 1]], dtype=torch.float64)
    geometry = SceneGeometry(depth=torch.full((1, 2, height, width), 4.0, dtype=torch.float64),
                             intrinsics=K.expand(1, 2, 3, 3).clone(),
                             extrinsics=torch.eye(3, 4, dtype=torch.float64).expand(1, 2, 3, 4).clone())
    flow = torch.zeros(1, 2, height, width, dtype=torch.float64)
    flow[0, 0, 2, 2] = 3.0  # B = (2, 2) flows to (5, 2); identical cameras: it reprojects onto itself
    masks = torch.zeros(2, height, width, dtype=torch.bool)
    masks[0, 1, 1] = True  # A = (1, 1) masked in the source
    masks[1, 2, 5] = True  # where B's flow lands
    masks[1, 4, 6] = True  # where C = (6, 4) reprojects (and, with zero flow, flows)
    pairs = [(0, 1)]
    corr = Correspondences(flow, torch.ones(1, height, width, dtype=torch.float64))
    config = GeCoLossConfig(confidence_percentile=None, depth_edge_tau=None)
    plain = geco_from_geometry(geometry, corr, pairs, config)
    masked = geco_from_geometry(geometry, corr, pairs, config, dynamic_masks=masks)
    motion, structure = masked.pair_maps.motion_valid[0, 0], masked.pair_maps.structure_valid[0, 0]
    assert plain.pair_maps.motion_valid.all() and plain.pair_maps.structure_valid.all()
    assert not motion[1, 1] and not structure[1, 1]  # A: masked in its source frame
    assert not motion[2, 2] and structure[2, 2]  # B: only its flow lands on the mask
    assert not motion[4, 6] and not structure[4, 6]  # C: both land there
    # the target's masked pixels are sources too: with zero flow and one camera they land on themselves
    assert sorted(map(tuple, (~motion).nonzero().tolist())) == [(1, 1), (2, 2), (2, 5), (4, 6)]
    assert sorted(map(tuple, (~structure).nonzero().tolist())) == [(1, 1), (2, 5), (4, 6)]
    assert motion[0, 0] and structure[0, 0]  # D
    assert masked.mask_source == "given"
    assert masked.masked_fraction.tolist() == [[pytest.approx(1 / 48), pytest.approx(2 / 48)]]


def test_true_masks_remove_the_moving_boxes_from_the_score(moving):
    still = _score(moving_clip(5, 24, 32, still=True))
    plain = _score(moving)
    masked = _score(moving, moving.dynamic_mask)
    assert plain.fused > 20 * still.fused
    assert masked.fused < 2 * still.fused
    assert masked.mask_source == "given"
    assert torch.equal(masked.dynamic_masks[0].cpu(), moving.dynamic_mask)


def test_frames_below_the_minimum_unmasked_area_do_not_count(moving):
    assert 1 / 32 < MIN_UNMASKED_FRACTION
    masks = torch.zeros(5, 24, 32, dtype=torch.bool)
    masks[1] = True
    masks[2] = True
    masks[2, :, 16] = False  # one column: 3.1 % of the frame, below the minimum
    result = _score(moving, masks, confidence_percentile=None)
    # frame 0's one pair lands on the all-masked frame 1; frame 2 keeps a column; frame 4 is no source
    assert result.frame_has_valid["fused"][0].tolist() == [False, False, False, True, False]
    assert result.frame_maps.fused_valid[0, 2].any()  # frame 2 has valid pixels, too few to count
    everything = _score(moving, torch.ones(5, 24, 32, dtype=torch.bool))
    assert float(everything.fused) == 0.0 and not everything.frame_has_valid["fused"].any()


# --- the loss ----------------------------------------------------------------------------------


@pytest.fixture(scope="module")
def tiny_loss():
    return GeCoLoss(Estimators(VGGT.random(VGGTConfig.tiny(), seed=0), UFM.random(UFMConfig.tiny(), seed=0)),
                    GeCoLossConfig(flow_downscale=0.5))


def test_loss_takes_masks_as_tensor_or_source_and_an_empty_clip_is_zero_without_gradient(tiny_loss):
    frames = rigid_clip(num_frames=3, height=28, width=42).frames[None].float().requires_grad_(True)
    half = torch.zeros(1, 3, 14, 21, dtype=torch.bool)
    half[..., :10] = True  # resized (nearest) to 28 x 42
    result = tiny_loss(frames, dynamic_masks=half)
    assert result.dynamic_masks.shape == (1, 3, 28, 42) and result.dynamic_masks[..., :20].all()
    result.loss.backward()
    assert frames.grad.abs().sum() > 0
    frames.grad = None
    empty = tiny_loss(frames, dynamic_masks=GivenMasks(torch.ones(3, 28, 42, dtype=torch.bool), "all of it"))
    assert empty.mask_source == "all of it" and float(empty.loss.detach()) == 0.0
    empty.loss.backward()
    assert frames.grad is None or frames.grad.abs().sum() == 0


class _Counting:
    """A mask source that records what it was given."""

    source_name = "counting"

    def __init__(self):
        self.calls = []

    def dynamic_masks(self, frames, geometry=None, flow=None, pairs=None):
        self.calls.append((frames.requires_grad, geometry.depth.shape, flow.flow.shape, list(pairs)))
        return torch.zeros(frames.shape[0], *frames.shape[-2:], dtype=torch.bool)


def test_a_mask_source_is_asked_once_per_clip_with_detached_inputs(tiny_loss):
    source = _Counting()
    assert isinstance(source, DynamicMaskSource)
    frames = rigid_clip(num_frames=3, height=28, width=42).frames[None].float().expand(2, -1, -1, -1, -1).clone()
    result = tiny_loss(frames.requires_grad_(True), dynamic_masks=source)
    assert result.mask_source == "counting" and result.dynamic_masks.shape == (2, 3, 28, 42)
    assert source.calls == [(False, (1, 3, 28, 42), (2, 2, 28, 42), [(0, 1), (1, 2)])] * 2


@pytest.mark.parametrize("masks, message", [
    (torch.zeros(3, 28), "shape [S, H, W] or [B, S, H, W]"),
    (torch.full((3, 28, 42), 0.5), "must be binary"),
    (torch.full((3, 28, 42), math.nan), "NaN or inf"),
    (torch.zeros(4, 28, 42, dtype=torch.bool), "hold 4 frame(s), the video 3"),
    (torch.zeros(3, 28, 28, dtype=torch.bool), "a different aspect ratio"),
    (torch.zeros(2, 3, 28, 42, dtype=torch.bool), "hold 2 clip(s), the frames 1"),
    ([[0, 1]], "must be a tensor, a path or a mask source"),
    ("/no/such/masks.npz", "no such file or folder"),
])
def test_bad_masks_are_one_line_before_any_estimator_runs(masks, message):
    class Refuse:
        def estimate_geometry(self, frames):
            raise AssertionError("the estimator ran")

        def estimate_flow(self, source, target):
            raise AssertionError("the estimator ran")

    frames = rigid_clip(num_frames=3, height=28, width=42).frames[None].float()
    with pytest.raises(MaskReadError) as err:
        GeCoLoss(Estimators(Refuse(), Refuse()))(frames, dynamic_masks=masks)
    assert message in str(err.value) and "\n" not in str(err.value)


# --- mask files --------------------------------------------------------------------------------


def test_mask_files_round_trip(tmp_path: Path, moving):
    truth = moving.dynamic_mask
    np.savez(tmp_path / "m.npz", masks=truth.numpy())
    folder = tmp_path / "pngs"
    folder.mkdir()
    for k, mask in enumerate(truth):  # 0/255 PNGs, natural order
        Image.fromarray(mask.numpy().astype(np.uint8) * 255).save(folder / f"{k}.png")
    big = truth.repeat_interleave(8, -1).repeat_interleave(8, -2)  # a lossy mp4 at 8x the size
    write_video(tmp_path / "m.mp4", big[:, None].float().expand(-1, 3, -1, -1), fps=8)
    for path in ("m.npz", "pngs"):
        masks, count = read_masks(tmp_path / path)
        assert count == 5 and torch.equal(masks, truth)
    video, count = read_masks(tmp_path / "m.mp4", select=[1, 3])
    assert count == 5
    resized = fit_masks(video, 2, (24, 32))
    assert (resized != truth[[1, 3]]).float().mean() < 0.02  # codec blur at the edges only
    assert torch.equal(read_masks(tmp_path / "m.npz", select=[4, 0])[0], truth[[4, 0]])


def test_mask_source_factory():
    assert mask_source(None) is None
    given = mask_source(torch.zeros(2, 4, 4, dtype=torch.bool))
    assert isinstance(given, GivenMasks) and given.source_name == "given"
    auto = mask_source("auto", dilation=2)
    assert isinstance(auto, MotionMasks) and auto.dilation == 2 and auto.source_name == "auto"
    assert mask_source(auto) is auto
    with pytest.raises(MaskReadError, match="no such file"):
        mask_source("masks/missing.npz")
    with pytest.raises(ValueError, match="take no options"):
        mask_source(torch.zeros(2, 4, 4), dilation=1)
    with pytest.raises(ValueError, match="empty string"):
        mask_source("  ")
    with pytest.raises(ValueError, match="dilation must be >= 0"):
        mask_source("auto", dilation=-1)


# --- evaluate_video ----------------------------------------------------------------------------


def test_evaluate_video_picks_the_protocol_frames_from_the_masks(tmp_path: Path):
    clip = moving_clip(12, 24, 32)
    oracle = dict(estimators=Estimators(OracleGeometry(clip), OracleFlow(clip)))
    # 12 frames at 16 fps sampled at 8 fps: every other frame. Masks that differ per frame show
    # whether the same frames were taken.
    np.savez(tmp_path / "m.npz", masks=clip.dynamic_mask.numpy())
    from_file = evaluate_video(clip.frames.float(), fps=16, dynamic_masks=tmp_path / "m.npz", maps=True, **oracle)
    from_tensor = evaluate_video(clip.frames.float(), fps=16, dynamic_masks=clip.dynamic_mask, maps=True, **oracle)
    evaluated = [row["index"] for row in from_file.frame_scores]
    assert evaluated == list(range(0, 12, 2))
    assert torch.equal(from_file.maps.dynamic_masks, clip.dynamic_mask[evaluated])
    assert from_file.fused == from_tensor.fused
    plain = evaluate_video(clip.frames.float(), fps=16, **oracle)
    assert from_file.fused < plain.fused / 50
    data = from_file.to_dict()
    assert data["dynamic_masks"]["source"] == f"given: {tmp_path / 'm.npz'}"
    assert 0.05 < data["dynamic_masks"]["masked_fraction"] < 0.15
    assert all("masked_fraction" in row for row in data["frame_scores"])
    assert "dynamic_masks" not in plain.to_dict() and "masked_fraction" not in plain.frame_scores[0]
    with pytest.raises(MaskReadError, match="hold 11 frame"):
        evaluate_video(clip.frames.float(), fps=16, dynamic_masks=clip.dynamic_mask[:11], **oracle)


def test_all_masked_video_scores_nan_with_its_reason():
    clip = moving_clip(4, 24, 32)
    result = evaluate_video(clip.frames.float(), Estimators(OracleGeometry(clip), OracleFlow(clip)), fps=8,
                            dynamic_masks=torch.ones(4, 24, 32, dtype=torch.bool))
    assert math.isnan(result.fused) and math.isnan(result.motion)
    data = json.loads(json.dumps(result.to_dict()))
    assert data["fused"] is None and data["nan_reason"] == data["dynamic_masks"]["nan_reason"]
    assert "outside the dynamic mask" in data["dynamic_masks"]["nan_reason"]
    assert all(row["fused"] is None and "dynamic mask" in row["note"] for row in data["frame_scores"])


def test_maps_draw_masked_pixels_striped(moving):
    oracle = Estimators(OracleGeometry(moving), OracleFlow(moving))
    maps = detection_maps(moving.frames.float(), oracle, window=3, dynamic_masks=moving.dynamic_mask)
    assert torch.equal(maps.dynamic_masks, moving.dynamic_mask)
    image = render_detection(maps, frame_scores(maps))
    plain = detection_maps(moving.frames.float(), oracle, window=3)
    assert not torch.equal(image, render_detection(plain, frame_scores(plain)))
    result = evaluate_video(moving.frames.float(), oracle, fps=8, dynamic_masks=moving.dynamic_mask, maps=True)
    unmasked = replace(result, maps=replace(result.maps, dynamic_masks=None))
    assert not torch.equal(render_maps(result), render_maps(unmasked))
    images = torch.zeros(2, 3, 8, 8)
    mask = torch.zeros(2, 8, 8, dtype=torch.bool)
    mask[1, 2:6, 2:6] = True
    striped = hatch(images, mask)
    assert torch.equal(striped[~mask[:, None].expand(-1, 3, -1, -1)], images[~mask[:, None].expand(-1, 3, -1, -1)])
    inside = {round(float(x), 2) for x in striped[1, 0, 2:6, 2:6].flatten()}
    assert inside == {0.85, INVALID_COLOR[0]}  # stripes: never read as plain "no valid pixel" grey


def test_evaluate_command_takes_dynamic_masks(tmp_path: Path, capsys):
    clip = rigid_clip(3, 24, 32)
    write_video(tmp_path / "v.mp4", clip.frames.float(), fps=8)
    np.savez(tmp_path / "m.npz", masks=np.zeros((3, 24, 32), dtype=bool))
    code = evaluate_main([str(tmp_path / "v.mp4"), "--preset", "tiny", "--pairs", "adjacent", "--out", str(tmp_path / "out"),
                          "--dynamic-masks", str(tmp_path / "m.npz")])
    assert code == 0
    data = json.loads((tmp_path / "out" / "v.geco.json").read_text())
    assert data["dynamic_masks"]["source"] == f"given: {tmp_path / 'm.npz'}"
    code = evaluate_main([str(tmp_path / "v.mp4"), "--preset", "tiny", "--out", str(tmp_path / "out2"),
                          "--dynamic-masks", str(tmp_path / "none.npz")])
    assert code == 2
    assert capsys.readouterr().err.strip().splitlines()[-1] == (f"error: mask file {str(tmp_path / 'none.npz')!r} does not "
                                                                "exist (no such file or folder)")


# --- masks with a clip cut short, empty strings, names ------------------------------------------


def test_masks_of_the_whole_video_are_cut_as_max_frames_cuts_the_frames(tmp_path: Path):
    from geco_guide.metric.protocol import EvaluationConfig

    clip = moving_clip(12, 24, 32)
    oracle = {"estimators": Estimators(OracleGeometry(clip), OracleFlow(clip))}
    cut = EvaluationConfig(max_frames=6)
    np.savez(tmp_path / "m.npz", masks=clip.dynamic_mask.numpy())
    short = clip.frames[:6].float()
    expected = evaluate_video(short, fps=16, dynamic_masks=clip.dynamic_mask[:6], maps=True, **oracle)
    for masks in (clip.dynamic_mask, tmp_path / "m.npz", clip.dynamic_mask[:6]):  # the video's, or the clip's
        result = evaluate_video(clip.frames.float(), fps=16, config=cut, dynamic_masks=masks, maps=True, **oracle)
        assert result.num_frames == 6 and result.fused == expected.fused
        assert torch.equal(result.maps.dynamic_masks, expected.maps.dynamic_masks)
    write_video(tmp_path / "clip.mp4", clip.frames.float(), fps=16)
    from_file = evaluate_video(tmp_path / "clip.mp4", config=cut, dynamic_masks=tmp_path / "m.npz", **oracle)
    assert from_file.num_frames == 6
    with pytest.raises(MaskReadError, match=r"^dynamic masks \(given\) hold 9 frame\(s\), the video 12 \(its first 6 "
                                            r"scored: evaluation.max_frames\): give one mask per frame$"):
        evaluate_video(clip.frames.float(), fps=16, config=cut, dynamic_masks=clip.dynamic_mask[:9], **oracle)


def test_an_empty_string_is_no_mask_folder(monkeypatch, tmp_path: Path):
    clip = moving_clip(4, 24, 32)
    oracle = {"estimators": Estimators(OracleGeometry(clip), OracleFlow(clip))}
    for name in range(4):  # the working folder holds mask-like PNGs: an empty string must not read them
        Image.fromarray(np.zeros((24, 32), dtype=np.uint8)).save(tmp_path / f"{name}.png")
    monkeypatch.chdir(tmp_path)
    for empty in ("", "  "):
        with pytest.raises(ValueError, match="empty string"):
            evaluate_video(clip.frames.float(), fps=8, dynamic_masks=empty, **oracle)
        with pytest.raises(MaskReadError, match="path is empty"):
            GeCoLoss(oracle["estimators"])(clip.frames[None].float(), dynamic_masks=empty)


def test_the_loss_takes_auto_as_evaluate_video_does(moving):
    loss = GeCoLoss(Estimators(OracleGeometry(moving), OracleFlow(moving)), GeCoLossConfig(pairs="all"))
    frames = moving.frames[None].float()
    named = loss(frames, dynamic_masks="auto")
    made = loss(frames, dynamic_masks=MotionMasks())
    assert named.mask_source == "auto" and torch.equal(named.dynamic_masks, made.dynamic_masks)
    assert named.dynamic_masks.any() and float(named.fused) == float(made.fused)


def test_a_result_says_how_many_pixels_it_measured_and_reports_nan_over_none(moving):
    some = _score(moving, moving.dynamic_mask)
    assert all(int(some.valid_pixels[cue][0]) > 0 for cue in ("fused", "motion", "structure"))
    assert some.empty_cues() == [] and all(math.isfinite(v) for v in some.scalars().values())
    everything = _score(moving, torch.ones(5, 24, 32, dtype=torch.bool))
    # the loss keeps its convention (0, zero gradient); what a user is shown is NaN, and why
    assert float(everything.loss) == 0.0 and everything.empty_cues() == ["fused", "motion", "structure"]
    assert all(int(everything.valid_pixels[cue][0]) == 0 for cue in ("fused", "motion", "structure"))
    shown = everything.scalars()
    assert shown["loss"] == 0.0 and all(math.isnan(shown[cue]) for cue in ("fused", "motion", "structure"))
    # without masks: no co-visible pixel leaves the motion cue over nothing
    pairs = frame_pairs(5, "adjacent")
    flow = moving.pair_correspondences(pairs, torch.float64)
    blind = geco_from_geometry(moving.geometry(torch.float64), replace(flow, covisibility=torch.zeros_like(flow.covisibility)),
                               pairs, GeCoLossConfig(cue="motion"))
    assert blind.empty_cues() == ["motion"] and float(blind.loss) == 0.0 and math.isnan(blind.scalars()["motion"])


def test_detection_scores_of_an_almost_all_masked_frame_are_none_with_the_reason(moving):
    oracle = Estimators(OracleGeometry(moving), OracleFlow(moving))
    masks = torch.zeros(5, 24, 32, dtype=torch.bool)
    masks[2] = True
    masks[2, :, 16] = False  # one column left: 3 % of the frame, below the minimum
    scores = frame_scores(detection_maps(moving.frames.float(), oracle, window=3, dynamic_masks=masks))
    assert scores[2]["fused"] is None and "fewer than 5% of the frame's pixels stay valid" in scores[2]["note"]
    assert scores[0]["fused"] is not None and "note" not in scores[0]
