"""What guidance computes (``guidance``) apart from how one machine runs it (``run``): run options
are never saved with a pipeline, stay out of the video key but for the options that change frames
to float rounding, and their old ``guidance.<key>`` spellings keep working with one warning each."""

from __future__ import annotations

import json
import warnings
from dataclasses import asdict, fields

import pytest
import torch

from geco_guide.cli.generate import default_name, video_key
from geco_guide.config import config_to_dict, load_config
from geco_guide.sampler.config import GuidanceConfig, resolve_call_options
from geco_guide.sampler.run_options import FRAME_ROUNDING_KEYS, RUN_KEYS, RenamedOptionWarning, RunOptions
from geco_guide.tiny import TINY_CALL_KWARGS, tiny_pipeline, tiny_run_options

PROMPT = "a marble bust on a table"


def renamed(record) -> list[str]:
    return [str(w.message) for w in record if issubclass(w.category, RenamedOptionWarning)]


def test_the_two_objects_share_no_option():
    assert not {f.name for f in fields(GuidanceConfig)} & set(RUN_KEYS)
    assert set(FRAME_ROUNDING_KEYS) <= set(RUN_KEYS)


def test_save_pretrained_writes_no_run_option(tmp_path):
    from geco_guide.sampler.pipeline_cogvideox import GeCoCogVideoXPipeline

    pipe = tiny_pipeline(0)
    pipe.run_options = {"memory_plan": "leanest", "memory_budget_gb": 3.0, "devices": ["cpu"]}
    assert pipe.run_options == RunOptions(memory_plan="leanest", memory_budget_gb=3.0, devices=["cpu"])
    pipe.save_pretrained(tmp_path)
    saved = json.loads((tmp_path / "model_index.json").read_text())
    assert not set(saved["guidance_config"]) & set(RUN_KEYS)
    assert not any(key in json.dumps(saved) for key in ("memory_budget_gb", "run_options", "decode_layout"))
    loaded = GeCoCogVideoXPipeline.from_pretrained(tmp_path, geometry_estimator=pipe.geometry_estimator,
                                                   flow_estimator=pipe.flow_estimator)
    assert loaded.guidance_config == pipe.guidance_config and loaded.run_options == RunOptions()


def test_a_folder_saved_with_run_options_in_its_guidance_loads_them_as_run_options(tmp_path):
    from geco_guide.sampler.pipeline_cogvideox import GeCoCogVideoXPipeline

    tiny_pipeline(0).save_pretrained(tmp_path)
    index = json.loads((tmp_path / "model_index.json").read_text())
    index["guidance_config"].update(memory_plan="chunked", memory_budget_gb=7.0)  # as written before the split
    (tmp_path / "model_index.json").write_text(json.dumps(index))
    with pytest.warns(RenamedOptionWarning, match=r"^guidance.memory_plan is now run.memory_plan"):
        loaded = GeCoCogVideoXPipeline.from_pretrained(tmp_path)
    assert (loaded.run_options.memory_plan, loaded.run_options.memory_budget_gb) == ("chunked", 7.0)
    assert "memory_plan" not in loaded.config["guidance_config"]


def test_old_keys_work_in_config_files_and_overrides_with_one_line_each(tmp_path):
    old = tmp_path / "old.yaml"
    old.write_text("guidance:\n  eta: 2.0\n  memory_plan: chunked\n  devices: [cpu, cpu]\n")
    new = tmp_path / "new.yaml"
    new.write_text("guidance:\n  step_size: 2.0\nrun:\n  memory_plan: chunked\n  devices: [cpu, cpu]\n")
    with warnings.catch_warnings(record=True) as record:
        warnings.simplefilter("always")
        from_old = load_config(old, preset="tiny")
        from_override = load_config(preset="tiny", overrides=["guidance.memory_budget_gb=5", "guidance.eta=2"])
    messages = renamed(record)
    assert len(messages) == 5 and all("\n" not in m for m in messages)
    assert messages[0] == f"guidance.eta ({old}) is now guidance.step_size: the old key works until the next release"
    assert messages[1] == (f"guidance.memory_plan ({old}) is now run.memory_plan: the old key works until the "
                           "next release")
    assert messages[3].startswith("guidance.memory_budget_gb (command line) is now run.memory_budget_gb")
    assert messages[4].startswith("guidance.eta (command line) is now guidance.step_size")
    with warnings.catch_warnings():
        warnings.simplefilter("error", RenamedOptionWarning)  # the new spelling says nothing
        from_new = load_config(new, preset="tiny")
        assert load_config(preset="tiny", overrides=["run.memory_budget_gb=5"]).run.memory_budget_gb == 5
    assert from_old == from_new and from_old.run.devices == ["cpu", "cpu"]
    assert from_override.run.memory_budget_gb == 5 and from_override.guidance.step_size == 2


def test_a_run_section_wins_over_the_old_spelling_in_the_same_file(tmp_path):
    both = tmp_path / "both.yaml"
    both.write_text("guidance:\n  memory_plan: leanest\nrun:\n  memory_plan: chunked\n")
    with pytest.warns(RenamedOptionWarning):
        assert load_config(both, preset="tiny").run.memory_plan == "chunked"


def test_old_keys_in_a_call_dict_give_the_same_video_as_run_options():
    pipe = tiny_pipeline(0)

    def frames(**options):
        return pipe(PROMPT, generator=torch.Generator().manual_seed(1), output_type="latent", **TINY_CALL_KWARGS,
                    **options).frames

    with pytest.warns(RenamedOptionWarning, match="guidance.vae_checkpointing is now run.vae_checkpointing"):
        old = frames(guidance={"eta": 2.0, "vae_checkpointing": True})
    new = frames(guidance={"step_size": 2.0}, run_options={"vae_checkpointing": True})
    assert torch.equal(old, new)
    assert pipe.geco_memory_plan["chunk_checkpointing"]  # the moved flag was used


def test_a_call_dict_with_old_keys_resolves_below_the_new_ones():
    with pytest.warns(RenamedOptionWarning):
        config, run = resolve_call_options(None, {"memory_plan": "leanest", "eta": 1.0}, tiny_run_options(),
                                           {"memory_plan": "chunked"})
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


def test_a_command_says_the_new_key_in_one_line(tmp_path, capsys):
    from geco_guide.cli import generate as generate_cli

    assert generate_cli.main(["--preset", "tiny", "--prompt", "a", "--out", str(tmp_path / "a.mp4"),
                              "guidance.memory_plan=chunked", "sampling.height=-16"]) == 2
    lines = capsys.readouterr().err.strip().splitlines()
    assert lines[0] == ("warning: guidance.memory_plan (command line) is now run.memory_plan: the old key works "
                        "until the next release")
    assert lines[1].startswith("error: invalid value for config key 'sampling.height'") and len(lines) == 2
