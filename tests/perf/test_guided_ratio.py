"""The card ``geco ab --best-of matched`` predicts for: the local GPU's, named as the cost model names it."""

from __future__ import annotations

import pytest
import torch

from geco_guide.config import load_config
from geco_guide.perf import guided_ratio


@pytest.mark.parametrize("name, card", [("NVIDIA H200", "H200"), ("NVIDIA L40S", "L40S"), ("NVIDIA L4", "L4"),
                                        ("NVIDIA GeForce RTX 4090", "RTX4090"), ("NVIDIA RTX A6000", "A6000"),
                                        ("NVIDIA H100 80GB HBM3", "H100"), ("Tesla V100-SXM2-16GB", None)])
def test_the_local_gpu_names_the_card_matched_predicts_for(name, card, monkeypatch):
    monkeypatch.setattr(guided_ratio, "resolve_device", lambda device: torch.device("cuda", 0))
    monkeypatch.setattr(torch.cuda, "get_device_name", lambda device=None: name)
    assert guided_ratio.local_card(load_config(preset="tiny")) == card


def test_a_cpu_is_no_card():
    assert guided_ratio.local_card(load_config(preset="tiny")) is None
