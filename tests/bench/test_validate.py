"""Benchmark builders (warp, occlusion), the three detection tasks, and the robustness sweep."""

import json
import math
from dataclasses import replace

import pytest
import torch

from geco_guide.bench import validate
from geco_guide.bench.datasets import load_benchmark, oracle_clip
from geco_guide.bench.occlusion import (
    OBJECT,
    OCCLUDER,
    OcclusionParams,
    composite_occlusion,
    occlusion_phases,
)
from geco_guide.bench.ranking import average_precision, best_threshold_iou_f1, spearman
from geco_guide.bench.synthetic import rigid_clip, with_warp
from geco_guide.bench.warp import (
    WarpParams,
    central_mask,
    farthest_point_sampling,
    feather_weights,
    warp_clip,
    warp_fields,
    warp_one_frame,
)
from geco_guide.cli import benchmarks, robustness
from geco_guide.cli import validate as validate_cli
from geco_guide.estimators import Estimators
from geco_guide.estimators.oracle import OracleFlow, OracleGeometry
from geco_guide.geometry import pixel_grid, sample_bilinear
from geco_guide.loss.geco import GeCoLossConfig
from geco_guide.metric.evaluate import score_frames

SIZE = ["7", "32", "48"]  # frames, height, width of the synthetic clips


# --- statistics --------------------------------------------------------------------------------


def test_ranking_statistics_on_hand_computed_cases():
    labels = torch.tensor([1, 0, 1, 0, 0], dtype=torch.bool)
    assert average_precision(torch.tensor([0.9, 0.1, 0.8, 0.2, 0.3]), labels) == 1.0
    # ranks of the positives: 1 and 3 -> (1/1 + 2/3) / 2
    assert average_precision(torch.tensor([0.9, 0.6, 0.5, 0.4, 0.1]), labels) == pytest.approx(5 / 6)
    # best threshold keeps the top 3 (TP 2, FP 1): IoU 2/3, F1 4/5
    iou, f1 = best_threshold_iou_f1(torch.tensor([0.9, 0.6, 0.5, 0.4, 0.1]), labels)
    assert (iou, f1) == (pytest.approx(2 / 3), pytest.approx(0.8))
    # ties are never split: all-equal scores can only predict everything
    assert best_threshold_iou_f1(torch.zeros(5), labels) == (pytest.approx(0.4), pytest.approx(4 / 7))
    assert spearman(torch.tensor([1.0, 2.0, 3.0, 4.0]), torch.tensor([10.0, 20.0, 20.0, 40.0])) == pytest.approx(
        0.9486832980505138)  # Pearson of the ranks (1, 2, 3, 4) and (1, 2.5, 2.5, 4)
    assert spearman(torch.arange(5.0), -torch.arange(5.0)) == pytest.approx(-1.0)
    assert math.isnan(average_precision(torch.rand(4), torch.zeros(4, dtype=torch.bool)))


# --- warp builder ------------------------------------------------------------------------------


def test_farthest_point_sampling_spreads_the_controls():
    points = pixel_grid(20, 20, dtype=torch.float64).reshape(-1, 2)
    chosen = points[farthest_point_sampling(points, 4, torch.Generator().manual_seed(0))]
    gaps = torch.cdist(chosen, chosen) + 1e6 * torch.eye(4, dtype=torch.float64)
    assert gaps.min() > 12  # four corners-ish of a 20x20 grid, not a cluster


def test_warp_fields_follow_the_papers_feather_and_ema():
    controls = torch.tensor([[4.0, 4.0], [12.0, 4.0], [8.0, 12.0], [8.0, 7.0]], dtype=torch.float64)
    constant = torch.tensor([[1.0, -2.0]] * 4, dtype=torch.float64).expand(5, 4, 2)  # a pure translation
    weights = torch.rand(16, 16, dtype=torch.float64, generator=torch.Generator().manual_seed(0))
    fields = warp_fields(controls, constant, weights, 16, 16, beta=0.5)
    for t in range(5):  # EMA from zero of a constant w U: (1 - beta^(t+1)) w U
        expected = (1 - 0.5 ** (t + 1)) * weights[..., None] * torch.tensor([1.0, -2.0], dtype=torch.float64)
        torch.testing.assert_close(fields[t], expected)


def test_warp_clip_stays_in_its_mask_and_is_deterministic():
    frames = rigid_clip(num_frames=4, height=32, width=48).frames.float()
    mask = central_mask(32, 48)
    warped = warp_clip(frames, mask, WarpParams(seed=1))
    assert (feather_weights(mask) <= mask.double()).all()
    assert not (warped.displacement.norm(dim=-1)[:, ~mask] > 0).any()
    assert warped.mask.any() and torch.equal(warped.mask, warped.magnitude > 0.1)
    assert torch.equal(warp_clip(frames, mask, WarpParams(seed=1)).frames, warped.frames)
    assert not torch.equal(warp_clip(frames, mask, WarpParams(seed=2)).frames, warped.frames)
    single = warp_one_frame(frames, mask, WarpParams(seed=1))
    changed = (single.frames - frames).abs().flatten(1).amax(1) > 0
    assert changed.tolist() == [t == single.anomalous_frame for t in range(4)]
    with pytest.raises(ValueError, match="num_controls"):
        WarpParams(num_controls=2)
    with pytest.raises(ValueError, match="mask must be"):
        warp_clip(frames, mask[:10])


def _photometric_error(clip, i, j):
    """Mean |frame_j(p + flow) - frame_i(p)| over covisible pixels of the clip's ground truth."""
    flow, covisible = clip.correspondences(i, j)
    target = pixel_grid(*flow.shape[-2:], dtype=flow.dtype) + flow.permute(1, 2, 0)
    warped = sample_bilinear(clip.frames[j][None].to(flow.dtype), target[None])[0]
    return (warped - clip.frames[i].to(flow.dtype)).abs().mean(0)[covisible > 0.5].mean().item()


def test_the_ground_truth_displacement_has_the_sign_of_the_warped_frames():
    base = rigid_clip(num_frames=3, height=32, width=48)
    clip = with_warp(base, warp_clip(base.frames, params=WarpParams(amplitude=4.0, seed=0)))
    right = _photometric_error(clip, 0, 2)
    flipped = _photometric_error(replace(clip, warp=-clip.warp), 0, 2)  # I(p - U) instead of I(p + U)
    assert right < 0.01 and flipped > 2 * right


# --- occlusion builder -------------------------------------------------------------------------


def test_occlusion_edit_hides_then_re_reveals_the_region():
    frames = rigid_clip(num_frames=8, height=32, width=48).frames.float()
    edit = composite_occlusion(frames, OcclusionParams(seed=3))
    a, b = edit.phases
    assert (a, b) == occlusion_phases(8) == (2, 4)
    left, top, right, bottom = edit.region
    region = (slice(None), slice(top, bottom), slice(left, right))
    assert torch.equal(edit.frames[:a], frames[:a])  # visible and empty
    assert all((edit.labels[t][region[1:]] == OCCLUDER).all() for t in range(a, b))  # fully hidden
    assert not (edit.labels[b:] == OCCLUDER).any() and not (edit.labels[:b] == OBJECT).any()
    assert torch.equal(edit.mask, edit.labels == OBJECT) and edit.mask[b:].flatten(1).any(1).all()
    assert torch.equal(composite_occlusion(frames, OcclusionParams(seed=3)).frames, edit.frames)
    with pytest.raises(ValueError, match="inside"):
        composite_occlusion(frames, OcclusionParams(region=(40, 0, 60, 10)))


# --- build -> validate, end to end -------------------------------------------------------------


@pytest.fixture(scope="module")
def built(tmp_path_factory):
    root = tmp_path_factory.mktemp("bench")
    common = ["synthetic", "--synthetic-size", *SIZE, "--seeds", "0", "1"]
    assert benchmarks.main(["warp", *common, "--out", str(root / "warp-frame"), "--mode", "frame"]) == 0
    assert benchmarks.main(["warp", *common, "--out", str(root / "warp-clip")]) == 0
    assert benchmarks.main(["occlusion", *common, "--out", str(root / "occlusion")]) == 0
    assert benchmarks.main(["occlusion", "synthetic-3d", "--synthetic-size", "9", "48", "64",
                            "--out", str(root / "occlusion-3d")]) == 0
    return root


def test_builders_write_complete_deterministic_folders(built, tmp_path):
    clip = built / "warp-frame" / "synthetic-s1"
    meta = json.loads((clip / "meta.json").read_text())
    assert meta["kind"] == "warp" and meta["mode"] == "frame" and meta["seed"] == 1
    assert meta["params"]["beta"] == WarpParams.beta and len(meta["controls"]) == WarpParams.num_controls
    bench = load_benchmark(clip)
    assert bench.frames.shape == (7, 3, 32, 48)
    assert bench.truth["mask"].flatten(1).any(1).tolist() == [t == meta["anomalous_frame"] for t in range(7)]
    assert benchmarks.main(["warp", "synthetic", "--synthetic-size", *SIZE, "--seeds", "1", "--mode", "frame",
                            "--out", str(tmp_path)]) == 0
    again = load_benchmark(tmp_path / "synthetic-s1")
    assert torch.equal(again.frames, bench.frames) and torch.equal(again.truth["displacement"], bench.truth["displacement"])


@pytest.mark.slow
def test_oracle_estimators_solve_the_three_tasks(built):
    out = built / "report"
    code = validate_cli.main([str(built / "warp-frame"), str(built / "warp-clip"), str(built / "occlusion"),
                          "--oracle", "--out", str(out)])
    assert code == 0
    summary = json.loads((out / "validation.json").read_text())["summary"]
    assert summary["task1"]["clips"] == 2
    for cue in ("motion", "fused"):
        assert summary["task1"][cue]["accuracy"] == 1.0
        assert summary["task2"][cue]["ap"] >= 0.9 and summary["task2"][cue]["iou"] >= 0.8
        assert summary["task2"][cue]["srcc"] > 0.5
    for cue in ("structure", "fused"):
        assert summary["task3"][cue]["ap"] >= 0.9 and summary["task3"][cue]["f1"] >= 0.9
    # The structure cue cannot see a warp of the image (the depth is unchanged): the paper's finding.
    assert summary["task2"]["structure"]["ap"] < 0.5
    table = (out / "validation.md").read_text()
    assert "| Fused M_geo |" in table and "Task 3 AP" in table
    assert min(p.name for p in (out / "grids").iterdir()) == "occlusion-synthetic-s0.png"


def test_a_3d_occlusion_edit_is_found_by_structure_and_missed_by_motion(built):
    out = built / "report-3d"
    assert validate_cli.main([str(built / "occlusion-3d"), "--oracle", "--no-grids", "--out", str(out)]) == 0
    summary = json.loads((out / "validation.json").read_text())["summary"]["task3"]
    # The paper's OccluBench finding: the flow follows the new surface, only depth contradicts it.
    assert summary["structure"]["ap"] >= 0.9 and summary["fused"]["ap"] >= 0.9
    assert summary["motion"]["ap"] < 0.2
    assert benchmarks.main(["warp", "synthetic-3d", "--out", str(out / "never")]) == 1


def test_a_wrong_mask_fails_the_tasks(built):
    for kind, task in (("warp-clip", "task2"), ("occlusion", "task3")):
        bench = load_benchmark(built / kind / "synthetic-s0")
        clip = oracle_clip(bench)
        _, result = score_frames(bench.frames, Estimators(OracleGeometry(clip), OracleFlow(clip)), GeCoLossConfig(pairs="all"))
        right = validate.summarise([validate.validate_clip(bench, result)])[task]["fused"]["ap"]
        shifted = torch.roll(bench.truth["mask"], shifts=bench.frames.shape[-1] // 2, dims=-1)
        wrong = replace(bench, truth={**bench.truth, "mask": shifted})
        assert right >= 0.9
        assert validate.summarise([validate.validate_clip(wrong, result)])[task]["fused"]["ap"] < 0.5


def test_bad_inputs_are_one_line_errors(tmp_path, capsys):
    assert validate_cli.main([str(tmp_path), "--oracle"]) == 2
    assert "holds no built benchmark clip" in capsys.readouterr().err
    assert benchmarks.main(["warp", str(tmp_path / "missing.mp4"), "--out", str(tmp_path / "o")]) == 1
    err = capsys.readouterr().err.strip()
    assert err.startswith("error:") and "\n" not in err
    assert benchmarks.main(["warp", "synthetic", "--synthetic-size", "3", "16", "24", "--out", str(tmp_path / "b")]) == 0
    (tmp_path / "b" / "synthetic-s0" / "truth.npz").write_bytes(b"damaged")
    assert validate_cli.main([str(tmp_path / "b"), "--oracle", "--no-grids"]) == 1
    err = capsys.readouterr().err.strip().splitlines()
    assert err[0].startswith("[1/1] scoring") and len(err) == 2  # progress, then one error line
    assert "cannot read truth.npz" in err[1]


def test_the_oracle_refuses_clips_built_from_real_footage(built, tmp_path):
    bench = load_benchmark(built / "warp-clip" / "synthetic-s0")
    with pytest.raises(ValueError, match="not a synthetic scene"):
        oracle_clip(replace(bench, meta={**bench.meta, "synthetic": None, "source": "clip.mp4"}))


# --- robustness sweep --------------------------------------------------------------------------


def test_robustness_sweep_degrades_with_noise(tmp_path, capsys):
    assert robustness.main(["--out", str(tmp_path), "--size", "5", "24", "32", "--depth-sigmas", "0", "0.5",
                            "--flow-sigmas", "0", "20"]) == 0
    lines = capsys.readouterr().out.splitlines()
    assert [line.split(":")[0] for line in lines[:4]] == ["depth sigma=0", "depth sigma=0.5", "flow sigma=0", "flow sigma=20"]
    report = json.loads((tmp_path / "robustness.json").read_text())
    assert (tmp_path / "robustness.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    flow, depth = report["flow"], report["depth"]
    assert flow["warp"]["motion"][0] >= 0.9 and flow["warp"]["motion"][1] < 0.6
    assert flow["occlusion"]["structure"] == [1.0, 1.0]  # flow noise does not touch the structure cue
    assert depth["rigid_fused"][0] < 1e-3 < depth["rigid_fused"][1]  # the noise floor rises
    assert depth["warp"]["motion"][1] < depth["warp"]["motion"][0]


def test_robustness_reports_each_level_as_soon_as_it_is_scored(monkeypatch):
    from geco_guide.bench import robustness as sweep

    lines: list[str] = []
    seen: list[int] = []  # lines reported when each level's rigid clip is scored
    detect = sweep.detection_ap

    def counting(*args, **kwargs):
        seen.append(len(lines))
        return detect(*args, **kwargs)

    monkeypatch.setattr(sweep, "detection_ap", counting)
    report = sweep.run_sweep(4, 16, 24, depth_sigmas=(0.0, 0.1), flow_sigmas=(0.0,), progress=lines.append)
    assert seen == [0, 0, 1, 1, 2, 2]  # two edited clips per level: the level before was reported already
    assert lines == [sweep.level_line(name, report[name], k) for name, k in (("depth", 0), ("depth", 1), ("flow", 0))]
