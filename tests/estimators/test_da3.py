"""Depth Anything 3 re-implementation: parity with the reference, checkpoint layout, the estimator API.

How the fixtures were made: the reference code (github.com/ByteDance-Seed/Depth-Anything-3 at
commit 2c21ea8, its ``src/depth_anything_3``) ran in a separate environment, never imported by
the package or these tests, with the weights of ``DA3.random(config, seed=0)`` copied into it
(key for key, under the published ``model.`` names; the reference's own modules we do not build,
its pose-conditioning encoder and its ray head's coarser levels, kept the reference's seeded
init). For each case it ran ``DepthAnything3Net`` on ImageNet-normalised images (the default
``saddle_balanced`` reference-view choice), the dual DPT head for the ray map and the camera
decoder for the pose encoding, and the gradient w.r.t. the ``[0, 1]`` images of
``log(depth).mean() + depth_conf.mean() + extrinsics.sum() + 0.01 * intrinsics.sum() +
ray.mean() + ray_conf.mean()``.

* ``da3_tiny.pt``: :meth:`DA3Config.tiny` (a reference ``DinoVisionTransformer`` / ``DualDPT`` /
  ``CameraDec`` of those sizes), the full state dict as a published file stores it (the ray
  head's shared LayerNorm once, under level 0), images ``[2, 3, 3, 42, 70]`` (three views: the
  reference view is chosen and the views reordered) and the same images' first two views.
* ``da3_small.pt``: the reference's own ``da3-small`` module sizes (its ``configs/da3-small.yaml``)
  with the weights of ``DA3.random(DA3Config.small(), seed=0)``, which the test regenerates;
  images ``[1, 3, 3, 42, 56]``; and the key names and shapes of the reference's DA3-SMALL and
  DA3-BASE state dicts.
* ``da3_base.pt``: the same for the reference's ``da3-base`` module sizes (its
  ``configs/da3-base.yaml``) with the weights of ``DA3.random(DA3Config.base(), seed=0)``, which
  the test regenerates; images ``[1, 3, 3, 42, 56]`` (another seed); the inputs and the outputs
  only, no weights.

Tolerance, as for the VGGT port: max |ours - reference| <= 1e-4 * max |reference| for every output
and for the gradient (measured: under 2.2e-6 relative on every fixture).
"""

from __future__ import annotations

import hashlib
from pathlib import Path

import pytest
import torch

from geco_guide.estimators.da3 import (
    DA3,
    IGNORED_CHECKPOINT_PREFIXES,
    DA3Config,
    network_size,
    restore_views,
    reorder_views,
)
from geco_guide.estimators.loading import CheckpointMismatchError
from geco_guide.types import GeometryEstimator

FIXTURES = Path(__file__).parents[1] / "fixtures"
FIXTURE_SHA256 = {
    "da3_tiny.pt": "ddbba2c9d026cd4e291c6c6ee88d5c0d0410b9e4a5a66be8cae0c3ce1994edd0",
    "da3_small.pt": "29a44bfd48aad26ae0afd1f57a25a0c67d17287347f8d5248619ff8c358220c5",
    "da3_base.pt": "71ed536c0e1a3167b08281a8dcc4a7abedb217a3f1934edee9d1788c160f20f0",
}
TOLERANCE = 1e-4


def _load(name: str) -> dict:
    return torch.load(FIXTURES / name, weights_only=False)


@pytest.fixture(scope="module")
def tiny_fixture() -> dict:
    return _load("da3_tiny.pt")


def _assert_parity(ours: torch.Tensor, ref: torch.Tensor, name: str) -> None:
    assert ours.shape == ref.shape, name
    err, scale = (ours - ref).abs().max().item(), ref.abs().max().item()
    assert err <= TOLERANCE * scale, f"{name}: max|diff| {err:.3g} > {TOLERANCE} * {scale:.3g}"


def _outputs_and_grad(model: DA3, images: torch.Tensor) -> dict[str, torch.Tensor]:
    """The fixture's outputs and the gradient of its scalar (see the module doc)."""
    x = images.clone().requires_grad_()
    out = model.forward_raw(x, rays=True)
    loss = (out["depth"].log().mean() + out["depth_conf"].mean() + out["extrinsic"].sum()
            + 1e-2 * out["intrinsic"].sum() + out["ray"].mean() + out["ray_conf"].mean())
    (out["grad"],) = torch.autograd.grad(loss, x)
    return out


# ---- parity with the reference ----------------------------------------------------------------


@pytest.mark.slow
@pytest.mark.parametrize("case", ["outputs", "two_view_outputs"])
def test_tiny_parity_outputs_rays_cameras_and_gradient(tiny_fixture: dict, case: str) -> None:
    model = DA3.from_state_dict(tiny_fixture["config"], tiny_fixture["state_dict"])
    images = tiny_fixture["inputs"]["images"]
    ours = _outputs_and_grad(model, images if case == "outputs" else images[:, :2])
    assert set(tiny_fixture[case]) == {"depth", "depth_conf", "extrinsic", "intrinsic", "pose_enc", "ray",
                                       "ray_conf", "grad"}
    for name, ref in tiny_fixture[case].items():
        _assert_parity(ours[name], ref, f"{case}.{name}")


@pytest.mark.slow
@pytest.mark.parametrize(("fixture_name", "published"), [("da3_small.pt", DA3Config.small()),
                                                         ("da3_base.pt", DA3Config.base())],
                         ids=["da3-small", "da3-base"])
def test_published_sizes_parity_with_regenerated_weights(fixture_name: str, published: DA3Config) -> None:
    fixture = _load(fixture_name)
    config = DA3Config.from_dict(fixture["config"])
    assert config == published
    model = DA3.random(config, seed=fixture["seed"])
    ours = _outputs_and_grad(model, fixture["inputs"]["images"])
    assert set(fixture["outputs"]) == {"depth", "depth_conf", "extrinsic", "intrinsic", "pose_enc", "ray",
                                       "ray_conf", "grad"}
    for name, ref in fixture["outputs"].items():
        _assert_parity(ours[name], ref, f"{fixture_name}.{name}")


@pytest.mark.parametrize("name", ["da3-small", "da3-base"])
def test_state_dict_is_the_reference_layout(name: str) -> None:
    reference = _load("da3_small.pt")["checkpoint_shapes"][name]
    expected = {k: v for k, v in reference.items() if not k.startswith(IGNORED_CHECKPOINT_PREFIXES)}
    with torch.device("meta"):
        model = DA3(DA3Config.small() if name == "da3-small" else DA3Config.base())
    assert {k: tuple(v.shape) for k, v in model.state_dict().items()} == expected


def test_fixtures_are_the_reference_files() -> None:
    for name, digest in FIXTURE_SHA256.items():
        assert hashlib.sha256((FIXTURES / name).read_bytes()).hexdigest() == digest, name


# ---- checkpoints and configs -------------------------------------------------------------------


def test_checkpoint_without_a_tensor_names_it(tiny_fixture: dict) -> None:
    state = dict(tiny_fixture["state_dict"])
    del state["model.cam_dec.fc_t.weight"]
    with pytest.raises(CheckpointMismatchError, match="missing 1: model.cam_dec.fc_t.weight"):
        DA3.from_state_dict(tiny_fixture["config"], state)


def test_save_and_load_round_trip(tmp_path: Path, tiny_fixture: dict) -> None:
    model = DA3.from_state_dict(tiny_fixture["config"], tiny_fixture["state_dict"])
    loaded = DA3.from_pretrained(model.save_pretrained(tmp_path / "da3"))
    assert loaded.config == model.config
    images = tiny_fixture["inputs"]["images"][:1, :2]
    with torch.no_grad():
        torch.testing.assert_close(loaded.forward_raw(images)["depth"], model.forward_raw(images)["depth"])


def test_published_config_json_is_read() -> None:
    published = {"model_name": "da3-base", "config": {
        "net": {"name": "vitb", "out_layers": [5, 7, 9, 11], "alt_start": 4, "qknorm_start": 4, "rope_start": 4,
                "cat_token": True},
        "head": {"dim_in": 1536, "output_dim": 2, "features": 128, "out_channels": [96, 192, 384, 768]}}}
    assert DA3Config.from_json(published) == DA3Config.base()
    assert DA3Config.from_json({"model_name": "da3-small"}) == DA3Config.small()
    with pytest.raises(ValueError, match="net 'vitg' is not supported"):
        DA3Config.from_json({"config": {"net": {"name": "vitg"}, "head": {}}})
    with pytest.raises(ValueError, match="ref_view_strategy"):
        DA3Config.from_dict({"ref_view_strategy": "last"})


# ---- estimator behaviour -----------------------------------------------------------------------


def test_network_size_follows_the_reference_resize() -> None:
    assert network_size(480, 832, 504) == (294, 504)  # 290.8 -> 291 -> 294 (nearer than 280)
    assert network_size(504, 504, 504) == (504, 504)
    assert network_size(30, 50, 70) == (42, 70)


def test_view_reordering_round_trips() -> None:
    x = torch.arange(2 * 4).reshape(2, 4, 1)
    ref_view = torch.tensor([2, 0])
    moved = reorder_views(x, ref_view)
    assert moved[:, :, 0].tolist() == [[2, 0, 1, 3], [4, 5, 6, 7]]
    assert torch.equal(restore_views(moved, ref_view), x)


def test_estimate_geometry_is_sane_and_differentiable() -> None:
    model = DA3.random(DA3Config.tiny(), seed=0)
    assert isinstance(model, GeometryEstimator)
    assert not model.training and not any(p.requires_grad for p in model.parameters())
    frames = torch.rand(1, 3, 3, 30, 50, generator=torch.Generator().manual_seed(1)).requires_grad_()
    geo = model.estimate_geometry(frames)
    assert geo.depth.shape == geo.confidence.shape == (1, 3, 30, 50)
    assert geo.intrinsics.shape == (1, 3, 3, 3) and geo.extrinsics.shape == (1, 3, 3, 4)
    assert (geo.depth > 0).all() and (geo.confidence >= 1).all()
    # K of the 42 x 70 network input, principal point at its centre, mapped to 30 x 50 pixels
    torch.testing.assert_close(geo.intrinsics[..., 0, 2], torch.full((1, 3), 24.5))
    torch.testing.assert_close(geo.intrinsics[..., 1, 2], torch.full((1, 3), 14.5))
    rotation = geo.extrinsics[..., :3]
    torch.testing.assert_close(rotation @ rotation.transpose(-1, -2), torch.eye(3).expand(1, 3, 3, 3),
                               atol=1e-5, rtol=0)
    (grad,) = torch.autograd.grad(geo.depth.mean() + geo.extrinsics.sum(), frames)
    assert torch.isfinite(grad).all() and grad.abs().sum() > 0


def test_gradient_checkpointing_keeps_the_gradient() -> None:
    model = DA3.random(DA3Config.tiny(), seed=0)
    frames = torch.rand(1, 3, 3, 28, 42, generator=torch.Generator().manual_seed(2))
    grads = []
    for checkpointed in (False, True):
        model.gradient_checkpointing = checkpointed
        x = frames.clone().requires_grad_()
        (grad,) = torch.autograd.grad(model.estimate_geometry(x).depth.mean(), x)
        grads.append(grad)
    torch.testing.assert_close(grads[0], grads[1])


def test_lifecycle_is_the_shared_one() -> None:
    from geco_guide.estimators.base import FrozenEstimator

    assert issubclass(DA3, FrozenEstimator)
    for name in ("random", "from_state_dict", "from_pretrained", "trunk_to", "gradient_checkpointing"):
        assert name not in vars(DA3), f"DA3 redefines {name}"
