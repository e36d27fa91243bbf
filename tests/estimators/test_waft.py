"""WAFT: parity with the reference implementation, checkpoint layout and loading, the flow
protocol with forward-backward covisibility, differentiability.

The fixture ``tests/fixtures/waft_tiny.pt`` was made by running the authors' code (``ViTWarpV8``
of ``princeton-vl/WAFT``, commit 8dd4172, with timm 1.0.31 and torch 2.13 on CPU) outside this
repository, at a tiny size of the same structure (:meth:`WAFTConfig.tiny`: DINOv2 and refinement
ViTs of width 32, depth 12 and 2 heads, DPT heads of widths 16 and 32, ResNet-18 stages of widths 8-32,
3 iterations), with every parameter and batch-norm statistic drawn at random (seeded), on two
random 64 x 80 image pairs (given to it as 0-255 values). It holds the state dict, the frames,
the final flow and uncertainty (``info``) upsampled to full resolution, and the gradient of
``sum(flow * flow_weights) + sum(info * info_weights)`` with respect to both frames.

Tolerance, as for UFM: ``max|ours - ref| <= 1e-4 * max|ref|``, for the outputs and the gradients
(measured: about 1e-6 relative). The same comparison at the published sizes (random weights,
5 iterations) was run once when porting; its state dict (64 M parameters) is too large to ship.
"""

from __future__ import annotations

import json
from pathlib import Path

import pytest
import torch

from geco_guide.estimators.loading import CheckpointMismatchError, WeightsNotFoundError
from geco_guide.estimators.waft import WAFT, WAFTConfig, forward_backward_covisibility
from geco_guide.types import FlowEstimator, OptionError

FIXTURE = Path(__file__).resolve().parents[1] / "fixtures" / "waft_tiny.pt"


def assert_close(ours: torch.Tensor, ref: torch.Tensor, name: str) -> None:
    """``max|ours - ref| <= 1e-4 * max|ref|``."""
    assert ours.shape == ref.shape, f"{name}: shape {tuple(ours.shape)} vs {tuple(ref.shape)}"
    err = (ours.detach().float() - ref.float()).abs().max().item()
    bound = 1e-4 * ref.abs().max().item()
    assert err <= bound, f"{name}: max|diff| {err:.3g} > {bound:.3g}"


@pytest.fixture(scope="module")
def fx() -> dict:
    return torch.load(FIXTURE, weights_only=True)


@pytest.fixture(scope="module")
def tiny() -> WAFT:
    return WAFT.random(WAFTConfig.tiny(), seed=0)


@pytest.mark.slow
def test_parity_with_reference(fx: dict) -> None:
    model = WAFT.from_state_dict(WAFTConfig.tiny(), fx["state_dict"])
    source = fx["source"].clone().requires_grad_(True)
    target = fx["target"].clone().requires_grad_(True)
    out = model(source, target, iters=fx["iters"])
    assert_close(out["flow"], fx["flow"], "flow")
    assert_close(out["info"], fx["info"], "info")
    ((out["flow"] * fx["flow_weights"]).sum() + (out["info"] * fx["info_weights"]).sum()).backward()
    assert_close(source.grad, fx["grad_source"], "grad source")
    assert_close(target.grad, fx["grad_target"], "grad target")
    # the fixture's flows are large enough that the warps sample between pixels
    assert fx["flow"].abs().mean() > 1.0


@pytest.mark.slow
def test_checkpoint_keys_are_the_reference_keys(fx: dict) -> None:
    model = WAFT.random(WAFTConfig.tiny())
    assert set(model.state_dict()) == set(fx["state_dict"])
    partial = {k: v for k, v in fx["state_dict"].items() if not k.startswith("flow_head.")}
    with pytest.raises(CheckpointMismatchError, match="missing 4: flow_head"):
        WAFT.from_state_dict(WAFTConfig.tiny(), partial)


def test_published_architecture_sizes() -> None:
    """The parameter counts of the reference model at its published sizes (Depth Anything V2
    Small, a ViT-S refiner on 8-pixel patches, ResNet-18 stages): 64.1 M in all."""
    with torch.device("meta"):
        model = WAFT()
    counts = {name: sum(p.numel() for p in getattr(model, name).parameters())
              for name in ("da_feature", "refine_net", "fnet")}
    assert counts == {"da_feature": 24_785_089, "refine_net": 25_619_905, "fnet": 13_553_792}
    assert sum(p.numel() for p in model.parameters()) == 64_145_068


@pytest.mark.slow
def test_save_pretrained_round_trip(tmp_path, tiny: WAFT) -> None:
    folder = tiny.save_pretrained(tmp_path / "waft")
    assert json.loads((folder / "config.json").read_text())["architecture"] == "waft"
    loaded = WAFT.from_pretrained(folder)
    frames = torch.rand(2, 1, 3, 40, 56, generator=torch.Generator().manual_seed(3))
    with torch.no_grad():
        assert torch.equal(loaded(frames[0], frames[1])["flow"], tiny(frames[0], frames[1])["flow"])


def test_missing_weights_one_line(tmp_path) -> None:
    with pytest.raises(WeightsNotFoundError) as err:
        WAFT.from_pretrained(tmp_path)
    assert "\n" not in str(err.value) and "WAFT" in str(err.value)


def test_config_round_trip_and_refusals() -> None:
    config = WAFTConfig.tiny()
    assert WAFTConfig.from_dict(json.loads(json.dumps(config.to_dict()))) == config
    with pytest.raises(OptionError, match="pad_factor"):
        WAFTConfig.from_dict({"pad_factor": 100})
    with pytest.raises(OptionError, match="architecture"):
        WAFTConfig.from_dict({"architecture": "ufm"})


@pytest.mark.slow
def test_estimate_flow_protocol_and_gradients(tiny: WAFT) -> None:
    assert isinstance(tiny, FlowEstimator)
    assert not tiny.training and not any(p.requires_grad for p in tiny.parameters())
    generator = torch.Generator().manual_seed(1)
    source = torch.rand(2, 3, 36, 52, generator=generator, requires_grad=True)
    target = torch.rand(2, 3, 36, 52, generator=generator, requires_grad=True)
    corr = tiny.estimate_flow(source, target)
    assert corr.flow.shape == (2, 2, 36, 52) and corr.covisibility.shape == (2, 36, 52)
    assert set(corr.covisibility.unique().tolist()) <= {0.0, 1.0}
    with torch.no_grad():
        direct = tiny(source, target)["flow"]
    torch.testing.assert_close(corr.flow.detach(), direct, atol=1e-5, rtol=1e-5)
    corr.flow.square().mean().backward()
    for x in (source, target):
        assert x.grad is not None and torch.isfinite(x.grad).all() and x.grad.abs().sum() > 0
    assert all(p.grad is None for p in tiny.parameters())
    with pytest.raises(ValueError, match="shapes differ"):
        tiny.estimate_flow(source[:, :, :30], target)


def test_forward_backward_covisibility() -> None:
    forward = torch.zeros(1, 2, 6, 8)
    forward[:, 0] = 2.0  # every pixel moves two columns right
    covisible = forward_backward_covisibility(forward, -forward, 0.01, 0.5)
    assert covisible[0, :, :6].eq(1).all() and covisible[0, :, 6:].eq(0).all()  # the last two leave the image
    assert forward_backward_covisibility(forward, forward, 0.01, 0.5).eq(0).all()  # backward does not cancel
    small = forward_backward_covisibility(forward, -forward + 0.3, 0.01, 0.5)  # residual |(0.3, 0.3)|^2 = 0.18 < 0.5
    assert small[0, :, :6].eq(1).all()


# ---------------------------------------------------------------------------------------------
# Selection through estimators.flow
# ---------------------------------------------------------------------------------------------


def test_flow_architecture_and_source(tmp_path, tiny: WAFT) -> None:
    from geco_guide.estimators import flow_architecture, flow_source

    assert flow_architecture("infinity1096/UFM-Base") == flow_architecture("ufm-base") == "ufm"
    assert flow_source("ufm-base") == "infinity1096/UFM-Base" and flow_source("waft") == WAFT.default_repo_id
    assert flow_architecture("waft") == flow_architecture("tiny-random-waft") == "waft"
    assert flow_architecture("waft:/weights/tar-c-t.pth") == "waft" and flow_source("waft:/w/a.pth") == "/w/a.pth"
    assert flow_architecture(str(tiny.save_pretrained(tmp_path / "saved"))) == "waft"  # its config.json says so
    assert flow_architecture(str(tmp_path / "missing")) == "ufm"
    with pytest.raises(OptionError, match="estimators.flow"):
        flow_source("waft:")


@pytest.mark.slow
def test_tiny_random_waft_loads_as_the_flow_estimator() -> None:
    from geco_guide.estimators import EstimatorsConfig, estimator_weight_sources, load_estimators

    config = EstimatorsConfig(geometry="tiny-random", flow="tiny-random-waft", dtype="float32", init_seed=2)
    assert estimator_weight_sources(config) == []
    estimators = load_estimators(config, "cpu")
    assert isinstance(estimators.flow, WAFT) and estimators.ids()["flow"] == "tiny-random-waft(seed=2)"
    frames = torch.rand(2, 3, 40, 56, generator=torch.Generator().manual_seed(0))
    with torch.no_grad():
        corr = estimators.flow.estimate_flow(frames[:1], frames[1:])
    # small random flows: most pixels pass the forward-backward test, as with the tiny UFM
    assert 0.5 < corr.covisibility.mean().item() < 1.0


def test_waft_offline_without_weights_is_one_line(tmp_path, monkeypatch: pytest.MonkeyPatch) -> None:
    import huggingface_hub.constants

    from geco_guide.estimators import EstimatorsConfig, check_weights, load_estimators

    monkeypatch.setenv("HF_HUB_OFFLINE", "1")
    monkeypatch.setattr(huggingface_hub.constants, "HF_HUB_OFFLINE", True)
    monkeypatch.setattr(huggingface_hub.constants, "HF_HUB_CACHE", str(tmp_path))
    config = EstimatorsConfig(geometry="tiny-random", flow="waft", dtype="float32")
    for call in (lambda: check_weights(config), lambda: load_estimators(config, "cpu")):
        with pytest.raises(WeightsNotFoundError) as err:
            call()
        message = str(err.value)
        assert "\n" not in message and WAFT.default_repo_id in message
        assert "estimators.flow=waft:/path/to/WAFT" in message


@pytest.mark.slow
def test_bfloat16_trunk_and_autocast_stay_close(tiny: WAFT) -> None:
    frames = torch.rand(2, 3, 40, 56, generator=torch.Generator().manual_seed(5))
    with torch.no_grad():
        plain = tiny(frames[:1], frames[1:])["flow"]
        stored = WAFT.random(WAFTConfig.tiny(), seed=0).trunk_to(torch.bfloat16)(frames[:1], frames[1:])["flow"]
        autocast = WAFT.random(WAFTConfig.tiny(), seed=0, autocast_dtype=torch.bfloat16)(frames[:1], frames[1:])["flow"]
    assert stored.dtype == autocast.dtype == torch.float32
    for low in (stored, autocast):
        torch.testing.assert_close(low, plain, atol=0.05 * plain.abs().max().item(), rtol=0.05)
