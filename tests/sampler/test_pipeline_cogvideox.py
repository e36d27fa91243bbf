"""GeCoCogVideoXPipeline and the model-agnostic guided step, with tiny random models on CPU."""

from __future__ import annotations

import copy

import pytest
import torch
from counting import CountingForward, HostSyncCounter
from diffusers import CogVideoXDDIMScheduler, CogVideoXDPMScheduler, CogVideoXPipeline

from geco_guide.loss.geco import GeCoLoss
from geco_guide.sampler.algorithm.config import GuidanceConfig, resolve_guidance_config
from geco_guide.sampler.algorithm.levels import VPLevels, ddim_step, renoise, v_to_x0
from geco_guide.sampler.algorithm.step import guided_step, loss_terms, score_anchor_frames
from geco_guide.tiny import (
    TINY_ANCHORS,
    TINY_CALL_KWARGS,
    tiny_estimators,
    tiny_cogvideox_components,
    tiny_guidance_decoder,
    tiny_pipeline,
    tiny_run_options,
)

PROMPT = "a marble bust on a table"


ESTIMATORS = tiny_estimators(0)


@pytest.fixture(scope="module")
def pipe():
    return tiny_pipeline(0)


def run(pipe, seed=0, **kwargs):
    """A call of the tiny pipeline: guided by the tiny estimators and run options unless told otherwise."""
    args = dict(TINY_CALL_KWARGS, output_type="pt", estimators=ESTIMATORS, run_options=tiny_run_options())
    args.update(kwargs)
    return pipe(PROMPT, generator=torch.Generator().manual_seed(seed), **args)


def scores(pipe, frames):
    loss = GeCoLoss(ESTIMATORS, pipe.guidance_config.loss)
    return score_anchor_frames(frames, TINY_ANCHORS, loss)


# ---- the guided step on its own ---------------------------------------------------------------


def ddim_guided(z, predict, levels, objective, repeats, **kwargs):
    """guided_step, then the deterministic DDIM step a sampler takes from its result: ``(z_prev,
    x0, updates)``."""
    updates = []
    z, out = guided_step(z, predict, levels, objective, repeats, on_update=updates.append, **kwargs)
    x0 = levels.to_x0(z, out)
    return levels.step(z, x0), x0, updates


def squared(target=0.0):
    """The objective ``x0 -> (||x0 - target||^2, terms)``."""
    return lambda x: loss_terms(((x - target) ** 2).sum())


def test_guided_step_without_repeats_is_a_ddim_step():
    z = torch.randn(1, 3, 2, 4, 4)
    v = torch.randn_like(z)
    a_t, a_prev = torch.tensor(0.3, dtype=torch.float64), torch.tensor(0.6, dtype=torch.float64)
    z_prev, x0, records = ddim_guided(z, lambda z, grad: v, VPLevels(a_t, a_prev), None, 0, step_size=3.0)
    assert records == []
    torch.testing.assert_close(x0, a_t.sqrt().float() * z - (1 - a_t).sqrt().float() * v)
    eps = ((z - a_t.sqrt().float() * x0) / (1 - a_t).sqrt().float())
    torch.testing.assert_close(z_prev, a_prev.sqrt().float() * x0 + (1 - a_prev).sqrt().float() * eps)


def test_fast_mode_update_is_the_normalised_gradient_through_sqrt_alpha():
    # loss = ||x0 - target||^2 with v held constant: dL/dz = 2 sqrt(a_t) (x0 - target)
    z = torch.randn(1, 2, 2, 3, 3, generator=torch.Generator().manual_seed(1))
    v = torch.randn_like(z)
    target = torch.randn_like(z)
    a_t, a_prev = torch.tensor(0.5, dtype=torch.float64), torch.tensor(0.8, dtype=torch.float64)
    seen = []

    def predict(z_in, grad):
        seen.append(grad)
        return v

    z_prev, _, records = ddim_guided(z, predict, VPLevels(a_t, a_prev), squared(target), 2, step_size=0.5,
                                     denoiser_grad=False)
    z_upd, norms = z, []
    for _ in range(2):
        g = 2 * 0.5**0.5 * (v_to_x0(z_upd, v, a_t) - target)
        z_upd, norms = z_upd - 0.5 * g / g.norm(), norms + [float(g.norm())]
    torch.testing.assert_close(z_prev, ddim_step(z_upd, v_to_x0(z_upd, v, a_t), a_t, a_prev))
    assert seen == [False]  # the one prediction serves both updates and the DDIM step
    assert [float(r.terms["grad_norm"]) for r in records] == pytest.approx(norms, rel=1e-5)


def test_fast_mode_predicts_again_after_each_time_travel():
    z = torch.randn(1, 2, 2, 3, 3, generator=torch.Generator().manual_seed(2))
    a_t, a_prev = torch.tensor(0.4, dtype=torch.float64), torch.tensor(0.7, dtype=torch.float64)
    seen = []

    def predict(z_in, grad):
        seen.append(z_in.clone())
        return torch.sin(z_in)  # an output that depends on z

    z_prev, x0, _ = ddim_guided(z, predict, VPLevels(a_t, a_prev), squared(), 2, step_size=1.0, time_travel=True,
                                denoiser_grad=False, generator=torch.Generator().manual_seed(3))
    # start, after the first re-noising (second update), after the second (final prediction)
    assert len(seen) == 3 and torch.equal(seen[0], z)
    torch.testing.assert_close(x0, v_to_x0(seen[2], torch.sin(seen[2]), a_t))


def test_time_travel_renoises_back_to_t_with_the_generator():
    z = torch.randn(1, 2, 2, 3, 3)
    v = torch.zeros_like(z)
    a_t, a_prev = torch.tensor(0.4, dtype=torch.float64), torch.tensor(0.7, dtype=torch.float64)
    kwargs = dict(predict=lambda z, g: v, levels=VPLevels(a_t, a_prev), objective=squared(), repeats=1, step_size=1.0,
                  time_travel=True)
    out1 = ddim_guided(z, generator=torch.Generator().manual_seed(5), **kwargs)[0]
    out2 = ddim_guided(z, generator=torch.Generator().manual_seed(5), **kwargs)[0]
    out3 = ddim_guided(z, generator=torch.Generator().manual_seed(6), **kwargs)[0]
    assert torch.equal(out1, out2) and not torch.equal(out1, out3)
    # by hand: DDIM step with the update, re-noise to t, then the final DDIM step
    x0 = v_to_x0(z, v, a_t)
    g = 2 * x0 * a_t.sqrt().float()
    noise = torch.randn(z.shape, generator=torch.Generator().manual_seed(5))
    z_t = renoise(ddim_step(z, x0, a_t, a_prev) - g / (g.norm() + 1e-8), a_t, a_prev, noise)
    torch.testing.assert_close(out1, ddim_step(z_t, v_to_x0(z_t, v, a_t), a_t, a_prev))


def test_resolve_guidance_config():
    base = GuidanceConfig()
    assert resolve_guidance_config(base, None) is base
    assert resolve_guidance_config(base, False).enabled is False
    changed = resolve_guidance_config(base, {"step_size": 1.5, "loss": {"cue": "motion"}})
    assert changed.step_size == 1.5 and changed.loss.cue == "motion" and changed.loss.flow_downscale == 0.5
    with pytest.raises(ValueError, match="guidance.bogus"):
        resolve_guidance_config(base, {"bogus": 1})
    with pytest.raises(ValueError, match="guidance.loss"):
        resolve_guidance_config(base, {"loss": {"cue": "nope"}})


# ---- the pipeline -------------------------------------------------------------------------------


def test_pipeline_exposes_components_and_geco_parts(pipe):
    for name in ("tokenizer", "text_encoder", "vae", "transformer", "scheduler"):
        assert getattr(pipe, name) is pipe.components[name]
    assert isinstance(pipe.scheduler, CogVideoXDDIMScheduler)
    assert set(pipe.components) == {"tokenizer", "text_encoder", "vae", "transformer", "scheduler"}
    assert isinstance(pipe.guidance_config, GuidanceConfig)


def test_guidance_off_matches_stock_pipeline_bitwise(pipe):
    stock = CogVideoXPipeline(**tiny_cogvideox_components(0))
    stock.set_progress_bar_config(disable=True)
    for output_type in ("pt", "latent"):
        ours = run(pipe, seed=3, guidance=False, output_type=output_type)
        ref = stock(PROMPT, generator=torch.Generator().manual_seed(3), output_type=output_type, **TINY_CALL_KWARGS)
        assert torch.equal(ours.frames, ref.frames), output_type
        assert ours.report.log == [] and ours.report.guidance is None
        assert ours.report.scheduler == "CogVideoXDDIMScheduler"


@pytest.mark.slow
def test_guided_run_lowers_geco_loss_on_anchor_frames(pipe):
    unguided = run(pipe, seed=0, guidance=False).frames
    guided = run(pipe, seed=0)
    fast = run(pipe, seed=0, guidance={"denoiser_grad": False})
    base = scores(pipe, unguided)["loss"]
    assert scores(pipe, guided.frames)["loss"] < 0.9 * base
    assert scores(pipe, fast.frames)["loss"] < 0.9 * base
    # the log: one entry per update, with every cue, ||g|| and time
    assert len(guided.report.log) == 5  # "0x1,2x2,1x1"
    entry = guided.report.log[0]
    assert {"step", "repeat", "t", "loss", "motion", "structure", "fused", "grad_norm", "seconds"} <= set(entry)
    assert [e["step"] for e in guided.report.log] == [1, 1, 2, 2, 3]
    assert [e["time_travel"] for e in guided.report.log] == [False, False, True, True, False]
    assert all(e["grad_norm"] > 0 and e["loss"] == e["fused"] for e in guided.report.log)
    assert guided.report.log[0]["t"] == int(pipe.scheduler.timesteps[1])


@pytest.mark.slow
def test_same_seed_same_frames_with_time_travel(pipe):
    cfg = {"repeats": "0x1,1x3", "time_travel": [1, 3]}  # every update time-travels
    a = run(pipe, seed=7, guidance=cfg).frames
    b = run(pipe, seed=7, guidance=cfg).frames
    c = run(pipe, seed=8, guidance=cfg).frames
    assert torch.equal(a, b)
    assert not torch.equal(a, c)


@pytest.mark.slow
def test_only_anchor_chunks_are_decoded_and_models_stay_frozen(pipe):
    models = {
        "transformer": pipe.transformer, "vae": pipe.vae, "text_encoder": pipe.text_encoder,
        "geometry": ESTIMATORS.geometry, "flow": ESTIMATORS.flow,
    }
    before = {k: copy.deepcopy(m.state_dict()) for k, m in models.items()}
    flags = {k: [p.requires_grad for p in m.parameters()] for k, m in models.items()}
    calls = []
    original = pipe.vae.decode

    def counting_decode(z, *args, **kwargs):
        calls.append((z.shape[0], z.shape[2]))
        return original(z, *args, **kwargs)

    pipe.vae.decode = counting_decode
    try:
        out = run(pipe, seed=1, output_type="latent")
    finally:
        del pipe.vae.decode
    updates = len(out.report.log)
    assert updates == 5
    # 4 anchors -> 4 chunks of <= 3 latents per update, never all 5: chunk [0, 2) of anchor 4 alone,
    # the three 3-latent chunks batched in one decode
    assert calls == [(1, 2), (3, 3)] * updates
    for k, m in models.items():
        after = m.state_dict()
        assert all(torch.equal(before[k][n], after[n]) for n in after), k
        assert [p.requires_grad for p in m.parameters()] == flags[k], k
        assert all(p.grad is None for p in m.parameters()), k


@pytest.mark.parametrize("denoiser_grad", [True, False])
@pytest.mark.slow
def test_denoiser_calls_per_mode_and_no_host_syncs_in_the_updates(pipe, denoiser_grad):
    # tiny schedule: R = 0, 2, 2, 1 with time travel at step 2
    counter, text = CountingForward(pipe.transformer), CountingForward(pipe.text_encoder)
    try:
        with HostSyncCounter() as unguided:
            run(pipe, guidance=False, output_type="latent")
        calls_unguided, counter.n, text.n = counter.n, 0, 0
        with HostSyncCounter() as guided:
            out = run(pipe, guidance={"denoiser_grad": denoiser_grad}, output_type="latent")
    finally:
        counter.handle.remove()
        text.handle.remove()
    assert len(out.report.log) == 5 and calls_unguided == 4
    assert text.n == 2  # prompt and negative prompt, encoded once for the whole call
    # faithful: one differentiated call per update + one final call per step; fast: one call per
    # step, plus one after each of the two time-travel re-noisings of step 2
    assert counter.n == (4 + 5 if denoiser_grad else 4 + 2)
    # the updates add no op that waits for the device (the record's one read is a copy, unseen on CPU)
    assert guided.counts == unguided.counts


def test_cue_is_selectable(pipe):
    out = run(pipe, seed=0, guidance={"repeats": "0x1,1x1,0x2", "loss": {"cue": "motion"}})
    assert len(out.report.log) == 1
    assert out.report.log[0]["loss"] == out.report.log[0]["motion"] != out.report.log[0]["fused"]


def test_callback_on_step_end_still_works(pipe):
    seen = []

    def callback(p, i, t, kwargs):
        seen.append((i, int(t), kwargs["latents"].dtype))
        return {"latents": kwargs["latents"] * 0 if i == 3 else kwargs["latents"]}

    out = run(pipe, seed=0, guidance=False, output_type="latent", callback_on_step_end=callback)
    assert [s[0] for s in seen] == [0, 1, 2, 3]
    assert [s[1] for s in seen] == [int(t) for t in pipe.scheduler.timesteps]
    assert torch.count_nonzero(out.frames) == 0


@pytest.mark.parametrize(
    "kwargs, match",
    [
        (dict(guidance={"anchors": [4, 20]}), "out of range"),
        (dict(guidance={"anchors": [8]}), "at least two"),
        (dict(guidance={"anchors": [0, 8]}), "latent 0"),
        (dict(num_frames=16), "num_frames=16"),
        (dict(num_frames=13), "even number of latents"),
        (dict(height=40), "multiples of 16"),
        (dict(width=56), "multiples of 16"),
        # (runs like "0x1,2x2,1x1" are scaled to other step counts; a per-step list must match)
        (dict(num_inference_steps=5, guidance={"repeats": [0, 2, 2, 1]}), "covers 4 steps but the sampler runs 5"),
        (dict(guidance={"loss": {"cue": "structure", "geometry_grad": False}}), "geometry_grad=true"),
        (dict(guidance={"step_size": -1.0}), r"step_size must be in \[0, 1000\]"),
        (dict(guidance={"time_travel": [3, 4]}), "time_travel"),
    ],
)
def test_invalid_inputs_raise_before_any_denoising_step(pipe, kwargs, match):
    counter = CountingForward(pipe.transformer)
    try:
        with pytest.raises(ValueError, match=match):
            run(pipe, **kwargs)
    finally:
        counter.handle.remove()
    assert counter.n == 0


def test_guidance_needs_estimators_but_unguided_does_not(pipe):
    with pytest.raises(ValueError, match=r"pass estimators=Estimators\(geometry, flow\)"):
        run(pipe, estimators=None)
    with pytest.raises(TypeError, match="Estimators"):
        run(pipe, estimators=(ESTIMATORS.geometry, ESTIMATORS.flow))  # a pair is no bundle
    assert run(pipe, guidance=False, estimators=None, output_type="latent").frames.shape[1] == 5


@pytest.mark.parametrize("component", ["geometry_estimator", "flow_estimator", "guidance_decoder"])
def test_the_earlier_components_are_refused_at_construction_and_loading(tmp_path, component):
    from geco_guide.sampler.pipelines.pipeline_cogvideox import GeCoCogVideoXPipeline

    with pytest.raises(TypeError, match=rf"^GeCoCogVideoXPipeline\({component}=...\) is the earlier spelling: the .* "
                                        r"to each call$"):
        GeCoCogVideoXPipeline(**tiny_cogvideox_components(0), **{component: None})
    with pytest.raises(TypeError, match=rf"^GeCoCogVideoXPipeline.from_pretrained\({component}=...\) is the earlier "
                                        r"spelling: the .* to each call$"):
        GeCoCogVideoXPipeline.from_pretrained(tmp_path, **{component: None})  # refused before reading the folder


@pytest.mark.slow
def test_from_pretrained_keeps_the_checkpoints_scheduler(tmp_path, pipe):
    # the scheduler the checkpoint ships (CogVideoXDPMScheduler for CogVideoX-5B) is kept;
    # the paper's DDIM is chosen explicitly (the cogvideox-5b preset does, see test_presets.py)
    from geco_guide.sampler.pipelines.pipeline_cogvideox import GeCoCogVideoXPipeline

    components = tiny_cogvideox_components(0)
    components["scheduler"] = CogVideoXDPMScheduler.from_config(components["scheduler"].config)
    stock = CogVideoXPipeline(**components)
    stock.save_pretrained(tmp_path)
    loaded = GeCoCogVideoXPipeline.from_pretrained(tmp_path, guidance_config=pipe.guidance_config)
    assert isinstance(loaded.scheduler, CogVideoXDPMScheduler)
    def settings(sched):
        return {k: v for k, v in sched.config.items() if not k.startswith("_")}

    assert settings(loaded.scheduler) == settings(stock.scheduler)
    assert loaded.guidance_config == pipe.guidance_config
    loaded.set_progress_bar_config(disable=True)
    stock.set_progress_bar_config(disable=True)
    a = run(loaded, seed=2, guidance=False, output_type="latent").frames
    b = stock(PROMPT, generator=torch.Generator().manual_seed(2), output_type="latent", **TINY_CALL_KWARGS).frames
    assert torch.equal(a, b)
    guided = run(loaded, seed=2, output_type="latent")  # guidance works with the DPM scheduler too
    assert len(guided.report.log) == 5 and guided.report.scheduler == "CogVideoXDPMScheduler"


@pytest.mark.slow
def test_gradient_checkpointing_gives_the_same_update(pipe):
    cfg = {"repeats": "0x2,1x1,0x1", "time_travel": []}
    explicit = {"memory_plan": "explicit"}  # the flags, as given
    plain = run(pipe, seed=4, output_type="latent", guidance=cfg,
                run_options={**explicit, "gradient_checkpointing": False})
    ckpt = run(pipe, seed=4, output_type="latent", guidance=cfg,
               run_options={**explicit, "gradient_checkpointing": True, "vae_checkpointing": True})
    # restored after the call
    assert not pipe.transformer.is_gradient_checkpointing and not pipe.vae.is_gradient_checkpointing
    torch.testing.assert_close(ckpt.frames, plain.frames, rtol=1e-4, atol=1e-5)
    assert ckpt.report.log[0]["grad_norm"] == pytest.approx(plain.report.log[0]["grad_norm"], rel=1e-4)


# ---- the caller's latents ----------------------------------------------------------------------


def tiny_latents_shape(pipe, batch=1):
    """[B, F, C, h, w] of a TINY_CALL_KWARGS call, as the stock prepare_latents draws them."""
    latent_frames = (TINY_CALL_KWARGS["num_frames"] - 1) // pipe.vae_scale_factor_temporal + 1
    scale = pipe.vae_scale_factor_spatial
    return (batch, latent_frames, pipe.transformer.config.in_channels,
            TINY_CALL_KWARGS["height"] // scale, TINY_CALL_KWARGS["width"] // scale)


def test_latents_of_the_calls_shape_are_taken_as_the_generators_noise(pipe):
    shape = tiny_latents_shape(pipe)
    noise = torch.randn(shape, generator=torch.Generator().manual_seed(3))
    given = run(pipe, seed=9, guidance=False, output_type="latent", latents=noise.clone())
    drawn = run(pipe, seed=3, guidance=False, output_type="latent")
    assert torch.equal(given.frames, drawn.frames)


@pytest.mark.parametrize("guidance", [None, False])
@pytest.mark.parametrize("value", [float("nan"), float("inf")])
def test_non_finite_latents_are_refused_before_any_step(pipe, guidance, value):
    latents = torch.randn(tiny_latents_shape(pipe))
    latents[0, 1, 0, 0, 0] = value
    counter = CountingForward(pipe.transformer)
    try:
        with pytest.raises(ValueError, match=r"^latents hold 1 NaN or infinite value\(s\) of \d+: pass finite latents"):
            run(pipe, guidance=guidance, latents=latents)
    finally:
        counter.handle.remove()
    assert counter.n == 0


@pytest.mark.parametrize("axis, size", [(2, 3), (1, 4), (3, 3), (4, 5), (0, 2)])
def test_latents_of_another_shape_are_refused_naming_the_expected_one(pipe, axis, size):
    expected = tiny_latents_shape(pipe)
    wrong = list(expected)
    wrong[axis] = size
    counter = CountingForward(pipe.transformer)
    try:
        with pytest.raises(ValueError) as err:
            run(pipe, latents=torch.randn(wrong))
    finally:
        counter.handle.remove()
    assert counter.n == 0
    message = str(err.value)
    assert message.startswith(f"latents must have shape {list(expected)} ") and message.endswith(f"got {wrong}")
    assert "num_frames=17, height=32, width=48" in message and "\n" not in message


@pytest.mark.parametrize("time_travel", [[], None])
@pytest.mark.slow
def test_a_nan_decode_by_the_tiny_decoder_skips_the_update_and_leaves_the_latents_finite(time_travel):
    guided = tiny_pipeline(0)
    decoder = tiny_guidance_decoder("cogvideox")
    decode = decoder.decode
    decoder.decode = lambda latents: decode(latents) * float("nan")
    estimators = ESTIMATORS.with_tiny_decoder(decoder)
    config = {"decoder": "tiny", **({} if time_travel is None else {"time_travel": time_travel})}
    out = run(guided, seed=5, output_type="latent", guidance=config, estimators=estimators)
    log = out.report.log
    assert log and all(e["skipped"] and e["grad_norm"] == 0 and e["loss"] != e["loss"] for e in log)  # NaN loss
    assert torch.isfinite(out.frames).all()
    if time_travel is None:  # the tiny schedule's time travel: the re-noised DDIM step, still finite
        assert any(e["time_travel"] for e in log)
    else:  # every update skipped: the latents are those of the same schedule without updates
        assert torch.equal(out.frames, run(guided, seed=5, output_type="latent", guidance=False).frames)


def test_an_update_with_a_nan_loss_moves_nothing_even_with_a_finite_gradient():
    z = torch.randn(1, 3, 2, 4, 4)
    v = torch.randn_like(z)
    levels = VPLevels(torch.tensor(0.3, dtype=torch.float64), torch.tensor(0.6, dtype=torch.float64))

    def nan_loss(x0):
        return loss_terms(x0.sum() + float("nan"))  # its gradient is finite: ones

    updates = []
    guided, _ = guided_step(z, lambda z, grad: v, levels, nan_loss, 2, step_size=1.0, on_update=updates.append)
    assert torch.equal(guided, z)
    assert [bool(u.terms["finite"]) for u in updates] == [False, False]
    moved, _ = guided_step(z, lambda z, grad: v, levels, squared(), 1, step_size=1.0)
    assert not torch.equal(moved, z)  # a finite loss does move it
