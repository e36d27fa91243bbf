"""``movers="drop"`` (the default) leaves every number of GeCoLoss and evaluate_video as it was
before movers could be scored: the numbers of ``tests/fixtures/drop_reference.pt`` were computed
by the code before ``movers`` existed, on the same inputs (a moving scene with a deformation;
no, true and automatic masks; the oracle and the tiny estimators, the gradient included).

The fixture was written with one intra-op thread, and the numbers are computed with one here:
the tiny networks' reductions split over more threads sum in another order. A CPU of another
vector width does too, so the comparison allows a few units in the last place of each tensor's
largest value, far below any change of the metric; on the machine that wrote the fixture the
numbers are equal bit for bit.
"""

from __future__ import annotations

import pytest
import torch
from drop_reference import FIXTURE, evaluation_numbers, loss_numbers

#: Units in the last place allowed, relative to a tensor's largest magnitude.
ULPS = 8


@pytest.fixture(autouse=True)
def one_thread():
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(threads)


@pytest.fixture(scope="module")
def reference():
    return torch.load(FIXTURE, weights_only=False)


def _assert_same(actual, expected, where: str) -> None:
    if isinstance(expected, dict):
        assert set(actual) == set(expected), where
        for key in expected:
            _assert_same(actual[key], expected[key], f"{where}.{key}")
    elif isinstance(expected, (list, tuple)):
        assert len(actual) == len(expected), where
        for k, (a, e) in enumerate(zip(actual, expected)):
            _assert_same(a, e, f"{where}[{k}]")
    elif isinstance(expected, torch.Tensor):
        assert actual.shape == expected.shape and actual.dtype == expected.dtype, where
        if not expected.is_floating_point():
            assert torch.equal(actual, expected), where
            return
        assert torch.equal(torch.isnan(actual), torch.isnan(expected)), where
        scale = expected.nan_to_num(0.0).abs().max().clamp_min(torch.finfo(expected.dtype).tiny)
        error = (actual - expected).nan_to_num(0.0).abs().max()
        assert error <= ULPS * torch.finfo(expected.dtype).eps * scale, f"{where}: off by {float(error):.3g}"
    elif isinstance(expected, float):
        # the report's floats come from float32 tensors
        assert actual == pytest.approx(expected, rel=ULPS * torch.finfo(torch.float32).eps, nan_ok=True), where
    else:
        assert actual == expected, where


def test_geco_loss_keeps_every_number_and_gradient(reference, estimators):
    _assert_same(loss_numbers(estimators), reference["loss"], "loss")


def test_evaluate_video_keeps_every_number_and_map(reference):
    actual = evaluation_numbers()
    for kind, (report, _) in actual.items():
        # the one change of the report: the config names the new option, at its default
        assert report["config"].pop("movers") == "drop" and report["config"]["loss"].pop("movers") == "drop", kind
        assert "movers" not in report, kind
        # the models' native rates come from the registry, which has grown: the recorded ones stay
        rates, recorded = report["config"].pop("model_fps"), reference["evaluation"][kind][0]["config"]["model_fps"]
        assert {name: rates[name] for name in recorded} == recorded, kind
        report["config"]["model_fps"] = recorded
    _assert_same(actual, reference["evaluation"], "evaluation")


def test_the_default_renames_no_video():
    from geco_guide.generation import video_key
    from geco_guide.config import config_to_dict, load_config

    config = config_to_dict(load_config(preset="tiny"))
    assert config["guidance"]["loss"]["movers"] == "drop"
    before = {**config, "guidance": {**config["guidance"], "loss": {k: v for k, v in config["guidance"]["loss"].items()
                                                                    if k != "movers"}}}
    assert video_key(config, "a bust") == video_key(before, "a bust")  # as before the option existed
    rigid = {**config, "guidance": {**config["guidance"], "loss": {**config["guidance"]["loss"], "movers": "rigid"}}}
    assert video_key(rigid, "a bust") != video_key(config, "a bust")  # scoring movers makes other frames
