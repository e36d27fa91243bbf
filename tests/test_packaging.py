"""Packaging: the presets in the checkout's configs/ are the installed package data, and a built
wheel works outside the checkout (--preset, the prompt suite, the console scripts)."""

from __future__ import annotations

import subprocess
import sys
import venv
from pathlib import Path

from geco_guide.config import CONFIG_DIR, load_config

ROOT = Path(__file__).resolve().parents[1]


def test_presets_come_from_the_top_level_configs_folder():
    assert CONFIG_DIR == ROOT / "configs"  # a checkout (editable install) reads them in place
    assert sorted(p.name for p in CONFIG_DIR.glob("*.yaml")) == ["cogvideox-5b-fused.yaml", "cogvideox-5b.yaml", "tiny.yaml"]
    assert load_config(ROOT / "configs" / "tiny.yaml") == load_config(preset="tiny")


def test_the_package_list_names_every_package():
    """pyproject lists the packages explicitly (to map configs/ into geco_guide.configs): a new
    subpackage must be added there, or the wheel would silently miss it."""
    from setuptools.config.pyprojecttoml import read_configuration

    listed = set(read_configuration(ROOT / "pyproject.toml")["tool"]["setuptools"]["packages"])
    found = {".".join(p.parent.relative_to(ROOT).parts) for p in (ROOT / "geco_guide").rglob("__init__.py")}
    assert listed == found | {"geco_guide.configs"}


def test_a_built_wheel_runs_the_tiny_preset_outside_the_checkout(tmp_path: Path):
    wheels = tmp_path / "wheels"
    subprocess.run([sys.executable, "-m", "pip", "wheel", "-q", "--no-deps", "--no-build-isolation", "-w", str(wheels),
                    str(ROOT)], check=True, capture_output=True, timeout=300)
    (wheel,) = wheels.glob("geco_guide-*.whl")
    env_dir = tmp_path / "venv"
    venv.create(env_dir, system_site_packages=True, with_pip=True)  # torch & co. from this environment
    python = env_dir / "bin" / "python"
    subprocess.run([python, "-m", "pip", "install", "-q", "--no-deps", "--no-index", str(wheel)], check=True,
                   capture_output=True, timeout=300)
    work = tmp_path / "elsewhere"
    work.mkdir()
    probe = ("import geco_guide, geco_guide.config as c; print(geco_guide.__file__); print(c.CONFIG_DIR); "
             "print(len(geco_guide.load_prompts()))")
    lines = subprocess.run([python, "-c", probe], cwd=work, check=True, capture_output=True, text=True,
                           timeout=120).stdout.split()
    assert lines[0].startswith(str(env_dir)) and lines[1].startswith(str(env_dir)) and lines[2] == "80"
    out = subprocess.run([env_dir / "bin" / "geco-generate", "--preset", "tiny", "--prompt", "a marble bust",
                          "--out", str(work / "bust.mp4"), "output.score_anchors=false"],
                         cwd=work, capture_output=True, text=True, timeout=300)
    assert out.returncode == 0, out.stderr
    assert (work / "bust.mp4").is_file() and (work / "bust.json").is_file()
