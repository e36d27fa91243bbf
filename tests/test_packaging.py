"""Packaging: the presets in the checkout's configs/ are the installed package data, and a built
wheel works outside the checkout (--preset, the prompt suite, the console scripts)."""

from __future__ import annotations

import subprocess
import sys
import sysconfig
import venv
from pathlib import Path

import pytest

from geco_guide.config import CONFIG_DIR, load_config

ROOT = Path(__file__).resolve().parents[1]


def test_presets_come_from_the_top_level_configs_folder():
    assert CONFIG_DIR == ROOT / "configs"  # a checkout (editable install) reads them in place
    from geco_guide.families import video_models

    # the paper's two, the tiny one, and one per registry model that has weights
    expected = {"cogvideox-5b-fused.yaml", "tiny.yaml", *(f"{name}.yaml" for name in video_models())}
    assert sorted(p.name for p in CONFIG_DIR.glob("*.yaml")) == sorted(expected)
    assert load_config(ROOT / "configs" / "tiny.yaml") == load_config(preset="tiny")


def test_the_package_list_names_every_package():
    """pyproject lists the packages explicitly (to map configs/ into geco_guide.configs): a new
    subpackage must be added there, or the wheel would silently miss it."""
    from setuptools.config.pyprojecttoml import read_configuration

    listed = set(read_configuration(ROOT / "pyproject.toml")["tool"]["setuptools"]["packages"])
    found = {".".join(p.parent.relative_to(ROOT).parts) for p in (ROOT / "geco_guide").rglob("__init__.py")}
    assert listed == found | {"geco_guide.configs"}


def run(command: list, **kwargs) -> subprocess.CompletedProcess:
    """``subprocess.run`` that fails with the child's stderr (not only its exit code)."""
    out = subprocess.run([str(c) for c in command], capture_output=True, text=True, timeout=300, **kwargs)
    assert out.returncode == 0, f"{command[0]} exited {out.returncode}:\n{out.stderr[-4000:]}"
    return out


@pytest.mark.slow
def test_a_built_wheel_runs_the_tiny_preset_outside_the_checkout(tmp_path: Path):
    wheels = tmp_path / "wheels"
    run([sys.executable, "-m", "pip", "wheel", "-q", "--no-deps", "--no-build-isolation", "-w", wheels, ROOT])
    (wheel,) = wheels.glob("geco_guide-*.whl")
    env_dir = tmp_path / "venv"
    venv.create(env_dir, with_pip=True)
    python = env_dir / "bin" / "python"
    # torch & co. from the environment running the tests (a user's venv or the base interpreter), as
    # plain paths: the .pth files there (this checkout's editable install) are not run
    site = run([python, "-c", "import sysconfig; print(sysconfig.get_paths()['purelib'])"]).stdout.strip()
    paths = dict.fromkeys(sysconfig.get_paths()[key] for key in ("purelib", "platlib"))
    (Path(site) / "host-environment.pth").write_text("".join(f"{p}\n" for p in paths))
    run([python, "-m", "pip", "install", "-q", "--no-deps", "--no-index", wheel])
    work = tmp_path / "elsewhere"
    work.mkdir()
    probe = ("import geco_guide, geco_guide.config as c; print(geco_guide.__file__); print(c.CONFIG_DIR); "
             "print(len(geco_guide.load_prompts()))")
    lines = run([python, "-c", probe], cwd=work).stdout.split()
    assert lines[0].startswith(str(env_dir)) and lines[1].startswith(str(env_dir)) and lines[2] == "80"
    run([env_dir / "bin" / "geco-generate", "--preset", "tiny", "--prompt", "a marble bust",
         "--out", work / "bust.mp4", "output.score_anchors=false"], cwd=work)
    assert (work / "bust.mp4").is_file() and (work / "bust.json").is_file()
    listing = run([env_dir / "bin" / "geco", "--help"], cwd=work).stdout  # the one command with subcommands
    assert "generate" in listing and "geco-eval" in listing
