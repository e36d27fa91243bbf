"""VGGT re-implementation: fixture parity, checkpoint layout, preprocessing and the estimator API."""

from __future__ import annotations

import hashlib
from pathlib import Path

import pytest
import torch

from geco_guide.estimators.loading import CheckpointMismatchError, WeightsNotFoundError
from geco_guide.estimators.vggt import (
    VGGT,
    PreprocessPlan,
    VGGTConfig,
    plan_preprocess,
    unmap_intrinsics,
)
from geco_guide.estimators.vit import imagenet_normalise
from geco_guide.types import GeometryEstimator

OUTPUT_NAMES = ("depth", "depth_conf", "pose_enc", "extrinsic", "intrinsic")


@pytest.fixture(scope="module")
def fixture(vggt_fixture) -> dict:
    return vggt_fixture


@pytest.fixture(scope="module")
def tiny() -> VGGT:
    return VGGT.random(VGGTConfig.tiny(), seed=0)


def _assert_parity(ours: torch.Tensor, ref: torch.Tensor, name: str) -> None:
    assert ours.shape == ref.shape, name
    err, scale = (ours - ref).abs().max().item(), ref.abs().max().item()
    assert err <= 1e-4 * scale, f"{name}: max|diff| {err:.3g} > 1e-4 * {scale:.3g}"


# ---- parity with the reference ----------------------------------------------------------------


def test_fixture_parity_outputs_and_debug(fixture: dict) -> None:
    model = VGGT.from_state_dict(fixture["config"], fixture["state_dict"])
    images = fixture["inputs"]["images"]
    debug = fixture["debug"]
    with torch.no_grad():
        out = model.forward_raw(images)
        dino_tokens = model.aggregator.patch_embed(imagenet_normalise(images.flatten(0, 1)))
        tokens = model.aggregator(images)
        iterations = model.camera_head(tokens[model.config.aggregator.depth - 1][:, :, 0])
    for name in OUTPUT_NAMES:
        _assert_parity(out[name], fixture["outputs"][name], name)
    assert model.aggregator.patch_start_idx == debug["patch_start_idx"]
    _assert_parity(dino_tokens, debug["dino_patch_tokens"], "dino_patch_tokens")
    assert set(tokens) == set(debug["aggregated_tokens"])
    for layer, ref in debug["aggregated_tokens"].items():
        _assert_parity(tokens[layer], ref, f"aggregated_tokens[{layer}]")
    _assert_parity(torch.stack(iterations), debug["pose_enc_iterations"], "pose_enc_iterations")


def test_four_dim_input_is_one_batch(fixture: dict) -> None:
    model = VGGT.from_state_dict(fixture["config"], fixture["state_dict"])
    with torch.no_grad():
        out = model.forward_raw(fixture["inputs"]["images"][0])
    _assert_parity(out["depth"], fixture["outputs"]["depth"], "depth")


def test_preprocess_cases_round_half_to_even(fixture: dict) -> None:
    for case in fixture["preprocess"]["cases"]:
        height, width = case["input_uint8_hwc"].shape[:2]
        plan = plan_preprocess(height, width, target_width=518, patch_size=14)
        assert plan.resized_hw == tuple(case["resized_hw"])
        assert plan.crop_top == case["crop_top"]
        assert plan.network_hw == tuple(case["output_uint8_chw"].shape[1:])


# ---- checkpoint layout -------------------------------------------------------------------------


def _spec_vggt1b_keys() -> dict[str, tuple[int, ...]]:
    """Key names and shapes of facebook/VGGT-1B (spec 3.6), minus point/track heads and mask_token."""
    c, d = 1024, 2048
    keys: dict[str, tuple[int, ...]] = {
        "aggregator.camera_token": (1, 2, 1, c),
        "aggregator.register_token": (1, 2, 4, c),
        "aggregator.patch_embed.cls_token": (1, 1, c),
        "aggregator.patch_embed.pos_embed": (1, 1370, c),
        "aggregator.patch_embed.register_tokens": (1, 4, c),
        "aggregator.patch_embed.patch_embed.proj.weight": (c, 3, 14, 14),
        "aggregator.patch_embed.patch_embed.proj.bias": (c,),
        "aggregator.patch_embed.norm.weight": (c,),
        "aggregator.patch_embed.norm.bias": (c,),
    }

    def block(prefix: str, dim: int, qk_norm_dim: int | None) -> None:
        for name in ("norm1", "norm2"):
            keys[f"{prefix}.{name}.weight"] = keys[f"{prefix}.{name}.bias"] = (dim,)
        keys[f"{prefix}.ls1.gamma"] = keys[f"{prefix}.ls2.gamma"] = (dim,)
        keys[f"{prefix}.attn.qkv.weight"], keys[f"{prefix}.attn.qkv.bias"] = (3 * dim, dim), (3 * dim,)
        keys[f"{prefix}.attn.proj.weight"], keys[f"{prefix}.attn.proj.bias"] = (dim, dim), (dim,)
        keys[f"{prefix}.mlp.fc1.weight"], keys[f"{prefix}.mlp.fc1.bias"] = (4 * dim, dim), (4 * dim,)
        keys[f"{prefix}.mlp.fc2.weight"], keys[f"{prefix}.mlp.fc2.bias"] = (dim, 4 * dim), (dim,)
        if qk_norm_dim:
            for name in ("q_norm", "k_norm"):
                keys[f"{prefix}.attn.{name}.weight"] = keys[f"{prefix}.attn.{name}.bias"] = (qk_norm_dim,)

    for i in range(24):
        block(f"aggregator.patch_embed.blocks.{i}", c, None)
        block(f"aggregator.frame_blocks.{i}", c, 64)
        block(f"aggregator.global_blocks.{i}", c, 64)
    for i in range(4):
        block(f"camera_head.trunk.{i}", d, None)
    keys.update({
        "camera_head.empty_pose_tokens": (1, 1, 9),
        "camera_head.token_norm.weight": (d,), "camera_head.token_norm.bias": (d,),
        "camera_head.trunk_norm.weight": (d,), "camera_head.trunk_norm.bias": (d,),
        "camera_head.embed_pose.weight": (d, 9), "camera_head.embed_pose.bias": (d,),
        "camera_head.poseLN_modulation.1.weight": (3 * d, d), "camera_head.poseLN_modulation.1.bias": (3 * d,),
        "camera_head.pose_branch.fc1.weight": (1024, d), "camera_head.pose_branch.fc1.bias": (1024,),
        "camera_head.pose_branch.fc2.weight": (9, 1024), "camera_head.pose_branch.fc2.bias": (9,),
        "depth_head.norm.weight": (d,), "depth_head.norm.bias": (d,),
        "depth_head.resize_layers.0.weight": (256, 256, 4, 4), "depth_head.resize_layers.0.bias": (256,),
        "depth_head.resize_layers.1.weight": (512, 512, 2, 2), "depth_head.resize_layers.1.bias": (512,),
        "depth_head.resize_layers.3.weight": (1024, 1024, 3, 3), "depth_head.resize_layers.3.bias": (1024,),
        "depth_head.scratch.output_conv1.weight": (128, 256, 3, 3), "depth_head.scratch.output_conv1.bias": (128,),
        "depth_head.scratch.output_conv2.0.weight": (32, 128, 3, 3), "depth_head.scratch.output_conv2.0.bias": (32,),
        "depth_head.scratch.output_conv2.2.weight": (2, 32, 1, 1), "depth_head.scratch.output_conv2.2.bias": (2,),
    })
    for k, ch in enumerate((256, 512, 1024, 1024)):
        keys[f"depth_head.projects.{k}.weight"], keys[f"depth_head.projects.{k}.bias"] = (ch, d, 1, 1), (ch,)
        keys[f"depth_head.scratch.layer{k + 1}_rn.weight"] = (256, ch, 3, 3)
    for k in range(1, 5):
        prefix = f"depth_head.scratch.refinenet{k}"
        keys[f"{prefix}.out_conv.weight"], keys[f"{prefix}.out_conv.bias"] = (256, 256, 1, 1), (256,)
        for unit in ("resConfUnit1", "resConfUnit2") if k != 4 else ("resConfUnit2",):
            for conv in ("conv1", "conv2"):
                keys[f"{prefix}.{unit}.{conv}.weight"], keys[f"{prefix}.{unit}.{conv}.bias"] = (256, 256, 3, 3), (256,)
    return keys


def test_full_size_state_dict_matches_checkpoint_layout() -> None:
    # We do not build the unused DINO mask token: 1341 checkpoint tensors - 1 = 1340.
    expected = _spec_vggt1b_keys()
    assert len(expected) == 1340
    with torch.device("meta"):
        model = VGGT()  # None = VGGT-1B
    assert model.config == VGGTConfig()
    ours = {k: tuple(v.shape) for k, v in model.state_dict().items()}
    assert ours == expected


def test_config_round_trip_and_fixture_config(fixture: dict) -> None:
    config = VGGTConfig.from_dict(fixture["config"])
    assert config == VGGTConfig.tiny()
    assert VGGTConfig.from_dict(config.to_dict()) == config
    assert VGGTConfig.from_dict({}) == VGGTConfig()
    with pytest.raises(ValueError, match="unknown"):
        VGGTConfig.from_dict({"dino": {"depht": 3}})


# ---- estimator behaviour -----------------------------------------------------------------------


def test_random_tiny_model_is_sane_frozen_and_differentiable(tiny: VGGT) -> None:
    assert isinstance(tiny, GeometryEstimator)
    assert not tiny.training and not any(p.requires_grad for p in tiny.parameters())
    frames = torch.rand(1, 3, 3, 48, 72, generator=torch.Generator().manual_seed(1)).requires_grad_()
    geo = tiny.estimate_geometry(frames)
    assert geo.depth.shape == geo.confidence.shape == (1, 3, 48, 72)
    assert geo.intrinsics.shape == (1, 3, 3, 3) and geo.extrinsics.shape == (1, 3, 3, 4)
    assert torch.isfinite(geo.depth).all() and (geo.depth > 0.1).all() and (geo.depth < 10).all()
    assert (geo.confidence >= 1).all()
    fov_x = 2 * torch.atan(36.0 / geo.intrinsics[..., 0, 0])
    assert ((fov_x > 0.5) & (fov_x < 1.5)).all()
    rotation = geo.extrinsics[..., :3]
    torch.testing.assert_close(rotation @ rotation.transpose(-1, -2), torch.eye(3).expand(1, 3, 3, 3),
                               atol=1e-4, rtol=0)
    loss = geo.depth.mean() + geo.intrinsics[..., 0, 0].mean() + geo.extrinsics.square().sum()
    loss.backward()
    assert frames.grad is not None and torch.isfinite(frames.grad).all() and frames.grad.abs().sum() > 0


def test_batch_elements_are_independent(tiny: VGGT) -> None:
    frames = torch.rand(2, 3, 3, 28, 42, generator=torch.Generator().manual_seed(6))
    with torch.no_grad():
        both = tiny.forward_raw(frames)
        second = tiny.forward_raw(frames[1:])
    for name in OUTPUT_NAMES:
        torch.testing.assert_close(both[name][1:], second[name], atol=1e-5, rtol=1e-5)


def test_random_is_seeded() -> None:
    rng_state = torch.get_rng_state()
    a, b = VGGT.random(VGGTConfig.tiny(), seed=3), VGGT.random(VGGTConfig.tiny(), seed=3)
    c = VGGT.random(VGGTConfig.tiny(), seed=4)
    assert torch.equal(torch.get_rng_state(), rng_state)
    for (name, pa), pb, pc in zip(a.state_dict().items(), b.state_dict().values(), c.state_dict().values()):
        assert torch.equal(pa, pb), name
    assert not torch.equal(a.aggregator.camera_token, c.aggregator.camera_token)


def test_landscape_geometry_maps_back_without_crop(tiny: VGGT) -> None:
    frames = torch.rand(1, 2, 3, 48, 72, generator=torch.Generator().manual_seed(2))
    plan = plan_preprocess(48, 72, target_width=70)  # 48*70/72/14 = 3.33 -> 42 rows, no crop
    assert plan == PreprocessPlan((48, 72), (42, 70), 0, (42, 70))
    with torch.no_grad():
        geo = tiny.estimate_geometry(frames)
        raw = tiny.forward_raw(torch.nn.functional.interpolate(frames[0], size=(42, 70), mode="bilinear"))
    k, k_net = geo.intrinsics[0], raw["intrinsic"][0]
    # Integer pixel centres: the principal point lands on the input's centre pixel.
    torch.testing.assert_close(k[:, 0, 2], torch.full((2,), 35.5))
    torch.testing.assert_close(k[:, 1, 2], torch.full((2,), 23.5))
    torch.testing.assert_close(k[:, 0, 0], k_net[:, 0, 0] * 72 / 70)
    torch.testing.assert_close(k[:, 1, 1], k_net[:, 1, 1] * 48 / 42)
    torch.testing.assert_close(geo.extrinsics[0], raw["extrinsic"][0])


def test_portrait_geometry_uncrops_rows(tiny: VGGT) -> None:
    frames = torch.rand(1, 2, 3, 72, 40, generator=torch.Generator().manual_seed(3))
    plan = plan_preprocess(72, 40, target_width=70)  # 72*70/40/14 = 9 -> 126 rows, crop 28
    assert plan == PreprocessPlan((72, 40), (126, 70), 28, (70, 70))
    with torch.no_grad():
        geo = tiny.estimate_geometry(frames)
    assert geo.depth.shape == geo.confidence.shape == (1, 2, 72, 40)
    k = geo.intrinsics[0]
    torch.testing.assert_close(k[:, 0, 2], torch.full((2,), 19.5))
    torch.testing.assert_close(k[:, 1, 2], torch.full((2,), 35.5))
    # Rows cut by the crop (input rows < 28*72/126 = 16 and >= 56) carry zero confidence.
    assert (geo.confidence[..., :15, :] == 0).all() and (geo.confidence[..., 57:, :] == 0).all()
    assert (geo.confidence[..., 17:55, :] >= 1).all()
    assert torch.isfinite(geo.depth).all() and (geo.depth > 0).all()


@pytest.mark.parametrize(
    ("input_hw", "resized_hw", "top"), [((480, 720), (350, 518), 0), ((720, 480), (784, 518), 133)]
)
def test_spec_worked_examples_of_intrinsics_mapping(input_hw, resized_hw, top) -> None:
    plan = plan_preprocess(*input_hw)
    assert plan.resized_hw == resized_hw and plan.crop_top == top
    hm, wm = plan.network_hw
    fx_m, fy_m = 400.0, 300.0
    k_net = torch.tensor([[fx_m, 0.0, wm / 2], [0.0, fy_m, hm / 2], [0.0, 0.0, 1.0]])
    k = unmap_intrinsics(k_net, plan)
    h0, w0 = input_hw
    # Spec 3.1 in the continuous convention (cx0 = W0/2, ...), shifted to integer centres.
    expected = torch.tensor([
        [fx_m * w0 / wm, 0.0, w0 / 2 - 0.5],
        [0.0, fy_m * h0 / resized_hw[0], h0 / 2 - 0.5],
        [0.0, 0.0, 1.0],
    ])
    torch.testing.assert_close(k, expected)


def test_checkpointing_and_bf16_autocast(tiny: VGGT) -> None:
    frames = torch.rand(1, 2, 3, 28, 42, generator=torch.Generator().manual_seed(4))
    x = frames.clone().requires_grad_()
    ref = tiny.forward_raw(x)
    (g_ref,) = torch.autograd.grad(ref["depth"].sum() + ref["pose_enc"].sum(), x)
    tiny.gradient_checkpointing = True
    try:
        out = tiny.forward_raw(x)
        (g_ckpt,) = torch.autograd.grad(out["depth"].sum() + out["pose_enc"].sum(), x)
    finally:
        tiny.gradient_checkpointing = False
    torch.testing.assert_close(out["depth"], ref["depth"])
    torch.testing.assert_close(g_ckpt, g_ref)
    tiny.autocast_dtype = torch.bfloat16
    try:
        with torch.no_grad():
            low = tiny.forward_raw(frames)
    finally:
        tiny.autocast_dtype = None
    assert all(low[name].dtype == torch.float32 for name in OUTPUT_NAMES)
    torch.testing.assert_close(low["depth"], ref["depth"].detach(), atol=0.05, rtol=0.05)


# ---- loading -----------------------------------------------------------------------------------


def test_from_pretrained_local_folder_and_errors(tmp_path: Path, tiny: VGGT, monkeypatch) -> None:
    from safetensors.torch import save_file

    state = {k: v.contiguous() for k, v in tiny.state_dict().items()}
    good = tmp_path / "good"
    good.mkdir()
    save_file(state, str(good / "model.safetensors"))
    loaded = VGGT.from_pretrained(good, config=VGGTConfig.tiny())
    frames = torch.rand(1, 2, 3, 28, 42, generator=torch.Generator().manual_seed(5))
    with torch.no_grad():
        torch.testing.assert_close(loaded.forward_raw(frames)["depth"], tiny.forward_raw(frames)["depth"])
    assert not any(p.requires_grad for p in loaded.parameters())

    bad = tmp_path / "bad"
    bad.mkdir()
    broken = dict(state)
    del broken["camera_head.embed_pose.bias"]
    broken["depth_head.norm.weight"] = torch.zeros(3)
    save_file(broken, str(bad / "model.safetensors"))
    with pytest.raises(CheckpointMismatchError, match="camera_head.embed_pose.bias") as err:
        VGGT.from_pretrained(bad, config=VGGTConfig.tiny())
    assert "depth_head.norm.weight" in str(err.value)

    import huggingface_hub.constants

    monkeypatch.setenv("HF_HUB_OFFLINE", "1")
    monkeypatch.setattr(huggingface_hub.constants, "HF_HUB_OFFLINE", True)
    with pytest.raises(WeightsNotFoundError) as err:
        VGGT.from_pretrained("geco-guide-tests/no-such-vggt", cache_dir=tmp_path / "hub")
    message = str(err.value)
    assert "\n" not in message and "geco-guide-tests/no-such-vggt" in message


@pytest.mark.parametrize("change, message", [
    ({"patch_size": "abc"}, "patch_size = 'abc': must be an integer >= 1"),
    ({"patch_size": 0}, "patch_size = 0: must be an integer >= 1"),
    ({"img_size": 70.5}, "img_size = 70.5: must be an integer >= 1"),
    ({"img_size": 72}, "img_size = 72: must be a multiple of patch_size 14"),
    ({"embed_dim": -4}, "embed_dim = -4: must be an integer >= 1"),
    ({"aggregator": {"depth": 3}}, "depth_head.intermediate_layer_idx = (0, 2, 3, 4): must index the aggregator's 3"),
    ({"aggregator": {"num_heads": 5}}, "aggregator.num_heads = 5: must divide the width 64"),
    ({"aggregator": {"rope_freq": float("nan")}}, "aggregator.rope_freq = nan: must be a finite number > 0"),
    ({"depth_head": {"out_channels": [16, 24, 32]}}, "depth_head.out_channels = (16, 24, 32): must be 4 integers"),
    ({"upstream": {"patch_size": "abc"}}, "patch_size = 'abc': must be an integer >= 1"),  # the hub's schema
])
def test_config_json_values_are_checked_in_one_line_naming_the_file(tmp_path: Path, tiny: VGGT, change, message):
    import json

    folder = tiny.save_pretrained(tmp_path / "vggt")
    config = tiny.config.to_dict()
    if "upstream" in change:
        config = {"img_size": 518, "patch_size": 14, "embed_dim": 1024, **change["upstream"]}
    for key, value in change.items():
        if key != "upstream":
            config[key] = {**config[key], **value} if isinstance(value, dict) else value
    (folder / "config.json").write_text(json.dumps(config))
    with pytest.raises(CheckpointMismatchError) as err:
        VGGT.from_pretrained(folder)
    text = str(err.value)
    assert text.startswith(f"VGGT: '{folder / 'config.json'}' is not a readable VGGT config.json (VGGT config field ")
    assert message in text and "\n" not in text


def test_trunk_to_bfloat16_keeps_heads_and_outputs_float32() -> None:
    model = VGGT.random(VGGTConfig.tiny(), seed=0)
    frames = torch.rand(1, 2, 3, 28, 42, generator=torch.Generator().manual_seed(0), requires_grad=True)
    ref = model.estimate_geometry(frames)
    assert model.trunk_to(torch.bfloat16) is model
    assert {p.dtype for p in model.aggregator.parameters()} == {torch.bfloat16}
    assert {p.dtype for n, p in model.named_parameters() if not n.startswith("aggregator.")} == {torch.float32}
    low = model.estimate_geometry(frames)
    for name in ("depth", "confidence", "intrinsics", "extrinsics"):
        assert getattr(low, name).dtype == torch.float32, name
    torch.testing.assert_close(low.depth, ref.depth, atol=0.05, rtol=0.05)
    (grad,) = torch.autograd.grad(low.depth.mean(), frames)
    assert torch.isfinite(grad).all() and grad.abs().sum() > 0


# The parity fixtures' contents: a fixture edited by accident (re-saved, regenerated) fails here
# instead of silently moving the reference the parity tests compare against.
FIXTURE_SHA256 = {
    "vggt_tiny.pt": "d7259dc6cfd6591aad1b7e3987ce1a2136fa4521f2c80def364c3c0e426367b0",
    "ufm_tiny.pt": "399a2898cded3fbb1433fdff10fab74843d5b59e113570f44ff54189578b56f5",
    "tiny_decoder.pt": "9722e3bc1c7fdec6fe94ef292b2d0d59b3890e9cf491bb774df06512b535325a",
}


def test_parity_fixtures_are_the_reference_files():
    for name, digest in FIXTURE_SHA256.items():
        assert hashlib.sha256((Path(__file__).parents[1] / "fixtures" / name).read_bytes()).hexdigest() == digest, name


def test_lifecycle_and_pose_decode_live_in_one_place() -> None:
    """VGGT and UFM share FrozenEstimator's construction, loading, trunk dtype and checkpointing;
    the pose-encoding decode is camera math in geco_guide.geometry."""
    from geco_guide import geometry
    from geco_guide.estimators import vggt
    from geco_guide.estimators.base import FrozenEstimator
    from geco_guide.estimators.ufm import UFM

    for cls in (VGGT, UFM):
        assert issubclass(cls, FrozenEstimator)
        for name in ("random", "from_state_dict", "from_pretrained", "trunk_to", "gradient_checkpointing"):
            assert name not in vars(cls), f"{cls.__name__} redefines {name}"
    assert vggt.pose_encoding_to_cameras is geometry.pose_encoding_to_cameras
