"""Bad inputs of the benchmark side: validate, benchmarks and robustness give one-line errors
before heavy work, name a damaged clip and go on, and write standard, complete outputs."""

from __future__ import annotations

import errno
import io
import json
import shutil
from pathlib import Path

import numpy as np
import pytest
import torch
from PIL import Image

from geco_guide.bench import validate
from geco_guide.bench.datasets import (
    evenly_spaced,
    load_benchmark,
    load_clip,
    oracle_clip,
)
from geco_guide.bench.robustness import plot, sweep_memory_bytes
from geco_guide.cli import benchmarks, robustness
from geco_guide.cli import validate as validate_cli
from geco_guide.config import SEED_RANGE
from geco_guide.estimators import Estimators
from geco_guide.estimators.oracle import OracleFlow, OracleGeometry
from geco_guide.io import devices, files
from geco_guide.io.video import write_video
from geco_guide.loss.geco import GeCoLossConfig
from geco_guide.metric.evaluate import score_frames
from geco_guide.metric.render import READABLE_HEIGHT, VIRIDIS, enlarge, text_scale, text_strip

SIZE = ["5", "24", "32"]


def _standard_json(path: Path):
    def refuse(name):
        raise AssertionError(f"non-standard JSON constant {name} in {path}")

    return json.loads(path.read_text(), parse_constant=refuse)


def _one_error_line(err: str) -> str:
    lines = [line for line in err.splitlines() if line.startswith("error:")]
    assert lines and "Traceback" not in err
    return lines[-1]


@pytest.fixture(scope="module")
def clips(tmp_path_factory) -> Path:
    root = tmp_path_factory.mktemp("bench")
    assert benchmarks.main(["warp", "synthetic", "--synthetic-size", *SIZE, "--seeds", "0", "1", "2", "3", "4",
                            "--mode", "frame", "--out", str(root)]) == 0
    return root


# --- validate ----------------------------------------------------------------------------------


def test_damaged_clips_are_named_and_the_others_scored(clips, tmp_path, capsys):


    root = tmp_path / "bench"
    shutil.copytree(clips, root)
    (root / "synthetic-s0" / "meta.json").write_text("[1, 2]")  # not an object
    with np.load(root / "synthetic-s1" / "truth.npz") as data:  # no displacement: no oracle
        arrays = {k: data[k] for k in data.files if k != "displacement"}
    np.savez(root / "synthetic-s1" / "truth.npz", **arrays)
    meta = json.loads((root / "synthetic-s2" / "meta.json").read_text())
    (root / "synthetic-s2" / "meta.json").write_text(json.dumps({**meta, "anomalous_frame": 99}))
    with np.load(root / "synthetic-s3" / "truth.npz") as data:
        arrays = {k: data[k] for k in data.files}
    mask = arrays["mask"].astype(np.float32)
    mask[0, 0, 0] = np.nan
    np.savez(root / "synthetic-s3" / "truth.npz", **{**arrays, "mask": mask})

    out = tmp_path / "report"
    assert validate_cli.main([str(root), "--oracle", "--no-grids", "--out", str(out)]) == 1  # some failed
    captured = capsys.readouterr()
    assert "Traceback" not in captured.err and "[5/5] scoring" in captured.err
    report = _standard_json(out / "validation.json")
    reasons = {Path(e["clip"]).name: e["error"] for e in report["errors"]}
    assert set(reasons) == {"synthetic-s0", "synthetic-s1", "synthetic-s2", "synthetic-s3"}
    assert "JSON object" in reasons["synthetic-s0"] and "'displacement'" in reasons["synthetic-s1"]
    assert "anomalous_frame" in reasons["synthetic-s2"] and "0/1" in reasons["synthetic-s3"]
    assert [r["clip"] for r in report["clips"]] == [f"{root.name}-synthetic-s4"]
    assert "4 of 5 clip(s) failed" in (out / "validation.md").read_text()


def test_validate_refuses_missing_folders_and_unwritable_outputs(clips, tmp_path, capsys):
    assert validate_cli.main([str(tmp_path / "missing"), "--oracle"]) == 2
    assert "does not exist" in _one_error_line(capsys.readouterr().err)
    (tmp_path / "a-file").write_text("")
    assert validate_cli.main([str(clips), "--oracle", "--out", str(tmp_path / "a-file")]) == 2
    assert "is a file" in _one_error_line(capsys.readouterr().err)


def test_validate_refuses_to_replace_an_earlier_report_without_overwrite(clips, tmp_path, capsys):
    out = tmp_path / "report"
    assert validate_cli.main([str(clips / "synthetic-s0"), "--oracle", "--no-grids", "--out", str(out)]) == 0
    earlier = (out / "validation.json").read_text()
    capsys.readouterr()
    assert validate_cli.main([str(clips / "synthetic-s0"), "--oracle", "--no-grids", "--out", str(out)]) == 2
    assert "validation.json' already exists (the report of an earlier run); pass --overwrite" in _one_error_line(
        capsys.readouterr().err)
    assert (out / "validation.json").read_text() == earlier
    assert validate_cli.main([str(clips / "synthetic-s0"), "--oracle", "--no-grids", "--out", str(out),
                              "--overwrite"]) == 0


def test_a_full_disk_writes_neither_report_file(clips, tmp_path, monkeypatch, capsys):
    def full(fd):
        raise OSError(errno.ENOSPC, "No space left on device")

    monkeypatch.setattr(files.os, "fsync", full)
    out = tmp_path / "report"
    assert validate_cli.main([str(clips / "synthetic-s0"), "--oracle", "--no-grids", "--out", str(out)]) == 1
    assert "No space left" in _one_error_line(capsys.readouterr().err)
    assert list(out.iterdir()) == []  # no validation.json without its .md, no temporaries


def test_validate_names_every_missing_model_before_its_loading_line(clips, tmp_path, capsys):
    code = validate_cli.main([str(clips), "--out", str(tmp_path / "r"), f"estimators.geometry={tmp_path / 'no-vggt'}",
                              f"estimators.flow={tmp_path / 'no-ufm'}"])
    err = capsys.readouterr().err.strip()
    assert code == 2 and "\n" not in err and "loading" not in err, err
    assert err.startswith("error: 2 models lack their weights: (1) VGGT: local path ") and "(2) UFM: " in err


def test_validate_interrupted_says_what_was_kept(clips, tmp_path, monkeypatch, capsys):
    def interrupt(*args, **kwargs):
        raise KeyboardInterrupt

    from geco_guide.metric import evaluate as metric_evaluate

    monkeypatch.setattr(metric_evaluate, "score_frames", interrupt)  # run imports it when it runs
    assert validate_cli.main([str(clips), "--oracle", "--out", str(tmp_path / "r")]) == 130
    err = capsys.readouterr().err.strip().splitlines()
    assert err[-1].startswith("interrupted: ") and "Traceback" not in "\n".join(err)
    assert not (tmp_path / "r" / "validation.json").exists()


def test_grids_carry_the_colour_scale_and_row_captions(clips):
    bench = load_benchmark(clips / "synthetic-s0")
    clip = oracle_clip(bench)
    _, result = score_frames(bench.frames, Estimators(OracleGeometry(clip), OracleFlow(clip)), GeCoLossConfig(pairs="all"))
    record = validate.validate_clip(bench, result)
    frames = validate.grid_frames(bench, record)
    grid = validate.grid_image(bench, result, frames, record["task1"])
    assert grid.shape[-2] >= len(frames) * READABLE_HEIGHT  # small clips are enlarged
    bottom = grid[:, -40:].permute(1, 2, 0).reshape(-1, 3)  # the colour bar under the rows
    for colour in (VIRIDIS[0], VIRIDIS[-1]):
        assert bool(((bottom - colour).abs().amax(1) < 0.02).any())
    # the row of the frame Task 1 picks says so, and whether it is the replaced one
    picked, replaced = record["task1"]["predicted"]["fused"], record["task1"]["anomalous_frame"]
    caption = validate.grid_caption(bench, picked, record["task1"])
    assert caption.startswith(f"frame {picked} (") and "Task 1: the fused score picks it as the replaced frame" in caption
    assert caption.endswith(f"{'rightly' if picked == replaced else f'wrongly: frame {replaced} was'}); maps: "
                            "residual, 0 = consistent")
    strip = text_strip(caption, grid.shape[-1], text_scale(enlarge(bench.frames).shape[-2]))
    first = grid[:, : strip.shape[-2]]  # the first row's caption (one row: the replaced frame, picked)
    assert frames == [picked] and torch.equal(first, strip)
    other = validate.grid_caption(bench, picked, None)
    assert "Task 1" not in other


def test_the_docs_say_how_many_rows_a_grid_shows():
    from geco_guide.bench.validate import GRID_ROWS

    text = (Path(__file__).resolve().parents[2] / "docs" / "validation.md").read_text()
    assert f"row for each of up to {GRID_ROWS} judged frames" in " ".join(text.split())


# --- benchmarks --------------------------------------------------------------------------------


def test_benchmarks_check_sizes_and_regions_first(tmp_path, capsys):
    assert benchmarks.main(["warp", "synthetic", "--synthetic-size", "0", "0", "0", "--out", str(tmp_path)]) == 2
    line = _one_error_line(capsys.readouterr().err)
    assert "--synthetic-size" in line and "at least 3 frames of 8x8" in line
    assert benchmarks.main(["occlusion", "synthetic", "--synthetic-size", *SIZE, "--region", "0", "0", "100", "100",
                            "--out", str(tmp_path / "o")]) == 1
    assert "region (0, 0, 100, 100)" in _one_error_line(capsys.readouterr().err)


def test_short_clips_are_kept_whole_and_spread_over_their_length(tmp_path):
    assert evenly_spaced(17, 20) == list(range(17))
    assert evenly_spaced(8, 4) == [0, 2, 5, 7] and evenly_spaced(100, 20)[-1] == 99
    levels = torch.linspace(0, 1, 17)[:, None, None, None].expand(17, 3, 16, 16)
    write_video(tmp_path / "clip.mp4", levels, fps=8)
    frames, _ = load_clip(str(tmp_path / "clip.mp4"), 20, (3, 8, 8))
    assert frames.shape[0] == 17 and abs(float(frames[-1].mean()) - 1.0) < 0.03
    folder = tmp_path / "frames"
    folder.mkdir()
    for k in range(8):
        Image.fromarray(np.full((16, 16, 3), 30 * k, dtype=np.uint8)).save(folder / f"{k}.png")
    frames, _ = load_clip(str(folder), 4, (3, 8, 8))
    assert [round(float(f.mean()) * 255 / 30) for f in frames] == [0, 2, 5, 7]


def test_inputs_with_one_stem_get_folders_of_their_own(tmp_path):
    for name in ("a", "b"):
        (tmp_path / name).mkdir()
        write_video(tmp_path / name / "clip.mp4", torch.rand(4, 3, 16, 16), fps=8)
    out = tmp_path / "out"
    assert benchmarks.main(["warp", str(tmp_path / "a" / "clip.mp4"), str(tmp_path / "b" / "clip.mp4"),
                            "--out", str(out)]) == 0
    assert sorted(p.name for p in out.iterdir()) == ["clip-2-s0", "clip-s0"]
    assert files.unique_names(["x", "x", "x-2", "x"]) == ["x", "x-3", "x-2", "x-4"]


# --- robustness --------------------------------------------------------------------------------


def test_robustness_with_one_level_each_and_an_overflowing_sigma(tmp_path):
    assert robustness.main(["--out", str(tmp_path), "--size", *SIZE, "--depth-sigmas", "1e308",
                            "--flow-sigmas", "0.5"]) == 0
    report = _standard_json(tmp_path / "robustness.json")
    assert report["depth"]["warp"]["fused"] == [None] and report["depth"]["rigid_fused"] == [None]
    assert report["flow"]["warp"]["fused"][0] is not None
    assert (tmp_path / "robustness.png").read_bytes()[:4] == b"\x89PNG"
    # the same report with the lines on top of each other: the plot still draws every cue
    same = {cue: [0.5] for cue in ("structure", "motion", "fused")}
    rows = {"sigmas": [0.0], "warp": same, "occlusion": same, "rigid_fused": [0.0]}
    image = Image.open(io.BytesIO(plot({"depth": rows, "flow": rows}))).convert("RGB")
    colours = {tuple(c) for c in np.asarray(image).reshape(-1, 3)}
    assert {(31, 119, 180), (255, 127, 14), (44, 160, 44)} <= colours


def test_robustness_refuses_sizes_seeds_and_outputs_before_the_sweep(tmp_path, monkeypatch, capsys):
    monkeypatch.setattr(devices, "memory_limit", lambda device: 24 * 2**30)
    assert robustness.main(["--out", str(tmp_path), "--size", "9", "4000", "4000"]) == 2
    line = _one_error_line(capsys.readouterr().err)
    assert "--size 9 4000 4000" in line and "24 GiB" in line
    devices.check_memory_fits(sweep_memory_bytes(9, 48, 64, "all"), "cpu", "the defaults")  # accepted
    assert robustness.main(["--out", str(tmp_path), "--seed", str(SEED_RANGE[1] + 1)]) == 2
    assert "--seed" in _one_error_line(capsys.readouterr().err)
    (tmp_path / "a-file").write_text("")
    assert robustness.main(["--out", str(tmp_path / "a-file"), "--size", *SIZE]) == 2
    assert "is a file" in _one_error_line(capsys.readouterr().err)


def test_robustness_on_a_full_disk_writes_neither_file(tmp_path, monkeypatch, capsys):
    def full(fd):
        raise OSError(errno.ENOSPC, "No space left on device")

    monkeypatch.setattr(files.os, "fsync", full)
    assert robustness.main(["--out", str(tmp_path), "--size", *SIZE, "--depth-sigmas", "0", "--flow-sigmas", "0"]) == 1
    assert "No space left" in _one_error_line(capsys.readouterr().err)
    assert list(tmp_path.iterdir()) == []  # no JSON without its plot, no temporaries
