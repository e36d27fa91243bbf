"""The geometry backbones of the benchmarks (:mod:`geco_guide.perf.geometry_backbones`): each name
builds its architecture, the FLOPs counted on fake tensors are those of its trunk, and
``geco bench estimators --geometry-estimator`` times the one chosen beside UFM."""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
from pathlib import Path
from types import SimpleNamespace

import pytest
import torch

from geco_guide.__main__ import build_parser

from geco_guide.estimators import GEOMETRY_BACKBONES
from geco_guide.estimators.da3 import DA3
from geco_guide.estimators.da3_config import DA3Config
from geco_guide.estimators.vggt import VGGT
from geco_guide.perf.geometry_backbones import BACKBONE_ARCHITECTURES, geometry_flops, geometry_model, network_hw
from geco_guide.perf.workloads import estimator_specs, run_worker

REPO = Path(__file__).resolve().parents[2]


def test_each_name_builds_its_architecture_and_input_size():
    assert list(BACKBONE_ARCHITECTURES) == list(GEOMETRY_BACKBONES) == ["vggt-1b", "da3-small", "da3-base"]
    small, base = geometry_model("da3-small", "tiny", 0), geometry_model("da3-base", "tiny", 0)
    assert isinstance(small, DA3) and isinstance(geometry_model("vggt-1b", "tiny", 0), VGGT)
    assert small.config == base.config  # one tiny DA3 stands in for both
    assert network_hw(small, 28, 42) == (42, 70)  # longest side to process_res 70, multiples of 14
    with pytest.raises(ValueError, match="unknown geometry backbone 'da3-large'; one of vggt-1b, da3-small, da3-base"):
        geometry_model("da3-large", "full", 0)


@pytest.mark.slow
def test_the_counted_flops_are_at_least_the_trunks_matrix_products():
    flops = geometry_flops("da3-small", 2, 480, 720)
    assert flops["network"] == "336x504" and flops["params_m"] == pytest.approx(26.8, abs=0.05)
    # every trunk weight multiplies every patch token at least once: 2 FLOPs per weight and token
    with torch.device("meta"):
        trunk = sum(p.numel() for p in DA3(DA3Config.small()).model.backbone.parameters())
    tokens = 2 * (336 // 14) * (504 // 14)
    assert trunk > 20e6 and flops["forward_tflop"] * 1e12 > 2 * trunk * tokens
    # the backward to the frames costs about twice the forward
    assert 2.0 * flops["forward_tflop"] < flops["forward_backward_tflop"] < 4.0 * flops["forward_tflop"]


def specs_of(geometry: str, size: str = "full") -> list[dict]:
    args = SimpleNamespace(size=size, frames=4, height=480, width=720, dtype="bfloat16", geometry_estimator=geometry,
                           device="cpu", threads=1, warmup=0, repeats=1, seed=0, rss_exact=False)
    return estimator_specs(args)


def test_geco_bench_estimators_offers_each_backbone_beside_ufm():
    _, parsers = build_parser()
    commands = next(a for a in parsers["bench"]._actions if isinstance(a, argparse._SubParsersAction))
    option = next(a for a in commands.choices["estimators"]._actions if a.dest == "geometry_estimator")
    assert list(option.choices) == list(BACKBONE_ARCHITECTURES) and option.default == "vggt-1b"
    for command in ("generate", "evaluate"):  # their --geometry-estimator takes any id: the help names each backbone
        help_text = next(a.help for a in parsers[command]._actions if a.dest == "geometry_estimator")
        assert all(name in help_text for name in GEOMETRY_BACKBONES), command
    # VGGT keeps its case names (the recorded reports use them)
    assert [(s["case"], s["mode"]) for s in specs_of("vggt-1b")] == [
        ("vggt-full", "forward"), ("vggt-full", "forward_backward"),
        ("ufm-full", "forward"), ("ufm-full", "forward_backward")]
    da3 = specs_of("da3-base")
    assert [(s["workload"], s["case"], s["geometry"]) for s in da3[:2]] == [("da3", "da3-base-full", "da3-base")] * 2
    assert [s["workload"] for s in da3[2:]] == ["ufm", "ufm"]


def test_the_da3_case_runs_forward_and_backward():
    for spec in specs_of("da3-small", "tiny")[:2]:
        result = run_worker({**spec, "frames": 2, "height": 28, "width": 42, "dtype": "float32"})
        assert result["time_median_s"] > 0 and result["mode"] == spec["mode"]
        assert result["network"] == "42x70" and 0.1 < result["params_m"] < 0.5  # the tiny DA3: 0.2 M


@pytest.mark.slow
def test_the_command_times_the_chosen_backbone(tmp_path):
    report = tmp_path / "estimators.json"
    done = subprocess.run([sys.executable, "-m", "geco_guide.cli.bench", "estimators", "--size", "tiny",
                           "--geometry-estimator", "da3-base", "--frames", "2", "--height", "28", "--width", "42",
                           "--threads", "1", "--warmup", "0", "--repeats", "1", "--json", str(report)],
                          capture_output=True, text=True, cwd=REPO, timeout=120)
    assert done.returncode == 0, done.stderr
    results = json.loads(report.read_text())["results"]
    assert [(r["case"], r["mode"]) for r in results] == [
        (case, mode) for case in ("da3-base-tiny", "ufm-tiny") for mode in ("forward", "forward_backward")]
    assert "| da3-base-tiny | forward_backward |" in done.stdout
