"""The faster guidance decode (geco_guide/sampler/running/fast_decode.py): the channels-last-3d layout of the
CogVideoX VAE decoder and ``run.compile``, against the stock eager decode, on the tiny models."""

from __future__ import annotations

import warnings
from functools import partial

import pytest
import torch
from counting import CountingHook
from diffusers.hooks import HookRegistry
from torch import nn

from geco_guide.sampler.running import fast_decode
from geco_guide.sampler.running.multi_device import module_replicas
from geco_guide.sampler.running.fast_decode import (
    CompileFallbackWarning,
    causal_time_pad,
    channels_last_group_norm,
    guidance_decode,
)
from geco_guide.sampler.running.run_options import RunOptions, check_run_for_guidance, resolve_run_options
from geco_guide.sampler.algorithm.slicing import decode_anchor_frames, decode_chunk
from geco_guide.tiny import (
    TINY_CALL_KWARGS,
    TINY_NUM_FRAMES,
    TinySizes,
    tiny_cogvideox_components,
    tiny_guidance_config,
    tiny_guidance_decoder,
    tiny_pipeline,
    tiny_run_options,
)

CL3D = torch.channels_last_3d
CHANNELS_LAST = RunOptions(decode_layout="channels_last")
# float32 accumulates other kernels' rounding over ~30 layers: frames in [0, 1] agree to a few 1e-6
TOLERANCE = {torch.float32: 2e-5, torch.float64: 1e-10}


def frozen_vae(dtype=torch.float32, sizes=None):
    vae = tiny_cogvideox_components(0, sizes)["vae"]
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # diffusers' note on casting with to()
        vae.to(dtype)
    return vae.requires_grad_(False)


def anchor_decode(vae, latents, checkpoint_chunks):
    """Frames ``[B, S, 3, H, W]`` of the tiny anchors and their gradient w.r.t. ``latents``."""
    latents = latents.detach().requires_grad_(True)
    chunks = tiny_guidance_config().anchor_chunks(TINY_NUM_FRAMES, 4)
    frames = decode_anchor_frames(partial(decode_chunk, vae, scaling_factor=0.7), latents, chunks,
                                  checkpoint_chunks=checkpoint_chunks)
    (grad,) = torch.autograd.grad((frames * torch.linspace(-1, 1, frames.shape[-1])).sum(), latents)
    return frames.detach(), grad


def latents_of(dtype=torch.float32, batch=1):
    return torch.randn(batch, 5, 4, 4, 6, generator=torch.Generator().manual_seed(1), dtype=dtype)


def assert_close(actual, expected, dtype):
    scale = expected.abs().max().item()
    assert (actual - expected).abs().max().item() <= TOLERANCE[dtype] * max(scale, 1.0)


def instance_forwards(module):
    return [name for name, m in module.named_modules() if "forward" in m.__dict__]


@pytest.fixture
def fresh_compile_cache(monkeypatch):
    monkeypatch.setattr(fast_decode, "_COMPILED", {})


# ---- the channels-last layout ------------------------------------------------------------------


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
@pytest.mark.parametrize("checkpoint_chunks", [False, True])
@pytest.mark.slow
def test_channels_last_decode_gives_the_stock_frames_and_gradients(dtype, checkpoint_chunks):
    vae, latents = frozen_vae(dtype), latents_of(dtype)
    frames, grad = anchor_decode(vae, latents, checkpoint_chunks)
    with guidance_decode(CHANNELS_LAST, "vae", vae):
        fast_frames, fast_grad = anchor_decode(vae, latents, checkpoint_chunks)
    assert fast_frames.shape == frames.shape and fast_frames.stride() == frames.stride()
    assert_close(fast_frames, frames, dtype)
    assert_close(fast_grad, grad, dtype)
    assert grad.abs().max() > 0


@pytest.mark.slow
def test_every_convolution_sees_channels_last_inputs_for_a_batch_of_one():
    vae = frozen_vae()
    seen = []
    hooks = [m.register_forward_pre_hook(lambda m, args, name=name: seen.append((name, args[0].is_contiguous(memory_format=CL3D))))
             for name, m in vae.decoder.named_modules() if isinstance(m, nn.Conv3d) and m.kernel_size != (1, 1, 1)]
    with guidance_decode(CHANNELS_LAST, "vae", vae):
        anchor_decode(vae, latents_of(), checkpoint_chunks=True)  # one chunk per decode: batch 1
    for hook in hooks:
        hook.remove()
    assert len(seen) > 20
    assert [name for name, kept in seen if not kept] == []


@pytest.mark.slow
def test_the_vae_is_restored_on_exit_even_after_an_error(fresh_compile_cache):
    vae = frozen_vae()
    weights = {name: p.detach().clone() for name, p in vae.named_parameters()}
    before = instance_forwards(vae)
    with pytest.raises(RuntimeError, match="inside"), guidance_decode(RunOptions(decode_layout="channels_last", compile=True), "vae", vae):
        assert "forward" in vae.decoder.__dict__ and len(instance_forwards(vae)) > 10
        raise RuntimeError("inside")
    assert instance_forwards(vae) == before == []
    for name, p in vae.named_parameters():
        assert p.is_contiguous() and torch.equal(p, weights[name])


def test_the_default_options_patch_nothing():
    vae = frozen_vae()
    pointers = [p.data_ptr() for p in vae.parameters()]
    with guidance_decode(RunOptions(), "vae", vae):
        assert instance_forwards(vae) == []
        assert [p.data_ptr() for p in vae.parameters()] == pointers


def test_channels_last_refuses_another_vae_in_one_line():
    refused = r"^run.decode_layout=channels_last is written for the CogVideoX VAE .*not Linear"
    with pytest.raises(TypeError, match=refused) as err, guidance_decode(CHANNELS_LAST, "vae", nn.Linear(2, 2)):
        pass
    assert "\n" not in str(err.value)


def test_channels_last_refuses_a_decoder_with_hooked_forwards():
    vae = frozen_vae()
    norm = next(m for m in vae.decoder.modules() if isinstance(m, nn.GroupNorm))
    norm.forward = norm.forward  # as an offload hook installs it
    hooked = r"1 of the modules whose forward it replaces .* own forward \(e.g. .*norm_layer.*offload hook"
    with pytest.raises(ValueError, match=hooked), guidance_decode(CHANNELS_LAST, "vae", vae):
        pass
    assert all(p.is_contiguous() for p in vae.parameters())


def test_channels_last_refuses_a_diffusers_hook_on_a_module_it_replaces_and_leaves_it_in_place():
    vae = frozen_vae()
    norm = next(m for m in vae.decoder.modules() if isinstance(m, nn.GroupNorm))
    counting = CountingHook()
    HookRegistry.check_if_exists_or_initialize(norm).register_hook(counting, "counting")
    forward = norm.__dict__["forward"]
    with pytest.raises(ValueError, match="already have their own forward"), guidance_decode(CHANNELS_LAST, "vae", vae):
        pass
    assert list(norm._diffusers_hook.hooks) == ["counting"] and norm.__dict__["forward"] is forward


def test_channels_last_keeps_a_diffusers_hook_on_a_module_it_does_not_replace():
    """A hook on one of the decoder's blocks (as diffusers' group offloading registers them) runs
    in the laid-out decode, which gives the same frames and gradients as without it; the block's
    registry is left as found."""
    vae, latents = frozen_vae(), latents_of()
    with guidance_decode(CHANNELS_LAST, "vae", vae):
        expected = anchor_decode(vae, latents, checkpoint_chunks=False)
    block = vae.decoder.up_blocks[0]
    counting = CountingHook()
    HookRegistry.check_if_exists_or_initialize(block).register_hook(counting, "counting")
    forward = block.__dict__["forward"]
    with guidance_decode(CHANNELS_LAST, "vae", vae):
        frames, grad = anchor_decode(vae, latents, checkpoint_chunks=False)
    assert counting.n == 2  # one decode per chunk length
    assert torch.equal(frames, expected[0]) and torch.equal(grad, expected[1])
    assert list(block._diffusers_hook.hooks) == ["counting"] and block.__dict__["forward"] is forward
    assert instance_forwards(vae) == ["decoder.up_blocks.0"]


def test_compile_refuses_a_vae_without_a_decoder_in_one_line(fresh_compile_cache):
    refused = r"^run.compile compiles the VAE's decoder module, and Linear has none"
    with pytest.raises(TypeError, match=refused), guidance_decode(RunOptions(compile=True), "vae", nn.Linear(2, 2)):
        pass


@pytest.mark.parametrize("affine", [True, False])
def test_channels_last_group_norm_is_group_norm(affine):
    generator = torch.Generator().manual_seed(0)
    x = (torch.randn(2, 8, 3, 4, 5, generator=generator, dtype=torch.float64) * 3 + 1).contiguous(memory_format=CL3D)
    weight = torch.randn(8, generator=generator, dtype=torch.float64) if affine else None
    bias = torch.randn(8, generator=generator, dtype=torch.float64) if affine else None
    inputs = [t.requires_grad_(True) for t in (x, weight, bias) if t is not None]
    out = channels_last_group_norm(x, 2, weight, bias, 1e-6)
    expected = nn.functional.group_norm(x, 2, weight, bias, 1e-6)
    assert out.is_contiguous(memory_format=CL3D)
    torch.testing.assert_close(out, expected, rtol=1e-12, atol=1e-12)
    upstream = torch.randn(expected.shape, generator=generator, dtype=torch.float64)
    for got, want in zip(torch.autograd.grad(out, inputs, upstream), torch.autograd.grad(expected, inputs, upstream)):
        torch.testing.assert_close(got, want, rtol=1e-10, atol=1e-10)


@pytest.mark.parametrize("offset", [0.5, 100.0])
def test_channels_last_group_norm_in_bf16_is_as_close_as_the_stock_kernel(offset):
    """Against float64 of the same bf16 inputs: the mean and the factors in float32, so a group far
    from zero (``offset`` 50 standard deviations) loses nothing to a rounded mean."""
    generator = torch.Generator().manual_seed(0)
    x = (torch.randn(1, 64, 5, 16, 24, generator=generator) * 2 + offset).bfloat16()
    weight, bias = torch.randn(64, generator=generator).bfloat16(), torch.randn(64, generator=generator).bfloat16()
    exact = nn.functional.group_norm(x.double(), 32, weight.double(), bias.double(), 1e-6)
    ours = channels_last_group_norm(x.contiguous(memory_format=CL3D), 32, weight, bias, 1e-6)
    stock = nn.functional.group_norm(x, 32, weight, bias, 1e-6)
    assert ours.dtype == torch.bfloat16 and ours.is_contiguous(memory_format=CL3D)

    def rms_error(y):
        return (y.double() - exact).square().mean().sqrt().item()

    assert rms_error(ours) <= 1.2 * rms_error(stock)


@pytest.mark.parametrize("with_cache", [False, True])
def test_causal_time_pad_is_the_stock_padding_in_channels_last(with_cache):
    inputs = torch.randn(1, 4, 3, 5, 6).contiguous(memory_format=CL3D)
    cache = torch.randn(1, 4, 2, 5, 6) if with_cache else None
    stock = torch.cat([cache, inputs] if with_cache else [inputs[:, :, :1]] * 2 + [inputs], dim=2)
    padded = causal_time_pad(inputs, 2, cache)
    assert torch.equal(padded, stock)
    assert padded.is_contiguous(memory_format=CL3D)


@pytest.mark.parametrize("compile", [False, True])
def test_a_replica_of_the_laid_out_vae_decodes_with_its_own_weights(monkeypatch, fresh_compile_cache, compile):
    """The replicas of ``run.devices`` are deep copies made inside the region: their layout's
    forwards must call the copy, not the module they were copied from."""
    monkeypatch.setattr(torch, "compile", RecordingCompile())
    vae, halved, latents = frozen_vae(), frozen_vae(), latents_of()[:, 1:4]
    with torch.no_grad():
        for p in halved.parameters():
            p.mul_(0.5)
        expected = decode_chunk(halved, latents, 0.7)
        with guidance_decode(RunOptions(decode_layout="channels_last", compile=compile), "vae", vae):
            _, replica = module_replicas(vae, [torch.device("cpu"), torch.device("cpu")])
            for p in replica.parameters():
                p.mul_(0.5)
            frames = decode_chunk(replica, latents, 0.7)
    assert_close(frames, expected, torch.float32)
    assert instance_forwards(vae) == []


@pytest.mark.slow
def test_a_guided_run_decodes_its_final_video_with_the_stock_vae(estimators):
    pipe = tiny_pipeline(0)
    final = {}

    def keep_latents(pipe, step, t, tensors):
        final["latents"] = tensors["latents"]
        return tensors

    out = pipe("a marble bust", generator=torch.Generator().manual_seed(0), output_type="pt",
               run_options=tiny_run_options(decode_layout="channels_last"), estimators=estimators,
               callback_on_step_end=keep_latents, **TINY_CALL_KWARGS)
    assert len(out.report.log) > 0
    assert instance_forwards(pipe.vae) == [] and all(p.is_contiguous() for p in pipe.vae.parameters())
    with torch.no_grad():
        stock = pipe.video_processor.postprocess_video(video=pipe.decode_latents(final["latents"]), output_type="pt")
    assert torch.equal(out.frames, stock)


# ---- the options ----------------------------------------------------------------------------------


def test_the_defaults_are_the_stock_decode():
    run = RunOptions()
    assert (run.decode_layout, run.compile) == ("default", False)


@pytest.mark.parametrize("changes, message", [
    ({"decode_layout": "nhwc"}, r"decode_layout must be one of default, channels_last, got 'nhwc'"),
    ({"compile": "yes"}, r"compile must be true or false, got 'yes'"),
])
def test_bad_options_are_refused_in_one_line(changes, message):
    with pytest.raises(ValueError, match=message) as err:
        resolve_run_options(RunOptions(), changes)
    assert "\n" not in str(err.value)


def test_the_layout_with_the_tiny_decoder_is_refused_in_one_line():
    laid_out = r"decode_layout channels_last lays out the VAE's decode, but guidance.decoder='tiny'"
    with pytest.raises(ValueError, match=laid_out) as err:
        check_run_for_guidance(CHANNELS_LAST, "tiny")
    assert "\n" not in str(err.value)


# ---- torch.compile --------------------------------------------------------------------------------


class RecordingCompile:
    """``torch.compile`` as an identity that records what it wraps and how often that is called."""

    def __init__(self):
        self.wrapped, self.calls = [], 0

    def __call__(self, function, **kwargs):
        self.wrapped.append(function)

        def run(*args, **kw):
            self.calls += 1
            return function(*args, **kw)

        return run


@pytest.mark.parametrize("layout", ["default", "channels_last"])
@pytest.mark.slow
def test_compile_wraps_the_decoder_once_for_every_step(monkeypatch, fresh_compile_cache, layout):
    recording = RecordingCompile()
    monkeypatch.setattr(torch, "compile", recording)
    vae, latents = frozen_vae(), latents_of()
    expected = anchor_decode(vae, latents, checkpoint_chunks=False)
    run = RunOptions(decode_layout=layout, compile=True)
    for _ in range(3):  # three guided steps
        with guidance_decode(run, "vae", vae):
            frames, grad = anchor_decode(vae, latents, checkpoint_chunks=False)
        assert_close(frames, expected[0], torch.float32)
        assert_close(grad, expected[1], torch.float32)
    assert len(recording.wrapped) == 1 and recording.calls == 3 * 2  # two chunk lengths per decode
    assert instance_forwards(vae) == []


def test_compiling_says_so_once_before_the_first_compiled_call(monkeypatch, fresh_compile_cache, caplog):
    """Compiling takes minutes on a CPU: one line says it is under way, not one per call."""
    recording = RecordingCompile()
    monkeypatch.setattr(torch, "compile", recording)
    decoder = tiny_guidance_decoder().requires_grad_(False)
    latents = torch.randn(1, 3, 4, 4, 6, generator=torch.Generator().manual_seed(2))
    with caplog.at_level("WARNING", logger="geco_guide.sampler.running.fast_decode"):
        for _ in range(2):
            with guidance_decode(RunOptions(compile=True), "tiny", vae=None, guidance_decoder=decoder):
                decoder.decode(latents)
    said = [r.getMessage() for r in caplog.records if "compiling the guidance decode" in r.getMessage()]
    assert len(said) == 1 and "minutes" in said[0] and recording.calls == 2


def test_compile_wraps_the_tiny_decoder(monkeypatch, fresh_compile_cache):
    recording = RecordingCompile()
    monkeypatch.setattr(torch, "compile", recording)
    decoder = tiny_guidance_decoder().requires_grad_(False)
    latents = torch.randn(1, 3, 4, 4, 6, generator=torch.Generator().manual_seed(2))
    expected = decoder.decode(latents)
    with guidance_decode(RunOptions(compile=True), "tiny", vae=None, guidance_decoder=decoder):
        frames = decoder.decode(latents)
    assert torch.equal(frames, expected) and recording.calls == 1
    assert "decode" not in decoder.__dict__


@pytest.mark.slow
def test_a_guided_run_with_compile_calls_the_compiled_decoder(monkeypatch, fresh_compile_cache, estimators):
    recording = RecordingCompile()
    monkeypatch.setattr(torch, "compile", recording)
    pipe = tiny_pipeline(0)
    out = pipe("a marble bust", generator=torch.Generator().manual_seed(0), output_type="latent",
               run_options=tiny_run_options(compile=True), estimators=estimators, **TINY_CALL_KWARGS)
    assert len(recording.wrapped) == 1
    assert recording.calls >= 2 * len(out.report.log) > 0  # the tiny anchors: two chunk lengths per update
    assert instance_forwards(pipe.vae) == []


def failing_compile(function, **kwargs):
    def run(*args, **kw):
        raise torch._inductor.exc.InductorError(RuntimeError("No working C++ compiler found\nmore detail"), None)

    return run


def test_a_failed_compile_warns_once_and_decodes_eagerly(monkeypatch, fresh_compile_cache):
    monkeypatch.setattr(torch, "compile", failing_compile)
    vae, latents = frozen_vae(), latents_of()
    expected = anchor_decode(vae, latents, checkpoint_chunks=False)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        for _ in range(2):
            with guidance_decode(RunOptions(compile=True), "vae", vae):
                frames, grad = anchor_decode(vae, latents, checkpoint_chunks=False)
            assert torch.equal(frames, expected[0]) and torch.equal(grad, expected[1])
    fallbacks = [w for w in caught if issubclass(w.category, CompileFallbackWarning)]
    assert len(fallbacks) == 1
    message = str(fallbacks[0].message)
    assert "\n" not in message and "No working C++ compiler found" in message and "runs eagerly" in message


def test_torch_compile_refusing_the_platform_warns_and_decodes_eagerly(monkeypatch, fresh_compile_cache):
    def refuse(function, **kwargs):
        raise RuntimeError("torch.compile is not supported on this Python")

    monkeypatch.setattr(torch, "compile", refuse)
    vae, latents = frozen_vae(), latents_of()
    expected = anchor_decode(vae, latents, checkpoint_chunks=False)
    with pytest.warns(CompileFallbackWarning, match="not supported on this Python"), guidance_decode(RunOptions(compile=True), "vae", vae):
        frames, _ = anchor_decode(vae, latents, checkpoint_chunks=False)
    assert torch.equal(frames, expected[0])


@pytest.mark.slow
def test_compiled_channels_last_decode_traces_forward_and_backward_once(monkeypatch, fresh_compile_cache):
    """Dynamo and AOTAutograd for real (no code generation, which takes minutes here): the traced
    graphs give the eager frames and gradients, and a second step reuses them."""
    from functorch.compile import make_boxed_func
    from torch._dynamo.backends.common import aot_autograd

    compiled_graphs = []

    def keep(kind):
        def compiler(graph, example_inputs):
            compiled_graphs.append(kind)
            return make_boxed_func(graph.forward)

        return compiler

    backend = aot_autograd(fw_compiler=keep("forward"), bw_compiler=keep("backward"))
    monkeypatch.setattr(torch, "compile", partial(torch.compile, backend=backend))
    torch._dynamo.reset()
    vae = frozen_vae(sizes=TinySizes(vae_channels=(8, 8)))  # two blocks: tracing takes seconds, not tens
    latents = latents_of()[:, 1:4]  # one chunk of three latents: one graph
    expected = anchor_decode_chunk(vae, latents)
    run = RunOptions(decode_layout="channels_last", compile=True)
    try:
        for step in range(2):
            with guidance_decode(run, "vae", vae):
                frames, grad = anchor_decode_chunk(vae, latents)
            assert_close(frames, expected[0], torch.float32)
            assert_close(grad, expected[1], torch.float32)
            if step == 0:
                first = list(compiled_graphs)
        assert "forward" in first and "backward" in first
        assert compiled_graphs == first
    finally:
        torch._dynamo.reset()


def anchor_decode_chunk(vae, latents):
    latents = latents.detach().requires_grad_(True)
    frames = decode_chunk(vae, latents, 0.7)
    (grad,) = torch.autograd.grad(frames.square().sum(), latents)
    return frames.detach(), grad


def test_a_hooked_pipeline_of_another_vae_is_refused_before_its_first_denoiser_call(estimators):
    from geco_guide.sampler.pipelines.hooks import attach_geco_guidance
    from geco_guide.tiny import tiny_call_kwargs, tiny_wan_pipeline

    pipe = tiny_wan_pipeline(0)
    calls = []
    pipe.transformer.register_forward_pre_hook(lambda module, args: calls.append(1))
    config = {"anchors": [4, 8], "repeats": "1x4", "time_travel": []}
    with attach_geco_guidance(pipe, config, estimators, run_options={"decode_layout": "channels_last"}):
        with pytest.raises(TypeError, match="written for the CogVideoX VAE"):
            pipe(prompt="a cat", output_type="latent", **tiny_call_kwargs(pipe, num_frames=9))
    assert calls == []
