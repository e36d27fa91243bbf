"""GeCoCogVideoXPipeline as a drop-in diffusers CogVideoXPipeline, tiny models on CPU.

With guidance off the call must be the stock call in every respect; with guidance on every
contract but the output values holds, or the combination is refused up front in one line. Each
test names the test of diffusers' ``tests/pipelines/cogvideo/test_cogvideox.py`` (or of the
mixins it uses, ``tests/pipelines/test_pipelines_common.py``) that it mirrors.
"""

from __future__ import annotations

import warnings

from dataclasses import replace

import pytest
import torch
from counting import CountingForward
from diffusers import (
    CogVideoXDDIMScheduler,
    CogVideoXDPMScheduler,
    CogVideoXPipeline,
    DDIMScheduler,
    FasterCacheConfig,
    FirstBlockCacheConfig,
    PyramidAttentionBroadcastConfig,
)

from geco_guide.sampler.algorithm.config import GuidanceConfig
from geco_guide.sampler.pipelines.hooks import attach_geco_guidance
from geco_guide.sampler.pipelines.pipeline_cogvideox import GeCoCogVideoXPipeline
from geco_guide.loss.presets import fused_guidance_loss
from geco_guide.tiny import (
    tiny_estimators,
    TINY_CALL_KWARGS,
    TinySizes,
    tiny_cogvideox_components,
    tiny_cogvideox_pipeline,
    tiny_cogvideox_transformer,
    tiny_run_options,
    tiny_guidance_config,
)

PROMPT = "a marble bust on a table"
# guidance on the last two of 4 steps, no time travel: short and deterministic
SHORT = dict(repeats="0x2,1x2", time_travel=[])


def pair(estimators, scheduler=None, seed=0, **guidance):
    """A stock CogVideoXPipeline and a GeCoCogVideoXPipeline with the same weights and scheduler."""
    components = tiny_cogvideox_components(seed)
    if scheduler is not None:
        components["scheduler"] = scheduler
    stock = CogVideoXPipeline(**components)
    ours = GeCoCogVideoXPipeline(**components, guidance_config=tiny_guidance_config(**{**SHORT, **guidance}))
    for pipe in (stock, ours):
        pipe.set_progress_bar_config(disable=True)
    return stock, ours


def call(pipe, seed=0, **kwargs):
    """A call of ``pipe``; ours with the tiny estimators and run options unless told otherwise."""
    args = dict(TINY_CALL_KWARGS, output_type="latent")
    if isinstance(pipe, GeCoCogVideoXPipeline):
        args.update(estimators=tiny_estimators(0), run_options=tiny_run_options())
    args.update(kwargs)
    return pipe(PROMPT, generator=torch.Generator().manual_seed(seed), **args)


def ddim_settings(**changes):
    return dict(tiny_cogvideox_components(0)["scheduler"].config, **changes)


# ---- the scheduler's own rule, eta and generator -----------------------------------------------


@pytest.mark.parametrize("spacing", ["linspace", "leading", "trailing"])
def test_guidance_off_is_stock_ddim_for_every_timestep_spacing(spacing, estimators):
    # mirrors test_inference (a stock call's output), for each timestep_spacing of the scheduler
    scheduler = CogVideoXDDIMScheduler.from_config(ddim_settings(timestep_spacing=spacing))
    stock, ours = pair(estimators, scheduler)
    for seed in (0, 1):
        assert torch.equal(call(ours, seed, guidance=False).frames, call(stock, seed).frames), spacing


@pytest.mark.parametrize("spacing", ["linspace", "leading"])
@pytest.mark.slow
def test_guided_pipeline_uses_the_schedulers_alpha_prev_like_the_hooks(spacing, estimators):
    # time travel steps and re-noises with alpha_prev = alphas[t - T // n], the rule scheduler.step
    # uses; the hooks use it too, so the pipeline and the hooked stock pipeline agree
    scheduler = CogVideoXDDIMScheduler.from_config(ddim_settings(timestep_spacing=spacing))
    stock, ours = pair(estimators, scheduler)
    config = tiny_guidance_config(repeats="0x2,1x2", time_travel=[2, 3], step_size=1.0, denoiser_grad=False)
    ours_out = call(ours, 1, guidance=config)
    with attach_geco_guidance(stock, config, estimators=estimators) as handle:
        hooked = call(stock, 1).frames
    assert [e["t"] for e in handle.log] == [e["t"] for e in ours_out.report.log]
    for a, b in zip(handle.log, ours_out.report.log):
        assert a["loss"] == pytest.approx(b["loss"], rel=1e-4)
    torch.testing.assert_close(hooked, ours_out.frames, rtol=1e-4, atol=1e-4)


@pytest.mark.slow
def test_eta_and_generator_reach_the_scheduler_step(estimators):
    # mirrors prepare_extra_step_kwargs in test_inference: a DDIM that honours eta draws its noise
    # from the call's generator, with guidance off (as stock) and on
    scheduler = DDIMScheduler.from_config(ddim_settings())
    stock, ours = pair(estimators, scheduler)
    assert torch.equal(call(ours, 2, guidance=False, eta=1.0).frames, call(stock, 2, eta=1.0).frames)
    deterministic = call(ours, 2, eta=0.0).frames
    torch.manual_seed(100)
    a = call(ours, 2, eta=1.0).frames
    torch.manual_seed(200)
    b = call(ours, 2, eta=1.0).frames
    assert torch.equal(a, b) and not torch.equal(a, deterministic)


# ---- guidance off behaves as the stock pipeline -----------------------------------------------


def test_inference_with_8_frames_and_guidance_off(estimators):
    # mirrors test_inference (diffusers' dummy inputs ask for num_frames=8)
    stock, ours = pair(estimators)
    ref = call(stock, 0, num_frames=8, output_type="pt").frames
    assert ref.shape[1] == 8
    assert torch.equal(call(ours, 0, num_frames=8, output_type="pt", guidance=False).frames, ref)
    with pytest.raises(ValueError, match="4\\*k \\+ 1"):  # what guidance needs, checked only when on
        call(ours, 0, num_frames=8)


def test_epsilon_prediction_scheduler_with_guidance_off(estimators):
    # mirrors test_inference with diffusers' dummy components: CogVideoXDDIMScheduler() defaults
    # to prediction_type="epsilon"
    scheduler = CogVideoXDDIMScheduler()
    assert scheduler.config.prediction_type == "epsilon"
    stock, ours = pair(estimators, scheduler)
    assert torch.equal(call(ours, 0, guidance=False).frames, call(stock, 0).frames)
    counter = CountingForward(ours.transformer)
    try:
        with pytest.raises(ValueError, match="prediction_type='epsilon'"):
            call(ours, 0)
    finally:
        counter.handle.remove()
    assert counter.n == 0


def test_none_components_are_accepted(estimators):
    # mirrors test_encode_prompt_works_in_isolation (a text-encoder-only pipeline)
    c = tiny_cogvideox_components(0)
    stock = CogVideoXPipeline(tokenizer=c["tokenizer"], text_encoder=c["text_encoder"], vae=None, transformer=None,
                              scheduler=None)
    ours = GeCoCogVideoXPipeline(tokenizer=c["tokenizer"], text_encoder=c["text_encoder"], vae=None, transformer=None,
                                 scheduler=None)
    kwargs = dict(do_classifier_free_guidance=True, max_sequence_length=16, device=torch.device("cpu"))
    for a, b in zip(ours.encode_prompt(PROMPT, **kwargs), stock.encode_prompt(PROMPT, **kwargs)):
        assert torch.equal(a, b)
    assert ours.scheduler is None and ours.vae is None


@pytest.mark.parametrize(
    "make",
    [
        lambda: CogVideoXDDIMScheduler.from_config(ddim_settings(snr_shift_scale=1.0)),
        lambda: CogVideoXDPMScheduler.from_config(ddim_settings()),
        lambda: DDIMScheduler.from_config(ddim_settings()),
    ],
    ids=["cogvideox-ddim", "cogvideox-dpm", "ddim"],
)
@pytest.mark.slow
def test_the_users_scheduler_is_kept(make, estimators):
    # mirrors test_components_function and test_save_load_local (the scheduler is a component,
    # kept as given); the paper's DDIM is chosen explicitly by the caller or the preset
    scheduler = make()
    stock, ours = pair(estimators, scheduler)
    assert ours.scheduler is scheduler and ours.components["scheduler"] is scheduler
    assert torch.equal(call(ours, 3, guidance=False).frames, call(stock, 3).frames)
    out = call(ours, 3)  # guidance runs with each of them, through the scheduler's own step
    assert len(out.report.log) == 2 and type(ours.scheduler) is type(scheduler)


def test_components_are_the_stock_ones(estimators):
    # mirrors test_components_function: the estimators enter at the call, like a guider
    stock, ours = pair(estimators)
    assert set(ours.components) == set(stock.components)
    again = GeCoCogVideoXPipeline(**ours.components)
    assert again.transformer is ours.transformer and again.guidance_config == GuidanceConfig()


def test_to_device_dtype_and_save_are_diffusers_own(estimators):
    # mirrors test_to_dtype / test_to_device: nothing of DiffusionPipeline is overridden
    for name in ("__setattr__", "to", "device", "dtype", "save_pretrained"):
        assert name not in vars(GeCoCogVideoXPipeline), name
    _, ours = pair(estimators)
    ours.to(torch.float64)
    assert ours.transformer.dtype == torch.float64 and ours.dtype == torch.float64
    ours.to("cpu")
    assert ours.device == torch.device("cpu")
    with pytest.raises(AttributeError):
        ours.guidance_config = GuidanceConfig()  # set once, at construction


# ---- with guidance on: contracts hold, or the combination is refused clearly --------------------


@pytest.mark.slow
def test_other_step_counts_scale_the_schedule_with_a_warning(estimators):
    # mirrors test_inference (diffusers' dummy inputs use num_inference_steps=2)
    _, ours = pair(estimators, repeats="0x2,2x2")  # written for 4 steps
    with pytest.warns(UserWarning, match="written for 4 steps, the sampler runs 2"):
        out = call(ours, 0, num_inference_steps=2)
    assert [e["step"] for e in out.report.log] == [1, 1]  # "0x1,2x1"
    with pytest.raises(ValueError, match="covers 4 steps but the sampler runs 2"):
        call(ours, 0, num_inference_steps=2, guidance={"repeats": [0, 0, 2, 2]})  # per step: exact
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        call(ours, 0)  # the step count it was written for: no warning


@pytest.mark.slow
def test_batched_guidance_normalises_per_video(estimators):
    # mirrors test_inference_batch_single_identical: two identical videos in one batch (same
    # prompt, same generator seed) stay identical when guided
    _, ours = pair(estimators, time_travel=[3, 3])
    out = ours([PROMPT, PROMPT], generator=[torch.Generator().manual_seed(5), torch.Generator().manual_seed(5)],
               estimators=estimators, run_options=tiny_run_options(), **dict(TINY_CALL_KWARGS, output_type="latent"))
    assert out.frames.shape[0] == 2 and len(out.report.log) == 2
    torch.testing.assert_close(out.frames[0], out.frames[1])


def test_callback_inputs_with_guidance_on(estimators):
    # mirrors test_callback_inputs and test_callback_cfg
    _, ours = pair(estimators)
    seen = []
    names = ["latents", "prompt_embeds", "negative_prompt_embeds"]

    def callback(pipe, i, t, kwargs):
        seen.append((i, sorted(kwargs)))
        if i == 1:
            pipe._guidance_scale = 1.0  # as test_callback_cfg: changing CFG mid-call is honoured
        return {"latents": kwargs["latents"]}

    out = call(ours, 0, callback_on_step_end=callback, callback_on_step_end_tensor_inputs=names)
    assert [i for i, _ in seen] == [0, 1, 2, 3] and all(keys == sorted(names) for _, keys in seen)
    assert len(out.report.log) == 2 and ours.guidance_scale == 1.0


@pytest.mark.slow
def test_fused_qkv_projections_with_guidance(estimators):
    # mirrors test_fused_qkv_projections
    _, ours = pair(estimators, denoiser_grad=True)
    plain_off, plain_on = call(ours, 0, guidance=False).frames, call(ours, 0).frames
    ours.fuse_qkv_projections()
    try:
        fused_off, fused_on = call(ours, 0, guidance=False).frames, call(ours, 0).frames
    finally:
        ours.unfuse_qkv_projections()
    torch.testing.assert_close(fused_off, plain_off, rtol=1e-3, atol=1e-3)
    torch.testing.assert_close(fused_on, plain_on, rtol=1e-3, atol=1e-3)


@pytest.mark.parametrize("cache", ["PyramidAttentionBroadcast", "FasterCache", "FirstBlockCache"])
def test_denoiser_caches_are_refused_with_guidance_and_work_without(cache, estimators):
    # mirrors PyramidAttentionBroadcastTesterMixin, FasterCacheTesterMixin, FirstBlockCacheTesterMixin
    _, ours = pair(estimators)
    if cache == "FirstBlockCache":  # it needs at least two transformer blocks
        torch.manual_seed(0)
        ours.transformer = tiny_cogvideox_transformer(TinySizes(), num_layers=2).eval()
    def timestep():
        return ours.current_timestep

    config = {
        "PyramidAttentionBroadcast": lambda: PyramidAttentionBroadcastConfig(
            spatial_attention_block_skip_range=2, spatial_attention_timestep_skip_range=(100, 800),
            current_timestep_callback=timestep,
        ),
        "FasterCache": lambda: FasterCacheConfig(
            spatial_attention_block_skip_range=2, spatial_attention_timestep_skip_range=(-1, 901),
            unconditional_batch_skip_range=2, attention_weight_callback=lambda _: 0.5,
            current_timestep_callback=timestep, is_guidance_distilled=False,
        ),
        "FirstBlockCache": lambda: FirstBlockCacheConfig(threshold=0.8),
    }[cache]()
    ours.transformer.enable_cache(config)
    try:
        counter = CountingForward(ours.transformer)
        try:
            with pytest.raises(ValueError) as err:
                call(ours, 0)
        finally:
            counter.handle.remove()
        assert counter.n == 0 and cache in str(err.value) and "disable_cache()" in str(err.value)
        assert "\n" not in str(err.value)
        assert call(ours, 0, guidance=False).frames.shape[0] == 1  # unguided: the cache works as stock
    finally:
        ours.transformer.disable_cache()


@pytest.mark.slow
def test_save_load_round_trips_the_guidance_config(tmp_path, estimators):
    # mirrors test_save_load_local and test_save_load_optional_components
    _, ours = pair(estimators, step_size=1.5, loss=replace(fused_guidance_loss(), cue="motion"))
    ours.save_pretrained(tmp_path)
    assert not any((tmp_path / name).exists() for name in ("geometry_estimator", "flow_estimator"))
    loaded = GeCoCogVideoXPipeline.from_pretrained(tmp_path)
    loaded.set_progress_bar_config(disable=True)
    assert loaded.guidance_config == ours.guidance_config
    assert loaded.guidance_config.step_size == 1.5 and loaded.guidance_config.loss.cue == "motion"
    a, b = call(ours, 4), call(loaded, 4)
    assert [e["loss"] for e in a.report.log] == [e["loss"] for e in b.report.log]
    torch.testing.assert_close(a.frames, b.frames, rtol=0, atol=0)
    # a guided call without estimators says what is missing, in one line
    with pytest.raises(ValueError, match=r"pass estimators=Estimators\(geometry, flow\) to the call"):
        call(loaded, 4, estimators=None)
    assert "guidance_config" in repr(ours)


@pytest.mark.slow
def test_model_cpu_offload_with_guidance(estimators):
    # mirrors test_model_cpu_offload_forward_pass / test_cpu_offload_forward_pass_twice: accelerate's
    # model offload hooks (device="cpu" here, so it runs without an accelerator) change nothing,
    # the estimators (excluded from offload) are placed on the execution device. Sequential offload
    # fails in this environment for the stock pipeline too (accelerate vs torch 2.13), so it is not
    # tested here.
    _, plain = pair(estimators)
    _, offloaded = pair(estimators)
    offloaded.enable_model_cpu_offload(device="cpu")
    for guidance in ({"denoiser_grad": True}, {"denoiser_grad": False}):
        ref = call(plain, 0, guidance=guidance)
        once, twice = call(offloaded, 0, guidance=guidance), call(offloaded, 0, guidance=guidance)
        assert torch.equal(once.frames, ref.frames) and torch.equal(twice.frames, ref.frames)
        assert len(once.report.log) == 2
    assert {p.device.type for p in estimators.geometry.parameters()} == {"cpu"}  # no component: left as it was


# ---- the caller's latents (``test_cogvideox.py`` passes none; the stock call takes them as given) --


@pytest.mark.parametrize("version", ["1.0", "1.5"])
@pytest.mark.slow
def test_latents_of_the_shape_the_stock_pipeline_draws_give_its_output(version, estimators):
    stock = tiny_cogvideox_pipeline(0, version=version)
    stock.set_progress_bar_config(disable=True)
    ours = GeCoCogVideoXPipeline(**stock.components, guidance_config=tiny_guidance_config(**SHORT))
    ours.set_progress_bar_config(disable=True)
    drawn = []
    prepare = stock.prepare_latents
    stock.prepare_latents = lambda *args, **kwargs: drawn.append(prepare(*args, **kwargs)) or drawn[-1]
    reference = call(stock, seed=1).frames
    shape, padding = ours.latents_shape(1, TINY_CALL_KWARGS["num_frames"], TINY_CALL_KWARGS["height"],
                                        TINY_CALL_KWARGS["width"])
    assert shape == tuple(drawn[0].shape) and padding == (1 if version == "1.5" else 0)  # 5 latents padded to 6
    assert torch.equal(call(ours, seed=5, guidance=False, latents=drawn[0].clone()).frames, reference)
    guided = call(ours, seed=5, latents=drawn[0].clone())
    assert torch.isfinite(guided.frames).all() and len(guided.report.log) == 2
