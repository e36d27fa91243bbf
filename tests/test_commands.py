"""The commands as a newcomer meets them: every option says what it does, internal subcommands stay
out of ``--help``, ``--help`` loads no diffusion library, and counts read as counts."""

from __future__ import annotations

import argparse
import importlib
import importlib.util
import subprocess
import sys
from pathlib import Path

import pytest

from script_modules import load_script

ROOT = Path(__file__).resolve().parents[1]
COMMANDS = ("generate", "evaluate", "geco_eval", "detection", "validate", "robustness", "benchmarks")
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


@pytest.mark.parametrize("command", [*COMMANDS, *SCRIPTS])
def test_help_loads_no_diffusion_library(command):
    if command in SCRIPTS:
        argv, run = [command, "--help"], f"runpy.run_path({str(ROOT / 'scripts' / command)!r}, run_name='__main__')"
    else:  # as `python -m geco_guide <command> --help` runs it
        argv, run = ["geco", command.replace("_", "-"), "--help"], "sys.exit(runpy.run_module('geco_guide', run_name='__main__'))"
    probe = (f"import runpy, sys\nsys.argv = {argv!r}\ntry:\n    {run}\nexcept SystemExit:\n    pass\n"
             "print(sorted(m for m in ('diffusers', 'transformers', 'accelerate') if m in sys.modules), file=sys.stderr)")
    proc = subprocess.run([sys.executable, "-c", probe], capture_output=True, text=True, timeout=120, cwd=ROOT)
    assert proc.stdout.startswith("usage:") and proc.stderr.strip().splitlines()[-1] == "[]", proc.stderr


def test_generate_says_what_the_progress_bar_and_the_update_count_count(tmp_path, capsys):
    from geco_guide.cli.generate import main

    assert main(["--preset", "tiny", "--prompt", "a marble bust", "--out", str(tmp_path / "v.mp4")]) == 0
    line = next(line for line in capsys.readouterr().out.splitlines() if line.startswith("guidance:"))
    # the tiny preset: 4 denoising steps (the bar's count), R_t = 0, 2, 2, 1 with time travel: 5 updates
    assert line.startswith("guidance: 5 updates over 4 denoising steps in ")
    assert line.endswith("s (the progress bar counts steps)")
