"""geco bench as a command: its help without torch, the internal worker out of the help, and what a
cost run prints (the per-stage table, a progress line per item it computes, one warning line for an
option that cannot act)."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest

from geco_guide.cli import bench
from geco_guide.cli.kit import Parser

ROOT = Path(__file__).resolve().parents[2]
HEAVY = ("torch", "diffusers", "transformers")
PUBLIC = "{loss,estimators,vae,sampling,cost,plans,attention-shapes,decoder-agreement,geco-eval}"


def test_help_answers_without_torch():
    probe = ("import sys\nfrom geco_guide.cli.bench import main\ntry:\n    main(['cost', '--help'])\n"
             "except SystemExit as stop:\n    code = stop.code\n"
             f"print(code, sorted(m for m in {HEAVY!r} if m in sys.modules), file=sys.stderr)")
    for argv in (["--help"], ["cost", "--help"]):
        done = subprocess.run([sys.executable, "-c", probe.replace("['cost', '--help']", repr(argv))],
                              capture_output=True, text=True, timeout=120, cwd=ROOT)
        assert done.stderr.strip().splitlines()[-1] == "0 []", done.stderr
        assert "usage: geco bench" in done.stdout


def test_the_worker_stays_out_of_the_help_and_still_parses():
    parser = bench.register_subcommand(Parser(prog="geco bench"))
    text = parser.format_help()
    assert "worker" not in text and PUBLIC in text
    assert parser.parse_args(["worker", "{}"]).command == "worker"  # the cases' processes still start it
    for name in ("cost", "plans", "sampling"):
        assert name in bench.SUBCOMMANDS and name in text


def test_geco_runs_bench_as_one_of_its_commands(capsys):
    from geco_guide.__main__ import main

    with pytest.raises(SystemExit) as stop:
        main(["bench", "--help"])
    assert stop.value.code == 0 and PUBLIC in capsys.readouterr().out


@pytest.mark.slow
def test_a_cost_run_prints_the_stage_table_and_a_line_per_trace(capsys, tmp_path):
    out = tmp_path / "cost.json"
    assert bench.main(["cost", "--preset", "tiny", "--mode", "fast", "--threads", "1", "--json", str(out)]) == 0
    captured = capsys.readouterr()
    assert "| stage | count | TFLOP forward |" in captured.out and "| anchor_decode | 5 |" in captured.out
    assert "mode fast: FLOPs unguided" in captured.out
    progress = [line for line in captured.err.splitlines() if line.startswith("traced ")]
    assert len(progress) == 2 and "unguided step" in progress[0] and "fast update" in progress[1]
    assert json.loads(out.read_text())["counts"]["updates"] == 5


@pytest.mark.slow
def test_several_gpus_print_one_progress_line_per_card(capsys):
    from geco_guide.perf.cards import GPU_SPECS

    assert bench.main(["cost", "--preset", "tiny", "--mode", "fast", "--num-gpus", "2", "--threads", "1"]) == 0
    captured = capsys.readouterr()
    cards = [line for line in captured.err.splitlines() if line.startswith("2 x ")]
    assert [line.split()[2].rstrip(":") for line in cards] == list(GPU_SPECS)
    assert "run.devices over 2 GPUs" in captured.out


@pytest.mark.slow
def test_dynamic_masks_without_guidance_is_one_warning_line(capsys):
    assert bench.main(["cost", "--preset", "tiny", "--mode", "unguided", "--dynamic-masks", "--threads", "1"]) == 0
    captured = capsys.readouterr()
    warnings = [line for line in captured.err.splitlines() if line.startswith("warning:")]
    assert warnings == ["warning: --dynamic-masks has no effect with --mode unguided (the masks act on guided "
                        "updates only)"]
    assert "dynamic masks:" not in captured.out


def test_all_models_prints_the_table_of_the_shipped_estimates(capsys, tmp_path):
    from geco_guide.perf.family_table import family_rows, family_table

    out = tmp_path / "rows.json"
    assert bench.main(["cost", "--all-models", "--json", str(out)]) == 0
    assert capsys.readouterr().out == family_table() + "\n"
    assert json.loads(out.read_text())["rows"] == family_rows()
    assert bench.main(["cost", "--all-models", "--mode", "fast"]) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith("error: --all-models prints the table") and "--mode" in err and "\n" not in err
