"""The commands' shared kit: one-line errors, the config flags and their aliases, overrides."""

from __future__ import annotations

from pathlib import Path

import pytest

from geco_guide.cli.kit import (
    Parser,
    add_config_flags,
    config_from_args,
    interruptible,
    is_config_key,
    split_overrides,
)


def parser() -> Parser:
    p = Parser(prog="test")
    add_config_flags(p)
    p.add_argument("inputs", nargs="*")
    return p


def test_errors_are_one_line(capsys):
    with pytest.raises(SystemExit) as info:
        parser().parse_args(["--nope"])
    assert info.value.code == 2
    err = capsys.readouterr().err
    assert err.startswith("error: ") and err.count("\n") == 1, err


def test_estimator_flags_set_the_estimators_and_their_earlier_names_are_refused(capsys):
    args = parser().parse_args(["--preset", "tiny", "--geometry-estimator", "g", "--flow-estimator", "f"])
    assert (args.geometry_estimator, args.flow_estimator) == ("g", "f")
    for old, new in (("--vggt", "--geometry-estimator"), ("--ufm", "--flow-estimator")):
        with pytest.raises(SystemExit):
            parser().parse_args([old, "g"])
        assert capsys.readouterr().err.strip() == f"error: {old} is the earlier name of {new}: use {new} instead (see --help)"


def test_overrides_are_told_from_inputs(tmp_path: Path):
    existing = tmp_path / "a=b.mp4"
    existing.write_bytes(b"")
    overrides, others = split_overrides(["guidance.step_size=2", str(existing), "clip.mp4", "x=1"])
    assert overrides == ["guidance.step_size=2", "x=1"] and others == [str(existing), "clip.mp4"]
    assert is_config_key("guidance.step_size") and is_config_key("evaluation.model_fps.mine") and not is_config_key("x")


def test_the_config_takes_preset_overrides_and_flags_in_that_order():
    args = parser().parse_args(["--preset", "tiny", "--geometry-estimator", "tiny-random"])
    cfg = config_from_args(args, ["seed=5", "estimators.geometry=tiny-random"], {"evaluation.loss.pairs": "center",
                                                                              "seed": None})
    assert cfg.seed == 5 and cfg.estimators.geometry == "tiny-random" and cfg.evaluation.loss.pairs == "center"
    with pytest.raises(ValueError, match="^evaluation.loss.pairs=all disagrees with the flag that sets"):
        config_from_args(args, ["evaluation.loss.pairs=all"], {"evaluation.loss.pairs": "center"})
    with pytest.raises(ValueError):
        config_from_args(args, ["guidance.step_sizea=1"])


def test_ctrl_c_is_one_line_and_exit_code_130(capsys):
    @interruptible("the finished videos are kept; rerun to resume")
    def main(argv=None):
        raise KeyboardInterrupt

    assert main([]) == 130
    err = capsys.readouterr().err
    assert err == "interrupted: the finished videos are kept; rerun to resume\n"


def test_overrides_typed_after_a_list_option_go_back_to_the_overrides(capsys):
    from geco_guide.cli.command_line import parse_command

    p = Parser(prog="test")
    p.add_argument("--devices", nargs="+", default=None)
    p.add_argument("--seeds", nargs="+", default=None)
    p.add_argument("overrides", nargs="*", metavar="key=value")
    args = parse_command(p, ["a=1", "--devices", "cuda:0", "cuda:1", "b=2", "--seeds", "0", "c.d=3"])
    assert args.devices == ["cuda:0", "cuda:1"] and args.seeds == ["0"] and args.overrides == ["a=1", "b=2", "c.d=3"]
    with pytest.raises(SystemExit) as info:
        parse_command(p, ["--devices", "b=2"])
    err = capsys.readouterr().err.strip()
    assert info.value.code == 2 and "\n" not in err
    assert "argument --devices: expected at least one value before 'b=2'" in err
