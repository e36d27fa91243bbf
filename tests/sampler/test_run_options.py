"""What guidance computes (``guidance``) apart from how one machine runs it (``run``): run options
are the call's, never saved with a pipeline, stay out of the video key but for the options that
change frames to float rounding, and their old ``guidance.<key>`` spellings are refused in one line
naming the new key."""

from __future__ import annotations

import json
import warnings
from dataclasses import asdict, fields

import pytest
import torch

from geco_guide.config import config_to_dict, load_config
from geco_guide.generation import default_name, video_key
from geco_guide.sampler.algorithm.config import GuidanceConfig
from geco_guide.sampler.running.run_options import FRAME_ROUNDING_KEYS, RUN_KEYS, RunOptions, resolve_call_options
from geco_guide.tiny import TINY_CALL_KWARGS, tiny_estimators, tiny_pipeline, tiny_run_options

PROMPT = "a marble bust on a table"
ESTIMATORS = tiny_estimators(0)


def one_line(err) -> str:
    message = str(err.value)
    assert "\n" not in message
    return message


def test_the_two_objects_share_no_option():
    assert not {f.name for f in fields(GuidanceConfig)} & set(RUN_KEYS)
    assert set(FRAME_ROUNDING_KEYS) <= set(RUN_KEYS)


@pytest.mark.slow
def test_save_pretrained_writes_no_run_option(tmp_path):
    from geco_guide.sampler.pipelines.pipeline_cogvideox import GeCoCogVideoXPipeline

    pipe = tiny_pipeline(0)
    run = {"memory_plan": "leanest", "memory_budget_gb": 3.0, "devices": ["cpu"]}
    out = pipe(PROMPT, generator=torch.Generator().manual_seed(1), output_type="latent", estimators=ESTIMATORS,
               run_options=run, **TINY_CALL_KWARGS)
    assert out.report.memory_plan["name"] == "leanest" and out.report.devices == ["cpu"]  # the call's, in its report
    assert not hasattr(pipe, "run_options")  # and nothing of them on the pipeline
    pipe.save_pretrained(tmp_path)
    saved = json.loads((tmp_path / "model_index.json").read_text())
    assert not set(saved["guidance_config"]) & set(RUN_KEYS)
    assert not any(key in json.dumps(saved) for key in ("memory_budget_gb", "run_options", "decode_layout"))
    loaded = GeCoCogVideoXPipeline.from_pretrained(tmp_path)
    assert loaded.guidance_config == pipe.guidance_config and not hasattr(loaded, "run_options")


def test_a_folder_saved_with_run_options_in_its_guidance_is_refused_naming_the_run_key(tmp_path):
    from geco_guide.sampler.pipelines.pipeline_cogvideox import GeCoCogVideoXPipeline

    tiny_pipeline(0).save_pretrained(tmp_path)
    index = json.loads((tmp_path / "model_index.json").read_text())
    index["guidance_config"].update(memory_plan="chunked", memory_budget_gb=7.0)  # as written before the split
    (tmp_path / "model_index.json").write_text(json.dumps(index))
    with pytest.raises(ValueError, match=r"^guidance.memory_budget_gb is the earlier name of run.memory_budget_gb: "
                                         r"use run.memory_budget_gb instead$") as err:
        GeCoCogVideoXPipeline.from_pretrained(tmp_path)
    one_line(err)


def test_old_keys_in_config_files_and_overrides_are_refused_naming_the_new_key(tmp_path):
    for key, value, new in (("eta", "2.0", "guidance.step_size"), ("memory_plan", "chunked", "run.memory_plan"),
                            ("devices", "[cpu, cpu]", "run.devices")):
        old = tmp_path / f"old_{key}.yaml"
        old.write_text(f"guidance:\n  {key}: {value}\n")
        with pytest.raises(ValueError) as err:
            load_config(old, preset="tiny")
        assert one_line(err) == f"guidance.{key} is the earlier name of {new}: use {new} instead ({old})"
    for override, new in (("guidance.memory_budget_gb=5", "run.memory_budget_gb"), ("guidance.eta=2", "guidance.step_size")):
        with pytest.raises(ValueError) as err:
            load_config(preset="tiny", overrides=[override])
        old_key = override.partition("=")[0]
        assert one_line(err) == f"{old_key} is the earlier name of {new}: use {new} instead (command line)"
    new = tmp_path / "new.yaml"
    new.write_text("guidance:\n  step_size: 2.0\nrun:\n  memory_plan: chunked\n  devices: [cpu, cpu]\n")
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # the new spelling says nothing
        from_new = load_config(new, preset="tiny")
        from_override = load_config(preset="tiny", overrides=["run.memory_budget_gb=5", "guidance.step_size=2"])
    assert from_new.guidance.step_size == 2 and from_new.run.memory_plan == "chunked"
    assert from_new.run.devices == ["cpu", "cpu"]
    assert from_override.run.memory_budget_gb == 5 and from_override.guidance.step_size == 2


def test_the_old_spelling_is_refused_even_beside_a_run_section(tmp_path):
    both = tmp_path / "both.yaml"
    both.write_text("guidance:\n  memory_plan: leanest\nrun:\n  memory_plan: chunked\n")
    with pytest.raises(ValueError, match=r"^guidance.memory_plan is the earlier name of run.memory_plan") as err:
        load_config(both, preset="tiny")
    one_line(err)


@pytest.mark.slow
def test_old_keys_in_a_call_dict_or_as_arguments_are_refused_before_any_step():
    pipe = tiny_pipeline(0)
    steps = []
    pipe.transformer.register_forward_pre_hook(lambda *_: steps.append(1))

    def call(**options):
        return pipe(PROMPT, generator=torch.Generator().manual_seed(1), output_type="latent", **TINY_CALL_KWARGS,
                    estimators=ESTIMATORS, **options)

    for guidance, old, new in (({"eta": 2.0}, "guidance.eta", "guidance.step_size"),
                               ({"vae_checkpointing": True}, "guidance.vae_checkpointing", "run.vae_checkpointing")):
        with pytest.raises(ValueError) as err:
            call(guidance=guidance)
        assert one_line(err) == f"{old} is the earlier name of {new}: use {new} instead"
    assert steps == []
    for kwargs, new in (({"eta": 2.0}, "GuidanceConfig(step_size=...)"),
                        ({"memory_plan": "chunked"}, "RunOptions(memory_plan=...)")):
        with pytest.raises(TypeError) as err:
            GuidanceConfig(**kwargs)
        assert one_line(err) == f"GuidanceConfig({next(iter(kwargs))}=...) is the earlier spelling of {new}: use that instead"
    new = call(guidance={"step_size": 2.0}, run_options=tiny_run_options(vae_checkpointing=True))
    assert new.report.memory_plan["chunk_checkpointing"] and new.report.guidance["step_size"] == 2.0  # the new spelling


def test_a_call_dict_with_old_keys_is_refused_and_the_new_ones_resolve_over_the_base():
    with pytest.raises(ValueError, match=r"^guidance.eta is the earlier name of guidance.step_size"):
        resolve_call_options(None, {"memory_plan": "leanest", "eta": 1.0}, tiny_run_options(),
                             {"memory_plan": "chunked"})
    config, run = resolve_call_options(None, {"step_size": 1.0}, tiny_run_options(), {"memory_plan": "chunked"})
    assert config.step_size == 1.0 and run.memory_plan == "chunked" and run.vae_checkpointing is False


def test_the_video_key_holds_what_guidance_computes_and_the_options_that_round_frames():
    base = load_config(preset="tiny")
    name = default_name(base, PROMPT)
    for override in ("run.memory_plan=leanest", "run.memory_budget_gb=3", "run.devices=[cpu,cpu]",
                     "run.vae_checkpointing=true", "run.gradient_checkpointing=true"):
        assert default_name(load_config(preset="tiny", overrides=[override]), PROMPT) == name, override
    for override in ("run.decode_layout=channels_last", "run.compile=true", "run.split_cfg=true",
                     "guidance.step_size=2"):
        assert default_name(load_config(preset="tiny", overrides=[override]), PROMPT) != name, override
    plain = config_to_dict(base)
    # the rounding options at their defaults name nothing: a run option added later renames no video
    without_run = {section: value for section, value in plain.items() if section != "run"}
    assert video_key(plain, PROMPT) == video_key(without_run, PROMPT)
    assert video_key({**plain, "run": asdict(RunOptions(memory_plan="leanest"))}, PROMPT) == video_key(plain, PROMPT)


def test_a_channels_last_decode_with_the_tiny_decoder_is_one_line_naming_the_run_key():
    with pytest.raises(ValueError, match=r"^invalid value for config key 'run.decode_layout': decode_layout "
                                         r"channels_last lays out the VAE's decode, but guidance.decoder='tiny'"):
        load_config(preset="tiny", overrides=["run.decode_layout=channels_last", "guidance.decoder=tiny"])
    with pytest.raises(ValueError, match=r"^run.decode_layout channels_last lays out"):
        resolve_call_options(None, {"decoder": "tiny"}, None, {"decode_layout": "channels_last"})


def test_an_unknown_run_option_is_one_line_naming_the_section():
    with pytest.raises(ValueError, match=r"unknown config key 'run.memory_planner'"):
        load_config(preset="tiny", overrides=["run.memory_planner=auto"])
    with pytest.raises(ValueError, match=r"^run: unknown key\(s\) \['run.memory_planner'\]"):
        resolve_call_options(None, None, None, {"memory_planner": "auto"})


def test_a_command_refuses_the_old_key_in_one_line_naming_the_new_one(tmp_path, capsys):
    from geco_guide.cli import generate as generate_cli

    assert generate_cli.main(["--preset", "tiny", "--prompt", "a", "--out", str(tmp_path / "a.mp4"),
                              "guidance.memory_plan=chunked", "sampling.height=-16"]) == 2
    lines = capsys.readouterr().err.strip().splitlines()
    assert lines == ["error: guidance.memory_plan is the earlier name of run.memory_plan: use run.memory_plan instead "
                     "(command line)"]
    assert list(tmp_path.iterdir()) == []
