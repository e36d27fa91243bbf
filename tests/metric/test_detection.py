"""Per-frame detection maps: windows, the two-way occlusion check, localisation, the CLI."""

import json

import pytest
import torch

import geco_guide.estimators as estimators_package
from geco_guide.bench.ranking import average_precision
from geco_guide.bench.synthetic import occlusion_swap_clip, rigid_clip, with_warp
from geco_guide.bench.warp import WarpParams, warp_one_frame
from geco_guide.cli import detection
from geco_guide.estimators import Estimators
from geco_guide.estimators.oracle import OracleFlow, OracleGeometry
from geco_guide.io.video import write_video
from geco_guide.metric.detection import detection_maps, frame_scores, window_indices
from geco_guide.metric.protocol import EvaluationConfig

LOSS = EvaluationConfig().loss


def test_windows_put_the_frame_first_and_stay_inside_the_clip():
    assert window_indices(10, 5, 4, "center") == [5, 3, 4, 6]
    assert window_indices(10, 0, 4, "center") == [0, 1, 2, 3]
    assert window_indices(10, 5, 4, "start") == [5, 6, 7, 8]
    assert window_indices(10, 8, 4, "start") == [8, 6, 7, 9]  # shifted back inside
    assert window_indices(10, 5, 4, "end") == [5, 2, 3, 4]
    assert window_indices(10, 1, 4, "end") == [1, 0, 2, 3]
    with pytest.raises(ValueError, match="anchor"):
        window_indices(10, 1, 4, "middle")


def test_each_frame_map_finds_the_replaced_frame_and_its_warp():
    base = rigid_clip(num_frames=6, height=32, width=48)
    warped = warp_one_frame(base.frames, params=WarpParams(seed=1))
    clip = with_warp(base, warped)
    maps = detection_maps(clip.frames, Estimators(OracleGeometry(clip), OracleFlow(clip)), LOSS, window=4)
    fused = [row["fused"] for row in frame_scores(maps)]
    t = warped.anomalous_frame
    assert max(range(6), key=fused.__getitem__) == t
    assert average_precision(torch.where(maps.fused_valid[t], maps.fused[t], 0.0), warped.mask[t]) >= 0.9
    rigid = detection_maps(base.frames, Estimators(OracleGeometry(base), OracleFlow(base)), LOSS, window=4)
    assert max(row["fused"] for row in frame_scores(rigid)) < 1e-3


def test_the_two_way_check_only_removes_structure_pixels():
    clip = occlusion_swap_clip(num_frames=5, height=32, width=48)
    oracle = Estimators(OracleGeometry(clip), OracleFlow(clip))
    one_way = detection_maps(clip.frames, oracle, LOSS, window=5, two_way=False)
    two_way = detection_maps(clip.frames, oracle, LOSS, window=5)
    assert not (two_way.structure_valid & ~one_way.structure_valid).any()
    assert two_way.structure_valid.sum() < one_way.structure_valid.sum()  # the pillar hides some
    torch.testing.assert_close(two_way.motion, one_way.motion)


@pytest.mark.slow
def test_cli_writes_every_format(tmp_path, capsys):
    video = write_video(tmp_path / "clip.mp4", rigid_clip(num_frames=4, height=32, width=48).frames, fps=8)
    out = tmp_path / "maps"
    assert detection.main([str(video), "--preset", "tiny", "--window", "3", "--anchor", "end",
                           "--format", "mp4", "gif", "png", "--out", str(out)]) == 0
    report = json.loads((out / "clip.detection.json").read_text())
    assert report["window"] == 3 and report["two_way"] and len(report["frames"]) == 4
    assert (out / "clip.detection.mp4").stat().st_size > 0 and (out / "clip.detection.gif").stat().st_size > 0
    assert sorted(p.name for p in (out / "clip.detection").iterdir()) == [f"{k:05d}.png" for k in range(4)]
    assert detection.main([str(video), "--preset", "tiny", "--window", "1"]) == 2
    assert "--window" in capsys.readouterr().err


# --------------------------------------------------------------------------------------------
# the CLI's outputs: named apart, inside --out, never stale, never silently replaced


def _clip(path, frames=4):
    return write_video(path, rigid_clip(num_frames=frames, height=32, width=48).frames, fps=8)


def _detect(*args):
    return detection.main([*map(str, args), "--preset", "tiny", "--window", "3"])


@pytest.mark.slow
def test_inputs_with_one_stem_get_numbered_outputs(tmp_path, capsys):
    (tmp_path / "a").mkdir()
    (tmp_path / "b").mkdir()
    first, second = _clip(tmp_path / "a" / "clip.mp4", 4), _clip(tmp_path / "b" / "clip.mp4", 5)
    out = tmp_path / "maps"
    assert _detect(first, second, "--out", out) == 0
    assert json.loads((out / "clip.detection.json").read_text())["source"] == str(first)
    assert json.loads((out / "clip-2.detection.json").read_text())["source"] == str(second)
    assert len(json.loads((out / "clip-2.detection.json").read_text())["frames"]) == 5
    err = capsys.readouterr().err
    assert f"[1/2] {first} ...\n" in err and f"[2/2] {second} ...\n" in err  # one line per video


def test_a_frame_folder_given_as_dot_writes_inside_out(tmp_path, monkeypatch):
    from geco_guide.metric.detection import write_pngs

    frames = tmp_path / "shot"
    write_pngs(frames, rigid_clip(num_frames=4, height=32, width=48).frames)
    monkeypatch.chdir(frames)
    out = tmp_path / "maps"
    assert _detect(".", "--out", out) == 0
    assert sorted(p.name for p in out.iterdir()) == ["shot.detection.json", "shot.detection.mp4"]
    assert sorted(p.name for p in tmp_path.iterdir()) == ["maps", "shot"]


@pytest.mark.slow
def test_existing_outputs_are_refused_before_loading_unless_overwrite(tmp_path, capsys, monkeypatch):
    video, out = _clip(tmp_path / "clip.mp4"), tmp_path / "maps"
    assert _detect(video, "--out", out, "--format", "png") == 0
    capsys.readouterr()

    def refuse(*args, **kwargs):
        raise AssertionError("estimators were loaded")

    with monkeypatch.context() as patch:
        patch.setattr(estimators_package, "load_estimators", refuse)
        assert _detect(video, "--out", out, "--format", "png") == 2
        err = capsys.readouterr().err.strip()
        assert err == (f"error: {str(out / 'clip.detection')!r} already exists; pass --overwrite to replace it, "
                       "or use another --out")
        (out / "clip.mp4").write_text("a file")
        assert _detect(video, "--out", out / "clip.mp4") == 2
        assert "is a file, not a folder" in capsys.readouterr().err

    # a shorter video under the same name: its PNG folder keeps no frame of the first run
    (out / "clip.detection" / "notes.txt").write_text("mine")
    _clip(video, 3)
    assert _detect(video, "--out", out, "--format", "png", "--overwrite") == 0
    assert sorted(p.name for p in (out / "clip.detection").iterdir()) == ["00000.png", "00001.png", "00002.png",
                                                                          "notes.txt"]


def test_a_window_longer_than_the_video_is_a_warning(tmp_path, capsys):
    video = _clip(tmp_path / "clip.mp4", 4)
    assert detection.main([str(video), "--preset", "tiny", "--window", "40", "--out", str(tmp_path / "maps")]) == 0
    err = capsys.readouterr().err
    assert f"warning: {video}: --window 40 is longer than its 4 frames; each window holds all 4\n" in err
    assert json.loads((tmp_path / "maps" / "clip.detection.json").read_text())["window"] == 4


def test_ctrl_c_is_one_line_and_exit_code_130(tmp_path, capsys, monkeypatch):
    def interrupted(*args, **kwargs):
        raise KeyboardInterrupt

    from geco_guide.metric import detection as detection_metric

    monkeypatch.setattr(detection_metric, "detection_maps", interrupted)
    assert _detect(_clip(tmp_path / "clip.mp4"), "--out", tmp_path / "maps") == 130
    err = capsys.readouterr().err.splitlines()
    assert err[-1] == "interrupted: the videos already done keep their outputs (each .detection.json is written last)"
    # stopped inside the maps: after the line saying what they take
    assert err[0] == "loading models: tiny-random + tiny-random on cpu" and err[1] == f"[1/1] {tmp_path / 'clip.mp4'} ..."
    assert "geometry-estimator calls" in err[2] and len(err) == 4


def test_an_fps_the_gif_writer_cannot_take_is_one_line_before_any_map(tmp_path, capsys, monkeypatch):
    video = _clip(tmp_path / "clip.mp4")

    def refuse(*args, **kwargs):
        raise AssertionError("models were loaded")

    monkeypatch.setattr(estimators_package, "load_estimators", refuse)
    assert detection.main([str(video), "--out", str(tmp_path / "out"), "--format", "gif", "--fps", "1e-300"]) == 2
    err = capsys.readouterr().err.strip()
    assert err == "error: fps must be in [0.01, 100] for a gif video, got 1e-300"
