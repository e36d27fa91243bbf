"""The tables the docs quote are what their commands print: each block of docs/validation.md
headed by ``<!-- geco validate ... -->`` is rerun on freshly built benchmarks, and the model table
of docs/geco_eval.md is rebuilt from the registry (``geco_guide.families.MODELS``)."""

from __future__ import annotations

import re
import shlex
from pathlib import Path

import pytest

from quoted_tables import same_table

from geco_guide.cli import benchmarks
from geco_guide.cli import validate as validate_cli
from geco_guide.families import MODELS

DOCS = Path(__file__).resolve().parents[1] / "docs"
QUOTED = re.compile(r"<!-- (geco validate [^>]*?) -->\n(.*?)<!-- end of the table -->", re.S)
MODEL_TABLE = ("<!-- model table: geco_guide.families.MODELS -->", "<!-- end of the model table -->")

#: The benchmarks the quoted validate commands read, as docs/validation.md's reproduce block builds them.
BUILDS = {
    "warp-frame": ["warp", "synthetic", "--mode", "frame", "--seeds", *map(str, range(10))],
    "warp-clip": ["warp", "synthetic", "--seeds", "0", "1", "2", "3", "4"],
    "occlusion": ["occlusion", "synthetic", "--seeds", "0", "1", "2", "3", "4"],
    "occlusion-3d": ["occlusion", "synthetic-3d"],
}


def quoted_validate_tables() -> list[tuple[str, str]]:
    """``(command, table)`` of every quoted ``geco validate`` table of docs/validation.md."""
    return [(command, table.strip()) for command, table in QUOTED.findall((DOCS / "validation.md").read_text())]


def test_validation_page_quotes_the_four_validate_tables():
    commands = [command for command, _ in quoted_validate_tables()]
    assert len(commands) == 4 and len(set(commands)) == 4
    text = (DOCS / "validation.md").read_text()
    assert all(command in text.split("### Reproduce", 1)[1] for command in commands)  # each one in the reproduce block


def test_same_table_takes_kernel_digits_and_refuses_a_real_change():
    page = "| Cue | Task 2 F1 (%) | Task 2 SRCC | Task 1 Acc (%) |\n|---|---|---|---|\n| M_struct | 33.11 | -0.439 | 10.00 |"
    assert same_table(page, page)
    assert same_table(page.replace("33.11", "33.08").replace("-0.439", "-0.444"), page)
    assert not same_table(page.replace("33.11", "32.90"), page)  # 0.6 %
    assert not same_table(page.replace("-0.439", "-0.445"), page)  # 6 units of the last digit
    assert not same_table(page.replace("M_struct", "M_motion"), page)
    assert not same_table(page + "\n| Fused | 1.00 | 0.100 | 0.00 |", page)
    noise = page.replace("33.11", "8.60")
    assert same_table(noise.replace("8.60", "11.24"), noise)  # both near chance: "sees nothing"
    assert not same_table(noise.replace("8.60", "15.20"), noise)
    assert not same_table(page.replace("10.00", "0.00"), page)  # Task 1 counts clips: exact


@pytest.mark.slow
def test_each_quoted_validate_table_is_what_its_command_prints(tmp_path, capsys):
    """The full reproduce run (about 20 s of CPU): any change of the numbers beyond what CPUs'
    float32 kernels move (``same_table``) must reach the page."""
    bench = tmp_path / "bench"
    for name, argv in BUILDS.items():
        assert benchmarks.main([*argv, "--out", str(bench / name)]) == 0
    capsys.readouterr()
    for command, documented in quoted_validate_tables():
        argv = [str(tmp_path / a) if a.startswith("bench/") else a for a in shlex.split(command)[2:]]
        assert validate_cli.main([*argv, "--no-grids", "--out", str(tmp_path / "report" / str(abs(hash(command))))]) == 0
        printed = "\n".join(line for line in capsys.readouterr().out.splitlines() if line.startswith("|"))
        assert same_table(printed, documented), f"{command}\nprinted:\n{printed}\non the page:\n{documented}"


def model_table() -> str:
    """The registry as docs/geco_eval.md shows it: a row per model that generates, then the
    scored-only ones in one row."""
    rows = ["| model name | checkpoint | pipeline | frames, size | steps, CFG | native fps |", "|---|---|---|---|---|---|"]
    for model in MODELS.values():
        if not model.generates:
            continue
        call = model.call
        cfg = f"{call['guidance_scale']:g}" + (f" / {call['guidance_scale_2']:g}" if "guidance_scale_2" in call else "")
        rows.append(f"| `{model.name}` | `{model.hub_id}` | `{model.pipeline}` | {call['num_frames']}, "
                    f"{call['height']}x{call['width']} | {call['num_inference_steps']}, {cfg} | {model.eval_fps:g} |")
    scored = [model for model in MODELS.values() if not model.generates]
    rows.append("| " + ", ".join(f"`{m.name}`" for m in scored) + " | scoring only (`--videos`) | - | - | - | "
                + ", ".join(f"{m.eval_fps:g}" for m in scored) + " |")
    return "\n".join(rows)


def test_the_model_table_of_geco_eval_is_the_registry():
    text = (DOCS / "geco_eval.md").read_text()
    begin, end = MODEL_TABLE
    assert begin in text and end in text
    assert text.split(begin, 1)[1].split(end, 1)[0].strip() == model_table()
    assert "bench/models.py" not in text  # the registry lives in geco_guide/families
