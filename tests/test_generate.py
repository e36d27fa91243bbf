"""python -m geco_guide.generate: offline tiny run, sidecar, atomic outputs, clear load errors."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

from geco_guide.cli.generate import main, output_paths
from geco_guide.config import load_config
from geco_guide.estimators.loading import WeightsNotFoundError
from geco_guide.io.video import read_video
from geco_guide.sampler.loading import load_video_pipeline

REPO = Path(__file__).resolve().parents[1]


def test_cli_tiny_preset_writes_playable_mp4_and_sidecar(tmp_path: Path):
    env = dict(os.environ, HF_HUB_OFFLINE="1", PYTHONPATH=str(REPO))
    proc = subprocess.run(
        [sys.executable, "-m", "geco_guide.generate", "--preset", "tiny", "--prompt", "a marble bust",
         "--out", str(tmp_path / "run.mp4")],
        cwd=tmp_path, env=env, capture_output=True, text=True, timeout=120,
    )
    assert proc.returncode == 0, proc.stderr
    video, sidecar = tmp_path / "run.mp4", tmp_path / "run.json"
    assert f"wrote video:   {video}" in proc.stdout and "GeCo scores of anchor frames" in proc.stdout
    frames, fps = read_video(video)
    assert frames.shape == (17, 3, 32, 48) and fps == pytest.approx(8.0)
    data = json.loads(sidecar.read_text())
    assert data["seed"] == 0 and data["prompt"] == "a marble bust"
    assert data["config"]["guidance"]["anchors"] == [4, 8, 12, 16]
    assert data["config"]["model"]["id"] == "tiny-random"
    assert {"torch", "diffusers", "transformers"} <= set(data["versions"])
    assert {"load_s", "sampling_s"} <= set(data["timings"])
    assert len(data["guidance_log"]) == 5 and "grad_norm" in data["guidance_log"][0]
    assert {"fused", "motion", "structure", "anchors"} <= set(data["geco_scores"])
    assert data["scheduler"].startswith("CogVideoXDDIMScheduler")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["run.json", "run.mp4"]  # no temporaries


def test_no_guidance_seed_and_overrides_in_process(tmp_path: Path, capsys):
    rc = main(["--preset", "tiny", "--prompt", "a cat", "--seed", "3", "--no-guidance", "--out", str(tmp_path),
               "sampling.num_inference_steps=2", "guidance.repeats=0x2", "guidance.time_travel=[]"])
    assert rc == 0
    out = capsys.readouterr().out
    assert "guidance: off" in out
    data = json.loads((tmp_path / "a-cat-seed3-unguided.json").read_text())
    assert data["seed"] == 3 and data["guidance_log"] == [] and data["config"]["guidance"]["enabled"] is False
    assert (tmp_path / "a-cat-seed3-unguided.mp4").is_file()


def test_bad_override_is_one_error_line(capsys):
    rc = main(["--preset", "tiny", "--prompt", "x", "guidance.etaa=1"])
    assert rc == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith("error:") and "guidance.etaa" in err and "\n" not in err


def test_offline_without_weights_is_one_clear_error(monkeypatch):
    monkeypatch.setenv("HF_HUB_OFFLINE", "1")
    cfg = load_config(preset="tiny", overrides=["model.id=geco-test-missing/CogVideoX-nothing"])
    with pytest.raises(WeightsNotFoundError) as info:
        load_video_pipeline(cfg)
    msg = str(info.value)
    assert "geco-test-missing/CogVideoX-nothing" in msg and "model.id=/path/to/" in msg and "\n" not in msg
    cfg = load_config(preset="tiny", overrides=["model.id=/nonexistent/folder/cogvideox"])
    with pytest.raises(WeightsNotFoundError, match="local folder '/nonexistent/folder/cogvideox' does not exist"):
        load_video_pipeline(cfg)


def test_output_paths(tmp_path: Path):
    cfg = load_config(preset="tiny", overrides=[f"output.dir={tmp_path}"])
    video, sidecar = output_paths(cfg, "A Marble Bust, on a table!")
    assert video == tmp_path / "a-marble-bust-on-a-table-seed0.mp4" and sidecar == video.with_suffix(".json")


@pytest.mark.parametrize(
    "choice, cls, note",
    [
        ("ddim", "CogVideoXDDIMScheduler", "built from the checkpoint's CogVideoXDPMScheduler config"),
        ("dpm", "CogVideoXDPMScheduler", "sampling.scheduler=dpm, the checkpoint's"),
        ("null", "CogVideoXDPMScheduler", "(the checkpoint's)"),
    ],
)
def test_scheduler_is_chosen_by_the_config_and_named_in_the_sidecar(choice, cls, note):
    # the pipeline keeps the scheduler it is given; the config (the presets: ddim) chooses
    from diffusers import CogVideoXDPMScheduler

    from geco_guide.sampler.loading import choose_scheduler
    from geco_guide.tiny import tiny_pipeline

    cfg = load_config(preset="tiny", overrides=[f"sampling.scheduler={choice}"])
    pipe = tiny_pipeline(0)
    pipe.scheduler = CogVideoXDPMScheduler.from_config(pipe.scheduler.config)  # as CogVideoX-5B ships
    text = choose_scheduler(pipe, cfg.sampling.scheduler)
    assert type(pipe.scheduler).__name__ == cls and text.startswith(cls) and note in text
    assert load_config(preset="cogvideox-5b").sampling.scheduler == "ddim"
    with pytest.raises(ValueError, match="sampling.scheduler"):
        load_config(preset="tiny", overrides=["sampling.scheduler=euler"])
