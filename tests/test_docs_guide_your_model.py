"""docs/hooks.md's "Guide your model" blocks: per family, the command lines (the tiny ones run, the
real ones parse to the registry's weights), the hooked tiny pipeline in Python (run by
tests/test_readme.py with every offline example) and the real-weights Python, whose imports
resolve and whose call is the model's preset's (frames, size, steps, CFG, anchors)."""

from __future__ import annotations

import re
import shlex
from pathlib import Path

import pytest

from geco_guide import tiny
from geco_guide.cli import generate
from geco_guide.cli.command_line import parse_command
from geco_guide.cli.kit import Parser, config_from_args
from geco_guide.config import load_config
from geco_guide.families import MODELS

HOOKS = Path(__file__).resolve().parents[1] / "docs" / "hooks.md"
FAMILIES = ("Wan 2.2", "HunyuanVideo 1.5", "LTX-2")


def section() -> str:
    text = HOOKS.read_text()
    start = text.index("## Guide your model")
    return text[start:text.index("\n## ", start + 1)]


def blocks(kind: str, text: str) -> list[str]:
    return re.findall(rf"```{kind}\n(.*?)```", text, flags=re.S)


def subsections() -> dict[str, str]:
    parts = re.split(r"^### ", section(), flags=re.M)[1:]
    return {part.splitlines()[0]: part for part in parts}


def command_lines() -> list[str]:
    return [line for block in blocks("bash", section()) for line in block.splitlines() if line.startswith("geco ")]


def real_blocks() -> list[str]:
    return [b for b in blocks("python", section()) if "from_pretrained" in b]


@pytest.mark.parametrize("family", FAMILIES)
def test_each_family_has_its_tiny_command_its_hooked_tiny_pipeline_and_its_real_call(family):
    [text] = [text for title, text in subsections().items() if title.startswith(family)]
    lines = [line for block in blocks("bash", text) for line in block.splitlines()]
    assert any("--preset tiny --model" in line for line in lines)
    assert any("--model" in line and "--preset tiny" not in line for line in lines)
    python = blocks("python", text)
    assert any("attach_geco_guidance" in b and "from geco_guide.tiny import" in b for b in python)
    assert any("attach_geco_guidance" in b and "from_pretrained" in b for b in python)


def parsed(line: str):
    """``geco generate ...`` as the command parses it: ``(args, config)``, nothing loaded."""
    argv = shlex.split(line)
    assert argv[:2] == ["geco", "generate"], line
    parser = Parser(prog="geco generate")
    generate.register_subcommand(parser)
    args = parse_command(parser, argv[2:])
    return args, config_from_args(args, args.overrides)


@pytest.mark.parametrize("line", [line for line in command_lines() if "--preset tiny" not in line])
def test_a_real_command_line_names_the_registry_model_and_its_weights(line):
    args, cfg = parsed(line)
    assert cfg.model.name == args.model and cfg.model.id == MODELS[args.model].hub_id


@pytest.mark.parametrize("code", real_blocks(), ids=lambda code: re.search(r'preset="([^"]+)"', code).group(1))
def test_a_real_weights_block_calls_its_model_as_its_preset(code):
    compile(code, str(HOOKS), "exec")
    imports = "\n".join(line for line in code.splitlines() if line.startswith(("import ", "from ")))
    exec(compile(imports, str(HOOKS), "exec"), {})  # every name it imports exists
    cfg = load_config(preset=re.search(r'load_config\(preset="([^"]+)"\)', code).group(1))
    s = cfg.sampling
    call = {key: float(value) for key, value in re.findall(
        r"\b(num_frames|height|width|num_inference_steps|guidance_scale|guidance_scale_2)=([\d.]+)", code)}
    expected = {"num_frames": s.num_frames, "height": s.height, "width": s.width,
                "num_inference_steps": s.num_inference_steps, "guidance_scale": s.guidance_scale,
                "guidance_scale_2": s.guidance_scale_2}
    assert call == {key: value for key, value in expected.items() if key in call}
    assert {"num_frames", "height", "width", "num_inference_steps", "guidance_scale"} <= set(call)
    anchors, frames, steps = re.search(r"anchors ([\d, ]+) of (\d+) frames; (\d+) steps", code).groups()
    assert [int(a) for a in anchors.split(", ")] == cfg.guidance.anchors
    assert (int(frames), int(steps)) == (s.num_frames, s.num_inference_steps)


@pytest.mark.slow
@pytest.mark.parametrize("line", [line for line in command_lines() if "--preset tiny" in line])
def test_a_tiny_command_line_runs(line, tmp_path, capsys):
    argv = shlex.split(line)[2:]
    if "--image" in argv:  # the page's photo.png: a small image made here
        image = tmp_path / "photo.png"
        tiny.tiny_image(0, 64, 64).save(image)
        argv[argv.index("--image") + 1] = str(image)
    out = tmp_path / "video.mp4"
    assert generate.main([*argv, "--out", str(out)]) == 0, capsys.readouterr().err
    assert out.is_file() and out.with_suffix(".json").is_file()
