"""Smoke test of scripts/benchmark.py: both subcommands run at a tiny size and write sane JSON.

No timing thresholds: only the report's structure and that the numbers are positive. The two
commands run concurrently to keep the test short (every case imports torch in its own process).
"""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest

SCRIPT = Path(__file__).resolve().parents[1] / "scripts" / "benchmark.py"
FAST = ["--threads", "1", "--warmup", "0", "--repeats", "1"]
COMMANDS = {
    "loss": ["loss", "--frames", "2", "--height", "24", "--width", "32", *FAST],
    "estimators": ["estimators", "--size", "tiny", "--frames", "2", "--height", "28", "--width", "42", *FAST],
}
POSITIVE_KEYS = (
    "time_median_s", "time_min_s", "cpu_per_wall",
    "baseline_mib", "after_setup_mib", "peak_mib", "peak_increase_mib",
)


@pytest.fixture(scope="module")
def reports(tmp_path_factory: pytest.TempPathFactory) -> dict[str, dict]:
    """Run both subcommands at once; name -> parsed JSON report (and the printed table)."""
    tmp = tmp_path_factory.mktemp("benchmark")
    procs = {
        name: subprocess.Popen(
            [sys.executable, str(SCRIPT), *args, "--json", str(tmp / f"{name}.json")],
            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
        )
        for name, args in COMMANDS.items()
    }
    out = {}
    for name, proc in procs.items():
        stdout, stderr = proc.communicate(timeout=120)
        assert proc.returncode == 0, stderr
        out[name] = {**json.loads((tmp / f"{name}.json").read_text()), "stdout": stdout}
    return out


def _check_result(result: dict) -> None:
    for key in POSITIVE_KEYS:
        assert result[key] > 0, (key, result)
    assert len(result["times_s"]) == result["repeats"] == 1
    assert result["peak_mib"] >= result["after_setup_mib"] >= result["baseline_mib"]
    assert result["memory_kind"] == "peak_rss" and result["threads"] == 1 and result["load_avg_1m"] >= 0


def test_loss_report(reports: dict[str, dict]) -> None:
    report = reports["loss"]
    assert report["subcommand"] == "loss"
    assert {"torch", "cpu_count", "processor", "torch_threads"} <= set(report["environment"])
    results = report["results"]
    assert [(r["case"], r["mode"]) for r in results] == [
        ("geco_from_geometry", "forward"), ("geco_from_geometry", "forward_backward")
    ]
    for result in results:
        _check_result(result)
        assert result["input"] == "2x24x32, 1 adjacent pairs"
    assert "| geco_from_geometry | forward_backward |" in report["stdout"]


def test_estimators_report(reports: dict[str, dict]) -> None:
    results = reports["estimators"]["results"]
    assert [(r["case"], r["mode"]) for r in results] == [
        (case, mode) for case in ("vggt-tiny", "ufm-tiny") for mode in ("forward", "forward_backward")
    ]
    for result in results:
        _check_result(result)
        assert result["params_m"] > 0
    networks = {r["case"]: r["network"] for r in results}
    assert networks == {"vggt-tiny": "42x70", "ufm-tiny": "56x98"}
