"""GeCo evaluation of any video: metric validity with ground truth, maps video, CLI, config."""

from __future__ import annotations

import csv
import errno
import json
import math
from dataclasses import replace
from pathlib import Path

import pytest
import torch
from PIL import Image

import geco_guide
from geco_guide.bench.synthetic import inject_deformation, rigid_clip
from geco_guide.cli.evaluate import main
from geco_guide.config import load_config
from geco_guide.estimators import Estimators, EstimatorsConfig, load_estimators
from geco_guide.estimators.oracle import OracleFlow, OracleGeometry
from geco_guide.io import files
from geco_guide.io.video import VideoReadError, read_video, write_video
from geco_guide.loss.geco import GeCoLossConfig
from geco_guide.metric.evaluate import (
    MAP_PANELS,
    evaluate_video,
    render_maps,
    write_maps_video,
)
from geco_guide.metric.protocol import EvaluationConfig
from geco_guide.metric.render import (
    READABLE_HEIGHT,
    VIRIDIS,
    colorize,
    enlarge,
    label_height,
    panel_layout,
    text_scale,
)
from geco_guide.metric.video_inputs import expand_inputs

H, W = 32, 48


@pytest.fixture(scope="module")
def clips():
    rigid = rigid_clip(num_frames=5, height=H, width=W)
    return {"rigid": rigid, "deformed": inject_deformation(rigid, amplitude=3.0)}


def oracle(clip):
    return {"estimators": Estimators(OracleGeometry(clip), OracleFlow(clip))}


@pytest.fixture(scope="module")
def evaluated(clips):
    """Tensor-path results with maps, computed once (the oracle's ray casts are the slow part)."""
    return {name: evaluate_video(clip.frames, **oracle(clip), fps=8, maps=True) for name, clip in clips.items()}


def test_rigid_scene_scores_zero_and_deformation_scores_higher(evaluated):
    for result in evaluated.values():
        assert result.num_frames == 5 and result.fps == 8 and result.sampled_fps == 8 and result.source is None
        assert [row["index"] for row in result.frame_scores] == list(range(5))
        assert [row["time_s"] for row in result.frame_scores] == [k / 8 for k in range(5)]
        assert len(result.windows) == 1 and result.windows[0]["frames"] == list(range(5))
        assert result.total_motion > 0 and result.mean_motion == pytest.approx(result.total_motion / (5 / 8))
        assert result.estimators == {"geometry": "OracleGeometry", "flow": "OracleFlow"}
        assert result.config["loss"]["pairs"] == "all" and result.config["loss"]["flow_downscale"] == 1.0
        assert result.fps_source == "--fps" and result.config["max_windows"] == 4
    rigid, deformed = evaluated["rigid"], evaluated["deformed"]
    assert rigid.fused < 1e-4
    assert deformed.fused > 1e-3 and deformed.fused > 20 * rigid.fused
    assert deformed.motion > 20 * rigid.motion


def test_overlapping_windows_are_frame_weighted(clips):
    clip = clips["deformed"]
    cfg = EvaluationConfig(window_seconds=1.0, loss=GeCoLossConfig(pairs="center", flow_downscale=1.0))
    # 5 frames at 4 fps = 1.25 s: ceil(1.25 / 1) = 2 windows of 1 s starting at 0 and 0.25 s
    result = evaluate_video(clip.frames, **oracle(clip), fps=4, config=cfg)
    assert [w["frames"] for w in result.windows] == [[0, 1, 2, 3], [1, 2, 3, 4]]
    assert [(w["start_s"], w["length_s"]) for w in result.windows] == [(0.0, 1.0), (0.25, 1.0)]
    assert [row["window"] for row in result.frame_scores] == [0] * 4 + [1] * 4
    assert [row["index"] for row in result.frame_scores] == [0, 1, 2, 3, 1, 2, 3, 4]
    for w, window in enumerate(result.windows):
        rows = [row["fused"] for row in result.frame_scores if row["window"] == w]
        assert window["fused"] == pytest.approx(sum(rows) / len(rows))
    assert result.fused == pytest.approx((4 * result.windows[0]["fused"] + 4 * result.windows[1]["fused"]) / 8)
    assert result.config["loss"]["pairs"] == "center" and result.mean_motion == pytest.approx(result.total_motion / 1.25)


def test_total_motion_of_a_known_flow():
    """A constant 2 px/frame flow on a 30x40 clip (diagonal 50) of 17 frames at 16 fps (1.0625 s):
    the motion grid takes floor(1.0625 * 8) = 8 frames (0, 2, ..., 14), so 7 steps of 4 px = 8 %
    of the diagonal each."""
    from geco_guide.types import Correspondences

    clip = rigid_clip(num_frames=17, height=30, width=40)
    lookup = OracleFlow(clip).lookup  # which clip frame an image is

    class ConstantFlow:
        def estimate_flow(self, source, target):
            steps = torch.tensor([float(j - i) for i, j in zip(lookup.indices(source), lookup.indices(target))])
            flow = torch.zeros(len(steps), 2, *source.shape[-2:])
            flow[:, 0] = 2.0 * steps[:, None, None]
            return Correspondences(flow=flow, covisibility=torch.ones(len(steps), *source.shape[-2:]))

    result = evaluate_video(clip.frames, Estimators(OracleGeometry(clip), ConstantFlow()), fps=16)
    assert result.total_motion == pytest.approx(7 * 8.0, rel=1e-5)
    assert result.mean_motion == pytest.approx(56.0 / (17 / 16), rel=1e-5)  # over the clip's duration
    assert result.estimators == {"geometry": "OracleGeometry", "flow": "ConstantFlow"}
    # the earlier keywords of the pair are refused in one line naming the bundle, before any work
    new = r"is the earlier spelling: pass the models as one estimators=Estimators\(geometry, flow\)"
    for earlier, first in (({"geometry": OracleGeometry(clip), "flow": ConstantFlow()}, "flow"),
                           ({"geometry_estimator": OracleGeometry(clip), "flow_estimator": ConstantFlow()},
                            "flow_estimator")):
        with pytest.raises(TypeError, match=rf"^evaluate_video\({first}=...\) {new}"):
            evaluate_video(clip.frames, fps=16, **earlier)
    with pytest.raises(TypeError, match=r"^evaluate_video takes the estimators as one Estimators\(geometry, flow\)"):
        evaluate_video(clip.frames, (OracleGeometry(clip), ConstantFlow()), fps=16)


def test_mp4_round_trip_with_oracle_of_the_decoded_frames(tmp_path: Path, clips, evaluated):
    fused = {}
    for name, clip in clips.items():
        path = write_video(tmp_path / f"{name}.mp4", clip.frames, fps=8)
        decoded = replace(clip, frames=read_video(path)[0])  # the oracle answers for what was decoded
        result = evaluate_video(path, **oracle(decoded))
        assert result.source == str(path) and result.fps == pytest.approx(8.0) and result.num_frames == 5
        fused[name] = result.fused
        assert result.fused == pytest.approx(evaluated[name].fused, rel=1e-3)  # same ground truth
    assert fused["rigid"] < 1e-4 and fused["deformed"] > 20 * fused["rigid"]


def test_to_dict_is_strict_json(evaluated):
    loaded = json.loads(json.dumps(evaluated["rigid"].to_dict(), allow_nan=False))
    assert {"motion", "structure", "fused", "total_motion", "mean_motion", "frame_scores", "windows",
            "estimators", "config", "num_frames", "fps", "fps_source", "duration_s", "sampled_fps"} <= set(loaded)
    assert loaded["paper_names"]["fused"] == "M_geo" and "maps" not in loaded


def test_maps_video_has_the_panel_layout(tmp_path: Path, clips, evaluated):
    clip, result = clips["deformed"], evaluated["deformed"]
    maps = result.maps
    assert maps.frames.shape == (5, 3, H, W) and maps.fused.shape == (5, H, W) and maps.fused_valid.dtype == torch.bool
    assert len(maps) == 5 and set(maps[0]) == {"frame", *(f"{c}{v}" for c in ("motion", "structure", "fused") for v in ("", "_valid"))}
    frames = render_maps(result)
    # a small clip's panels are enlarged by a whole factor to a readable height, pixels kept square
    k = math.ceil(READABLE_HEIGHT / H)
    (grid_h, grid_w), boxes = panel_layout([(k * H, k * W)] * len(MAP_PANELS))
    gap = 2 * text_scale(k * H)  # black columns between panels
    assert [left for _, left, _, _ in boxes] == [0, k * W + gap, 2 * (k * W + gap), 3 * (k * W + gap)]
    assert grid_w == 4 * k * W + 3 * gap
    assert frames.shape[0] == 5 and frames.shape[-1] == grid_w and frames.shape[-2] > grid_h + label_height(text_scale(H))
    top = boxes[0][0]
    assert torch.allclose(frames[:, :, top : top + k * H, : k * W], enlarge(clip.frames.float()))
    for name, (_, left, _, _) in zip(MAP_PANELS[1:], boxes[1:]):
        expected = colorize(getattr(maps, name), getattr(maps, f"{name}_valid"))
        assert torch.allclose(frames[:, :, top : top + k * H, left : left + k * W], enlarge(expected))
    # the legend under the panels: a colour bar from viridis' first to its last colour
    bar = frames[0, :, grid_h + gap + 1]  # the bar starts a margin of 2 * scale below the panels
    on_bar = [x for x in range(grid_w) if any(torch.allclose(bar[:, x], c) for c in (VIRIDIS[0], VIRIDIS[-1]))]
    assert torch.allclose(bar[:, on_bar[0]], VIRIDIS[0]) and torch.allclose(bar[:, on_bar[-1]], VIRIDIS[-1])

    path = write_maps_video(result, tmp_path / "m.maps.mp4")
    video, fps = read_video(path)
    assert fps == pytest.approx(8.0) and video.shape[0] == 5 and video.shape[-1] == grid_w
    assert video.shape[-2] == frames.shape[-2] and frames.shape[-2] % 2 == 0  # even: no yuv420p padding
    assert (video[:, :, : frames.shape[-2]] - frames).abs().mean() < 0.05
    assert sorted(p.name for p in tmp_path.iterdir()) == ["m.maps.mp4"]
    with pytest.raises(ValueError, match="maps=True"):
        render_maps(replace(result, maps=None))


def test_bad_inputs_give_clear_errors(tmp_path: Path, clips):
    clip = clips["rigid"]
    with pytest.raises(ValueError, match="fps"):
        evaluate_video(clip.frames, **oracle(clip))
    with pytest.raises(ValueError, match="at least 2 frames"):
        evaluate_video(clip.frames[:1], **oracle(clip), fps=8)
    with pytest.raises(ValueError, match=r"\[S, 3, H, W\]"):
        evaluate_video(clip.frames[None], **oracle(clip), fps=8)
    single = write_video(tmp_path / "one.mp4", clip.frames[:1], fps=8)
    with pytest.raises(VideoReadError, match="1 frame"):
        evaluate_video(single, **oracle(clip))
    with pytest.raises(VideoReadError, match="no such file"):
        evaluate_video(tmp_path / "missing.mp4", **oracle(clip))


def test_evaluate_video_is_exported():
    assert geco_guide.evaluate_video is evaluate_video and "evaluate_video" in geco_guide.__all__


# --- configuration and the shared estimator loader -----------------------------------------


def test_evaluation_config_section():
    cfg = load_config(preset="tiny")
    e = cfg.evaluation
    assert (e.window_seconds, e.max_fps, e.device) == (3.0, 8.0, "cpu")
    assert e.loss.flow_downscale == 1.0 and e.loss.pairs == "all" and e.loss.covisibility_threshold == 0.5
    assert e.max_windows == 4 and e.model_fps["cogvideox-5b"] == 16.0 and e.model_fps["sora-2"] == 30.0
    assert e.loss.structure_occlusion == "covisibility" and cfg.guidance.loss.structure_occlusion == "depth"
    assert cfg.guidance.loss.flow_downscale == 0.5  # guidance keeps its own loss settings
    cfg = load_config(preset="cogvideox-5b", overrides=["evaluation.loss.pairs=center", "evaluation.loss.occlusion_tau=0.05"])
    assert cfg.evaluation.loss.pairs == "center" and cfg.evaluation.loss.occlusion_tau == 0.05


@pytest.mark.parametrize(
    "override, key",
    [
        ("evaluation.window_seconds=0", "evaluation.window_seconds"),
        ("evaluation.loss.pairs=some", "evaluation.loss.pairs"),
        ("evaluation.loss.covisibility_threshold=2", "evaluation.loss.covisibility_threshold"),
        ("guidance.loss.pairs=some", "guidance.loss.pairs"),
        ("evaluation.device=tpu", "evaluation.device"),
        ("evaluation.windows=3", "evaluation.windows"),
    ],
)
def test_invalid_evaluation_keys_are_named(override, key):
    with pytest.raises(ValueError, match=f"'{key}'"):
        load_config(preset="tiny", overrides=[override])


def test_shared_estimator_loader_builds_tiny_models():
    estimators = load_estimators(EstimatorsConfig(geometry="tiny-random", flow="tiny-random"), "cpu")
    geometry, flow = estimators.geometry, estimators.flow
    assert estimators.ids() == {"geometry": "tiny-random(seed=0)", "flow": "tiny-random(seed=0)"}
    assert not hasattr(geometry, "geco_estimator_id")  # the bundle keeps the ids, the modules carry none
    assert not any(p.requires_grad for p in geometry.parameters()) and not geometry.training
    assert not geometry.gradient_checkpointing and not flow.gradient_checkpointing
    assert estimators.segmenter is None  # loaded only when asked for
    cfg = load_config(preset="tiny", overrides=["estimators.gradient_checkpointing=true"])
    estimators = load_estimators(cfg.estimators, "cpu")
    assert estimators.geometry.gradient_checkpointing and estimators.flow.gradient_checkpointing


# --- CLI ----------------------------------------------------------------------------------


@pytest.mark.slow
def test_cli_scores_videos_and_reports_bad_inputs(tmp_path: Path, capsys):
    rigid = rigid_clip(num_frames=6, height=32, width=48)
    write_video(tmp_path / "static.mp4", rigid.frames, fps=8)
    write_video(tmp_path / "deformed.mp4", inject_deformation(rigid).frames, fps=8)
    mixed = tmp_path / "mixed"
    mixed.mkdir()
    (mixed / "corrupt.mp4").write_bytes(b"not a video" * 40)
    (mixed / "notes.txt").write_text("ignored")
    frames = mixed / "frames"  # a frame folder inside a folder of videos is one more video
    frames.mkdir()
    import imageio.v2 as imageio

    for k, frame in enumerate(rigid.frames[:3]):
        imageio.imwrite(frames / f"{k}.png", (frame.permute(1, 2, 0).numpy() * 255).astype("uint8"))
    empty = tmp_path / "empty"
    empty.mkdir()
    out = tmp_path / "out"

    rc = main([str(tmp_path / "static.mp4"), str(tmp_path / "deformed.mp4"), str(mixed), str(empty),
               "--preset", "tiny", "--out", str(out), "--maps", "--pairs", "all", "evaluation.flow_batch_size=7"])
    captured = capsys.readouterr()
    assert rc == 0, captured.err
    errors = [line for line in captured.err.strip().splitlines() if not line.startswith(("loading models:", "["))]
    assert len(errors) == 2 and all(line.startswith("error: ") for line in errors)  # the rest is progress
    assert "corrupt.mp4" in errors[0] and "cannot read video" in errors[0]
    assert "empty" in errors[1] and "holds no video" in errors[1]
    assert "static: M_geo=" in captured.out

    names = ["static", "deformed", "frames"]
    assert sorted(p.name for p in out.iterdir()) == sorted(
        [f"{n}.geco.json" for n in names] + [f"{n}.maps.mp4" for n in names] + ["geco_scores.csv", "geco_summary.json"]
    )
    data = json.loads((out / "static.geco.json").read_text())
    assert data["estimators"] == {"geometry": "tiny-random(seed=0)", "flow": "tiny-random(seed=0)"}
    assert data["config"]["loss"]["pairs"] == "all" and data["config"]["flow_batch_size"] == 7
    assert data["num_frames"] == 6 and len(data["frame_scores"]) == 6 and math.isfinite(data["fused"])
    assert read_video(out / "static.maps.mp4")[0].shape[0] == 6
    assert json.loads((out / "frames.geco.json").read_text())["fps"] == 8.0  # a folder's default rate

    rows = list(csv.DictReader((out / "geco_scores.csv").open()))
    assert [r["name"] for r in rows] == ["static", "deformed", "corrupt", "frames", "empty"]
    assert [bool(r["error"]) for r in rows] == [False, False, True, False, True]
    assert float(rows[0]["fused"]) > 0 and rows[2]["fused"] == ""
    summary = json.loads((out / "geco_summary.json").read_text())
    assert (summary["num_videos"], summary["num_ok"], summary["num_failed"]) == (5, 3, 2)
    ok = [float(r["fused"]) for r in rows if not r["error"]]
    assert summary["mean"]["fused"] == pytest.approx(sum(ok) / 3)


def test_cli_exit_codes(tmp_path: Path, capsys):
    (tmp_path / "bad.mp4").write_bytes(b"junk" * 100)
    assert main([str(tmp_path / "bad.mp4"), "--preset", "tiny", "--out", str(tmp_path / "o")]) == 1
    err = capsys.readouterr().err.strip().splitlines()
    assert err[:2] == ["loading models: tiny-random + tiny-random on cpu", f"[1/1] scoring {tmp_path / 'bad.mp4'}"]
    assert len(err) == 3 and err[2].startswith("error: ")  # progress, then one error line
    assert main([str(tmp_path / "bad.mp4"), "--preset", "tiny", "evaluation.max_fps=-1"]) == 2
    err = capsys.readouterr().err.strip()
    assert "evaluation.max_fps" in err and "\n" not in err


@pytest.mark.slow
def test_cli_detection_view_writes_every_frames_own_maps(tmp_path: Path, capsys):
    rigid = rigid_clip(num_frames=6, height=32, width=48)
    video = write_video(tmp_path / "deformed.mp4", inject_deformation(rigid).frames, fps=8)
    out = tmp_path / "out"
    assert main([str(video), "--preset", "tiny", "--out", str(out), "--detection"]) == 0
    assert "detection maps" in capsys.readouterr().out
    rendered, fps = read_video(out / "deformed.detection.mp4")
    assert rendered.shape[0] == 6 and fps == pytest.approx(8.0)  # one map row per source frame


# --- outputs that cannot be written, names, progress -------------------------------------------


def _two_videos(tmp_path: Path) -> list[str]:
    torch.manual_seed(0)
    paths = []
    for name in ("a", "b"):
        write_video(tmp_path / f"{name}.mp4", torch.rand(6, 3, 24, 32), fps=8)
        paths.append(str(tmp_path / f"{name}.mp4"))
    return paths


def test_an_unwritable_out_is_refused_before_scoring(tmp_path: Path, capsys):
    (tmp_path / "a-file").write_text("")
    assert main([*_two_videos(tmp_path), "--preset", "tiny", "--out", str(tmp_path / "a-file")]) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith("error: --out") and "is a file" in err and "\n" not in err


@pytest.mark.slow
def test_a_full_disk_is_one_line_per_output_and_leaves_no_table(tmp_path: Path, monkeypatch, capsys):
    videos = _two_videos(tmp_path)

    def full(fd):
        raise OSError(errno.ENOSPC, "No space left on device")

    monkeypatch.setattr(files.os, "fsync", full)
    out = tmp_path / "out"
    assert main([*videos, "--preset", "tiny", "--out", str(out)]) == 1
    err = capsys.readouterr().err
    assert "Traceback" not in err and err.count("No space left") == 3  # two videos and the table
    assert list(out.iterdir()) == []  # no csv without its summary, no temporaries


@pytest.mark.slow
def test_progress_goes_to_stderr_and_a_dot_is_named_after_its_folder(tmp_path: Path, monkeypatch, capsys):
    folder = tmp_path / "myclips"
    folder.mkdir()
    _two_videos(folder)
    monkeypatch.chdir(folder)
    assert main([".", "--preset", "tiny", "--out", str(tmp_path / "out")]) == 0
    err = capsys.readouterr().err
    assert err.count("loading models:") == 1 and "[1/2] scoring" in err and "[2/2]   window 1/1" in err
    assert sorted(p.name for p in (tmp_path / "out").iterdir()) == [
        "a.geco.json", "b.geco.json", "geco_scores.csv", "geco_summary.json"]
    frames = tmp_path / "frames"  # a folder of frames given as "." is one video named after it
    frames.mkdir()
    for k in range(2):
        Image.new("RGB", (8, 8)).save(frames / f"{k}.png")
    monkeypatch.chdir(frames)
    assert [item.name for item in expand_inputs(["."])] == ["frames"]


def test_an_output_name_too_long_is_one_error_line(tmp_path: Path, capsys):
    video = tmp_path / f"{'a' * 235}.mp4"  # a name that fits, whose .geco.json's temporary does not
    write_video(video, torch.rand(4, 3, 16, 16), fps=8)
    assert main([str(video), "--preset", "tiny", "--out", str(tmp_path / "out")]) == 1
    error = capsys.readouterr().err.strip().splitlines()[-1]
    assert error.startswith(f"error: {video}: ") and "cannot write" in error and "too long" in error
    assert list((tmp_path / "out").iterdir()) == []
