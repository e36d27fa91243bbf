"""``geco <command>`` / ``python -m geco_guide <command>``: one name for every command."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest

from geco_guide.__main__ import COMMANDS, main


def test_help_lists_every_command_without_importing_torch():
    done = subprocess.run([sys.executable, "-c", "import sys; from geco_guide.__main__ import main; rc = main(['--help']); "
                           "print('torch' in sys.modules, rc)"], capture_output=True, text=True, check=True)
    listing, last = done.stdout.rsplit("\n", 2)[0], done.stdout.strip().splitlines()[-1]
    assert last == "False 0"
    for name in COMMANDS:
        assert f"  {name} " in listing


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


@pytest.mark.parametrize("name", sorted(COMMANDS))
def test_each_command_is_reached_through_geco(name, capsys):
    with pytest.raises(SystemExit) as exit:
        main([name, "--help"])
    assert exit.value.code == 0 and "usage:" in capsys.readouterr().out


def test_no_or_an_unknown_command_is_one_line_and_exit_code_2(capsys):
    assert main([]) == 2 and "usage: geco <command>" in capsys.readouterr().err
    assert main(["generat"]) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith("geco: error: unknown command 'generat'") and "\n" not in err


def test_generate_through_geco_writes_a_video(tmp_path, capsys):
    out = tmp_path / "v.mp4"
    assert main(["generate", "--preset", "tiny", "--prompt", "a marble bust", "--out", str(out),
                 "--no-guidance", "output.score_anchors=false"]) == 0
    assert out.is_file() and out.with_suffix(".json").is_file()
