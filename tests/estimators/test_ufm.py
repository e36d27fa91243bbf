"""UFM: parity with the reference fixture, checkpoint layout and loading, differentiability."""

from __future__ import annotations

import copy
import json
from pathlib import Path

import pytest
import torch

from geco_guide.estimators.loading import CheckpointMismatchError, WeightsNotFoundError
from geco_guide.estimators.ufm import (
    UFM,
    UFMConfig,
    choose_resolution,
    region_size,
    sinusoid_view_table,
)
from geco_guide.types import FlowEstimator


@pytest.fixture(scope="module")
def fx(ufm_fixture) -> dict:
    return ufm_fixture


@pytest.fixture(scope="module")
def tiny() -> UFM:
    return UFM.random(UFMConfig.tiny(), seed=0)


def assert_close(ours: torch.Tensor, ref: torch.Tensor, name: str) -> None:
    """Spec 7.4: ``max|ours - ref| <= 1e-4 * max|ref|``."""
    assert ours.shape == ref.shape, f"{name}: shape {tuple(ours.shape)} vs {tuple(ref.shape)}"
    err = (ours.detach().float() - ref.float()).abs().max().item()
    bound = 1e-4 * ref.abs().max().item()
    assert err <= bound, f"{name}: max|diff| {err:.3g} > {bound:.3g}"


# ---------------------------------------------------------------------------------------------
# Parity with the reference fixture
# ---------------------------------------------------------------------------------------------


@pytest.mark.parametrize("route", ["config_dict", "config_json"])
def test_parity_with_reference(fx: dict, route: str) -> None:
    if route == "config_dict":
        config = UFMConfig.from_dict(fx["config"])
    else:
        config = UFMConfig.from_config_json(fx["reference_config_json"], fx["reference_hub_override"])
        assert config == UFMConfig.from_dict(fx["config"])
    model = UFM.from_state_dict(config, fx["state_dict"])
    inputs, debug = fx["inputs"], fx["debug"]
    out = model.predict_correspondences(
        inputs["source_image"], inputs["target_image"], inputs["data_norm_type"]
    )
    for name, ref in fx["outputs"].items():
        assert_close(out[name], ref, name)
    assert_close(out["flow_head_decoded"], debug["flow_head_decoded"], "flow_head_decoded")
    assert_close(
        out["uncertainty_head_decoded"], debug["uncertainty_head_decoded"], "uncertainty_head_decoded"
    )

    net_source, net_target = model.preprocess(
        inputs["source_image"], inputs["target_image"], inputs["data_norm_type"]
    )
    assert_close(net_source, debug["network_input_source"], "network_input_source")
    assert_close(net_target, debug["network_input_target"], "network_input_target")
    feats_source, feats_target = model.encode_views(net_source, net_target)
    assert_close(feats_source[0], debug["encoder_features"]["source"], "encoder_features.source")
    assert_close(feats_target[0], debug["encoder_features"]["target"], "encoder_features.target")
    for k in range(4):
        assert_close(feats_source[k], debug["head_inputs_source"][k], f"head_inputs_source[{k}]")
        assert_close(feats_target[k], debug["head_inputs_target"][k], f"head_inputs_target[{k}]")


def test_region_bookkeeping_float32_quirk() -> None:
    # Spec 4.1 step 5: the float32 ratio lands one row short for these sizes.
    assert region_size((56, 98), (92, 130)) == (55, 98)
    assert region_size((420, 560), (25, 100)) == (419, 560)
    assert region_size((420, 560), (480, 720)) == (420, 560)


def test_resolution_choice_prefers_matching_aspect() -> None:
    candidates = [[98, 56], [70, 70], [56, 98]]
    assert choose_resolution(candidates, (48, 80), (48, 80)) == (56, 98)
    assert choose_resolution(candidates, (90, 60), (90, 60)) == (98, 56)
    assert choose_resolution([[70, 70], [70, 70]], (10, 20), (20, 10)) == (70, 70)


# ---------------------------------------------------------------------------------------------
# Checkpoint layout of UFM-Base (spec table 4.7), built from the spec's patterns
# ---------------------------------------------------------------------------------------------


def _block_keys(prefix: str, dim: int, layerscale: bool) -> dict[str, tuple[int, ...]]:
    keys = {f"{prefix}.{n}.{p}": (dim,) for n in ("norm1", "norm2") for p in ("weight", "bias")}
    if layerscale:
        keys.update({f"{prefix}.ls1.gamma": (dim,), f"{prefix}.ls2.gamma": (dim,)})
    keys.update(
        {
            f"{prefix}.attn.qkv.weight": (3 * dim, dim),
            f"{prefix}.attn.qkv.bias": (3 * dim,),
            f"{prefix}.attn.proj.weight": (dim, dim),
            f"{prefix}.attn.proj.bias": (dim,),
            f"{prefix}.mlp.fc1.weight": (4 * dim, dim),
            f"{prefix}.mlp.fc1.bias": (4 * dim,),
            f"{prefix}.mlp.fc2.weight": (dim, 4 * dim),
            f"{prefix}.mlp.fc2.bias": (dim,),
        }
    )
    return keys


def _head_keys(head: str, out: int) -> dict[str, tuple[int, ...]]:
    p = f"{head}.0.0"
    keys = {
        f"{p}.input_process.0.0.0.weight": (96, 1024, 1, 1),
        f"{p}.input_process.0.0.0.bias": (96,),
        f"{p}.input_process.0.0.1.weight": (96, 96, 4, 4),
        f"{p}.input_process.0.0.1.bias": (96,),
        f"{p}.input_process.0.1.weight": (256, 96, 3, 3),
        f"{p}.input_process.1.0.0.weight": (192, 768, 1, 1),
        f"{p}.input_process.1.0.0.bias": (192,),
        f"{p}.input_process.1.0.1.weight": (192, 192, 2, 2),
        f"{p}.input_process.1.0.1.bias": (192,),
        f"{p}.input_process.1.1.weight": (256, 192, 3, 3),
        f"{p}.input_process.2.0.0.weight": (384, 768, 1, 1),
        f"{p}.input_process.2.0.0.bias": (384,),
        f"{p}.input_process.2.1.weight": (256, 384, 3, 3),
        f"{p}.input_process.3.0.0.weight": (768, 768, 1, 1),
        f"{p}.input_process.3.0.0.bias": (768,),
        f"{p}.input_process.3.0.1.weight": (768, 768, 3, 3),
        f"{p}.input_process.3.0.1.bias": (768,),
        f"{p}.input_process.3.1.weight": (256, 768, 3, 3),
    }
    for k in (1, 2, 3, 4):
        units = (2,) if k == 4 else (1, 2)
        for u in units:
            for c in (1, 2):
                keys[f"{p}.scratch.refinenet{k}.resConfUnit{u}.conv{c}.weight"] = (256, 256, 3, 3)
                keys[f"{p}.scratch.refinenet{k}.resConfUnit{u}.conv{c}.bias"] = (256,)
        keys[f"{p}.scratch.refinenet{k}.out_conv.weight"] = (256, 256, 1, 1)
        keys[f"{p}.scratch.refinenet{k}.out_conv.bias"] = (256,)
    keys.update(
        {
            f"{head}.0.1.conv1.weight": (128, 256, 3, 3),
            f"{head}.0.1.conv1.bias": (128,),
            f"{head}.0.1.conv2.0.weight": (128, 128, 3, 3),
            f"{head}.0.1.conv2.0.bias": (128,),
            f"{head}.0.1.conv2.2.weight": (out, 128, 1, 1),
            f"{head}.0.1.conv2.2.bias": (out,),
        }
    )
    return keys


def expected_ufm_base_keys() -> dict[str, tuple[int, ...]]:
    keys = {
        "encoder.model.cls_token": (1, 1, 1024),
        "encoder.model.pos_embed": (1, 1370, 1024),
        "encoder.model.patch_embed.proj.weight": (1024, 3, 14, 14),
        "encoder.model.patch_embed.proj.bias": (1024,),
        "encoder.model.norm.weight": (1024,),
        "encoder.model.norm.bias": (1024,),
        "info_sharing.proj_embed.weight": (768, 1024),
        "info_sharing.proj_embed.bias": (768,),
        "info_sharing.view_pos_table": (2, 768),
        "info_sharing.norm.weight": (768,),
        "info_sharing.norm.bias": (768,),
        "head1.1.adaptors.flow.flow_mean": (1, 2, 1, 1),
        "head1.1.adaptors.flow.flow_std": (1, 2, 1, 1),
    }
    for i in range(24):
        keys.update(_block_keys(f"encoder.model.blocks.{i}", 1024, layerscale=True))
    for i in range(12):
        keys.update(_block_keys(f"info_sharing.self_attention_blocks.{i}", 768, layerscale=False))
    keys.update(_head_keys("head1", 2))
    keys.update(_head_keys("uncertainty_head", 1))
    return keys


def test_ufm_base_layout_on_meta() -> None:
    expected = expected_ufm_base_keys()
    assert len(expected) == 613
    with torch.device("meta"):
        model = UFM()  # None = UFM-Base
    assert model.config == UFMConfig()
    ours = {k: tuple(v.shape) for k, v in model.state_dict().items()}
    assert sorted(set(ours) - set(expected)) == [] and sorted(set(expected) - set(ours)) == []
    assert ours == expected
    assert sum(v.numel() for v in model.state_dict().values()) == pytest.approx(428.3e6, rel=1e-3)


# ---------------------------------------------------------------------------------------------
# Loading
# ---------------------------------------------------------------------------------------------


def test_alias_names_load(fx: dict) -> None:
    reference = UFM.from_state_dict(fx["config"], fx["state_dict"])
    by_stored: dict[str, list[str]] = {}
    for alias, stored in sorted(fx["state_dict_aliases"].items()):
        by_stored.setdefault(stored, []).append(alias)
    assert len(by_stored) == 8
    renamed = dict(fx["state_dict"])
    for i, (stored, aliases) in enumerate(sorted(by_stored.items())):
        renamed[aliases[i % 2]] = renamed.pop(
            stored
        )  # alternate scratch.layer{k}_rn / scratch.layer_rn.{k-1}
    model = UFM.from_state_dict(fx["config"], renamed)
    for key, value in reference.state_dict().items():
        assert torch.equal(model.state_dict()[key], value), key
    # A non-de-duplicated checkpoint (all three names of each conv) loads too.
    full = dict(fx["state_dict"])
    full.update({alias: fx["state_dict"][stored] for alias, stored in fx["state_dict_aliases"].items()})
    UFM.from_state_dict(fx["config"], full)


def test_readable_errors_on_bad_checkpoints(fx: dict) -> None:
    broken = dict(fx["state_dict"])
    broken.pop("info_sharing.norm.weight")
    broken["info_sharing.extra.weight"] = torch.zeros(1)
    with pytest.raises(
        CheckpointMismatchError,
        match=r"missing 1: info_sharing\.norm\.weight.*unexpected 1: info_sharing\.extra\.weight",
    ):
        UFM.from_state_dict(fx["config"], broken)

    mask_only = copy.deepcopy(fx["config"])
    mask_only["uncertainty_adaptors"] = [{"name": "non_occluded_mask", "type": "mask"}]
    with pytest.raises(CheckpointMismatchError, match="4 output channels.*need 1"):
        UFM.from_state_dict(mask_only, fx["state_dict"])

    no_buffers = {k: v for k, v in fx["state_dict"].items() if not k.endswith("flow_std")}
    with pytest.raises(CheckpointMismatchError, match="flow_std"):
        UFM.from_state_dict(fx["config"], no_buffers)


def test_from_pretrained_local_folder(tmp_path: Path, tiny: UFM) -> None:
    from safetensors.torch import save_file

    (tmp_path / "config.json").write_text(json.dumps(tiny.config.to_dict()))
    save_file({k: v.contiguous() for k, v in tiny.state_dict().items()}, str(tmp_path / "model.safetensors"))
    loaded = UFM.from_pretrained(tmp_path)
    assert loaded.config == tiny.config
    source, target = torch.rand(1, 3, 40, 60), torch.rand(1, 3, 40, 60)
    assert torch.equal(loaded.estimate_flow(source, target).flow, tiny.estimate_flow(source, target).flow)


def test_missing_repo_offline_is_one_line(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    import huggingface_hub.constants

    monkeypatch.setenv("HF_HUB_OFFLINE", "1")
    monkeypatch.setattr(huggingface_hub.constants, "HF_HUB_OFFLINE", True)
    with pytest.raises(WeightsNotFoundError) as info:
        UFM.from_pretrained("geco-guide-tests/no-such-ufm", cache_dir=tmp_path)
    message = str(info.value)
    assert "\n" not in message and "geco-guide-tests/no-such-ufm" in message and "local folder" in message


# ---------------------------------------------------------------------------------------------
# config.json translation
# ---------------------------------------------------------------------------------------------


@pytest.mark.parametrize(
    ("path", "value", "field"),
    [
        (("info_sharing_str",), "cross_attention", "info_sharing_str"),
        (("encoder_kwargs", "size"), "giant", "encoder_kwargs.size"),
        (("feature_head_kwargs", "dpt_feature", "use_bn"), True, "use_bn"),
        (("feature_head_kwargs", "dpt_feature", "hooks"), [2, 5, 8, 11], "hooks"),
        (("info_sharing_kwargs", "use_rand_idx_pe_for_non_reference_views"), True, "use_rand_idx_pe"),
        (
            ("uncertainty_adaptors_kwargs", "non_occluded_mask", "class"),
            "ConfidenceAdaptor",
            "non_occluded_mask.class",
        ),
        (
            ("adaptors_kwargs", "flow", "kwargs", "output_normalized_coordinate"),
            True,
            "output_normalized_coordinate",
        ),
    ],
)
def test_config_json_rejects_out_of_scope(fx: dict, path: tuple, value: object, field: str) -> None:
    d = copy.deepcopy(fx["reference_config_json"])
    node = d
    for key in path[:-1]:
        node = node[key]
    node[path[-1]] = value
    with pytest.raises(ValueError, match=field):
        UFMConfig.from_config_json(
            d, None if field == "encoder_kwargs.size" else fx["reference_hub_override"]
        )


def test_config_json_hub_sizes_and_defaults() -> None:
    d = {
        "encoder_kwargs": {"size": "large", "with_registers": False},
        "info_sharing_kwargs": {
            "name": "info_sharing",
            "input_embed_dim": 1024,
            "max_num_views": 2,
            "use_rand_idx_pe_for_non_reference_views": False,
            "indices": [5, 8],
        },
        "feature_head_kwargs": {
            "dpt_feature": {"hooks": [0, 1, 2, 3], "input_feature_dims": [1024, 768, 768, 768]},
            "dpt_processor": {"output_dim": 2, "hidden_dims": [128, 128]},
        },
        "uncertainty_head_kwargs": {
            "dpt_feature": {"hooks": [0, 1, 2, 3], "input_feature_dims": [1024, 768, 768, 768]},
            "dpt_processor": {"output_dim": 1},
        },
        "adaptors_kwargs": {
            "flow": {
                "class": "FlowAdaptor",
                "kwargs": {
                    "flow_mean": [0, 0],
                    "flow_std": [50, 50],
                    "base_shape": [420, 560],
                    "scale_strategy": "scale_both",
                },
            }
        },
        "uncertainty_adaptors_kwargs": {"non_occluded_mask": {"class": "MaskAdaptor", "kwargs": {}}},
    }
    assert UFMConfig.from_config_json(d) == UFMConfig()
    d["encoder_kwargs"].update(size="base", with_registers=True, keep_first_n_layers=8)
    d["info_sharing_kwargs"]["input_embed_dim"] = 768
    for head in ("feature_head_kwargs", "uncertainty_head_kwargs"):
        d[head]["dpt_feature"]["input_feature_dims"] = 768
    config = UFMConfig.from_config_json(d)
    assert (config.encoder.embed_dim, config.encoder.depth, config.encoder.num_register_tokens) == (768, 8, 4)
    assert config.encoder.interpolate_antialias and config.encoder.interpolate_offset == 0.0
    assert config.uncertainty_head.hidden_dims == [128, 128]  # null -> [in/2, in/2]


def test_config_dict_roundtrip_and_unknown_keys() -> None:
    config = UFMConfig.tiny()
    assert UFMConfig.from_dict(json.loads(json.dumps(config.to_dict()))) == config
    with pytest.raises(ValueError, match="encoder: unknown key"):
        UFMConfig.from_dict({"encoder": {"embed_dims": 48}})
    with pytest.raises(ValueError, match="flow_adaptor.scale_strategy"):
        UFMConfig.from_dict({"flow_adaptor": {"scale_strategy": "stretch"}})


# ---------------------------------------------------------------------------------------------
# Behaviour of a random tiny model: protocol, inputs, gradients
# ---------------------------------------------------------------------------------------------


def test_tiny_random_model_is_sane(tiny: UFM) -> None:
    assert isinstance(tiny, FlowEstimator)
    gen = torch.Generator().manual_seed(1)
    source, target = torch.rand(2, 3, 48, 80, generator=gen), torch.rand(2, 3, 48, 80, generator=gen)
    corr = tiny.estimate_flow(source, target)
    assert corr.flow.shape == (2, 2, 48, 80) and corr.covisibility.shape == (2, 48, 80)
    assert torch.isfinite(corr.flow).all() and corr.flow.abs().max() < 5.0
    assert 0.01 < corr.covisibility.min() and corr.covisibility.max() < 0.99
    # Mostly above GeCo's 0.5 covisibility threshold (else its motion cue sees no pixel), and
    # depending on the images rather than constant.
    assert 0.6 < corr.covisibility.mean() < 0.9 and (corr.covisibility > 0.5).float().mean() > 0.9
    assert corr.covisibility.std() > 1e-3 and corr.flow.std() > 1e-2
    # Layouts: channel-last and unbatched inputs give the same answer.
    out_hwc = tiny.predict_correspondences(source[0].permute(1, 2, 0), target[0].permute(1, 2, 0))
    assert torch.allclose(out_hwc["flow"], corr.flow[:1], atol=1e-5)
    with pytest.raises(ValueError, match="data_norm_type"):
        tiny.predict_correspondences(source, target, data_norm_type="unheard_of")
    with pytest.raises(ValueError, match="source and target shapes differ"):
        tiny.estimate_flow(source, target[:, :, :40])


def test_random_is_seeded_and_leaves_the_global_rng_alone() -> None:
    rng_state = torch.get_rng_state()
    a, b = UFM.random(UFMConfig.tiny(), seed=3), UFM.random(UFMConfig.tiny(), seed=3)
    c = UFM.random(UFMConfig.tiny(), seed=4, gradient_checkpointing=True)
    assert torch.equal(torch.get_rng_state(), rng_state)
    assert c.gradient_checkpointing and not a.gradient_checkpointing
    for (name, ta), tb in zip(a.state_dict().items(), b.state_dict().values(), strict=True):
        assert torch.equal(ta, tb), name
    differ = [k for k, v in a.state_dict().items() if v.numel() > 1 and not torch.equal(v, c.state_dict()[k])]
    assert "encoder.model.patch_embed.proj.weight" in differ and "head1.0.1.conv2.2.weight" in differ
    # Buffers are initialised too (the model was materialised from the meta device).
    assert torch.equal(a.info_sharing.view_pos_table, sinusoid_view_table(2, 64))
    assert a.head1[1].adaptors["flow"].flow_std.flatten().tolist() == [1.0, 1.0]
    source, target = torch.rand(2, 1, 3, 42, 56, generator=torch.Generator().manual_seed(0))
    with torch.no_grad():
        flow_a, flow_c = a.estimate_flow(source, target).flow, c.estimate_flow(source, target).flow
    assert torch.isfinite(flow_a).all() and flow_a.abs().max() < 5.0
    assert not torch.allclose(flow_a, flow_c)


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_random_covisibility_is_mostly_above_threshold(seed: int) -> None:
    model = UFM.random(UFMConfig.tiny(), seed=seed)
    gen = torch.Generator().manual_seed(10 + seed)
    source, target = torch.rand(2, 2, 3, 48, 64, generator=gen)
    with torch.no_grad():
        corr = model.estimate_flow(source, target)
    assert 0.6 < corr.covisibility.mean() < 0.9
    assert torch.isfinite(corr.flow).all() and corr.flow.abs().max() < 5.0


def test_gradients_reach_both_inputs_and_params_are_frozen(tiny: UFM) -> None:
    assert not tiny.training and not any(p.requires_grad for p in tiny.parameters())
    source = torch.rand(2, 3, 40, 60, requires_grad=True)
    target = torch.rand(2, 3, 40, 60, requires_grad=True)
    corr = tiny.estimate_flow(source, target)
    (corr.flow.square().mean() + corr.covisibility.mean()).backward()
    for x in (source, target):
        assert x.grad is not None and torch.isfinite(x.grad).all() and x.grad.abs().sum() > 0
    assert all(p.grad is None for p in tiny.parameters())


def test_checkpointing_and_autocast_options(tiny: UFM) -> None:
    source = torch.rand(1, 3, 40, 60, requires_grad=True)
    target = torch.rand(1, 3, 40, 60)
    plain = tiny.estimate_flow(source, target).flow
    (grad_plain,) = torch.autograd.grad(plain.sum(), source)
    try:
        tiny.gradient_checkpointing = True
        ckpt = tiny.estimate_flow(source, target).flow
        (grad_ckpt,) = torch.autograd.grad(ckpt.sum(), source)
        tiny.gradient_checkpointing = False
        tiny.autocast_dtype = torch.bfloat16
        low = tiny.estimate_flow(source, target)
    finally:
        tiny.gradient_checkpointing = False
        tiny.autocast_dtype = None
    assert torch.equal(ckpt, plain) and torch.allclose(grad_ckpt, grad_plain, atol=1e-6)
    assert low.flow.dtype == torch.float32 and torch.allclose(
        low.flow, plain, atol=0.05 * plain.abs().max().item()
    )


def test_trunk_to_bfloat16_keeps_heads_and_outputs_float32() -> None:
    model = UFM.random(UFMConfig.tiny(), seed=0)
    source = torch.rand(1, 3, 40, 60, generator=torch.Generator().manual_seed(0), requires_grad=True)
    target = torch.rand(1, 3, 40, 60, generator=torch.Generator().manual_seed(1))
    ref = model.estimate_flow(source, target)
    assert model.trunk_to(torch.bfloat16) is model
    trunk = ("encoder.", "info_sharing.")
    assert {p.dtype for n, p in model.named_parameters() if n.startswith(trunk)} == {torch.bfloat16}
    assert {p.dtype for n, p in model.named_parameters() if not n.startswith(trunk)} == {torch.float32}
    low = model.estimate_flow(source, target)
    assert low.flow.dtype == low.covisibility.dtype == torch.float32
    torch.testing.assert_close(low.flow, ref.flow, atol=0.05 * float(ref.flow.detach().abs().max()), rtol=0.05)
    (grad,) = torch.autograd.grad(low.flow.mean(), source)
    assert torch.isfinite(grad).all() and grad.abs().sum() > 0
