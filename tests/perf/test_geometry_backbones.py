"""The geometry backbones of the benchmarks (:mod:`geco_guide.perf.geometry_backbones`): each name
builds its architecture, and the FLOPs counted on fake tensors are those of its trunk."""

from __future__ import annotations

import pytest
import torch

from geco_guide.estimators.da3 import DA3
from geco_guide.estimators.da3_config import DA3Config
from geco_guide.estimators.vggt import VGGT
from geco_guide.perf.geometry_backbones import GEOMETRY_BACKBONES, geometry_flops, geometry_model, network_hw


def test_each_name_builds_its_architecture_and_input_size():
    assert list(GEOMETRY_BACKBONES) == ["vggt-1b", "da3-small", "da3-base"]
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
