"""Long inputs: ``evaluate`` and ``detection`` say what is coming before the work (frames,
windows, flow pairs, and for ``evaluate`` an estimate of the time left after the first window),
and ``max_frames`` / ``--max-frames`` bounds it."""

from __future__ import annotations

import json

import pytest

from geco_guide.estimators import Estimators
from geco_guide.bench.synthetic import rigid_clip
from geco_guide.cli import detection
from geco_guide.config import load_config
from geco_guide.estimators.oracle import OracleFlow, OracleGeometry
from geco_guide.io.video import write_video
from geco_guide.loss.geco import frame_pairs
from geco_guide.metric.evaluate import evaluate_video
from geco_guide.metric.protocol import EvaluationConfig, evaluation_windows, motion_grid, scoring_plan


def test_scoring_plan_counts_the_windows_and_the_motion_pairs():
    cfg = EvaluationConfig()
    plan = scoring_plan(49, 16.0, cfg)  # CogVideoX: 2 windows of 24 frames, motion on the 8 fps grid
    windows = evaluation_windows(49, 16.0, 3.0, 4, 8.0)
    motion = motion_grid(49, 16.0, 8.0)
    assert plan == {"windows": 2, "window_frames": 24, "motion_frames": len(motion),
                    "flow_pairs": sum(len(frame_pairs(len(w.indices), "all")) for w in windows) + len(motion) - 1}
    # a 300 s clip: still 4 windows, but each longer and the motion statistics over every second
    long = scoring_plan(3000, 10.0, cfg)
    assert long["windows"] == 4 and long["motion_frames"] == 2400 and long["flow_pairs"] > 50 * plan["flow_pairs"]
    assert scoring_plan(40, 10.0, EvaluationConfig(max_frames=40)) == scoring_plan(40, 10.0, cfg)
    with pytest.raises(ValueError, match="max_frames must be >= 2"):
        EvaluationConfig(max_frames=1)


@pytest.mark.slow
def test_evaluate_says_what_is_coming_and_max_frames_bounds_it():
    clip = rigid_clip(num_frames=9, height=32, width=48)
    frames = clip.frames.repeat(5, 1, 1, 1)  # 45 frames, 4.5 s at 10 fps: two windows
    oracle = {"estimators": Estimators(OracleGeometry(clip), OracleFlow(clip))}
    lines: list[str] = []
    full = evaluate_video(frames, fps=10, progress=lines.append, **oracle)
    plan = scoring_plan(45, 10.0, EvaluationConfig())
    assert lines[0].startswith("45 frames at 10 fps (4.5 s): 2 windows of up to 24 frames")
    assert f"{plan['flow_pairs']} flow-estimator pairs in all" in lines[0] and "evaluation.max_frames" in lines[0]
    # the estimate comes once, after the first window and before the second
    estimates = [k for k, line in enumerate(lines) if "to go (estimated)" in line]
    assert len(estimates) == 1 and lines[estimates[0] + 1].startswith("window 2/2")

    lines.clear()
    bounded = evaluate_video(frames, fps=10, config=EvaluationConfig(max_frames=20), progress=lines.append, **oracle)
    assert bounded.num_frames == 20 and max(row["index"] for row in bounded.frame_scores) < 20
    assert full.num_frames == 45 and lines[0].startswith("20 frames at 10 fps (2.0 s): 1 window of")
    assert not any("estimated" in line for line in lines)  # one window: nothing left to estimate


def test_evaluate_config_key_and_cli_option():
    assert load_config(preset="tiny", overrides=["evaluation.max_frames=30"]).evaluation.max_frames == 30
    with pytest.raises(ValueError, match="evaluation.max_frames"):
        load_config(preset="tiny", overrides=["evaluation.max_frames=1"])


def test_detection_says_what_is_coming_and_max_frames_bounds_it(tmp_path, capsys):
    clip = rigid_clip(num_frames=9, height=32, width=48)
    video = write_video(tmp_path / "long.gif", clip.frames.repeat(3, 1, 1, 1), fps=8)  # 27 frames
    out = tmp_path / "out"
    assert detection.main([str(video), "--preset", "tiny", "--out", str(out), "--window", "4",
                           "--max-frames", "5"]) == 0
    err = capsys.readouterr().err
    assert err.splitlines()[0] == "loading models: tiny-random + tiny-random on cpu"  # before the models load
    assert "5 frames (the first of 27: --max-frames): one window of 4 frames per frame, 5 geometry-estimator " \
           "calls and 15 flow pairs" in err
    report = json.loads((out / "long.detection.json").read_text())
    assert len(report["frames"]) == 5 and report["window"] == 4

    assert detection.main([str(video), "--preset", "tiny", "--out", str(out), "--max-frames", "1"]) == 2
    assert capsys.readouterr().err.strip() == "error: --max-frames must be >= 2 (a window compares frames), got 1"
    # a long input is told how to bound it
    assert detection.work_line(3000, 3000, 20).endswith("57000 flow pairs; --max-frames N bounds it")
    assert detection.work_line(1, 1, 1).startswith("1 frame:")
