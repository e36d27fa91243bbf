"""attach_geco_guidance: GeCo guidance hooked into stock diffusers video pipelines (tiny, CPU)."""

from __future__ import annotations

import copy
import inspect
import re

import pytest
import torch
from counting import CountingForward, CountingHook
from diffusers.hooks import HookRegistry

from geco_guide import tiny as T
from geco_guide.loss.geco import GeCoLoss, GeCoLossConfig
from geco_guide.sampler.algorithm.levels import keep_update
from geco_guide.sampler.pipelines.hooks import attach_geco_guidance
from geco_guide.sampler.algorithm.levels import FlowLevels, flow_renoise, flow_step, flow_to_x0
from geco_guide.sampler.algorithm.step import score_anchor_frames

PROMPT = "a marble bust on a table"
NUM_FRAMES = 9  # 3 latents at r=4 (2 at r=8, LTX)
ANCHORS = [5, 8]  # both in the last latent: one causal chunk, the whole (short) video
# guidance on the last of 4 steps only: what it changes is what comes out
LAST_STEP = dict(anchors=ANCHORS, chunk_latents=3, repeats="0x3,2x1", time_travel=[], step_size=1.0)

BUILDERS = {
    "cogvideox": lambda seed: T.tiny_cogvideox_pipeline(seed),
    "cogvideox-1.5": lambda seed: T.tiny_cogvideox_pipeline(seed, version="1.5"),
    "cogvideox-1.5-dpm": lambda seed: T.tiny_cogvideox_pipeline(seed, version="1.5", scheduler="dpm"),
    "cogvideox-i2v": lambda seed: T.tiny_cogvideox_i2v_pipeline(seed),
    "wan": lambda seed: T.tiny_wan_pipeline(seed),  # UniPC: corrector reads last_sample
    "ltx": lambda seed: T.tiny_ltx_pipeline(seed),
    "hunyuan": lambda seed: T.tiny_hunyuan_pipeline(seed),
}


def run(pipe, seed=0, **changes):
    kwargs = T.tiny_call_kwargs(pipe, **{"num_frames": NUM_FRAMES, **changes})
    kwargs.setdefault("output_type", "pt")
    return pipe(prompt=PROMPT, negative_prompt="blurry", generator=torch.Generator().manual_seed(seed), **kwargs).frames


def score(frames, estimators, config):
    return score_anchor_frames(frames, config.anchors, GeCoLoss(estimators, config.loss))["loss"]


def counting(module):
    """A :class:`CountingHook` in ``module``'s hook registry: the forward calls that really ran."""
    hook = CountingHook()
    HookRegistry.check_if_exists_or_initialize(module).register_hook(hook, "count")
    return hook


def state_of(pipe):
    """Everything a hook could leave behind: instance dicts and torch hooks."""
    modules = [m for m in pipe.components.values() if isinstance(m, torch.nn.Module)]
    return (
        set(pipe.__dict__),
        set(pipe.scheduler.__dict__),
        [(len(m._forward_pre_hooks), len(m._forward_hooks), "forward" in m.__dict__, hasattr(m, "_diffusers_hook"))
         for mod in modules for m in mod.modules()],
        [p.requires_grad for mod in modules for p in mod.parameters()],
    )


# ---- every supported pipeline ------------------------------------------------------------------


@pytest.mark.parametrize(
    "family, faithful",
    [
        ("cogvideox", False),
        ("cogvideox-1.5", True),
        ("cogvideox-1.5-dpm", False),
        ("cogvideox-i2v", True),
        ("wan", True),
        ("ltx", False),
        ("hunyuan", True),
    ],
)
@pytest.mark.slow
def test_guidance_lowers_geco_loss_and_detach_restores_bitwise(family, faithful, estimators):
    config = T.tiny_guidance_config(**LAST_STEP, denoiser_grad=faithful)
    never_hooked = BUILDERS[family](0)
    reference = run(never_hooked)
    pipe = BUILDERS[family](0)
    handle = attach_geco_guidance(pipe, config, estimators=estimators)
    guided = run(pipe)
    handle.detach()
    after = run(pipe)

    assert torch.equal(after, reference), "detach() must restore the pipeline bit for bit"
    assert state_of(pipe) == state_of(never_hooked)  # (both have run: the pipelines set call attributes)
    base = score(reference, estimators, config)
    assert score(guided, estimators, config) < base
    assert [e["step"] for e in handle.log] == [3, 3] and all(e["grad_norm"] > 0 for e in handle.log)
    if family != "cogvideox-1.5-dpm":  # (its last step is stochastic)
        # the first update scores x0 of the unguided last step, decoded by the adapter from the
        # anchor chunk: it must be what the pipeline itself decodes (layout, padding, normalisation)
        assert handle.log[0]["loss"] == pytest.approx(base, rel=1e-3)


# ---- the shared guided step: same as GeCoCogVideoXPipeline ------------------------------------


@pytest.mark.parametrize("faithful", [False, True])
def test_hook_on_stock_cogvideox_matches_geco_pipeline(faithful, estimators):
    from diffusers import CogVideoXPipeline

    from geco_guide.sampler.pipelines.pipeline_cogvideox import GeCoCogVideoXPipeline

    config = T.tiny_guidance_config(
        anchors=ANCHORS, repeats="0x2,1x1,1x1", time_travel=[2, 2], step_size=1.0, denoiser_grad=faithful
    )
    geco = GeCoCogVideoXPipeline(**T.tiny_cogvideox_components(0))
    geco.set_progress_bar_config(disable=True)
    stock = CogVideoXPipeline(**T.tiny_cogvideox_components(0))
    stock.set_progress_bar_config(disable=True)
    kwargs = dict(T.TINY_CALL_KWARGS, num_frames=NUM_FRAMES, output_type="latent")
    ours = geco(PROMPT, generator=torch.Generator().manual_seed(1), guidance=config, estimators=estimators,
                run_options=T.tiny_run_options(), **kwargs)
    with attach_geco_guidance(stock, config, estimators=estimators) as handle:
        hooked = stock(PROMPT, generator=torch.Generator().manual_seed(1), **kwargs).frames
    assert [(e["step"], e["time_travel"]) for e in handle.log] == [(2, True), (3, False)]
    for a, b in zip(handle.log, ours.report.log):
        assert a["loss"] == pytest.approx(b["loss"], rel=1e-4) and a["t"] == b["t"]
    torch.testing.assert_close(hooked, ours.frames, rtol=1e-4, atol=1e-4)


@pytest.mark.slow
def test_time_travel_is_reproducible_from_the_generator(estimators):
    pipe = T.tiny_hunyuan_pipeline(0)
    config = T.tiny_guidance_config(anchors=ANCHORS, repeats="0x2,1x2", time_travel=[2, 3], step_size=1.0, denoiser_grad=False)
    with attach_geco_guidance(pipe, config, estimators=estimators) as handle:
        a, b, c = run(pipe, seed=7), run(pipe, seed=7), run(pipe, seed=8)
    assert len(handle.log) == 2 and all(e["time_travel"] for e in handle.log)
    assert torch.equal(a, b) and not torch.equal(a, c)


# ---- flow matching arithmetic and multistep history ----------------------------------------------


def test_flow_levels_step_is_euler_and_renoise_is_the_forward_process():
    from diffusers import FlowMatchEulerDiscreteScheduler

    sched = FlowMatchEulerDiscreteScheduler(shift=3.0)
    sched.set_timesteps(5)
    z, v = torch.randn(2, 4, 3, 5, 5), torch.randn(2, 4, 3, 5, 5)
    levels = FlowLevels(sched.sigmas[1], sched.sigmas[2])
    euler = sched.step(v, sched.timesteps[1], z, return_dict=False)[0]
    torch.testing.assert_close(levels.step(z, levels.to_x0(z, v)), euler, rtol=1e-5, atol=1e-5)
    assert torch.equal(flow_to_x0(z, v, 0.25), z - 0.25 * v)
    # z_prev = (1 - s_p) x0 + s_p e  ->  renoise to s_t: mean (1 - s_t) x0, std s_t
    x0 = torch.full((400_000,), 0.7)
    s_t, s_p = 0.8, 0.3
    g = torch.Generator().manual_seed(0)
    z_prev = (1 - s_p) * x0 + s_p * torch.randn(x0.shape, generator=g)
    z_t = flow_renoise(z_prev, s_t, s_p, torch.randn(x0.shape, generator=g))
    assert float(z_t.mean()) == pytest.approx((1 - s_t) * 0.7, abs=3e-3)
    assert float(z_t.std()) == pytest.approx(s_t, rel=3e-3)
    assert torch.equal(flow_step(z, z, 0.5, 0.2), z)  # x0 = z: nothing left to remove


def test_unipc_corrector_keeps_the_guided_update():
    from diffusers import UniPCMultistepScheduler

    sched = UniPCMultistepScheduler(prediction_type="flow_prediction", use_flow_sigmas=True, flow_shift=3.0)
    sched.set_timesteps(6)
    g = torch.Generator().manual_seed(0)
    z = torch.randn(1, 4, 3, 4, 6, generator=g)
    for i in range(2):  # fill the history: from now on the corrector runs
        z = sched.step(torch.randn(z.shape, generator=g), sched.timesteps[i], z, return_dict=False)[0]
    i, t = 2, sched.timesteps[2]
    sigma, sigma_next = float(sched.sigmas[i]), float(sched.sigmas[i + 1])
    v = torch.randn(z.shape, generator=g)
    delta = 0.1 * torch.randn(z.shape, generator=g)
    v_moved = v + delta / sigma  # the same x0 = z - sigma v at the moved sample

    plain = copy.deepcopy(sched).step(v, t, z, return_dict=False)[0]
    naive = copy.deepcopy(sched).step(v_moved, t, z + delta, return_dict=False)[0]
    kept_sched = copy.deepcopy(sched)
    keep_update(kept_sched, z, z + delta)
    kept = kept_sched.step(v_moved, t, z + delta, return_dict=False)[0]
    # handing the scheduler a moved sample is not enough: the corrector rebuilds it from last_sample
    torch.testing.assert_close(naive, plain, rtol=1e-5, atol=1e-5)
    # with the history shifted the update survives, scaled as the predictor scales its sample
    torch.testing.assert_close(kept - plain, (sigma_next / sigma) * delta, rtol=1e-4, atol=1e-5)


# ---- up-front checks, errors, detach ------------------------------------------------------------


@pytest.mark.parametrize(
    "family, changes, call, match",
    [
        ("wan", dict(anchors=[5, 12]), {}, "out of range for a 9-frame video"),
        ("ltx", dict(anchors=[8, 16]), {}, "out of range for a 9-frame video"),  # r = 8
        ("cogvideox", dict(anchors=[0, 8]), {}, "latent 0"),
        ("cogvideox", {}, dict(num_frames=13), "even number of latents"),
        # (runs are scaled to other step counts; a per-step list must match)
        ("hunyuan", dict(repeats=[0, 0, 0, 1, 1]), {}, "covers 5 steps but the sampler runs 4"),
        ("cogvideox", dict(loss=GeCoLossConfig(cue="structure", geometry_grad=False)), {},
         "geometry_grad=true"),
    ],
)
def test_bad_calls_are_rejected_before_any_denoising_step(family, changes, call, match, estimators):
    pipe = BUILDERS[family](0)
    config = T.tiny_guidance_config(**{**LAST_STEP, **changes})
    counter = counting(pipe.transformer)  # registered first: it runs inside the guidance's capture
    with attach_geco_guidance(pipe, config, estimators=estimators):
        with pytest.raises(ValueError, match=match):
            run(pipe, **call)
    assert counter.n == 0


def test_default_anchors_spread_over_the_video_and_explicit_ones_must_fit(estimators):
    pipe = T.tiny_wan_pipeline(0)  # 17 frames: the paper's four anchors spread over them
    with attach_geco_guidance(pipe, {"step_size": 2.0, "repeats": "0x3,1x1", "time_travel": []}, estimators) as handle:
        run(pipe, num_frames=17)
    assert handle.last.guidance["anchors"] is None and len(handle.log) == 1
    with attach_geco_guidance(pipe, {"anchors": [12, 24, 36, 48]}, estimators=estimators):
        with pytest.raises(ValueError) as err:
            run(pipe, num_frames=17)
    assert str(err.value) == ("anchors [24, 36, 48] are out of range for a 17-frame video: set anchors "
                              "(guidance.anchors) to frames in 1..16, or to null (the paper's four, spread over the "
                              "video)")


def test_unsupported_pipelines_get_a_clear_error(estimators):
    from diffusers import DiffusionPipeline

    class MyVideoPipeline(DiffusionPipeline):
        pass

    with pytest.raises(ValueError) as err:
        attach_geco_guidance(MyVideoPipeline(), estimators=estimators)
    message = str(err.value)
    for name in ("CogVideoXPipeline", "CogVideoXImageToVideoPipeline", "WanPipeline", "LTXPipeline", "HunyuanVideoPipeline"):
        assert name in message
    assert "register_adapter" in message and "MyVideoPipeline" in message
    with pytest.raises(ValueError, match="guides itself"):
        attach_geco_guidance(T.tiny_pipeline(0), estimators=estimators)
    with pytest.raises(ValueError, match="estimators.flow must implement"):
        attach_geco_guidance(T.tiny_wan_pipeline(0), None, estimators.__class__(estimators.geometry, None))
    with pytest.raises(ValueError, match="needs its models"):
        attach_geco_guidance(T.tiny_wan_pipeline(0))


def test_attach_twice_is_refused_and_detach_is_idempotent(estimators):
    pipe = T.tiny_ltx_pipeline(0)
    before = state_of(pipe)
    handle = attach_geco_guidance(pipe, T.tiny_guidance_config(**LAST_STEP), estimators=estimators)
    assert handle.attached and state_of(pipe) != before
    with pytest.raises(ValueError, match="already"):
        attach_geco_guidance(pipe, estimators=estimators)
    handle.detach()
    handle.detach()
    assert not handle.attached and state_of(pipe) == before
    with attach_geco_guidance(pipe, estimators=estimators) as again:
        assert again.attached
    assert state_of(pipe) == before


def test_guidance_off_and_models_untouched(estimators):
    pipe = T.tiny_wan_pipeline(0, scheduler="euler")
    reference = run(pipe)
    weights = copy.deepcopy(pipe.transformer.state_dict())
    with attach_geco_guidance(pipe, {**LAST_STEP, "enabled": False}, estimators=estimators) as h:
        assert torch.equal(run(pipe), reference) and h.log == []
        h.config = T.tiny_guidance_config(**LAST_STEP, denoiser_grad=True)
        guided = run(pipe)
    assert len(h.log) == 2 and not torch.equal(guided, reference)
    assert all(torch.equal(weights[k], v) for k, v in pipe.transformer.state_dict().items())
    assert all(p.grad is None for p in pipe.transformer.parameters())
    assert all(p.grad is None for p in pipe.vae.parameters())


def test_ltx_guidance_rescale_is_rebuilt_and_wrong_combinations_fail_loudly(estimators, monkeypatch):
    from geco_guide.sampler.pipelines.adapters import LTXAdapter

    pipe = T.tiny_ltx_pipeline(0)
    config = T.tiny_guidance_config(**LAST_STEP, denoiser_grad=False)
    with attach_geco_guidance(pipe, config, estimators=estimators) as handle:
        run(pipe, guidance_rescale=0.7)
        assert len(handle.log) == 2
        # an adapter whose combination does not reproduce the pipeline's model output (here: the
        # text branch alone, no CFG) is refused instead of guiding with a wrong prediction
        monkeypatch.setattr(LTXAdapter, "combine", lambda self, pipe, parts, weights, **step: parts[1].float())
        with pytest.raises(ValueError, match="cannot rebuild the model output"):
            run(pipe, guidance_rescale=0.7)


# ---- the wrapped scheduler.step keeps the scheduler's call contract ----------------------------


def test_wrapped_step_keeps_the_signature_pipelines_inspect(estimators):
    import inspect

    pipe = T.tiny_cogvideox_pipeline(0, scheduler="dpm")
    before = inspect.signature(pipe.scheduler.step)
    assert {"eta", "generator"} <= set(before.parameters)
    g = torch.Generator().manual_seed(0)
    with attach_geco_guidance(pipe, T.tiny_guidance_config(**LAST_STEP), estimators=estimators):
        assert inspect.signature(pipe.scheduler.step) == before
        # diffusers' prepare_extra_step_kwargs decides from the signature what to pass
        assert pipe.prepare_extra_step_kwargs(g, 0.5) == {"eta": 0.5, "generator": g}


def test_stochastic_scheduler_noise_comes_from_the_calls_generator(estimators):
    # CogVideoXDPMScheduler (the scheduler CogVideoX-5B ships) draws noise at every step: with the
    # hook attached, the call's generator must still be what determines the video, not the global RNG
    pipe = T.tiny_cogvideox_pipeline(0, scheduler="dpm")
    config = T.tiny_guidance_config(**LAST_STEP, denoiser_grad=False)
    with attach_geco_guidance(pipe, config, estimators=estimators) as handle:
        torch.manual_seed(100)
        a = run(pipe, seed=3, output_type="latent")
        torch.manual_seed(200)
        b = run(pipe, seed=3, output_type="latent")
        c = run(pipe, seed=4, output_type="latent")
        assert len(handle.log) == 2
    assert torch.equal(a, b) and not torch.equal(a, c)


@pytest.mark.slow
def test_eta_reaches_a_ddim_scheduler_through_the_hook(estimators):
    from diffusers import DDIMScheduler

    pipe = T.tiny_cogvideox_pipeline(0)
    pipe.scheduler = DDIMScheduler.from_config(pipe.scheduler.config)  # honours eta (CogVideoX's DDIM ignores it)
    config = T.tiny_guidance_config(**LAST_STEP, denoiser_grad=False)
    with attach_geco_guidance(pipe, config, estimators=estimators) as handle:
        deterministic = run(pipe, seed=3, output_type="latent", eta=0.0)
        torch.manual_seed(100)
        a = run(pipe, seed=3, output_type="latent", eta=1.0)
        torch.manual_seed(200)
        b = run(pipe, seed=3, output_type="latent", eta=1.0)
        assert len(handle.log) == 2
    assert not torch.equal(a, deterministic)  # eta reached the step: it added noise ...
    assert torch.equal(a, b)  # ... drawn from the call's generator


def test_denoiser_cache_is_refused_before_any_denoising_step(estimators):
    # with guidance on, a cache would count the guidance's denoiser calls as steps
    from diffusers import FasterCacheConfig

    pipe = T.tiny_cogvideox_pipeline(0)
    pipe.transformer.enable_cache(FasterCacheConfig(
        spatial_attention_block_skip_range=2, spatial_attention_timestep_skip_range=(-1, 901),
        unconditional_batch_skip_range=2, attention_weight_callback=lambda _: 0.5,
        current_timestep_callback=lambda: pipe.current_timestep, is_guidance_distilled=False,
    ))
    with attach_geco_guidance(pipe, T.tiny_guidance_config(**LAST_STEP), estimators=estimators):
        counter = CountingForward(pipe.transformer)
        with pytest.raises(ValueError, match="FasterCache cache enabled") as err:
            run(pipe)
    counter.handle.remove()
    assert counter.n == 0 and "\n" not in str(err.value)


@pytest.mark.parametrize("family, faithful", [("wan", True), ("cogvideox", False)])
@pytest.mark.slow
def test_model_cpu_offload_with_the_hook_gives_the_same_video(family, faithful, estimators):
    """accelerate's model offload hooks (device="cpu", so it runs without an accelerator) on a
    pipeline that the guidance hook guides: every model still runs where its inputs are, the
    differentiated denoiser re-runs (faithful) through the offload hook too, same frames."""
    config = T.tiny_guidance_config(**LAST_STEP, denoiser_grad=faithful)
    plain, offloaded = BUILDERS[family](0), BUILDERS[family](0)
    offloaded.enable_model_cpu_offload(device="cpu")
    videos = []
    for pipe in (plain, offloaded):
        with attach_geco_guidance(pipe, config, estimators=estimators) as handle:
            videos.append(run(pipe))
        assert len(handle.log) == 2
    assert torch.equal(videos[0], videos[1])


@pytest.mark.parametrize("keywords", [
    {"geometry": 0, "flow": 0}, {"geometry_estimator": 0, "flow_estimator": 0}, {"decoder": 0}, {"dynamic_masks": 0},
])
def test_the_earlier_spellings_are_refused_naming_the_new_one(keywords, estimators):
    pipe = T.tiny_ltx_pipeline(0)
    with pytest.raises(TypeError, match="is the earlier spelling") as err:
        attach_geco_guidance(pipe, T.tiny_guidance_config(**LAST_STEP), **keywords)
    assert "Estimators(" in str(err.value) and "\n" not in str(err.value)
    with pytest.raises(TypeError, match="Estimators is not a"):
        geometry, flow = estimators  # the bundle is no pair
    with pytest.raises(TypeError, match="takes the estimators as one"):
        attach_geco_guidance(pipe, None, (estimators.geometry, estimators.flow))


def test_attach_takes_the_pipeline_config_estimators_and_run_options_and_refuses_other_keywords():
    assert list(inspect.signature(attach_geco_guidance).parameters) == ["pipe", "config", "estimators", "run_options"]
    with pytest.raises(TypeError, match=r"^attach_geco_guidance\(\) got an unexpected keyword argument 'run'$"):
        attach_geco_guidance(T.tiny_ltx_pipeline(0), run={})


def test_the_handle_reports_what_the_last_call_decided(estimators):
    pipe = T.tiny_wan_pipeline(0)
    with attach_geco_guidance(pipe, T.tiny_guidance_config(**LAST_STEP), estimators) as handle:
        assert handle.last is None
        run(pipe)
        report = handle.last
    assert report.log is handle.log and len(report.log) == 2
    assert report.memory_plan["name"] and report.scheduler == type(pipe.scheduler).__name__
    assert report.decoder.startswith("vae") and report.devices is None and report.mask_source is None
    assert report.guidance["anchors"] == list(T.tiny_guidance_config(**LAST_STEP).anchors)


def test_a_calls_state_is_one_diffusers_state_object_reset_by_the_next_call(estimators):
    from diffusers.hooks.hooks import BaseState

    from geco_guide.sampler.pipelines.hooks import GuidanceCallState

    pipe = T.tiny_wan_pipeline(0)
    with attach_geco_guidance(pipe, T.tiny_guidance_config(**LAST_STEP), estimators) as handle:
        state = handle.state
        assert isinstance(state, GuidanceCallState) and isinstance(state, BaseState) and state.call is None
        run(pipe)
        first = handle.last
        assert handle.state is state and state.report is first and state.log is first.log and state.counter == 4
        assert state.geometry is handle.geometry and state.geometry.num_frames == NUM_FRAMES
        run(pipe, seed=1)
        assert handle.last is not first and handle.log is not first.log and len(first.log) == len(handle.log) == 2
    assert state.call is None and handle.last.log is handle.log  # detached: nothing to act on, the report kept


def test_the_denoiser_capture_is_a_hook_of_diffusers_registry(estimators):
    from diffusers.hooks import HookRegistry

    from geco_guide.sampler.pipelines.hooks import CAPTURE_HOOK, DenoiserCapture

    pipe = T.tiny_wan_pipeline(0)
    with attach_geco_guidance(pipe, T.tiny_guidance_config(**LAST_STEP), estimators):
        registry = HookRegistry.check_if_exists_or_initialize(pipe.transformer)
        assert isinstance(registry.get_hook(CAPTURE_HOOK), DenoiserCapture)
    assert not hasattr(pipe.transformer, "_diffusers_hook") and "forward" not in pipe.transformer.__dict__


@pytest.mark.parametrize("family", ["cogvideox", "cogvideox-1.5", "wan", "hunyuan", "ltx"])
@pytest.mark.slow
def test_the_callers_latents_are_checked_before_any_denoising_step(family, estimators):
    pipe = BUILDERS[family](0)
    shapes = []

    def record(p, i, t, tensors):
        shapes.append(list(tensors["latents"].shape))
        return tensors

    run(pipe, callback_on_step_end=record, output_type="latent")
    shape = shapes[0]
    config = T.tiny_guidance_config(**LAST_STEP)
    with attach_geco_guidance(pipe, config, estimators=estimators) as handle:
        counter = CountingForward(pipe.transformer)
        try:
            nan = torch.randn(shape)
            nan.view(-1)[7] = float("nan")
            with pytest.raises(ValueError, match=r"^latents hold 1 NaN or infinite value\(s\)"):
                run(pipe, latents=nan)
            if family != "ltx":  # packed tokens: the adapter does not know the shape
                wrong = [*shape[:-1], shape[-1] + 1]
                with pytest.raises(ValueError, match=re.escape(f"latents must have shape {shape} (those of this ")):
                    run(pipe, latents=torch.randn(wrong))
            assert counter.n == 0
            run(pipe, latents=torch.randn(shape, generator=torch.Generator().manual_seed(1)))  # the call's own shape
        finally:
            counter.handle.remove()
    assert len(handle.log) == 2


@pytest.mark.parametrize("detach", ["detach", "with block"])
def test_a_detached_handle_refuses_a_search_in_one_line(detach, estimators):
    from geco_guide.sampler.search.particle_search import SearchConfig

    pipe = T.tiny_ltx_pipeline(0)
    if detach == "detach":
        handle = attach_geco_guidance(pipe, T.tiny_guidance_config(**LAST_STEP), estimators=estimators)
        handle.detach()
    else:
        with attach_geco_guidance(pipe, T.tiny_guidance_config(**LAST_STEP), estimators=estimators) as handle:
            pass
    with pytest.raises(ValueError, match=r"^this guidance handle is detached .*attach_geco_guidance\(pipe, \.\.\.\) again") as err:
        handle.enable_search(SearchConfig(particles=2), torch.Generator().manual_seed(0))
    assert "\n" not in str(err.value) and handle.search is None
