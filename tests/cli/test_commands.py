"""The commands as a newcomer meets them: every option says what it does, internal subcommands stay
out of ``--help``, ``--help`` and a mistyped option answer at once (no torch, no diffusion library),
and counts read as counts."""

from __future__ import annotations

import argparse
import importlib
import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

from geco_guide.__main__ import COMMANDS as GECO_COMMANDS
from geco_guide.__main__ import main as geco_main

ROOT = Path(__file__).resolve().parents[2]


def options_without_help(parser: argparse.ArgumentParser, prefix: str) -> list[str]:
    missing = []
    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            for name, sub in action.choices.items():
                missing += options_without_help(sub, f"{prefix} {name}")
        elif not action.help and not isinstance(action, (argparse._HelpAction, argparse._VersionAction)):
            missing.append(f"{prefix} {'/'.join(action.option_strings) or action.dest}")
    return missing


def test_every_command_has_the_shape_and_every_option_has_help():
    from geco_guide.__main__ import COMMANDS, build_parser

    parser, parsers = build_parser()
    assert list(parsers) == list(COMMANDS)
    for module_name in COMMANDS.values():
        module = importlib.import_module(f"geco_guide.cli.{module_name}")
        assert {"SUMMARY", "DESCRIPTION", "register_subcommand", "run", "main"} <= set(vars(module)), module_name
        assert not hasattr(module, "build_parser"), module_name  # one way to build a command's options
    missing = options_without_help(parser, "geco")
    assert not missing, missing


def test_geco_lists_every_command_with_its_summary(capsys):
    from geco_guide.__main__ import COMMANDS, main

    with pytest.raises(SystemExit) as stop:
        main(["--help"])
    out = " ".join(capsys.readouterr().out.split())
    assert stop.value.code == 0
    for name, module_name in COMMANDS.items():
        assert f" {name} {importlib.import_module(f'geco_guide.cli.{module_name}').SUMMARY}" in out
    assert main([]) == 2 and capsys.readouterr().err.startswith("usage: geco")
    with pytest.raises(SystemExit) as stop:
        main(["genrate", "--prompt", "x"])
    assert stop.value.code == 2 and capsys.readouterr().err.startswith("error: unknown command 'genrate'; one of generate")


def test_the_defaults_a_help_text_states_are_the_code_s():
    from geco_guide.__main__ import build_parser
    from geco_guide.bench.robustness import DEPTH_SIGMAS, FLOW_SIGMAS
    from geco_guide.bench.warp import WarpParams

    _, parsers = build_parser()
    robustness = " ".join(parsers["robustness"].format_help().split())
    for sigmas in (DEPTH_SIGMAS, FLOW_SIGMAS):
        assert f"(default: {' '.join(f'{s:g}' for s in sigmas)})" in robustness
    benchmarks = " ".join(parsers["benchmarks"].format_help().split())
    defaults = WarpParams()
    for value in (defaults.num_controls, defaults.amplitude, defaults.beta, defaults.mask_threshold):
        assert f"(default: {value:g})" in benchmarks


HEAVY = ("torch", "diffusers", "transformers", "accelerate")
#: Per command, arguments argparse itself refuses (a missing required argument): they answer, as
#: ``--help`` and an unknown option do, without torch.
REFUSED_BY_ARGPARSE = {
    "generate": [[]],
    "evaluate": [[], ["clip.mp4", "--out", ""]],
    "geco_eval": [["--models", "cogvideox-5b"], ["--models", "cogvideox-5b", "--out", " "]],
    "detection": [[], ["clip.mp4", "--out", ""]],
    "validate": [["bench", "--out", ""]],
    "robustness": [[], ["--out", ""]],
    "benchmarks": [["warp"], ["warp", "synthetic", "--out", ""]],
    "ab": [["--seeds", "0"], ["--prompts", "p.txt", "--seeds", "0", "--out", ""]],
    "compare": [["run-a", "run-b"], ["run-a", "--out", "cmp"], ["run-a", "run-b", "--out", ""]],
}
#: Per command, values the command refuses in one line before any work (their choices live with
#: the code that reads them, which imports torch).
REFUSED_BY_THE_COMMAND = {
    "evaluate": ["clip.mp4", "--pairs", "every"],
    "geco_eval": ["--out", "bench", "--models", "cogvideox-5b", "--scenario", "underwater"],
    "detection": ["clip.mp4", "--anchor", "middle"],
    "validate": ["bench", "--pairs", "every"],
    "robustness": ["--out", "sweep", "--pairs", "every"],
    "benchmarks": ["blur", "clip.mp4", "--out", "bench"],
}
COMMANDS = tuple(REFUSED_BY_ARGPARSE)


def run_probe(argv: list[str], run: str, cwd: Path = ROOT) -> tuple[int, str, str, list[str]]:
    """``run`` with ``sys.argv = argv`` in a fresh interpreter: (exit code, stdout, stderr, which of
    :data:`HEAVY` it imported)."""
    probe = (f"import json, runpy, sys\nsys.argv = {argv!r}\ntry:\n    code = {run}\nexcept SystemExit as stop:\n"
             "    code = stop.code\n"
             f"print(code, json.dumps(sorted(m for m in {HEAVY!r} if m in sys.modules)), file=sys.stderr)")
    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    proc = subprocess.run([sys.executable, "-c", probe], capture_output=True, text=True, timeout=120, cwd=cwd, env=env)
    *err, last = proc.stderr.strip().splitlines()
    code, _, loaded = last.partition(" ")
    return int(code), proc.stdout, "\n".join(err), json.loads(loaded)


GECO = "__import__('geco_guide.__main__', fromlist=['main']).main(sys.argv[1:])"
CASES = [(command, extra) for command in COMMANDS
         for extra in (["--help"], ["--no-such-option"], *REFUSED_BY_ARGPARSE[command])]


@pytest.mark.parametrize("command, extra", CASES, ids=[f"{c}-{' '.join(x) or 'nothing'}" for c, x in CASES])
def test_help_and_argument_errors_answer_without_torch(command, extra):
    code, out, err, loaded = run_probe(["geco", command.replace("_", "-"), *extra], GECO)
    assert loaded == [], (loaded, err)
    if extra == ["--help"]:
        assert code == 0 and out.startswith(f"usage: geco {command.replace('_', '-')}"), err
    else:
        assert code == 2 and err.startswith("error:") and "\n" not in err, err
    if "--out" in extra and not extra[extra.index("--out") + 1].strip():  # never the working folder
        assert "argument --out: must name an output folder, got an empty string" in err, err


@pytest.mark.parametrize("command", sorted(REFUSED_BY_THE_COMMAND))
@pytest.mark.slow
def test_a_bad_value_is_one_line_before_any_work(command, tmp_path):
    code, out, err, _ = run_probe(["geco", command.replace("_", "-"), *REFUSED_BY_THE_COMMAND[command]], GECO,
                                  cwd=tmp_path)
    assert code == 2 and err.startswith("error:") and "\n" not in err, err
    assert list(tmp_path.iterdir()) == []  # nothing written


def test_geco_help_loads_no_torch():
    code, out, err, loaded = run_probe(["geco", "--help"], GECO)
    assert code == 0 and loaded == [] and "commands:" in out, err


@pytest.mark.parametrize("extra", [["--help"], ["--seed", "3"]])
def test_the_generate_module_answers_without_torch(extra):
    code, out, err, loaded = run_probe(["geco_guide.generate", *extra],
                                       "runpy.run_module('geco_guide.generate', run_name='__main__')")
    assert loaded == [] and code == (0 if extra == ["--help"] else 2), (loaded, err)


@pytest.mark.parametrize("arguments", [["generate", "--help"], ["evaluate", "--no-such-option"]])
def test_the_installed_geco_script_answers_help_and_errors_without_torch(arguments):
    script = Path(sys.executable).with_name("geco")
    if not script.is_file():
        pytest.skip("no geco script beside this interpreter (the package is not installed in its environment)")
    done = subprocess.run([sys.executable, "-X", "importtime", str(script), *arguments], capture_output=True, text=True,
                          timeout=120)
    imported = {line.rpartition("|")[2].strip() for line in done.stderr.splitlines() if line.startswith("import time:")}
    if "--help" in arguments:
        assert done.returncode == 0 and done.stdout.startswith("usage:")
    else:
        assert done.returncode == 2 and done.stderr.splitlines()[-1].startswith("error:")
    assert "torch" not in imported and "geco_guide.cli.kit" in imported, done.stderr[-2000:]


@pytest.mark.parametrize("name", sorted(GECO_COMMANDS))
def test_each_command_is_reached_through_geco(name, capsys):
    with pytest.raises(SystemExit) as exit:
        geco_main([name, "--help"])
    assert exit.value.code == 0 and "usage:" in capsys.readouterr().out


@pytest.mark.slow
def test_generate_says_what_the_progress_bar_and_the_update_count_count(tmp_path, capsys):
    from geco_guide.cli.generate import main

    assert main(["--preset", "tiny", "--prompt", "a marble bust", "--out", str(tmp_path / "v.mp4")]) == 0
    line = next(line for line in capsys.readouterr().out.splitlines() if line.startswith("guidance:"))
    # the tiny preset: 4 denoising steps (the bar's count), R_t = 0, 2, 2, 1 with time travel: 5 updates
    assert line.startswith("guidance: 5 updates over 4 denoising steps in ")
    assert line.endswith("s (the progress bar counts steps)")
