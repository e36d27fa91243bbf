"""``movers="drop"`` (the default) leaves every number of GeCoLoss and evaluate_video as it was
before movers could be scored: the numbers of ``tests/fixtures/drop_reference.pt`` were computed
by the code before ``movers`` existed, on the same inputs (a moving scene with a deformation;
no, true and automatic masks; the oracle and the tiny estimators, the gradient included).

What is exact on every CPU is compared bit for bit: the integer and boolean tensors (masks,
validity maps, counts) and every non-float value of the reports. The float numbers depend on the
CPU's kernels: the fixture was written with one intra-op thread (more threads split the
reductions), and a CPU of another vector width (AVX2 or AVX-512 lanes, its BLAS) sums in
another order too. A float sum of ``n`` terms reordered moves by at most ``(n - 1) eps`` of the sum
of their magnitudes; the longest sums here are over a 24x32 frame (768 pixels), so the floats are
compared within :data:`ULPS` units in the last place of each tensor's largest magnitude: a bound
that holds on any CPU, and still a hundred times below what scoring the movers changes
(:func:`test_the_tolerance_tells_a_change_of_the_metric`). On the machine that wrote the fixture
the numbers are equal bit for bit.
"""

from __future__ import annotations

import pytest
import torch
from drop_reference import FIXTURE, evaluation_numbers, loss_numbers

#: Units in the last place allowed, relative to a tensor's largest magnitude: a reordered sum over
#: a frame's 768 pixels (see the module's docstring), rounded up to a power of two.
ULPS = 1024


@pytest.fixture(autouse=True)
def one_thread():
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(threads)


@pytest.fixture(scope="module")
def reference():
    return torch.load(FIXTURE, weights_only=False)


def _float_error(actual: torch.Tensor, expected: torch.Tensor) -> tuple[float, float]:
    """(the largest difference, the tolerance) of two float tensors, NaNs aside."""
    scale = expected.nan_to_num(0.0).abs().max().clamp_min(torch.finfo(expected.dtype).tiny)
    error = (actual - expected).nan_to_num(0.0).abs().max()
    return float(error), float(ULPS * torch.finfo(expected.dtype).eps * scale)


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
        error, tolerance = _float_error(actual, expected)
        assert error <= tolerance, f"{where}: off by {error:.3g} where {tolerance:.3g} is allowed"
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
        # the one change of the report: the config names the new option, at its default, in the loss
        assert "movers" not in report["config"] and report["config"]["loss"].pop("movers") == "drop", kind
        assert "movers" not in report, kind
        # the models' native rates come from the registry, which has grown: the recorded ones stay
        rates, recorded = report["config"].pop("model_fps"), reference["evaluation"][kind][0]["config"]["model_fps"]
        assert {name: rates[name] for name in recorded} == recorded, kind
        report["config"]["model_fps"] = recorded
    _assert_same(actual, reference["evaluation"], "evaluation")


def test_the_tolerance_tells_a_change_of_the_metric(reference):
    """Scoring the movers (``movers="rigid"``) on the same inputs moves the losses and maps by far
    more than the tolerance: the comparisons above would see a change of what is computed."""
    from drop_reference import reference_clip

    from geco_guide.estimators.bundle import Estimators
    from geco_guide.estimators.oracle import OracleFlow, OracleGeometry
    from geco_guide.loss.geco import GeCoLoss, GeCoLossConfig

    clip = reference_clip()
    loss = GeCoLoss(Estimators(OracleGeometry(clip), OracleFlow(clip)), GeCoLossConfig(movers="rigid"))
    rigid = loss(clip.frames.float()[None], dynamic_masks=clip.dynamic_mask)
    expected = reference["loss"]["oracle/default/true"]
    for name in ("loss", "pair_maps.fused"):
        actual = rigid.loss if name == "loss" else rigid.pair_maps.fused
        error, tolerance = _float_error(actual.detach(), expected[name])
        assert error > 100 * tolerance, name


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
