"""guidance.decoder='tiny': the tiny decoder decodes the loss' anchor frames, the VAE the video."""

from __future__ import annotations

import re

import pytest
import torch

from geco_guide import tiny as T
from geco_guide.estimators.tiny_decoder import CONTEXT_LATENTS, TinyDecoder
from geco_guide.sampler.algorithm.config import GuidanceConfig
from geco_guide.sampler.pipelines.hooks import attach_geco_guidance

PROMPT = "a marble bust on a table"


def run(pipe, estimators, seed=0, **kwargs):
    """A call of the tiny GeCo pipeline guided by ``estimators``, with the tiny run options."""
    args = dict(T.TINY_CALL_KWARGS, output_type="pt", estimators=estimators, run_options=T.tiny_run_options())
    args.update(kwargs)
    return pipe(PROMPT, generator=torch.Generator().manual_seed(seed), **args)


class Counted:
    """Counts the calls of one method of an instance."""

    def __init__(self, obj, name):
        self.calls, original = 0, getattr(obj, name)

        def counted(*args, **kwargs):
            self.calls += 1
            return original(*args, **kwargs)

        setattr(obj, name, counted)


@pytest.mark.slow
def test_the_context_is_the_shortest_that_gives_the_whole_sequence_frame():
    decoder = TinyDecoder.random("cogvideox", seed=0)
    latents = torch.randn(1, 13, 16, 4, 6, generator=torch.Generator().manual_seed(0))
    with torch.no_grad():
        whole = decoder.decode(latents)[:, -1]
        exact = decoder.decode(latents[:, -CONTEXT_LATENTS:])[:, -1]
        shorter = decoder.decode(latents[:, -(CONTEXT_LATENTS - 1):])[:, -1]
    assert torch.equal(exact, whole)
    assert not torch.equal(shorter, whole)


def test_anchor_chunks_follow_the_decoder():
    vae, tiny = GuidanceConfig(), GuidanceConfig(decoder="tiny")
    assert [c.stop - c.start for c in vae.anchor_chunks(49, 4)] == [3, 3, 3, 3]
    # latent 3 has only 4 latents up to it; the later anchors get the whole context
    assert [c.stop - c.start for c in tiny.anchor_chunks(49, 4)] == [4, 7, CONTEXT_LATENTS, CONTEXT_LATENTS]
    with pytest.raises(ValueError, match="decoder"):
        GuidanceConfig(decoder="taesd")


@pytest.mark.slow
def test_pipeline_guides_with_the_tiny_decoder_and_decodes_the_video_with_the_vae(estimators):
    pipe = T.tiny_pipeline(0)
    decoder = T.tiny_guidance_decoder("cogvideox")
    with_decoder = estimators.with_tiny_decoder(decoder)
    assert "guidance_decoder" not in pipe.components  # the tiny decoder comes with the estimators, at the call
    tiny_calls, vae_calls = Counted(decoder, "decode"), Counted(pipe.vae, "decode")
    out = run(pipe, with_decoder, guidance={"decoder": "tiny"})
    assert out.report.log and all(e["grad_norm"] > 0 and not e["skipped"] for e in out.report.log)
    assert tiny_calls.calls >= len(out.report.log) and vae_calls.calls == 1  # the final video only
    assert out.report.guidance["decoder"] == "tiny" and out.report.decoder == "TinyDecoder(cogvideox) from random"
    # the guided latents differ from the VAE-guided run (another gradient), the frames are finite
    tiny_before = tiny_calls.calls
    exact = run(pipe, with_decoder)  # guidance.decoder=vae: the bundle's tiny decoder is not used
    assert exact.report.decoder == "vae (the model's own)" and tiny_calls.calls == tiny_before
    assert torch.isfinite(out.frames).all() and not torch.equal(out.frames, exact.frames)
    assert all(p.requires_grad is False for p in decoder.parameters())


def test_the_tiny_decoder_is_loaded_onto_the_pipelines_device_and_dtype():
    from geco_guide.generation import load_models

    models = load_models(tiny_config("guidance.decoder=tiny", "model.dtype=bfloat16"), estimators=True)
    decoder = models.estimators.tiny_decoder
    assert decoder.device == models.pipe.device and decoder.dtype == models.pipe.vae.dtype == torch.bfloat16


def test_tiny_without_a_decoder_or_with_the_wrong_one_is_one_line_before_any_step(estimators):
    pipe = T.tiny_pipeline(0)
    steps = Counted(pipe.transformer, "forward")
    with pytest.raises(ValueError, match=r"needs a tiny decoder: give the estimators one, "
                                         r"Estimators\(..., tiny_decoder=") as err:
        run(pipe, estimators, guidance={"decoder": "tiny"})
    assert "\n" not in str(err.value)
    wrong = estimators.with_tiny_decoder(T.tiny_guidance_decoder("cogvideox", latent_channels=48))
    with pytest.raises(ValueError, match="takes 48 latent channels but this VAE makes 4"):
        run(pipe, wrong, guidance={"decoder": "tiny"})
    assert steps.calls == 0


def test_the_hook_takes_the_tiny_decoder_too(estimators):
    pipe = T.tiny_wan_pipeline(0)
    config = T.tiny_guidance_config(anchors=[4, 8], chunk_latents=3, repeats="0x3,2x1", time_travel=[], step_size=1.0,
                                    decoder="tiny")
    decoder = T.tiny_guidance_decoder("wan2.1")
    tiny_calls = Counted(decoder, "decode")
    with attach_geco_guidance(pipe, config, estimators.with_tiny_decoder(decoder)) as handle:
        pipe(PROMPT, generator=torch.Generator().manual_seed(0), **T.tiny_call_kwargs(pipe, num_inference_steps=4),
             output_type="pt")
    assert len(handle.log) == 2 and tiny_calls.calls >= 2
    assert handle.last.decoder == "TinyDecoder(wan2.1) from random"
    with pytest.raises(TypeError, match=r"attach_geco_guidance\(decoder=...\) is the earlier spelling: the tiny "
                                        r"decoder is Estimators\(..., tiny_decoder=...\)"):
        attach_geco_guidance(pipe, config, estimators, decoder=decoder)
    with attach_geco_guidance(pipe, config, estimators):
        with pytest.raises(ValueError, match="needs a tiny decoder"):
            pipe(PROMPT, generator=torch.Generator().manual_seed(0), **T.tiny_call_kwargs(pipe, num_inference_steps=4),
                 output_type="pt")


# ---- estimators.tiny_decoder: the config key, loaded by the generation path --------------------


def tiny_config(*overrides):
    from geco_guide.config import load_config

    return load_config(preset="tiny", overrides=list(overrides))


def no_model_loads(monkeypatch):
    """Make every model load fail loudly: a check must come before it."""
    from geco_guide import estimators, generation
    from geco_guide.sampler.pipelines import loading

    def refuse(*args, **kwargs):
        raise AssertionError("a model loaded before the tiny decoder's weights were checked")

    monkeypatch.setattr(generation, "load_models", refuse)
    monkeypatch.setattr(estimators, "load_estimators", refuse)
    monkeypatch.setattr(loading, "load_video_pipeline", refuse)
    monkeypatch.setattr(loading, "load_tiny_decoder", refuse)


def generate_tiny(tmp_path, *overrides):
    """``generate`` of the tiny preset with ``overrides`` into ``tmp_path``."""
    from geco_guide.generation import generate

    return generate(tiny_config(*overrides), "a bust", out=tmp_path / "bust.mp4")


def load_tiny_decoder_of(cfg, latent_channels=16):
    """``load_tiny_decoder`` of ``cfg``'s estimators for its model's latents."""
    from geco_guide.sampler.pipelines.loading import load_tiny_decoder

    return load_tiny_decoder(cfg.estimators, cfg.model.video_model, latent_channels, torch.float32)


def test_the_tiny_preset_loads_the_tiny_random_decoder_for_its_vae():
    from geco_guide.generation import load_models
    from geco_guide.sampler.running.context import decoder_note

    cfg = tiny_config("guidance.decoder=tiny")
    assert cfg.estimators.tiny_decoder == "tiny-random"
    models = load_models(cfg)
    decoder = models.estimators.tiny_decoder
    assert isinstance(decoder, TinyDecoder)
    assert decoder.latent_channels == models.pipe.vae.config.latent_channels == 4
    assert models.estimators.ids()["tiny_decoder"] == "tiny-random(seed=0)"  # the bundle names it, not the module
    assert decoder_note(cfg.guidance.decoder, models.estimators) == "TinyDecoder(cogvideox) from tiny-random(seed=0)"
    # the VAE guides by default: no tiny decoder is loaded, even though the preset names one
    exact = load_models(tiny_config())
    assert exact.estimators.tiny_decoder is None and decoder_note("vae", exact.estimators) == "vae (the model's own)"


def test_tiny_without_weights_is_one_line_with_the_url_and_the_key_before_any_model_loads(monkeypatch, tmp_path):
    no_model_loads(monkeypatch)
    with pytest.raises(ValueError) as err:
        generate_tiny(tmp_path, "guidance.decoder=tiny", "estimators.tiny_decoder=null")
    message = str(err.value)
    assert "\n" not in message and "github.com/madebyollin/taehv" in message
    assert "estimators.tiny_decoder=/path/to/taecvx.pth" in message
    assert list(tmp_path.iterdir()) == []


@pytest.mark.parametrize(("model", "expected"), [
    ("wan2.1-t2v-1.3b", "download taew2_1.pth (for wan2.1-t2v-1.3b)"),
    ("wan2.2-ti2v-5b", "download taew2_2.pth (for wan2.2-ti2v-5b)"),
    ("hunyuanvideo-1.5", "download taehv1_5.pth (for hunyuanvideo-1.5)"),
    ("ltx-video", "there is no tiny decoder for ltx-video's latents; use guidance.decoder=vae"),
])
def test_the_tiny_decoder_line_names_the_file_of_the_models_latents(model, expected):
    from geco_guide.estimators import EstimatorsConfig
    from geco_guide.families import model_named
    from geco_guide.sampler.pipelines.loading import check_tiny_decoder

    # a model without a tiny decoder says so before asking for weights it could not use
    with pytest.raises(ValueError, match=f"^guidance.decoder=tiny.*{re.escape(expected)}"):
        check_tiny_decoder(EstimatorsConfig(tiny_decoder=None), model_named(model))


def test_a_missing_tiny_decoder_file_is_one_line_naming_it_and_the_key(monkeypatch, tmp_path):
    from geco_guide.estimators.loading import WeightsNotFoundError

    no_model_loads(monkeypatch)
    missing = tmp_path / "taecvx.pth"
    with pytest.raises(WeightsNotFoundError) as err:
        generate_tiny(tmp_path, "guidance.decoder=tiny", f"estimators.tiny_decoder={missing}")
    assert "\n" not in str(err.value) and str(missing) in str(err.value) and "estimators.tiny_decoder=" in str(err.value)
    assert list(tmp_path.iterdir()) == []


def test_a_checkpoint_file_loads_with_its_path_recorded(tmp_path, estimators):
    from geco_guide.sampler.running.context import decoder_note

    saved = T.tiny_guidance_decoder("cogvideox", seed=3, latent_channels=16)  # the published variant's channels
    path = tmp_path / "taecvx.pth"
    torch.save(saved.state_dict(), path)
    cfg = tiny_config("guidance.decoder=tiny", f"estimators.tiny_decoder={path}")
    loaded = load_tiny_decoder_of(cfg)
    assert loaded.checkpoint_file == str(path) and loaded.decoder_widths == saved.decoder_widths
    assert all(torch.equal(a, b) for a, b in zip(loaded.state_dict().values(), saved.state_dict().values()))
    bundle = estimators.with_tiny_decoder(loaded)
    assert decoder_note(cfg.guidance.decoder, bundle) == f"TinyDecoder(cogvideox) from {path}"
    # the decoder of another model is refused by its name
    torch.save(saved.state_dict(), tmp_path / "taew2_1.pth")
    with pytest.raises(ValueError, match="Wan 2.1.*cogvideox-5b needs taecvx.pth"):
        load_tiny_decoder_of(tiny_config("guidance.decoder=tiny", f"estimators.tiny_decoder={tmp_path / 'taew2_1.pth'}"))


@pytest.mark.parametrize(("key", "example"), [("geometry", "/path/to/VGGT-1B"), ("flow", "/path/to/UFM-Base")])
def test_missing_estimator_weights_name_the_config_key(tmp_path, key, example):
    from geco_guide.estimators import EstimatorsConfig, load_estimators
    from geco_guide.estimators.loading import WeightsNotFoundError

    other = "flow" if key == "geometry" else "geometry"
    cfg = EstimatorsConfig(**{key: str(tmp_path / "missing"), other: "tiny-random"}, dtype="float32")
    with pytest.raises(WeightsNotFoundError) as err:
        load_estimators(cfg, "cpu")
    assert "\n" not in str(err.value) and f"estimators.{key}={example}" in str(err.value)


@pytest.mark.slow
def test_generate_runs_the_tiny_preset_with_the_tiny_decoder_offline(tmp_path):
    import json

    from geco_guide.cli.generate import main

    out = tmp_path / "bust.mp4"
    assert main(["--preset", "tiny", "--prompt", "a bust", "--out", str(out), "guidance.decoder=tiny"]) == 0
    sidecar = json.loads(out.with_suffix(".json").read_text())
    assert sidecar["config"]["guidance"]["decoder"] == "tiny"
    assert sidecar["config"]["estimators"]["tiny_decoder"] == "tiny-random"
    assert sidecar["guidance_decoder"] == "TinyDecoder(cogvideox) from tiny-random(seed=0)"
    assert sidecar["guidance_log"] and all(r["grad_norm"] > 0 and not r["skipped"] for r in sidecar["guidance_log"])
