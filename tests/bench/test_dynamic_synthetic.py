"""Synthetic scenes with objects that move on their own, and the dynamic validation command."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
import torch
from photometric import photometric_error

from geco_guide.bench.dynamic_suite import (
    DynamicScenes,
    dynamic_validation,
    edited_clips,
)
from geco_guide.bench.synthetic import moving_clip, rigid_clip
from geco_guide.cli.validate import main as validate_main


def test_moving_boxes_flow_with_their_own_motion():
    clip = moving_clip(3, 48, 64)
    on_box = clip.dynamic_mask[0]
    error, count = photometric_error(clip, 0, 2, on_box)
    assert count > 50 and error < 0.02
    # The camera's flow alone does not explain the boxes: the test has teeth.
    rigid_flow, _ = clip.rigid_correspondences(0, 2)
    assert (clip.correspondences(0, 2)[0] - rigid_flow).norm(dim=0)[on_box].mean() > 2.0
    background, _ = photometric_error(clip, 0, 2, ~on_box)
    assert background < 0.01
    static = ~on_box & (clip.correspondences(0, 2)[1] > 0.5)
    assert clip.residual_displacement(0, 2)[static].max() < 1e-9  # float64: the background moves with the camera only


def test_still_and_empty_movers_are_the_static_scenes():
    still = moving_clip(3, 24, 32, still=True)
    assert still.dynamic_mask.any() and (still.object_paths == 0).all()
    covisible = still.correspondences(0, 2)[1] > 0.5
    assert torch.equal(covisible, still.rigid_correspondences(0, 2)[1] > 0.5)
    assert still.residual_displacement(0, 2)[covisible].max() < 1e-9
    empty = moving_clip(3, 24, 32, movers=[])
    assert torch.equal(empty.frames, rigid_clip(3, 24, 32).frames) and not empty.dynamic_mask.any()


def test_edits_sit_on_the_static_background():
    clips = edited_clips(DynamicScenes(4, 24, 32))
    for kind in ("deformation", "occlusion"):
        for clip in clips[kind].values():
            assert clip.mask.any()
            assert not (clip.mask & clip.dynamic_mask).any()


@pytest.mark.slow
def test_dynamic_validation_command_end_to_end(tmp_path: Path, capsys, monkeypatch):
    code = validate_main(["--dynamic", "--dynamic-size", "4", "24", "32", "--out", str(tmp_path / "out")])
    assert code == 0
    progress = [line for line in capsys.readouterr().err.splitlines() if " scored the " in line]
    assert [line.split("]")[0] for line in progress] == ([f"[{k}/13" for k in range(1, 14)] + [f"[{k}/14" for k in range(1, 15)]
                                                         + [f"[{k}/8" for k in range(1, 9)])
    assert progress[0].startswith("[1/13] scored the still clean clip with no mask (")
    # an earlier run's report is not replaced without --overwrite
    earlier = (tmp_path / "out" / "dynamic.json").read_text()
    assert validate_main(["--dynamic", "--dynamic-size", "4", "24", "32", "--out", str(tmp_path / "out")]) == 2
    err = capsys.readouterr().err.strip()
    assert err == (f"error: {str(tmp_path / 'out' / 'dynamic.json')!r} already exists (the report of an earlier run); "
                   "pass --overwrite to replace it, or choose another --out folder")
    assert (tmp_path / "out" / "dynamic.json").read_text() == earlier
    report = json.loads((tmp_path / "out" / "dynamic.json").read_text())
    assert (tmp_path / "out" / "dynamic.md").read_text().startswith("# GeCo dynamic masks (oracle)")
    fp = report["false_positives"]
    assert fp["moving/none"]["fused"] > 20 * fp["still"]["fused"]
    assert fp["moving/true"]["fused"] < 2 * fp["still"]["fused"]
    assert set(report["detection"]) == {"deformation", "occlusion"}
    assert set(report["targets"]) == {"auto_iou", "hidden_deformation", "score_ratio", "ap_ratio_deformation", "ap_ratio_occlusion",
                                      "movers_removed", "movers_score_ratio", "movers_ap_ratio", "movers_non_rigid_left_out",
                                      "movers_false_positive_removed", "movers_deformation_recovered"}
    assert list(report["drawn_movers"]) == [str(seed) for seed in range(8)]
    assert "| seed | false positive removed | deformation recovered |" in (tmp_path / "out" / "dynamic.md").read_text()
    assert set(report["movers"]) == {"box_fraction", "rigid", "deformed", "non_rigid", "movers"}
    assert report == json.loads(json.dumps(dynamic_validation(DynamicScenes(4, 24, 32))))  # deterministic
    assert validate_main(["--dynamic", "somewhere"]) == 2
    assert validate_main(["--dynamic-size", "4", "24", "32", str(tmp_path)]) == 2
    assert validate_main(["--dynamic", "--dynamic-size", "2", "24", "32"]) == 2
    errors = capsys.readouterr().err.strip().splitlines()
    assert errors[-1] == "error: dynamic validation clips need >= 4 frames of >= 24x32 pixels, got 2x24x32"


@pytest.mark.slow
def test_dynamic_validation_logs_each_scored_clip_as_it_finishes(monkeypatch):
    import logging

    from geco_guide.bench import dynamic_suite

    lines: list[str] = []
    seen_at_call: list[int] = []
    handler = logging.Handler()
    handler.emit = lambda record: lines.append(record.getMessage())
    logger = logging.getLogger(dynamic_suite.__name__)
    logger.addHandler(handler)
    score = dynamic_suite.score_clip

    def counting(clip, masks, movers="drop"):
        seen_at_call.append(len(lines))
        return score(clip, masks, movers)

    monkeypatch.setattr(dynamic_suite, "score_clip", counting)
    try:
        dynamic_suite.dynamic_validation(DynamicScenes(4, 24, 32))
    finally:
        logger.removeHandler(handler)
    # the k-th clip starts once k - 1 lines were logged: 13 clips of the masks, then 14 of the movers,
    # then a line per drawn mover scene (five clips each)
    assert seen_at_call[:27] == list(range(27)) and len(lines) == 27 + 8
    assert seen_at_call[27:] == [27 + k for k in range(8) for _ in range(5)]
    assert lines[12].startswith("[13/13] scored the still clean clip with true mask (")
    assert lines[26].startswith("[14/14] scored the movers' stretching clip with auto mask, movers rigid (")
    assert lines[-1].startswith("[8/8] scored the drawn mover scene of seed 7 (")
