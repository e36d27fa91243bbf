"""The rules every command applies to its options before anything loads: an option that cannot act
on the run is one warning and is left at its default in what runs (and what the sidecar records),
what it names is checked all the same, and a flag and a ``key=value`` override that set one key to
two values are refused in one line (tiny preset, CPU)."""

from __future__ import annotations

import json
import logging

import pytest
import torch

from geco_guide.cli.generate import main
from geco_guide.config import config_to_dict, load_config
from geco_guide.generation import acting_config, check_generation, video_key

TINY = ["--preset", "tiny", "--prompt", "a marble bust"]
PROMPT = "a marble bust"


def tiny(*overrides: str):
    return load_config(preset="tiny", overrides=list(overrides))


def test_without_guidance_every_moving_subject_option_and_the_devices_are_left_at_their_defaults(caplog):
    cfg = tiny("guidance.enabled=false", "guidance.dynamic=auto", "guidance.loss.movers=rigid",
               "guidance.dynamic_dilation=2", "run.devices=[cpu]", "run.particle_batch=2")
    with caplog.at_level(logging.WARNING, logger="geco_guide.generation"):
        ran = check_generation(cfg, PROMPT)

    assert (ran.guidance.dynamic, ran.guidance.loss.movers, ran.guidance.dynamic_dilation) == (None, "drop", 0)
    assert ran.run.devices is None and ran.run.particle_batch is None
    assert [record.getMessage() for record in caplog.records] == [
        "guidance.dynamic='auto', guidance.dynamic_dilation=2, guidance.loss.movers='rigid', run.devices=['cpu'] do nothing "
        "without guidance or a search (--no-guidance): left at the default, as the sidecar records",
        "run.particle_batch=2 does nothing without a search (search.particles): left at the default, as the sidecar "
        "records"]
    # what ran makes the video of the plain unguided config: the same name
    plain = check_generation(tiny("guidance.enabled=false"), PROMPT)
    assert video_key(config_to_dict(ran), PROMPT) == video_key(config_to_dict(plain), PROMPT)


@pytest.mark.parametrize("overrides", [
    ("guidance.dynamic=auto", "guidance.loss.movers=rigid", "run.devices=[cpu]"),  # guided
    ("guidance.enabled=false", "search.particles=2", "guidance.dynamic=auto", "guidance.loss.movers=rigid"),  # a search
])
def test_an_option_that_acts_is_kept_without_a_word(overrides, caplog):
    cfg = tiny(*overrides)
    with caplog.at_level(logging.WARNING, logger="geco_guide.generation"):
        assert acting_config(cfg) == cfg
    assert caplog.records == []


def test_a_device_the_machine_lacks_is_refused_without_guidance_as_with_it(monkeypatch, tmp_path, capsys, no_loading):
    monkeypatch.setattr(torch.cuda, "is_available", lambda: False)
    codes = [main([*TINY, *argv, "--devices", "cuda:0", "--out", str(tmp_path)]) for argv in (["--no-guidance"], [])]
    lines = capsys.readouterr().err.strip().splitlines()

    assert codes == [2, 2] and len(lines) == 2 and lines[0] == lines[1], lines
    assert lines[0].startswith("error: device 'cuda:0' is not available") and "run.devices" in lines[0]
    assert list(tmp_path.iterdir()) == []


@pytest.mark.parametrize("argv, line", [
    (["--model", "wan2.1-t2v-1.3b", "model.name=cogvideox-5b"],
     "error: model.name=cogvideox-5b disagrees with the flag that sets model.name to 'wan2.1-t2v-1.3b' (--model "
     "wan2.1-t2v-1.3b): give model.name once"),
    (["--seed", "3", "seed=4"], "error: seed=4 disagrees with the flag that sets seed to 3: give seed once"),
    (["--no-guidance", "guidance.enabled=true"],
     "error: guidance.enabled=true disagrees with the flag that sets guidance.enabled to false: give guidance.enabled "
     "once"),
    (["--geometry-estimator", "tiny-random", "estimators.geometry=facebook/VGGT-1B"],
     "error: estimators.geometry=facebook/VGGT-1B disagrees with the flag that sets estimators.geometry to "
     "'tiny-random' (--geometry-estimator tiny-random): give estimators.geometry once"),
])
def test_a_flag_and_an_override_that_disagree_are_one_line(argv, line, tmp_path, capsys, no_loading):
    assert main([*TINY, *argv, "--out", str(tmp_path)]) == 2
    assert capsys.readouterr().err.strip() == line
    assert list(tmp_path.iterdir()) == []


def test_an_override_that_agrees_with_its_flag_passes():
    from geco_guide.cli.kit import check_flags_agree

    check_flags_agree(["model.name=cogvideox-5b", "seed=3", "guidance.enabled=false", "run.devices=[cuda:0]"],
                      {"model.name": "cogvideox-5b", "seed": 3, "guidance.enabled": False, "run.devices": ["cuda:0"]})


@pytest.mark.slow
@pytest.mark.parametrize("best_of", [[], ["--best-of", "2"]])
def test_no_guidance_with_masks_and_movers_runs_and_records_what_ran(best_of, tmp_path, capsys):
    argv = [*TINY, "--no-guidance", "--dynamic", "auto", "--movers", "rigid", "sampling.num_inference_steps=2",
            *best_of, "--out", str(tmp_path)]
    assert main(argv) == 0
    err = capsys.readouterr().err
    assert sum("do nothing without guidance or a search" in line for line in err.splitlines()) == 1, err
    assert err.index("do nothing without guidance") < err.index("loading models")
    (sidecar,) = tmp_path.glob("*.json")
    guidance = json.loads(sidecar.read_text())["config"]["guidance"]
    assert (guidance["enabled"], guidance["dynamic"], guidance["loss"]["movers"]) == (False, None, "drop")


@pytest.mark.slow
def test_the_sidecar_of_the_tiny_preset_names_the_tiny_stand_in(tmp_path):
    out = tmp_path / "video.mp4"
    assert main([*TINY, "sampling.num_inference_steps=2", "--out", str(out)]) == 0
    sidecar = json.loads(out.with_suffix(".json").read_text())
    assert sidecar["model"] == "cogvideox-5b (tiny random stand-in)"
    assert sidecar["config"]["model"]["name"] == "cogvideox-5b"  # the config as given: it runs again as it is


@pytest.fixture
def no_runs(monkeypatch):
    from geco_guide.bench import ab_run
    from geco_guide.cli import geco_eval

    def refuse(*args, **kwargs):
        raise AssertionError("the run started")

    monkeypatch.setattr(geco_eval, "execute", refuse)
    monkeypatch.setattr(ab_run, "execute", refuse)
    monkeypatch.setattr(torch.cuda, "is_available", lambda: False)


@pytest.mark.parametrize("command, argv, line", [
    ("geco-eval", ["--models", "cogvideox-5b", "model.name=wan2.1-t2v-1.3b"],
     "error: model.name=wan2.1-t2v-1.3b disagrees with the flag that sets model.name to 'cogvideox-5b' (--models "
     "cogvideox-5b): give model.name once"),
    ("geco-eval", ["--models", "cogvideox-5b", "run.devices=[cuda:0]"], "error: device 'cuda:0' is not available"),
    ("ab", ["--model", "wan2.1-t2v-1.3b", "model.name=cogvideox-5b"],
     "error: model.name=cogvideox-5b disagrees with the flag that sets model.name to 'wan2.1-t2v-1.3b' (--model "
     "wan2.1-t2v-1.3b): give model.name once"),
    ("ab", ["run.devices=[cuda:0]"], "error: device 'cuda:0' is not available"),
])
def test_every_command_applies_the_same_rules(command, argv, line, tmp_path, capsys, no_runs):
    from geco_guide.cli import ab, geco_eval

    prompts = tmp_path / "prompts.txt"
    prompts.write_text("a marble bust\n")
    out = tmp_path / "out"
    common = {"geco-eval": ["--limit", "1"], "ab": ["--prompts", str(prompts)]}[command]
    main_of = {"geco-eval": geco_eval.main, "ab": ab.main}[command]
    assert main_of(["--preset", "tiny", "--seeds", "0", "--out", str(out), *common, *argv]) == 2
    err = capsys.readouterr().err.strip()
    assert "\n" not in err and err.startswith(line), err
    assert not out.exists()


def test_the_ab_arms_leave_out_what_they_cannot_act_on_without_a_word(caplog):
    from geco_guide.bench.ab import Pair, arm_config
    from geco_guide.cli.prompt_files import Prompt

    cfg = tiny("guidance.dynamic=auto", "guidance.loss.movers=rigid", "run.devices=[cpu]")
    pair = Pair(Prompt("bust", PROMPT), 3)
    with caplog.at_level(logging.WARNING, logger="geco_guide.generation"):
        unguided, guided = (arm_config(cfg, pair, arm) for arm in ("unguided", "guided"))
    assert caplog.records == []
    assert (unguided.guidance.dynamic, unguided.guidance.loss.movers, unguided.run.devices) == (None, "drop", None)
    assert (guided.guidance.dynamic, guided.guidance.loss.movers, guided.run.devices) == ("auto", "rigid", ["cpu"])
    assert unguided.seed == guided.seed == 3
