"""The tiny preset runs every registry model: ``geco generate --preset tiny --model NAME`` (and
``geco ab``, ``geco geco-eval``) fit the preset's 17 x 32 x 48 call to the model: the size
multiple (48 -> 64 for LTX, LTX-2 and the Wan 2.2 16x VAE), no text length for HunyuanVideo 1.5's
pipeline, which takes none. What the user sets stays as set, and is refused if it does not fit.
LTX-2's sound, which its pipeline makes with the video, is the mp4's sound stream."""

from __future__ import annotations

import json

import pytest

from geco_guide import tiny
from geco_guide.bench.geco_eval import job_config
from geco_guide.cli import generate
from geco_guide.config import load_config
from geco_guide.families import model_named, video_models
from geco_guide.io.video import audio_stream
from geco_guide.sampler.pipelines.sampling import sampling_problem

GENERATING = video_models()


def tiny_config(name: str, overrides: tuple[str, ...] = ()):
    return load_config(None, "tiny", list(overrides), changes={"model.name": name})


@pytest.mark.parametrize("name", GENERATING)
def test_the_tiny_preset_fits_its_call_to_every_model(name):
    model = model_named(name)
    cfg = tiny_config(name)
    s = cfg.sampling
    assert cfg.model.id == "tiny-random" and sampling_problem(s, model) is None
    assert s.num_frames == 17 and s.height == 32
    assert s.width == (64 if model.size_multiple == 32 else 48)
    assert s.max_sequence_length == (16 if model.text_length else None)


def test_the_tiny_preset_of_the_default_model_is_unchanged():
    s = load_config(None, "tiny").sampling
    assert (s.num_frames, s.height, s.width, s.max_sequence_length) == (17, 32, 48, 16)


def test_a_size_the_user_sets_is_kept_and_refused_when_it_does_not_fit():
    with pytest.raises(ValueError, match=r"sampling.width.*multiple of 32 for ltx-2.*got 48"):
        tiny_config("ltx-2", ("sampling.width=48",))
    assert tiny_config("ltx-2", ("sampling.width=96",)).sampling.width == 96
    with pytest.raises(ValueError, match=r"sampling.max_sequence_length.*HunyuanVideo15Pipeline.*use null"):
        tiny_config("hunyuanvideo-1.5", ("sampling.max_sequence_length=16",))


def test_a_real_models_preset_is_not_fitted():
    cfg = load_config(None, None, changes={"model.name": "ltx-2"}, model_preset="ltx-2")
    assert cfg.model.id != "tiny-random" and cfg.sampling.width == model_named("ltx-2").call["width"]


@pytest.mark.parametrize("name", ["hunyuanvideo-1.5", "ltx-2"])
def test_geco_eval_fits_the_tiny_call_of_each_model(name):
    cfg = job_config(load_config(None, "tiny"), name)
    model = model_named(name)
    assert sampling_problem(cfg.sampling, model) is None
    assert cfg.sampling.width % model.size_multiple == 0
    assert (cfg.sampling.max_sequence_length is None) == (not model.text_length)


@pytest.fixture(scope="module")
def image(tmp_path_factory):
    path = tmp_path_factory.mktemp("image") / "image.png"
    tiny.tiny_image(0, 64, 64).save(path)
    return path


@pytest.mark.slow
@pytest.mark.parametrize("name", GENERATING)
def test_geco_generate_preset_tiny_runs_every_model(name, image, tmp_path, capsys):
    out = tmp_path / "video.mp4"
    argv = ["--preset", "tiny", "--model", name, "--prompt", "a marble bust", "--out", str(out)]
    if model_named(name).image_to_video:
        argv += ["--image", str(image)]
    rc = generate.main(argv)
    assert rc == 0, capsys.readouterr().err
    sidecar = json.loads(out.with_suffix(".json").read_text())
    assert sidecar["model"] == f"{name} (tiny random stand-in)" and sidecar["config"]["model"]["id"] == "tiny-random"
    assert sidecar["num_frames"] == 17 and out.stat().st_size > 0
    if name == "ltx-2":  # its vocoder's 16 kHz stereo, as long as the video at the tiny preset's 8 fps
        assert audio_stream(out) == {"codec": "aac", "sample_rate": 16000, "channels": "stereo"}
        assert sidecar["fps"] == 8 and sidecar["audio"] == {"file": "video.mp4", "sample_rate": 16000, "channels": 2,
                                                            "seconds": pytest.approx(17 / 8, abs=0.05)}
    else:
        assert audio_stream(out) is None and "audio" not in sidecar
