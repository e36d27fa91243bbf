"""A misspelt model name or config key is one line naming the close ones; a model GeCo-Eval only
scores, asked to generate, is one line pointing to scoring its videos."""

from __future__ import annotations

import pytest

from geco_guide.__main__ import main
from geco_guide.config import load_config
from geco_guide.families import did_you_mean, generating_model, model_named


def _one_error(capsys) -> str:
    err = capsys.readouterr().err.strip()
    assert "\n" not in err and "Traceback" not in err and err.startswith("error: "), err
    return err


@pytest.mark.parametrize("typed, close", [
    ("wan2.2", "(did you mean 'wan2.2-t2v-a14b' or 'wan2.2-ti2v-5b'?)"),
    ("LTX", "(did you mean 'ltx-video' or 'ltx-2'?)"),
    ("cogvideox5b", "(did you mean 'cogvideox-5b'"),
    ("sora", "(did you mean 'sora-2'?)"),
])
def test_an_unknown_model_names_the_close_ones(typed, close):
    with pytest.raises(ValueError, match="unknown model") as err:
        model_named(typed)
    assert close in str(err.value) and "\n" not in str(err.value)


def test_a_name_close_to_none_gets_no_suggestion():
    assert did_you_mean("zzz", ["cogvideox-5b", "ltx-video"]) == ""
    with pytest.raises(ValueError) as err:
        model_named("zzz")
    assert "did you mean" not in str(err.value)


@pytest.mark.parametrize("override, close", [
    ("guidance.stepsize=2", "unknown config key 'guidance.stepsize' (did you mean 'guidance.step_size'?)"),
    ("sampling.num_frame=9", "(did you mean 'sampling.num_frames'?)"),
    ("guidanc.step_size=2", "unknown config key 'guidanc' (did you mean 'guidance'?)"),
    ("model.name=wan2.2", "got 'wan2.2' (did you mean 'wan2.2-t2v-a14b' or 'wan2.2-ti2v-5b'?)"),
])
def test_a_misspelt_config_key_or_model_names_the_close_ones(override, close):
    with pytest.raises(ValueError) as err:
        load_config(preset="tiny", overrides=[override])
    assert close in str(err.value) and "\n" not in str(err.value)


@pytest.mark.parametrize("argv, expected", [
    (["generate", "--prompt", "x", "--model", "wan2.2"], "unknown model 'wan2.2' (did you mean 'wan2.2-t2v-a14b'"),
    (["generate", "--prompt", "x", "--preset", "tiny", "guidance.stepsize=2"],
     "(did you mean 'guidance.step_size'?)"),
    (["geco-eval", "--models", "wan2.2"], "unknown model 'wan2.2' (did you mean 'wan2.2-t2v-a14b'"),
])
def test_the_commands_say_the_close_names_in_one_line(argv, expected, tmp_path, capsys):
    assert main([*argv, "--out", str(tmp_path / "out")]) == 2
    assert expected in _one_error(capsys)
    assert not (tmp_path / "out").exists()


@pytest.mark.parametrize("name", ["sora-2", "veo-3.1"])
def test_geco_eval_of_a_scored_only_model_points_to_its_videos(name, tmp_path, capsys):
    assert main(["geco-eval", "--models", name, "--out", str(tmp_path / "out")]) == 2
    err = _one_error(capsys)
    assert f"{name} has no open weights to generate with" in err and f"geco geco-eval --videos {name}=DIR" in err
    assert "unknown model" not in err
    assert not (tmp_path / "out").exists()


def test_a_model_that_generates_is_returned():
    assert generating_model("ltx-video").name == "ltx-video"
