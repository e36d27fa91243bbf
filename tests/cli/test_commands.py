"""The commands as a newcomer meets them: every option says what it does, internal subcommands stay
out of ``--help``, ``--help`` and a mistyped option answer at once (no torch, no diffusion library),
and counts read as counts."""

from __future__ import annotations

import argparse
import importlib
import importlib.util
import json
import subprocess
import sys
from pathlib import Path

import pytest

from script_modules import load_script

ROOT = Path(__file__).resolve().parents[2]
COMMANDS = ("generate", "evaluate", "geco_eval", "detection", "validate", "robustness", "benchmarks", "ab")
SCRIPTS = ("benchmark.py", "ab_compare.py")


def script_module(name: str):
    return load_script(name, f"script_{Path(name).stem}")


def options_without_help(parser: argparse.ArgumentParser, prefix: str) -> list[str]:
    missing = []
    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            for name, sub in action.choices.items():
                missing += options_without_help(sub, f"{prefix} {name}")
        elif not action.help and not isinstance(action, (argparse._HelpAction, argparse._VersionAction)):
            missing.append(f"{prefix} {'/'.join(action.option_strings) or action.dest}")
    return missing


def test_every_option_has_help():
    parsers = {name: importlib.import_module(f"geco_guide.cli.{name}").build_parser() for name in COMMANDS}
    parsers.update({name: script_module(name).build_parser() for name in SCRIPTS})
    missing = [m for name, parser in parsers.items() for m in options_without_help(parser, name)]
    assert not missing, missing


def test_benchmark_help_hides_the_internal_worker():
    module = script_module("benchmark.py")
    parser = module.build_parser()
    text = parser.format_help()
    assert "worker" not in text and "{loss,estimators,vae,sampling,cost,plans,decoder-agreement,geco-eval}" in text
    assert parser.parse_args(["worker", "{}"]).command == "worker"  # the cases' processes still start it


HEAVY = ("torch", "diffusers", "transformers", "accelerate")
#: Per command, arguments argparse refuses before any work: a missing required argument, a bad
#: choice (an unknown option is tried on every command).
REFUSED = {
    "generate": [[]],
    "evaluate": [[], ["clip.mp4", "--pairs", "every"]],
    "geco_eval": [["--models", "cogvideox-5b"], ["--out", "bench", "--scenario", "underwater"]],
    "detection": [[], ["clip.mp4", "--anchor", "middle"]],
    "validate": [["--pairs", "every"]],
    "robustness": [[], ["--out", "sweep", "--pairs", "every"]],
    "benchmarks": [["blur", "clip.mp4", "--out", "bench"]],
    "ab": [["--prompts", "p.txt", "--seeds", "0"]],
}


def run_probe(argv: list[str], run: str) -> tuple[int, str, str, list[str]]:
    """``run`` with ``sys.argv = argv`` in a fresh interpreter: (exit code, stdout, stderr, which of
    :data:`HEAVY` it imported)."""
    probe = (f"import json, runpy, sys\nsys.argv = {argv!r}\ntry:\n    {run}\nexcept SystemExit as stop:\n    code = stop.code\n"
             "else:\n    code = 0\n"
             f"print(code, json.dumps(sorted(m for m in {HEAVY!r} if m in sys.modules)), file=sys.stderr)")
    proc = subprocess.run([sys.executable, "-c", probe], capture_output=True, text=True, timeout=120, cwd=ROOT)
    *err, last = proc.stderr.strip().splitlines()
    code, _, loaded = last.partition(" ")
    return int(code), proc.stdout, "\n".join(err), json.loads(loaded)


CASES = [(command, extra) for command in COMMANDS for extra in (["--help"], ["--no-such-option"], *REFUSED[command])]


@pytest.mark.parametrize("command, extra", CASES, ids=[f"{c}-{' '.join(x) or 'nothing'}" for c, x in CASES])
def test_help_and_argument_errors_answer_without_torch(command, extra):
    # as `python -m geco_guide <command> ...` (and so `geco <command> ...`) runs it
    code, out, err, loaded = run_probe(["geco", command.replace("_", "-"), *extra],
                                       "runpy.run_module('geco_guide', run_name='__main__')")
    assert loaded == [], (loaded, err)
    if extra == ["--help"]:
        assert code == 0 and out.startswith("usage:"), err
    else:
        assert code == 2 and err.startswith("error:") and "\n" not in err, err


def test_a_command_module_still_has_the_names_it_imports_later():
    from geco_guide.cli import evaluate, generate
    from geco_guide.estimators import load_estimators
    from geco_guide.sampler import loading

    assert evaluate.load_estimators is load_estimators and generate.loading is loading
    with pytest.raises(AttributeError, match="no attribute 'no_such_name'"):
        evaluate.no_such_name


@pytest.mark.parametrize("extra", [["--help"], ["--seed", "3"]])
def test_the_generate_module_answers_without_torch(extra):
    code, out, err, loaded = run_probe(["geco_guide.generate", *extra],
                                       "runpy.run_module('geco_guide.generate', run_name='__main__')")
    assert loaded == [] and code == (0 if extra == ["--help"] else 2), (loaded, err)


@pytest.mark.parametrize("script", SCRIPTS)
def test_script_help_loads_no_diffusion_library(script):
    code, out, err, loaded = run_probe([script, "--help"],
                                       f"runpy.run_path({str(ROOT / 'scripts' / script)!r}, run_name='__main__')")
    assert code == 0 and out.startswith("usage:") and not set(loaded) - {"torch"}, (loaded, err)


def test_generate_says_what_the_progress_bar_and_the_update_count_count(tmp_path, capsys):
    from geco_guide.cli.generate import main

    assert main(["--preset", "tiny", "--prompt", "a marble bust", "--out", str(tmp_path / "v.mp4")]) == 0
    line = next(line for line in capsys.readouterr().out.splitlines() if line.startswith("guidance:"))
    # the tiny preset: 4 denoising steps (the bar's count), R_t = 0, 2, 2, 1 with time travel: 5 updates
    assert line.startswith("guidance: 5 updates over 4 denoising steps in ")
    assert line.endswith("s (the progress bar counts steps)")
