"""TinyDecoder (TAEHV architecture): parity with the reference fixture, the published key layout,
time alignment, loading, and the one-line errors.

The fixture ``tests/fixtures/tiny_decoder.pt`` (see ``shared/specs/tiny_decoder.md``) holds the
reference's key names and shapes, inputs and outputs; its weights are regenerated here from the
key names by the spec's rule, written out independently of the module's own helper.
"""

from __future__ import annotations

import math
import zlib
from pathlib import Path

import pytest
import torch

from geco_guide.estimators.loading import CheckpointMismatchError, WeightsNotFoundError
from geco_guide.estimators.tiny_decoder import (
    TINY_DECODER_WIDTHS,
    VARIANTS,
    TinyDecoder,
    resolve_variant,
    variant_from_filename,
)

FIXTURE = Path(__file__).resolve().parents[1] / "fixtures" / "tiny_decoder.pt"
TOL = {"atol": 1e-4, "rtol": 1e-4}


def weight_for(key: str, shape, seed: int) -> torch.Tensor:
    """The spec's weight rule, spelled out here so the test does not trust the module's copy."""
    g = torch.Generator().manual_seed(zlib.crc32(key.encode()) + seed)
    w = torch.randn(tuple(shape), generator=g, dtype=torch.float32)
    return w / math.sqrt(w.numel() / shape[0]) if w.ndim > 1 else w * 0.1


def widths_from_shapes(shapes) -> dict:
    """The stage widths a fixture's key shapes imply (the published ones for the shared fixture)."""
    dec = tuple(shapes[f"decoder.{i}.weight"][0] for i in (1, 8, 14, 20))
    return {"decoder_widths": dec, "encoder_width": shapes["encoder.0.weight"][0]}


@pytest.fixture(scope="module")
def fixture() -> dict:
    return torch.load(FIXTURE, weights_only=False)


@pytest.fixture(scope="module")
def reference_state_dict(fixture) -> dict:
    return {k: weight_for(k, s, fixture["seed"]) for k, s in fixture["state_dict_shapes"].items()}


@pytest.fixture(scope="module")
def model(fixture, reference_state_dict) -> TinyDecoder:
    return TinyDecoder.from_state_dict(reference_state_dict, fixture["variant"])


def _forbid_convs(model: TinyDecoder):
    """Make the first conv of the decoder and of the encoder fail if they run."""
    def boom(*_):
        raise AssertionError("a conv ran before the input check")
    return [model.decoder[1].register_forward_pre_hook(boom), model.encoder[0].register_forward_pre_hook(boom)]


# ---- parity with the reference ---------------------------------------------------------------------


def test_published_key_layout_loads_strictly(fixture, reference_state_dict):
    built = TinyDecoder(fixture["variant"], **widths_from_shapes(fixture["state_dict_shapes"]))
    ours = {k: tuple(v.shape) for k, v in built.state_dict().items()}
    assert ours == {k: tuple(s) for k, s in fixture["state_dict_shapes"].items()}
    result = built.load_state_dict(reference_state_dict, strict=True)
    assert not result.missing_keys and not result.unexpected_keys
    assert fixture["reference_checkpoint_name"] == f"{built.variant.checkpoint}.pth"


def test_decode_matches_reference_and_its_gradient(fixture, model):
    latents = fixture["latents"].clone().requires_grad_(True)
    decoded = model.decode(latents)
    assert decoded.shape == fixture["decoded"].shape == (1, 9, 3, 32, 48)
    torch.testing.assert_close(decoded, fixture["decoded"], **TOL)
    weights = torch.linspace(0, 1, decoded.numel()).reshape(decoded.shape)
    (grad,) = torch.autograd.grad((decoded * weights).sum(), latents)
    torch.testing.assert_close(grad, fixture["grad_latents"], **TOL)
    assert grad.abs().max() > 1  # a real gradient, not a vanishing one
    # frozen: the gradient reaches the latents only
    assert not any(p.requires_grad for p in model.parameters())


def test_encode_matches_reference(fixture, model):
    encoded = model.encode(fixture["frames"])
    assert encoded.shape == fixture["encoded"].shape
    torch.testing.assert_close(encoded, fixture["encoded"], **TOL)


def test_random_follows_the_fixture_rule(fixture, reference_state_dict):
    shapes = fixture["state_dict_shapes"]
    built = TinyDecoder.random(fixture["variant"], seed=fixture["seed"], **widths_from_shapes(shapes))
    for key, value in built.state_dict().items():
        assert torch.equal(value, reference_state_dict[key]), key
    other = TinyDecoder.tiny(fixture["variant"], seed=fixture["seed"] + 1)
    assert other.decoder_widths == TINY_DECODER_WIDTHS
    assert not torch.equal(other.state_dict()["decoder.22.bias"], reference_state_dict["decoder.22.bias"])


# ---- time alignment and layout ----------------------------------------------------------------------


@pytest.mark.parametrize("variant, counts", [
    ("cogvideox", {1: 1, 2: 8, 3: 9, 4: 16, 13: 49}),
    ("wan2.1", {1: 1, 2: 5, 3: 9, 4: 13, 21: 81}),
    ("hunyuanvideo", {2: 5, 33: 129}),
])
def test_num_frames_follow_the_published_trim_rule(variant, counts):
    model = TinyDecoder.tiny(variant)
    assert {t: model.num_frames(t) for t in counts} == counts
    assert model.num_latents(49) == 13 and model.num_latents(8) == 2


def test_trim_keeps_the_last_frame_of_the_last_latent():
    """Same weights (same keys and seed) as CogVideoX and Wan 2.1: the CogVideoX even-count decode
    keeps the 3 leading frames the Wan decode drops; the frames after them agree."""
    cvx, wan = TinyDecoder.tiny("cogvideox", seed=3), TinyDecoder.tiny("wan2.1", seed=3)
    latents = torch.randn(1, 4, 16, 2, 3, generator=torch.Generator().manual_seed(0))
    full, trimmed = cvx.decode(latents), wan.decode(latents)
    assert full.shape[1] == 16 and trimmed.shape[1] == 13
    torch.testing.assert_close(full[:, 3:], trimmed)
    odd = cvx.decode(latents[:, :3])
    assert odd.shape[1] == 9
    torch.testing.assert_close(odd, full[:, 3:12])  # causal: a prefix decodes like the whole


def test_decode_is_causal_and_batched():
    model = TinyDecoder.tiny("wan2.1", seed=1)
    latents = torch.randn(2, 5, 16, 2, 2, generator=torch.Generator().manual_seed(1))
    full = model.decode(latents)
    assert full.shape == (2, 17, 3, 16, 16) and 0 <= full.min() and full.max() <= 1
    torch.testing.assert_close(model.decode(latents[:, :2]), full[:, :5])
    torch.testing.assert_close(model.decode(latents[1:]), full[1:])
    assert not torch.allclose(full[0], full[1])


def test_output_is_clamped_to_unit_range_with_zero_gradient_outside():
    model = TinyDecoder.tiny("wan2.1", seed=5)
    with torch.no_grad():
        model.decoder[22].bias.copy_(torch.tensor([10.0, -10.0, 0.5]))  # red far above 1, green below 0
    latents = torch.randn(1, 2, 16, 2, 2, requires_grad=True)
    frames = model.decode(latents)
    assert torch.equal(frames[:, :, 0], torch.ones_like(frames[:, :, 0]))
    assert torch.equal(frames[:, :, 1], torch.zeros_like(frames[:, :, 1]))
    (grad_outside,) = torch.autograd.grad(frames[:, :, :2].sum(), latents, retain_graph=True)
    assert torch.count_nonzero(grad_outside) == 0
    (grad_inside,) = torch.autograd.grad(frames[:, :, 2].sum(), latents)
    assert grad_inside.abs().sum() > 0


def test_encode_pads_with_the_last_frame():
    model = TinyDecoder.tiny("cogvideox", seed=2)
    frames = torch.rand(1, 9, 3, 16, 24, generator=torch.Generator().manual_seed(2))
    encoded = model.encode(frames)
    assert encoded.shape == (1, 3, 16, 2, 3)
    padded = torch.cat([frames, frames[:, -1:].repeat(1, 3, 1, 1, 1)], 1)
    torch.testing.assert_close(encoded, model.encode(padded))


@pytest.mark.parametrize("variant, channels", [("wan2.2-5b", 48), ("hunyuanvideo1.5", 32)])
def test_patch_two_variants(variant, channels):
    model = TinyDecoder.tiny(variant)
    assert model.patch_size == 2 and model.latent_channels == channels
    assert model.state_dict()["decoder.22.weight"].shape[0] == 12
    assert model.decode(torch.randn(1, 2, channels, 2, 3)).shape == (1, 5, 3, 32, 48)
    assert model.encode(torch.rand(1, 5, 3, 32, 48)).shape == (1, 2, channels, 2, 3)
    with pytest.raises(ValueError, match="multiples of the patch size 2"):
        model.encode(torch.rand(1, 5, 3, 32, 47))


def test_pipeline_latents_convention():
    cvx, wan = TinyDecoder.tiny("cogvideox"), TinyDecoder.tiny("wan2.1")
    ntchw = torch.randn(1, 3, 16, 2, 2)
    torch.testing.assert_close(cvx.pipeline_latents(ntchw, {"scaling_factor": 0.7}), ntchw / 0.7)

    class Config:
        scaling_factor = 1.15258426

    torch.testing.assert_close(cvx.pipeline_latents(ntchw, Config()), ntchw / 1.15258426)
    with pytest.raises(ValueError, match="needs the VAE's scaling_factor"):
        cvx.pipeline_latents(ntchw)
    ncthw = ntchw.transpose(1, 2)  # Wan holds NCTHW; no mean/std is applied for the tiny decoder
    assert torch.equal(wan.pipeline_latents(ncthw, {"latents_mean": [1.0] * 16}), ntchw)


# ---- loading ---------------------------------------------------------------------------------------


def test_from_pretrained_pth_and_safetensors(tmp_path, fixture, reference_state_dict):
    from safetensors.torch import save_file

    pth = tmp_path / "taecvx.pth"
    torch.save(reference_state_dict, pth)
    folder = tmp_path / "weights"
    (folder / "safetensors").mkdir(parents=True)
    save_file(reference_state_dict, str(folder / "safetensors" / "taecvx.safetensors"))
    for source in (pth, folder / "safetensors" / "taecvx.safetensors", folder):
        loaded = TinyDecoder.from_pretrained(source)
        assert loaded.variant.name == "cogvideox", source
        assert not loaded.training
        torch.testing.assert_close(loaded.decode(fixture["latents"]), fixture["decoded"], **TOL)
    # an explicit variant wins over the name and changes the time rule only
    wan = TinyDecoder.from_pretrained(pth, variant="wan2.1")
    assert wan.num_frames(2) == 5


def test_from_pretrained_hub_id_goes_through_hf_hub_download(tmp_path, monkeypatch):
    import huggingface_hub

    source = TinyDecoder.tiny("wan2.1", seed=4)
    torch.save(source.state_dict(), tmp_path / "taew2_1.pth")
    asked = []

    def fake_download(repo_id, filename, **_):
        asked.append((repo_id, filename))
        if not (tmp_path / filename).is_file():
            raise huggingface_hub.utils.EntryNotFoundError(filename)
        return str(tmp_path / filename)

    monkeypatch.setattr(huggingface_hub, "hf_hub_download", fake_download)
    loaded = TinyDecoder.from_pretrained("someone/taehv", variant="wan2.1")
    assert loaded.variant.name == "wan2.1" and loaded.decoder_widths == TINY_DECODER_WIDTHS
    assert asked == [("someone/taehv", "taew2_1.safetensors"), ("someone/taehv", "taew2_1.pth")]
    assert torch.equal(loaded.state_dict()["decoder.1.weight"], source.state_dict()["decoder.1.weight"])


def test_from_pretrained_missing_weights_is_one_line(tmp_path, monkeypatch):
    import huggingface_hub

    with pytest.raises(WeightsNotFoundError, match=r"checkpoint file .*taecvx\.pth.* does not exist; download "
                                                   r"taecvx\.pth from .* pass its local path") as err:
        TinyDecoder.from_pretrained(tmp_path / "taecvx.pth")
    assert "\n" not in str(err.value)
    with pytest.raises(WeightsNotFoundError, match=r"none of .*taehv1_5\.pth.* found in local folder"):
        TinyDecoder.from_pretrained(tmp_path, variant="hunyuanvideo1.5")

    def offline(*_, **__):
        raise huggingface_hub.utils.LocalEntryNotFoundError("offline")

    monkeypatch.setattr(huggingface_hub, "hf_hub_download", offline)
    with pytest.raises(WeightsNotFoundError, match=r"'someone/taecvx'.*offline.*pass its local path") as err:
        TinyDecoder.from_pretrained("someone/taecvx", variant="cogvideox")
    assert "\n" not in str(err.value)


def test_checkpoint_with_wrong_keys_lists_them(tmp_path):
    state = TinyDecoder.tiny("cogvideox").state_dict()
    del state["decoder.22.bias"]
    state["decoder.23.weight"] = torch.zeros(1)
    listed = r"checkpoint does not fit: missing 1: decoder\.22\.bias; unexpected 1: decoder\.23\.weight$"
    with pytest.raises(CheckpointMismatchError, match=listed):
        TinyDecoder.from_state_dict(state, "cogvideox")
    wan22 = TinyDecoder.tiny("wan2.2-5b").state_dict()
    torch.save(wan22, tmp_path / "taecvx_misnamed.pth")  # a 48-channel file under a taecvx name
    misshaped = r"wrong shape .*decoder\.1\.weight \(32, 48, 3, 3\) vs \(32, 16, 3, 3\)"
    with pytest.raises(CheckpointMismatchError, match=misshaped):
        TinyDecoder.from_pretrained(tmp_path / "taecvx_misnamed.pth")


@pytest.mark.parametrize("name, variant", [
    ("taecvx.pth", "cogvideox"), ("safetensors/taew2_1.safetensors", "wan2.1"), ("taehv.pth", "hunyuanvideo"),
    ("taew2_2.pth", "wan2.2-5b"), ("taehv1_5.safetensors", "hunyuanvideo1.5"), ("my_taecvx_ft.pth", "cogvideox"),
])
def test_variant_from_file_name(name, variant):
    assert variant_from_filename(name).name == variant
    assert resolve_variant(VARIANTS[variant].checkpoint).name == variant


@pytest.mark.parametrize("name, message", [
    ("taeltx_2.pth", "taeltx checkpoints .* not supported"),
    ("taehv1_5_super.pth", "'\\*_super' checkpoints .* not supported"),
    ("model.safetensors", "cannot infer the variant from the file name 'model.safetensors'.*pass variant="),
])
def test_refused_or_unknown_file_names(tmp_path, name, message):
    with pytest.raises(ValueError, match=message) as err:
        variant_from_filename(name)
    assert "\n" not in str(err.value)
    path = tmp_path / Path(name).name
    torch.save({}, path)
    with pytest.raises(ValueError, match=message):
        TinyDecoder.from_pretrained(path)


@pytest.mark.parametrize("variant, message", [
    ("ltx-video", "taeltx checkpoints"),
    ("taew2_2_super", "super"),
    ("mochi", "unknown variant 'mochi'; supported: 'cogvideox'"),
])
def test_refused_or_unknown_variants(variant, message):
    with pytest.raises(ValueError, match=message):
        TinyDecoder(variant)


# ---- bad inputs -------------------------------------------------------------------------------------


def test_wrong_latent_channels_fail_before_any_conv():
    model = TinyDecoder.tiny("cogvideox")
    hooks = _forbid_convs(model)
    try:
        with pytest.raises(ValueError, match=r"^TinyDecoder\(cogvideox\) expects 16 latent channels at dim 2, got 48 "
                                             r"in latents of shape \[1, 3, 48, 2, 2\]$"):
            model.decode(torch.randn(1, 3, 48, 2, 2))
        with pytest.raises(ValueError, match=r"look NCTHW: permute\(0, 2, 1, 3, 4\)"):
            model.decode(torch.randn(1, 16, 3, 2, 2))
        with pytest.raises(ValueError, match=r"\[N, T, C, h, w\] \(NTCHW\) with T >= 1, got shape \[3, 16, 2, 2\]"):
            model.decode(torch.randn(3, 16, 2, 2))
        with pytest.raises(ValueError, match=r"got shape \[1, 0, 16, 2, 2\]"):
            model.decode(torch.randn(1, 0, 16, 2, 2))
        with pytest.raises(ValueError, match=r"encode: frames must have shape \[B, S, 3, H, W\], got \[1, 4, 16, 2\]"):
            model.encode(torch.rand(1, 4, 16, 2))
    finally:
        for hook in hooks:
            hook.remove()
