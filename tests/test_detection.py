"""Per-frame detection maps: windows, the two-way occlusion check, localisation, the CLI."""

import json

import pytest
import torch

from geco_guide.bench.ranking import average_precision
from geco_guide.bench.synthetic import occlusion_swap_clip, rigid_clip, with_warp
from geco_guide.bench.warp import WarpParams, warp_one_frame
from geco_guide.cli import detection
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
    maps = detection_maps(clip.frames, OracleGeometry(clip), OracleFlow(clip), LOSS, window=4)
    fused = [row["fused"] for row in frame_scores(maps)]
    t = warped.anomalous_frame
    assert max(range(6), key=fused.__getitem__) == t
    assert average_precision(torch.where(maps.fused_valid[t], maps.fused[t], 0.0), warped.mask[t]) >= 0.9
    rigid = detection_maps(base.frames, OracleGeometry(base), OracleFlow(base), LOSS, window=4)
    assert max(row["fused"] for row in frame_scores(rigid)) < 1e-3


def test_the_two_way_check_only_removes_structure_pixels():
    clip = occlusion_swap_clip(num_frames=5, height=32, width=48)
    one_way = detection_maps(clip.frames, OracleGeometry(clip), OracleFlow(clip), LOSS, window=5, two_way=False)
    two_way = detection_maps(clip.frames, OracleGeometry(clip), OracleFlow(clip), LOSS, window=5)
    assert not (two_way.structure_valid & ~one_way.structure_valid).any()
    assert two_way.structure_valid.sum() < one_way.structure_valid.sum()  # the pillar hides some
    torch.testing.assert_close(two_way.motion, one_way.motion)


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
