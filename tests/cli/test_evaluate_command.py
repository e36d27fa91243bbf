"""``geco evaluate`` before and around the work: a mask file read and checked before any model
loads, every missing model named at once, an output lock on what it writes, the score JSON written
last, and a NaN score printed with its reason."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch

import geco_guide.estimators as estimators_package
from geco_guide.cli import evaluate as evaluate_cli
from geco_guide.io.files import WriteError
from geco_guide.io.video import write_video
from geco_guide.metric import score_files

FRAMES = 9


@pytest.fixture
def video(tmp_path: Path) -> Path:
    return write_video(tmp_path / "v.mp4", torch.rand(FRAMES, 3, 24, 32, generator=torch.Generator().manual_seed(0)),
                       fps=8)


@pytest.fixture
def no_estimators(monkeypatch):
    def refuse(*args, **kwargs):
        raise AssertionError("the estimators were loaded")

    monkeypatch.setattr(estimators_package, "load_estimators", refuse)


def _masks(frames: int = FRAMES, height: int = 24, width: int = 32) -> np.ndarray:
    masks = np.zeros((frames, height, width), dtype=bool)
    masks[:, 4:10, 5:12] = True
    return masks


def _complex(path: Path) -> None:
    np.savez(path, masks=_masks().astype(np.complex64))


def _nan(path: Path) -> None:
    values = _masks().astype(np.float32)
    values[3, 0, 0] = np.nan
    np.savez(path, masks=values)


BAD_MASKS = [
    ("nan.npz", _nan, "must be binary (0/1), got NaN or inf values"),
    ("complex.npz", _complex, "got complex values (complex64)"),
    ("flat.npz", lambda path: np.savez(path, masks=_masks()[0]), "must have shape [S, H, W]"),
    ("masks.npy", lambda path: np.save(path, _masks()), "is a .npy array"),
    ("random.npz", lambda path: path.write_bytes(b"\x00\x13junk" * 100), "is not an .npz archive"),
    ("short.npz", lambda path: np.savez(path, masks=_masks(5)),
     "holds 5 frame(s), the video 9: give one mask per frame"),
    ("square.npz", lambda path: np.savez(path, masks=_masks(FRAMES, 24, 24)), "a different aspect ratio"),
]


@pytest.mark.parametrize("name, make, message", BAD_MASKS, ids=[case[0] for case in BAD_MASKS])
def test_a_bad_mask_file_is_one_sentence_before_any_model_loads(tmp_path, capsys, video, no_estimators, name, make,
                                                                message):
    make(tmp_path / name)
    code = evaluate_cli.main(["--preset", "tiny", str(video), "--out", str(tmp_path / "out"),
                              "--dynamic-masks", str(tmp_path / name)])
    err = capsys.readouterr().err.strip()
    assert code == 2 and "\n" not in err and "loading" not in err, err
    assert f"mask file {str(tmp_path / name)!r}" in err and message in err, err


def test_masks_of_the_whole_video_fit_a_clip_cut_by_max_frames(tmp_path, capsys, video):
    np.savez(tmp_path / "m.npz", masks=_masks())
    assert evaluate_cli.main(["--preset", "tiny", str(video), "--out", str(tmp_path / "out"), "--max-frames", "5",
                              "--dynamic-masks", str(tmp_path / "m.npz")]) == 0
    data = json.loads((tmp_path / "out" / "v.geco.json").read_text())
    assert data["num_frames"] == 5 and data["dynamic_masks"]["source"] == f"given: {tmp_path / 'm.npz'}"
    line = capsys.readouterr().out.strip().splitlines()[-1]  # the masks are said on screen, not only in the JSON
    fraction = 100 * data["dynamic_masks"]["masked_fraction"]
    assert f"dynamic masks given: {tmp_path / 'm.npz'} masking {fraction:.1f}% of the pixels scored" in line, line


@pytest.mark.slow
def test_a_score_over_no_pixel_prints_nan_with_its_reason(tmp_path, capsys, video):
    np.savez(tmp_path / "all.npz", masks=np.ones((FRAMES, 24, 32), dtype=bool))
    assert evaluate_cli.main(["--preset", "tiny", str(video), "--out", str(tmp_path / "out"),
                              "--dynamic-masks", str(tmp_path / "all.npz")]) == 0
    line = capsys.readouterr().out.strip().splitlines()[-1]
    assert "M_geo=nan" in line and "(NaN: no frame kept 5% of its pixels valid outside the dynamic mask)" in line
    data = json.loads((tmp_path / "out" / "v.geco.json").read_text())
    assert data["fused"] is None and "outside the dynamic mask" in data["nan_reason"]


def test_every_missing_model_is_named_at_once_before_anything_loads(tmp_path, capsys, video, no_estimators):
    code = evaluate_cli.main(["--preset", "tiny", str(video), "--out", str(tmp_path / "out"),
                              f"estimators.geometry={tmp_path / 'no-vggt'}", f"estimators.flow={tmp_path / 'no-ufm'}"])
    err = capsys.readouterr().err.strip()
    assert code == 2 and "\n" not in err and "loading" not in err, err
    assert err.startswith("error: 2 models lack their weights: (1) VGGT: local path ")
    assert "(config: estimators.geometry=/path/to/no-vggt); (2) UFM: local path " in err
    assert "(config: estimators.flow=/path/to/no-ufm)" in err
    # the segmenter too, checked before a loading line is printed
    code = evaluate_cli.main(["--preset", "tiny", str(video), "--out", str(tmp_path / "out"), "--dynamic-masks",
                              "a dog", f"estimators.segmenter={tmp_path / 'no-sam3'}"])
    err = capsys.readouterr().err.strip()
    assert code == 2 and "\n" not in err and err.startswith("error: SAM 3 video: local path "), err
    assert "(config: estimators.segmenter=/path/to/sam3)" in err


def test_a_second_run_into_the_same_outputs_is_refused(tmp_path, capsys, video, no_estimators):
    out = tmp_path / "out"
    out.mkdir()
    holder = subprocess.Popen([sys.executable, "-c", "import time; time.sleep(60)"])
    try:
        (out / ".v.geco.json.lock").write_text(f"{holder.pid}\n")  # a run in progress holds the score
        assert evaluate_cli.main(["--preset", "tiny", str(video), "--out", str(out), "--overwrite"]) == 2
        err = capsys.readouterr().err.strip()
        assert err == (f"error: another run (pid {holder.pid}) is writing {str(out / 'v.geco.json')!r}; wait for it "
                       "to end or choose another --out")
    finally:
        holder.kill()
        holder.wait()
    # the lock of a run that is gone is taken over, and released when the run ends
    with pytest.raises(AssertionError, match="the estimators were loaded"):
        evaluate_cli.main(["--preset", "tiny", str(video), "--out", str(out)])
    assert not (out / ".v.geco.json.lock").exists()


@pytest.mark.slow
def test_an_output_that_cannot_be_written_takes_back_the_others_and_the_score(tmp_path, capsys, video, monkeypatch):
    out = tmp_path / "out"

    def full_disk(stem, estimators, evaluation, **kwargs):
        raise WriteError(f"cannot write '{stem}.detection.mp4': No space left on device")

    monkeypatch.setattr(score_files, "write_detection_video",
                        lambda video, stem, estimators, evaluation, masks: full_disk(stem, estimators, evaluation))
    assert evaluate_cli.main(["--preset", "tiny", str(video), "--out", str(out), "--maps", "--detection"]) == 1
    assert "No space left on device" in capsys.readouterr().err
    assert sorted(p.name for p in out.iterdir()) == []  # neither the maps written before, nor a score
    monkeypatch.undo()
    # the rerun needs no --overwrite
    assert evaluate_cli.main(["--preset", "tiny", str(video), "--out", str(out), "--maps"]) == 0
    assert sorted(p.name for p in out.iterdir()) == ["v.geco.json", "v.maps.mp4"]


def test_detection_names_every_missing_model_before_its_loading_line(tmp_path, capsys, video, monkeypatch):
    from geco_guide.cli import detection

    monkeypatch.setattr(estimators_package, "load_estimators", lambda *args, **kwargs: pytest.fail("the estimators loaded"))
    assert detection.main([str(video), f"estimators.geometry={tmp_path / 'no-vggt'}",
                           f"estimators.flow={tmp_path / 'no-ufm'}", "--preset", "tiny", "--out", str(tmp_path / "d")]) == 2
    err = capsys.readouterr().err.strip()
    assert "\n" not in err and err.startswith("error: 2 models lack their weights: (1) VGGT: ") and "(2) UFM: " in err


def test_a_segmenter_that_fails_to_load_fails_before_the_models_line(tmp_path, capsys, video, no_estimators):
    (tmp_path / "vggt").mkdir()  # a folder, not a SAM 3 one: refused while loading, after the weights check
    (tmp_path / "vggt" / "config.json").write_text("{}")
    code = evaluate_cli.main(["--preset", "tiny", str(video), "--out", str(tmp_path / "out"), "--dynamic-masks",
                              "a dog", f"estimators.segmenter={tmp_path / 'vggt'}"])
    err = capsys.readouterr().err.strip().splitlines()
    assert code == 2 and len(err) == 2 and err[0].startswith("loading segmenter: ")
    assert err[1].startswith(f"error: estimators.segmenter={str(tmp_path / 'vggt')!r}: the folder's config.json")


def test_detection_with_masks_that_are_not_a_file_is_one_line_before_loading(video, tmp_path, capsys, no_estimators):
    for masks in ("auto", "a dog"):
        code = evaluate_cli.main([str(video), "--preset", "tiny", "--detection", "--dynamic-masks", masks,
                                  "--out", str(tmp_path / "out")])
        err = capsys.readouterr().err.strip()
        assert code == 2 and err.startswith("error: --detection draws its maps with given masks only"), err
        assert "\n" not in err and not (tmp_path / "out" / "v.detection.mp4").exists()


@pytest.mark.slow
def test_detection_maps_leave_out_the_given_masks_of_the_frames_scored(video, tmp_path, monkeypatch):
    from geco_guide.metric import detection

    np.savez(tmp_path / "m.npz", masks=_masks())
    seen = []
    real = detection.detection_maps

    def recorded(frames, estimators, config=None, **kwargs):
        seen.append(kwargs["dynamic_masks"])
        return real(frames, estimators, config, **kwargs)

    monkeypatch.setattr(detection, "detection_maps", recorded)
    assert evaluate_cli.main([str(video), "--preset", "tiny", "--detection", "--dynamic-masks", str(tmp_path / "m.npz"),
                              "--max-frames", "6", "--out", str(tmp_path / "out")]) == 0
    (masks,) = seen  # the first 6 frames' masks, as the scores cut them
    assert torch.equal(masks, torch.from_numpy(_masks()[:6]))
    assert (tmp_path / "out" / "v.detection.mp4").is_file()
