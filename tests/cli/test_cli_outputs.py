"""What the commands refuse before any model loads, and what they never overwrite silently:
existing scores in ``evaluate``, stale formats of ``detection --overwrite``, an output two
``generate`` runs write at once, prompts that are not UTF-8 text, a bad ``output_type``."""

from __future__ import annotations

import json
import subprocess
import sys

import pytest
import torch

import geco_guide.estimators as estimators_package
from geco_guide import generation
from geco_guide.cli import detection as detection_cli
from geco_guide.cli import evaluate as evaluate_cli
from geco_guide.cli import generate as generate_cli
from geco_guide.io.video import write_video


@pytest.fixture
def no_estimators(monkeypatch):
    def refuse(*args, **kwargs):
        raise AssertionError("the estimators were loaded")

    monkeypatch.setattr(estimators_package, "load_estimators", refuse)
    monkeypatch.setattr(estimators_package, "load_estimators", refuse)


def _one_error_line(capsys) -> str:
    err = capsys.readouterr().err.strip()
    assert err.startswith("error:") and "\n" not in err, err
    return err


def test_evaluate_a_missing_video_is_one_line_before_the_estimators_load(tmp_path, capsys, no_estimators):
    assert evaluate_cli.main(["--preset", "tiny", str(tmp_path / "missing.mp4"), "--out", str(tmp_path / "s")]) == 2
    assert "missing.mp4: no such file or folder" in _one_error_line(capsys)
    assert detection_cli.main(["--preset", "tiny", str(tmp_path / "missing.mp4"), "--out", str(tmp_path / "d")]) == 2
    assert "missing.mp4: no such file or folder" in _one_error_line(capsys)


def test_evaluate_refuses_to_replace_an_earlier_score_without_overwrite(tmp_path, capsys, no_estimators,
                                                                         monkeypatch):
    for folder in ("a", "b"):
        (tmp_path / folder).mkdir()
        write_video(tmp_path / folder / "g17.gif", torch.rand(4, 3, 16, 16), fps=8)
    out = tmp_path / "scores"
    out.mkdir()
    (out / "g17.geco.json").write_text(json.dumps({"video": "a/g17.gif"}))  # the score of a/g17.gif
    assert evaluate_cli.main(["--preset", "tiny", str(tmp_path / "b" / "g17.gif"), "--out", str(out)]) == 2
    err = _one_error_line(capsys)
    assert "g17.geco.json' already exists" in err and "--overwrite" in err
    assert json.loads((out / "g17.geco.json").read_text()) == {"video": "a/g17.gif"}
    # --maps adds its own output to the check
    (out / "g17.geco.json").unlink()
    (out / "g17.maps.mp4").write_bytes(b"earlier maps")
    assert evaluate_cli.main(["--preset", "tiny", str(tmp_path / "b" / "g17.gif"), "--out", str(out), "--maps"]) == 2
    assert "g17.maps.mp4' already exists" in _one_error_line(capsys)
    # with --overwrite the checks pass and the estimators load
    with pytest.raises(AssertionError, match="the estimators were loaded"):
        evaluate_cli.main(["--preset", "tiny", str(tmp_path / "b" / "g17.gif"), "--out", str(out), "--maps",
                           "--overwrite"])


def test_detection_overwrite_leaves_only_the_formats_asked_for(tmp_path):
    stem = tmp_path / "clip"
    (tmp_path / "clip.detection.mp4").write_bytes(b"an earlier mp4")
    frames = tmp_path / "clip.detection"
    frames.mkdir()
    (frames / "00000.png").write_bytes(b"png")
    detection_cli.remove_other_formats(stem, ["gif", "png"])
    assert not (tmp_path / "clip.detection.mp4").exists() and (frames / "00000.png").exists()
    (frames / "notes.txt").write_text("the user's own file")
    detection_cli.remove_other_formats(stem, ["mp4"])
    assert not (frames / "00000.png").exists() and (frames / "notes.txt").exists()  # only frame PNGs go
    (frames / "notes.txt").unlink()
    detection_cli.remove_other_formats(stem, ["mp4"])
    assert not frames.exists()


def test_a_prompt_that_is_not_utf8_is_one_line_before_loading(tmp_path, capsys, monkeypatch):
    monkeypatch.setattr(generation, "load_models", lambda cfg, estimators=True: pytest.fail("models were loaded"))
    prompt = b"a caf\xe9 on a street".decode("utf-8", "surrogateescape")  # Latin-1 bytes from a terminal
    assert generate_cli.main(["--preset", "tiny", "--prompt", prompt, "--out", str(tmp_path)]) == 2
    assert "not valid UTF-8 text (an undecodable byte at character 6)" in _one_error_line(capsys)


def test_a_bad_output_type_is_refused_before_denoising():
    from geco_guide.tiny import TINY_CALL_KWARGS, tiny_pipeline

    pipe = tiny_pipeline(seed=0)
    calls = []
    pipe.transformer.register_forward_hook(lambda *args: calls.append(1))
    with pytest.raises(ValueError, match=r"output_type must be one of \['pil', 'np', 'pt', 'latent'\], got 'mp4'"):
        pipe("a marble bust", generator=torch.Generator().manual_seed(0), output_type="mp4", **TINY_CALL_KWARGS)
    assert calls == []


@pytest.mark.slow
def test_two_generate_runs_of_one_output_at_once_refuse_the_second(tmp_path, capsys):
    out = tmp_path / "x.mp4"
    holder = subprocess.Popen([sys.executable, "-c", "import time; time.sleep(60)"])
    try:
        (tmp_path / ".x.mp4.lock").write_text(f"{holder.pid}\n")  # a run in progress holds the name
        assert generate_cli.main(["--preset", "tiny", "--prompt", "a cat", "--out", str(out), "--seed", "1"]) == 2
        err = _one_error_line(capsys)
        assert f"another run (pid {holder.pid}) is writing {str(out)!r}" in err and not out.exists()
    finally:
        holder.kill()
        holder.wait()
    # the lock of a run that is gone is taken over, and released at the end
    assert generate_cli.main(["--preset", "tiny", "--prompt", "a cat", "--out", str(out),
                              "output.score_anchors=false"]) == 0
    assert out.exists() and not (tmp_path / ".x.mp4.lock").exists()
    # a run that finished meanwhile: the existence check under the lock refuses the second writer
    capsys.readouterr()
    assert generate_cli.main(["--preset", "tiny", "--prompt", "a cat", "--out", str(out), "--seed", "1"]) == 2
    assert "already exists" in _one_error_line(capsys)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["x.json", "x.mp4"]
