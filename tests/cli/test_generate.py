"""python -m geco_guide.generate: offline tiny run, sidecar, atomic outputs, clear load errors."""

from __future__ import annotations

import json
import os
import re
import subprocess
import sys
from pathlib import Path

import pytest
import torch

from geco_guide import generation
from geco_guide.cli.generate import main
from geco_guide.generation import SCORES_NOTE, default_name, output_paths, video_key
from geco_guide.config import config_to_dict, load_config
from geco_guide.estimators.loading import WeightsNotFoundError
from geco_guide.io.files import WriteError
from geco_guide.io.video import read_video
from geco_guide.sampler.pipelines.loading import load_video_pipeline

REPO = Path(__file__).resolve().parents[2]


@pytest.mark.slow
def test_cli_tiny_preset_writes_playable_mp4_and_sidecar(tmp_path: Path):
    env = dict(os.environ, HF_HUB_OFFLINE="1", PYTHONPATH=str(REPO))
    proc = subprocess.run(
        [sys.executable, "-m", "geco_guide.generate", "--preset", "tiny", "--prompt", "a marble bust",
         "--out", str(tmp_path / "run.mp4")],
        cwd=tmp_path, env=env, capture_output=True, text=True, timeout=120, check=False,
    )
    assert proc.returncode == 0, proc.stderr
    video, sidecar = tmp_path / "run.mp4", tmp_path / "run.json"
    assert f"wrote video:   {video}" in proc.stdout and "GeCo scores of anchor frames" in proc.stdout
    assert SCORES_NOTE in proc.stdout  # says why evaluate prints another number for the same video
    assert "loading models: cogvideox-5b tiny-random, geometry tiny-random, flow tiny-random ..." in proc.stderr
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
    assert data["guidance_decoder"] == "vae (the model's own)"
    assert data["memory_plan"]["name"] == "explicit"  # the tiny preset's: its flags as given
    assert sorted(p.name for p in tmp_path.iterdir()) == ["run.json", "run.mp4"]  # no temporaries


def test_no_guidance_seed_and_overrides_in_process(tmp_path: Path, capsys):
    rc = main(["--preset", "tiny", "--prompt", "a cat", "--seed", "3", "--no-guidance", "--out", str(tmp_path),
               "sampling.num_inference_steps=2", "guidance.repeats=0x2", "guidance.time_travel=[]"])
    assert rc == 0
    out = capsys.readouterr().out
    assert "guidance: off" in out
    (sidecar,) = tmp_path.glob("*.json")
    assert re.fullmatch(r"a-cat-[0-9a-f]{8}-seed3-unguided\.json", sidecar.name)
    data = json.loads(sidecar.read_text())
    assert data["seed"] == 3 and data["guidance_log"] == [] and data["config"]["guidance"]["enabled"] is False
    assert sidecar.with_suffix(".mp4").is_file() and data["video"] == sidecar.with_suffix(".mp4").name


def test_bad_override_is_one_error_line(capsys):
    rc = main(["--preset", "tiny", "--prompt", "x", "guidance.step_sizea=1"])
    assert rc == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith("error:") and "guidance.step_sizea" in err and "\n" not in err


def test_offline_without_weights_is_one_clear_error(monkeypatch):
    monkeypatch.setenv("HF_HUB_OFFLINE", "1")
    cfg = load_config(preset="tiny", overrides=["model.id=geco-test-missing/CogVideoX-nothing"])
    with pytest.raises(WeightsNotFoundError) as info:
        load_video_pipeline(cfg.model)
    msg = str(info.value)
    assert "geco-test-missing/CogVideoX-nothing" in msg and "model.id=/path/to/" in msg and "\n" not in msg
    cfg = load_config(preset="tiny", overrides=["model.id=/nonexistent/folder/cogvideox"])
    with pytest.raises(WeightsNotFoundError, match="local folder '/nonexistent/folder/cogvideox' does not exist"):
        load_video_pipeline(cfg.model)


def test_output_paths(tmp_path: Path):
    cfg = load_config(preset="tiny", overrides=[f"output.dir={tmp_path}"])
    video, sidecar = output_paths(cfg, "A Marble Bust, on a table!")
    key = video_key(config_to_dict(cfg), "A Marble Bust, on a table!")
    assert video == tmp_path / f"a-marble-bust-on-a-table-{key}-seed0.mp4" and sidecar == video.with_suffix(".json")
    assert re.fullmatch(r"[0-9a-f]{8}", key)
    assert output_paths(cfg, "x", tmp_path / "run.MP4") == (tmp_path / "run.MP4", tmp_path / "run.json")
    assert output_paths(cfg, "x", tmp_path / "runs")[0].parent == tmp_path / "runs"  # no suffix: a folder


def test_default_names_differ_for_prompts_with_one_prefix_and_for_configs_that_change_the_video():
    cfg = load_config(preset="tiny")
    prefix = "a very long prompt about a marble bust on a wooden table in a quiet"  # longer than the slug
    first, second = default_name(cfg, prefix + " room"), default_name(cfg, prefix + " hall")
    assert first != second and first.split("-seed")[0].rsplit("-", 1)[0] == second.split("-seed")[0].rsplit("-", 1)[0]
    for override in ("guidance.step_size=2.0", "sampling.num_inference_steps=3", "model.init_seed=1", "seed=1",
                     "guidance.loss.cue=fused", "estimators.flow=some/other-flow"):
        assert default_name(load_config(preset="tiny", overrides=[override]), "a cat") != default_name(cfg, "a cat")
    # where the files go, whether the anchors are scored, the evaluation protocol and the device do not rename
    same = ["output.dir=elsewhere", "output.score_anchors=false", "evaluation.max_fps=4", "model.device=cpu"]
    assert default_name(load_config(preset="tiny", overrides=same), "a cat") == default_name(cfg, "a cat")
    unguided = load_config(preset="tiny", overrides=["guidance.enabled=false"])
    assert default_name(unguided, "a cat").endswith("-seed0-unguided")


@pytest.mark.slow
def test_the_video_key_is_the_same_in_another_process():
    cfg = load_config(preset="tiny")
    code = ("from geco_guide.generation import default_name; from geco_guide.config import load_config; "
            "print(default_name(load_config(preset='tiny'), 'a cat'))")
    env = dict(os.environ, PYTHONHASHSEED="123", PYTHONPATH=str(REPO))
    proc = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True, timeout=60,
                          check=False)
    assert proc.returncode == 0, proc.stderr
    assert proc.stdout.strip() == default_name(cfg, "a cat")


# --------------------------------------------------------------------------------------------
# outputs are never lost: checked before anything loads, written together


@pytest.fixture
def stub_loading(stub_generation):
    stub_generation(torch.rand(1, 9, 3, 32, 48))


def _run(out: Path, *extra: str) -> int:
    return main(["--preset", "tiny", "--prompt", "a cat", "--out", str(out), "output.score_anchors=false", *extra])


def _error_line(capsys) -> str:
    err = capsys.readouterr().err.strip()
    assert err.startswith("error:") and "\n" not in err, err
    return err


def test_an_existing_output_is_refused_before_loading_unless_overwrite(tmp_path: Path, capsys, stub_generation,
                                                                       no_loading):
    video = tmp_path / "clip.mp4"
    video.write_bytes(b"an earlier video")
    assert _run(video) == 2
    assert f"{str(video)!r} already exists; pass --overwrite" in _error_line(capsys)
    video.unlink()
    (tmp_path / "clip.json").write_text("{}")  # a sidecar alone is an output too
    assert _run(video) == 2 and "clip.json' already exists" in _error_line(capsys)
    assert video.exists() is False

    stub_generation(torch.rand(1, 9, 3, 32, 48))
    assert _run(video, "--overwrite") == 0
    assert json.loads((tmp_path / "clip.json").read_text())["video"] == "clip.mp4"
    assert read_video(video)[0].shape[0] == 9


def test_default_names_in_one_folder_do_not_overwrite(tmp_path: Path, capsys, stub_loading):
    assert _run(tmp_path) == 0
    capsys.readouterr()
    assert _run(tmp_path) == 2 and "already exists" in _error_line(capsys)
    assert _run(tmp_path, "guidance.step_size=2.0") == 0  # another config: another name
    assert len(list(tmp_path.glob("*.mp4"))) == 2 and len(list(tmp_path.glob("*.json"))) == 2


@pytest.mark.parametrize("name, message", [
    ("x.avi", "a video path must end with .mp4 or .gif"),
    ("x.webm", "a path without a suffix is a folder"),
])
def test_out_suffixes_other_than_mp4_or_gif_are_one_line(tmp_path: Path, capsys, no_loading, name, message):
    assert _run(tmp_path / name) == 2
    assert message in _error_line(capsys)
    assert list(tmp_path.iterdir()) == []  # no folder named x.avi


@pytest.mark.slow
def test_out_gif_writes_a_gif_and_its_sidecar(tmp_path: Path, capsys):
    assert _run(tmp_path / "x.gif") == 0
    assert sorted(p.name for p in tmp_path.iterdir()) == ["x.gif", "x.json"]
    assert (tmp_path / "x.gif").read_bytes()[:6] in (b"GIF89a", b"GIF87a")
    frames = read_video(tmp_path / "x.gif")[0]
    assert frames.shape[0] == 17


def test_a_video_too_big_for_the_device_is_one_line_before_loading(tmp_path: Path, capsys, monkeypatch, no_loading):
    from geco_guide.io import devices

    monkeypatch.setattr(devices, "memory_limit", lambda device: 24 * 2**30)  # a 24 GiB machine, whatever runs this
    assert _run(tmp_path, "sampling.height=16384", "sampling.width=16384", "sampling.num_frames=49") == 2
    err = _error_line(capsys)
    assert ("a 49-frame 16384x16384 video (sampling.num_frames/height/width) needs at least 147 GiB of memory, more "
            "than the 24 GiB of RAM") in err
    generation.check_generation(load_config(preset="tiny"), "a cat")  # the tiny preset fits


def test_out_paths_that_cannot_be_written_are_one_line_before_loading(tmp_path: Path, capsys, monkeypatch,
                                                                      no_loading):
    (tmp_path / "x.mp4").mkdir()
    assert _run(tmp_path / "x.mp4") == 2
    assert "a folder of that name is in the way" in _error_line(capsys)

    read_only = tmp_path / "read-only"
    read_only.mkdir()
    read_only.chmod(0o555)
    real_access = os.access  # root writes anywhere: the check asks access(), so ask it for this folder
    monkeypatch.setattr(os, "access", lambda path, mode: Path(path) != read_only and real_access(path, mode))
    try:
        assert _run(read_only / "run.mp4") == 2
        assert f"the folder {str(read_only)!r} is not writable" in _error_line(capsys)
    finally:
        read_only.chmod(0o755)

    assert _run(tmp_path / "long", "output.name=" + "n" * 300) == 2
    assert "the name is 304 bytes, over the" in _error_line(capsys)
    assert _run(tmp_path / "long", "output.name=" + "n" * 250) == 2  # fits, but its temporary would not
    assert "the name is 254 bytes" in _error_line(capsys)
    assert _run(tmp_path / ("d" * 300) / "run.mp4") == 2
    assert "the folder name 'dddddddddddddddddddddddd'... is 300 bytes" in _error_line(capsys)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["read-only", "x.mp4"]


def test_a_failed_sidecar_write_leaves_no_video_without_its_sidecar(tmp_path: Path, capsys, monkeypatch, stub_loading):
    def full_disk(path, data):
        raise WriteError(f"cannot write {str(path)!r}: No space left on device")

    monkeypatch.setattr(generation, "write_json_atomic", full_disk)
    assert _run(tmp_path / "clip.mp4") == 2
    loading, error = capsys.readouterr().err.strip().splitlines()  # the error follows the line of what loaded
    assert loading.startswith("loading models: ") and error.startswith("error: ") and "No space left on device" in error
    assert list(tmp_path.iterdir()) == []


def test_ctrl_c_is_one_line_and_exit_code_130(tmp_path: Path, capsys, monkeypatch):
    def interrupted(cfg, estimators=True):
        raise KeyboardInterrupt

    monkeypatch.setattr(generation, "load_models", interrupted)
    assert _run(tmp_path / "clip.mp4") == 130
    assert capsys.readouterr().err.splitlines()[-1] == "interrupted: nothing was written (outputs are written atomically)"
    assert list(tmp_path.iterdir()) == []


@pytest.mark.parametrize(
    "choice, cls, note",
    [
        ("ddim", "CogVideoXDDIMScheduler", "built from the checkpoint's CogVideoXDPMScheduler config"),
        ("dpm", "CogVideoXDPMScheduler", "sampling.scheduler=dpm, the checkpoint's"),
        ("checkpoint", "CogVideoXDPMScheduler", "(the checkpoint's)"),
    ],
)
def test_scheduler_is_chosen_by_the_config_and_named_in_the_sidecar(choice, cls, note):
    # the pipeline keeps the scheduler it is given; the config (the presets: ddim) chooses
    from diffusers import CogVideoXDPMScheduler

    from geco_guide.sampler.pipelines.loading import load_video_pipeline
    from geco_guide.tiny import tiny_pipeline

    cfg = load_config(preset="tiny", overrides=[f"sampling.scheduler={choice}"])
    pipe = tiny_pipeline(0)
    pipe.scheduler = CogVideoXDPMScheduler.from_config(pipe.scheduler.config)  # as CogVideoX-5B ships
    loaded = load_video_pipeline(cfg.model, cfg.sampling.scheduler, pipe.components)
    text = loaded.scheduler
    assert type(loaded.pipe.scheduler).__name__ == cls and text.startswith(cls) and note in text
    assert load_config(preset="cogvideox-5b").sampling.scheduler == "ddim"
    with pytest.raises(ValueError, match="sampling.scheduler"):
        load_config(preset="tiny", overrides=["sampling.scheduler=euler"])


@pytest.mark.parametrize("overrides, message", [
    (["guidance.repeats=1,1,1"], "covers 3 steps but the sampler runs 4"),  # the tiny preset takes 4 steps
    (["guidance.decoder=tiny", "estimators.tiny_decoder=null"], "guidance.decoder=tiny needs the tiny decoder's weights"),
])
def test_guidance_the_call_would_refuse_is_one_line_before_loading(tmp_path: Path, capsys, no_loading, overrides,
                                                                    message):
    assert main(["--preset", "tiny", "--prompt", "a cat", "--out", str(tmp_path / "out"), *overrides]) == 2
    assert message in _error_line(capsys)


@pytest.mark.slow
def test_guidance_over_no_valid_pixel_says_so_and_its_scores_are_nan_with_the_reason(tmp_path: Path, capsys):
    # the tiny random segmenter masks about 96 % of every anchor frame: no frame keeps the 5 % a
    # score needs, so each update measures nothing (loss 0, zero gradient), which must not read as perfect
    out = tmp_path / "dog.mp4"
    assert main(["--preset", "tiny", "--prompt", "a dog runs", "--dynamic", "a dog", "estimators.segmenter=tiny-random",
                 "--out", str(out)]) == 0
    captured = capsys.readouterr()
    assert "fused=nan motion=nan structure=nan" in captured.out
    assert "(NaN: no frame kept 5% of its pixels valid outside the dynamic mask)" in captured.out
    assert "guidance update(s) saw no valid pixel (everything masked or invalid: loss 0, zero gradient)" in captured.err
    sidecar = json.loads(out.with_suffix(".json").read_text())
    assert sidecar["geco_scores"]["fused"] is None and sidecar["geco_scores"]["nan_reason"].startswith("no frame kept")
    assert all(record["valid_fraction"] == 0 for record in sidecar["guidance_log"])
