"""Structured config: presets, overrides, rejection of unknown keys and invalid values."""

from __future__ import annotations

import re
from pathlib import Path

import pytest

from geco_guide.config import GeCoConfig, config_to_dict, load_config, to_config
from geco_guide.loss.geco import GeCoLossConfig
from geco_guide.sampler.algorithm.config import GuidanceConfig
from geco_guide.sampler.running.run_options import RunOptions


def test_schema_defaults_are_the_paper():
    cfg = to_config({})
    assert cfg.model.id == "THUDM/CogVideoX-5b"
    s = cfg.sampling
    assert (s.num_inference_steps, s.guidance_scale, s.num_frames, s.height, s.width) == (50, 6.0, 49, 480, 720)
    g = cfg.guidance
    assert g.anchors == [12, 24, 36, 48] and g.chunk_latents == 3
    assert g.repeats == "0x3,3x17,2x30" and g.step_size == 3.0 and g.time_travel == [15, 20]
    assert g.denoiser_grad and g.enabled
    assert isinstance(g.loss, GeCoLossConfig)
    # the paper's experiment: residual motion, depth and cameras constant in the update
    assert g.loss.cue == "motion" and g.loss.pairs == "adjacent" and g.loss.flow_downscale == 0.5
    assert not g.loss.geometry_grad and s.scheduler == "ddim"


def test_presets_load_and_paper_preset_equals_schema_defaults():
    paper = load_config(preset="cogvideox-5b")
    assert isinstance(paper, GeCoConfig) and isinstance(paper.guidance, GuidanceConfig)
    assert config_to_dict(paper) == config_to_dict(to_config({}))
    tiny = load_config(preset="tiny")
    assert tiny.model.id == "tiny-random" and tiny.model.device == "cpu"
    assert tiny.sampling.num_frames == 17 and tiny.guidance.anchors == [4, 8, 12, 16]


def test_file_and_overrides_merge_in_order(tmp_path: Path):
    path = tmp_path / "c.yaml"
    path.write_text("seed: 5\nguidance:\n  step_size: 1.0\n")
    cfg = load_config(path, preset="tiny", overrides=["guidance.step_size=2.5", "guidance.loss.cue=motion"])
    assert cfg.seed == 5 and cfg.guidance.step_size == 2.5 and cfg.guidance.loss.cue == "motion"
    assert cfg.model.id == "tiny-random"


@pytest.mark.parametrize(
    "override, key",
    [
        ("model.nope=1", "model.nope"),
        ("guidance.loss.bogus=1", "guidance.loss.bogus"),
        ("colour=red", "colour"),
    ],
)
def test_unknown_keys_are_rejected_naming_the_key(override, key):
    with pytest.raises(ValueError, match=f"unknown config key '{key}'"):
        load_config(preset="tiny", overrides=[override])


def test_unknown_keys_in_yaml_are_rejected(tmp_path: Path):
    path = tmp_path / "bad.yaml"
    path.write_text("sampling:\n  num_step: 4\n")
    with pytest.raises(ValueError, match="sampling.num_step"):
        load_config(path)


@pytest.mark.parametrize(
    "override, key",
    [
        ("sampling.num_inference_steps=abc", "sampling.num_inference_steps"),
        ("sampling.height=100", "sampling.height"),
        ("sampling.num_frames=16", "sampling.num_frames"),
        ("guidance.step_size=-1", "guidance.step_size"),
        ("guidance.loss.cue=colour", "guidance.loss.cue"),
        ("guidance.loss.flow_downscale=0", "guidance.loss.flow_downscale"),
        ("model.dtype=float8", "model.dtype"),
        ("model.device=tpu", "model.device"),
        ("guidance.anchors=[8]", "guidance.anchors"),
        ("guidance.repeats=1,1,1,1,1", "guidance.repeats"),  # per step: exact (runs such as 1x5 are scaled)
        ("guidance.time_travel=[3,9]", "guidance.time_travel"),
    ],
)
def test_invalid_values_are_rejected_naming_the_key(override, key):
    with pytest.raises(ValueError, match=key.replace(".", r"\.")):
        load_config(preset="tiny", overrides=[override])


def test_unknown_preset_and_missing_file():
    with pytest.raises(ValueError, match="unknown preset 'nope'.*tiny"):
        load_config(preset="nope")
    with pytest.raises(FileNotFoundError):
        load_config("/nonexistent/config.yaml")


def test_string_overrides_are_taken_verbatim():
    cfg = load_config(
        preset="tiny",
        overrides=["sampling.num_inference_steps=2", "guidance.repeats=0x2", "guidance.time_travel=[]", "output.name=0x5"],
    )
    assert cfg.guidance.repeats == "0x2"  # not YAML's hex 2
    assert cfg.guidance.schedule(2).repeats == (0, 0)
    assert cfg.output.name == "0x5" and cfg.guidance.time_travel == []


def test_merge_dataclass_is_the_one_dict_to_config_merger():
    """GuidanceConfig dicts, VGGTConfig.from_dict and UFMConfig.from_dict all go through it."""
    from geco_guide.estimators.ufm import UFMConfig
    from geco_guide.estimators.vggt import VGGTConfig
    from geco_guide.sampler import GuidanceConfig
    from geco_guide.types import merge_dataclass

    merged = merge_dataclass(GuidanceConfig(), {"step_size": 2.0, "anchors": (4, 8), "loss": {"cue": "motion"}}, "guidance")
    assert merged.step_size == 2.0 and merged.anchors == [4, 8] and merged.loss.cue == "motion"  # list stays a list
    assert merged.loss.pairs == GuidanceConfig().loss.pairs  # untouched nested keys keep their values
    tiny = VGGTConfig.tiny()
    assert VGGTConfig.from_dict(tiny.to_dict()) == tiny  # JSON lists become the config's tuples again
    adaptors = UFMConfig.from_dict({"uncertainty_adaptors": [{"name": "non_occluded_mask", "type": "mask"}]}).uncertainty_adaptors
    assert type(adaptors[0]).__name__ == "UFMAdaptorSpec" and adaptors[0].type == "mask"
    with pytest.raises(ValueError, match=r"loss: unknown key\(s\) \['guidance.loss.cues'\]"):
        merge_dataclass(GuidanceConfig(), {"loss": {"cues": "motion"}}, "guidance")
    with pytest.raises(ValueError, match="guidance.loss must be a mapping"):
        merge_dataclass(GuidanceConfig(), {"loss": 3}, "guidance")


def test_yaml_syntax_error_names_the_line_and_column(tmp_path: Path):
    path = tmp_path / "x.yaml"
    path.write_text("seed: 1\nsampling:\n  a: b: c\n")
    with pytest.raises(ValueError, match=r"'.*x\.yaml' is not valid YAML: line 3, column 7: mapping values are not allowed") as info:
        load_config(path)
    assert "\n" not in str(info.value) and "UTF-8" not in str(info.value)


def test_undecodable_file_is_called_not_utf8(tmp_path: Path):
    path = tmp_path / "latin1.yaml"
    path.write_bytes(b"seed: 1\n# caf\xe9\n")
    with pytest.raises(ValueError, match=r"is not UTF-8 text \(byte 13: invalid continuation byte\)$"):
        load_config(path)


@pytest.mark.parametrize(
    "text, key, expected, shown, override",
    [
        ("sampling: 5\n", "sampling", "a mapping of options", "5", "5"),
        ("guidance:\n  loss: 3\n", "guidance.loss", "a mapping of options", "3", "3"),
        ("sampling:\n", "sampling", "a mapping of options", "None", "null"),
        ("sampling: [1]\n", "sampling", "a mapping of options", "[1]", "[1]"),
        ("evaluation:\n  model_fps: 5\n", "evaluation.model_fps", "a mapping", "5", "5"),
        ("guidance:\n  anchors: {a: 1}\n", "guidance.anchors", "a list", "{'a': 1}", "{a: 1}"),
        ("guidance:\n  anchors: \"4,8\"\n", "guidance.anchors", "a list", "'4,8'", '"4,8"'),
        ("guidance:\n  anchors: 12\n", "guidance.anchors", "a list", "12", "12"),
        ("guidance:\n  time_travel: 15\n", "guidance.time_travel", "a list", "15", "15"),
    ],
)
def test_a_section_or_list_given_another_kind_of_value_is_named(tmp_path: Path, text, key, expected, shown, override):
    path = tmp_path / "c.yaml"
    path.write_text(text)
    message = f"{key} must be {expected}, got {shown}"
    with pytest.raises(ValueError, match=rf"^{re.escape(message)} \(.*c\.yaml\)$"):
        load_config(path)
    with pytest.raises(ValueError, match=rf"^{re.escape(message)} \(command line\)$"):
        load_config(preset="tiny", overrides=[f"{key}={override}"])


def test_config_path_that_is_a_folder_is_called_a_folder(tmp_path: Path):
    with pytest.raises(ValueError, match=r"is a folder, not a config file$"):
        load_config(tmp_path)


@pytest.mark.parametrize("section, changes, message", [
    ("guidance", {"anchors": [4.7, 8.9, 12, 16]}, "anchors must hold integers only, e.g. [12, 24, 36, 48], got 4.7 in"),
    ("guidance", {"anchors": "4,8"}, "anchors must be a list of integers, e.g. [12, 24, 36, 48], got '4,8'"),
    ("guidance", {"anchors": [4, True]}, "anchors must hold integers only"),
    ("guidance", {"step_size": "3"}, "step_size must be a number, got '3'"),
    ("guidance", {"grad_eps": None}, "grad_eps must be a number, got None"),
    ("guidance", {"chunk_latents": 2.5}, "chunk_latents must be an integer, got 2.5"),
    ("guidance", {"time_travel": [15.5, 20]}, "time_travel must hold integers only, e.g. [15, 20], got 15.5"),
    ("guidance", {"enabled": "false"}, "enabled must be true or false, got 'false'"),
    ("run", {"memory_budget_gb": "8"}, "memory_budget_gb must be a number of GiB (or null: the device's memory), got '8'"),
    ("run", {"vae_block_checkpointing": 1}, "vae_block_checkpointing must be true, false or null, got 1"),
    ("run", {"compile": "yes"}, "compile must be true or false, got 'yes'"),
    ("run", {"memory_plan": "smallest"}, "memory_plan must be one of auto, explicit, fastest"),
])
def test_options_of_the_wrong_type_are_one_line_naming_the_key(section, changes, message):
    """A float anchor would be truncated to another frame; a string step size would fail deep in a call."""
    from geco_guide.sampler.pipelines.hooks import attach_geco_guidance
    from geco_guide.tiny import tiny_estimators, tiny_wan_pipeline

    options = {"guidance": GuidanceConfig, "run": RunOptions}[section]
    with pytest.raises(ValueError, match=re.escape(message)):
        options(**changes)
    argument = {"config": changes} if section == "guidance" else {"run_options": changes}
    with pytest.raises(ValueError, match=f"^{section}: {re.escape(message)}"):  # the hook's dict, before any call
        attach_geco_guidance(tiny_wan_pipeline(0), estimators=tiny_estimators(0), **argument)


def test_numbers_of_other_numeric_types_are_taken_as_they_are():
    import numpy as np

    config = GuidanceConfig(anchors=[np.int64(4), 8], step_size=2, time_travel=(1, 2))
    assert config.anchors == [4, 8] and config.step_size == 2 and config.time_travel == (1, 2)
    assert RunOptions(memory_budget_gb=np.float32(8.0)).memory_budget_gb == 8.0
    assert load_config(preset="tiny", overrides=["guidance.step_size=2"]).guidance.step_size == 2.0


def test_a_float_anchor_in_a_config_is_refused_not_truncated(tmp_path: Path):
    path = tmp_path / "c.yaml"
    path.write_text("guidance:\n  anchors: [4.7, 8.9, 12, 16]\n")
    with pytest.raises(ValueError, match=r"guidance.anchors\[0\].*4.7"):
        load_config(path)
    with pytest.raises(ValueError, match=r"guidance.anchors\[0\].*4.7"):
        load_config(preset="tiny", overrides=["guidance.anchors=[4.7,8.9,12,16]"])
