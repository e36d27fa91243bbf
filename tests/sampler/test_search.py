"""Particle search (geco_guide.sampler.search.particle_search, .particles): the pure parts, and its exactness in
GeCoCogVideoXPipeline and under the hooks (tiny models, CPU)."""

from __future__ import annotations

import math
import re

import pytest
import torch
from counting import CountingHook
from diffusers import CogVideoXDPMScheduler, UniPCMultistepScheduler
from diffusers.hooks import HookRegistry

from geco_guide import tiny as T
from geco_guide.loss.geco import GeCoLoss
from geco_guide.sampler.search import particles as P
from geco_guide.sampler.search import particle_search as S
from geco_guide.sampler.algorithm.dynamic import RefreshedMasks
from geco_guide.sampler.pipelines.hooks import attach_geco_guidance
from geco_guide.sampler.running.memory_plan import PlanChoice, plan_named
from geco_guide.sampler.running.multi_device import dealt_work
from geco_guide.sampler.pipelines.pipeline_cogvideox import GeCoCogVideoXPipeline
from geco_guide.sampler.search.particle_search import SearchConfig
from geco_guide.types import OptionError

PROMPT = "a marble bust on a table"
NUM_FRAMES = 9  # 3 latents: both anchors in the last one's chunk
ANCHORS = [5, 8]
UNGUIDED = T.tiny_guidance_config(anchors=ANCHORS, enabled=False)  # what the search scores, no guidance
GUIDED = T.tiny_guidance_config(anchors=ANCHORS, repeats="0x1,1x2,0x1", time_travel=[2, 2], step_size=1.0,
                                denoiser_grad=False)


def gens(*seeds):
    return [torch.Generator().manual_seed(s) for s in seeds]


def fixed_scheme(monkeypatch, name, ancestors):
    """A resampling scheme that always draws ``ancestors`` (registered for the test)."""
    monkeypatch.setitem(S.RESAMPLERS, name, lambda weights, generator: torch.tensor(ancestors))
    return name


# ---- the pure parts ------------------------------------------------------------------------------


def test_systematic_and_multinomial_resampling_are_seeded_and_follow_the_weights():
    weights = torch.tensor([0.5, 0.0, 0.3, 0.2], dtype=torch.float64)
    for resample in (S.systematic_resample, S.multinomial_resample):
        a = resample(weights, torch.Generator().manual_seed(3))
        assert torch.equal(a, resample(weights, torch.Generator().manual_seed(3)))  # the same seed, the same draw
        assert 1 not in a.tolist() and a.tolist() == sorted(a.tolist()) and len(a) == 4
    # systematic: floor or ceil of K w copies for every seed
    for seed in range(20):
        counts = torch.bincount(S.systematic_resample(weights, torch.Generator().manual_seed(seed)), minlength=4)
        for count, w in zip(counts.tolist(), weights.tolist()):
            assert math.floor(4 * w) <= count <= math.ceil(4 * w)
    # multinomial: frequencies follow the weights over many draws
    draws = torch.cat([S.multinomial_resample(weights, torch.Generator().manual_seed(s)) for s in range(500)])
    frequencies = torch.bincount(draws, minlength=4).double() / draws.numel()
    torch.testing.assert_close(frequencies, weights, atol=0.03, rtol=0)


def test_weights_favour_low_scores_and_drop_non_finite_ones():
    scores = torch.tensor([0.10, 0.12, math.nan, 0.10], dtype=torch.float64)
    w = S.normalized_weights(S.log_weights(scores, None, temperature=0.02))
    assert w[2] == 0 and w[0] == w[3] and w[0] / w[1] == pytest.approx(math.exp(1.0))
    assert S.effective_sample_size(torch.full((4,), 0.25)) == pytest.approx(4.0)
    assert S.normalized_weights(S.log_weights(torch.full((3,), math.nan), None, 0.02)) is None
    # the difference potential weighs the change since the ancestor's score (where that is finite)
    previous = torch.tensor([0.10, 0.02, 0.3, math.nan], dtype=torch.float64)
    log_w = S.log_weights(scores, previous, 0.02)
    assert log_w[0] == 0 and log_w[1] == pytest.approx(-5.0) and log_w[3] == pytest.approx(-5.0)


@pytest.mark.parametrize("key, value, match", [
    ("particles", 0, "particles must be a whole number of particles in"),
    ("particles", 2.5, "particles must be"),
    ("particles", 1001, r"\[1, 1000\]"),
    ("resample_steps", [1, 1], "lists a step twice"),
    ("resample_steps", [-1], "0-based denoising steps"),
    ("resample_steps", "1,2", "0-based denoising steps"),
    ("temperature", math.inf, "finite number > 0"),
    ("temperature", 0.0, "finite number > 0"),
    ("potential", "max", "score, difference"),
    ("scheme", "residual", "systematic, multinomial"),
    ("renoise", "yes", "true or false"),
])
def test_bad_search_options_are_one_line_naming_the_key(key, value, match):
    with pytest.raises(OptionError, match=match) as err:
        SearchConfig(**{"particles": 2, key: value})
    assert err.value.key == key and "\n" not in str(err.value)


def test_resample_steps_default_and_range():
    assert S.default_resample_steps(50) == [5, 10, 15, 20, 25]
    assert S.default_resample_steps(4) == [1, 2]
    assert SearchConfig(particles=2, resample_steps=[3, 1]).steps(4) == [1, 3]
    assert SearchConfig(particles=2, resample_steps=[]).steps(4) == []
    with pytest.raises(ValueError, match=r"search.resample_steps \[4\] are outside the 4 denoising steps \(0 to 3\)"):
        SearchConfig(particles=2, resample_steps=[0, 4]).steps(4)
    assert S.resolve_search_config(None) is None and S.resolve_search_config(SearchConfig()) is None
    assert S.resolve_search_config({"particles": 3}).particles == 3
    with pytest.raises(ValueError, match="search: particles must be"):
        S.resolve_search_config({"particles": -1})


def test_search_counts_are_the_work_a_cost_model_prices():
    counts = S.search_counts(SearchConfig(particles=4, resample_steps=[5, 10, 15]), 50)
    assert counts == S.SearchCounts(denoiser_forwards=200, renoise_forwards_max=9, scorings=12, final_decodes=4,
                                    final_evaluations=4)
    assert S.search_counts(SearchConfig(particles=4, renoise=False), 50).renoise_forwards_max == 0


def test_particle_rows_follow_the_cfg_blocks():
    assert P.particle_rows(3, 6, [1, 2]) == [1, 2, 4, 5]
    assert P.particle_rows(3, 3, [2]) == [2]
    assert P.particle_batches(5, 2) == [[0, 1], [2, 3], [4]]
    with pytest.raises(ValueError, match="no multiple"):
        P.particle_rows(3, 4, [0])


def test_scheduler_state_of_the_particles_is_found_and_carried():
    scheduler = UniPCMultistepScheduler(prediction_type="flow_prediction", use_flow_sigmas=True, flow_shift=3.0)
    scheduler.set_timesteps(4)
    shape = (3, 2, 1, 2, 2)
    sample = torch.randn(shape)
    for t in scheduler.timesteps[:2]:
        sample = scheduler.step(torch.randn(shape), t, sample).prev_sample
    before = {name: value for name, value in vars(scheduler).items()}
    ancestors = torch.tensor([2, 2, 0])
    carried = P.reorder_scheduler_state(scheduler, ancestors, torch.Size(shape))
    assert carried == ["model_outputs", "last_sample"]
    assert torch.equal(scheduler.last_sample, before["last_sample"][ancestors])
    for new, old in zip(scheduler.model_outputs, before["model_outputs"]):
        assert (new is None and old is None) or torch.equal(new, old[ancestors])
    assert scheduler.sigmas is before["sigmas"] and scheduler.timesteps is before["timesteps"]


def test_refreshed_masks_follow_their_particles():
    class Source:
        source_name = "test"
        calls = 0

        def dynamic_masks(self, frames, *rest):
            Source.calls += 1
            return torch.full(frames.shape[:1] + frames.shape[2:], Source.calls % 2 == 0)

    masks = RefreshedMasks(Source(), refresh=2)
    frames = torch.zeros(2, 3, 4, 4)
    masks.start_step(0, first_clip=0)
    masks.start_update()
    first = [masks.dynamic_masks(frames), masks.dynamic_masks(frames)]  # particles 0 and 1
    masks.start_step(0, first_clip=2)  # the same step's next sub-batch: particle 2, fresh too
    masks.start_update()
    third = masks.dynamic_masks(frames)
    masks.reorder([2, 2, 0])
    masks.start_step(1, first_clip=0)  # no refresh due: each slot answers with its ancestor's masks
    masks.start_update()
    again = [masks.dynamic_masks(frames) for _ in range(3)]
    assert Source.calls == 3
    assert again[0] is third and again[1] is third and again[2] is first[0]


def test_particle_batches_run_a_call_in_sub_batches_and_over_replicas():
    torch.manual_seed(0)
    layer = torch.nn.Sequential(torch.nn.Linear(6, 16), torch.nn.GELU(), torch.nn.Linear(16, 6)).eval()

    def denoiser(hidden_states, timestep, flags=None):
        return (layer(hidden_states) * timestep[:, None],)

    hidden = torch.randn(8, 6)  # 2 CFG blocks of 4 particles
    timestep = torch.arange(8.0)
    whole = denoiser(hidden, timestep)[0]
    one = P.ParticleBatches(4, 1, [(None, denoiser)])(hidden_states=hidden, timestep=timestep, flags="x")[0]
    for k in range(4):  # a sub-batch of one particle is that particle's call alone, bit for bit
        rows = [k, 4 + k]
        assert torch.equal(one[rows], denoiser(hidden[rows], timestep[rows])[0])
    torch.testing.assert_close(one, whole)
    # dealt over two places (a replica each): the same sub-batches, the same numbers
    replica = __import__("copy").deepcopy(layer)
    dealt = P.ParticleBatches(4, 2, [(torch.device("cpu"), denoiser),
                                     (torch.device("cpu"), lambda hidden_states, timestep, flags=None:
                                      (replica(hidden_states) * timestep[:, None],))])
    halves = P.ParticleBatches(4, 2, [(None, denoiser)])
    assert torch.equal(dealt(hidden_states=hidden, timestep=timestep)[0],
                       halves(hidden_states=hidden, timestep=timestep)[0])


def test_clip_scores_are_each_clips_own_score(estimators):
    frames = torch.rand(3, 2, 3, 32, 48, generator=torch.Generator().manual_seed(0))
    loss = GeCoLoss(estimators, T.tiny_guidance_config().loss)
    batch = S.clip_scores(loss(frames))
    alone = torch.stack([loss(frames[k:k + 1]).fused for k in range(3)])
    torch.testing.assert_close(batch, alone, rtol=1e-4, atol=1e-6)


def test_the_particle_batch_is_the_memory_plans_choice():
    # an unguided search runs no backward: its work is the unguided call's 14 GiB (its 20 GiB peak
    # less the 6 GiB of video models), not a fast update's 20
    entry = {"signature": {"num_layers": 1}, "model_ids": ["m"], "video": {"frames": 1, "height": 1, "width": 1},
             "unguided": {"peak_gb": 20.0, "offload_peak_gb": 17.0},
             "estimates": {f"{mode}/vae": {name: {"weights_gb": 10.0, "activations_gb": 20.0, "offload_weights_gb": 4.0}
                                           for name in ("fastest", "leanest")} for mode in ("fast", "faithful")}}
    estimates = {"models": {"m": entry}}
    args = dict(model_id="m", frames=1, height=1, width=1, device_gb=None, estimates=estimates)
    run = T.tiny_run_options(memory_plan="auto", memory_budget_gb=100.0)
    plan = PlanChoice(plan_named("leanest"), "test")
    unguided = S.choose_particle_batch(UNGUIDED, run, 8, None, **args)
    assert unguided.size == 6  # (100 - 10 - the particles' latents) // 14
    assert unguided.reason.endswith("(m, unguided, no backward: bounded by the unguided call's activations)")
    offloaded = S.choose_particle_batch(UNGUIDED, run, 8, None, offload=True, **args)
    assert offloaded.size == 6  # the estimators' 4 GiB and the model at work's 3: (100 - 7) // 14
    guided = S.choose_particle_batch(GUIDED, run, 3, plan, **args)
    assert re.search(r"\(m, (fast|faithful) mode, plan leanest\)$", guided.reason)
    assert S.choose_particle_batch(UNGUIDED, run, 8, None, devices=4, **args).size == 2  # a sub-batch per device
    assert S.choose_particle_batch(GUIDED, run, 3, plan, **args).size == 3
    assert S.choose_particle_batch(UNGUIDED, T.tiny_run_options(particle_batch=5), 3, None, **args).size == 3
    assert S.choose_particle_batch(UNGUIDED, run, 8, None, **{**args, "model_id": "other"}).size == 1  # unknown
    big = dict(args, frames=400, height=1000, width=1000)  # 13.4 GiB per particle beside the work
    with pytest.raises(ValueError, match=r"search.particles=8 does not fit 100.0 GiB: .* at most 5 particles fit"):
        S.choose_particle_batch(UNGUIDED, run, 8, None, **{**big, "estimates": {"models": {"m": {
            **entry, "video": {"frames": 400, "height": 1000, "width": 1000}}}}})


# ---- GeCoCogVideoXPipeline -------------------------------------------------------------------------


def cogvideox(scheduler: str = "ddim") -> GeCoCogVideoXPipeline:
    components = T.tiny_cogvideox_components(0)
    if scheduler == "dpm":
        components["scheduler"] = CogVideoXDPMScheduler.from_config(components["scheduler"].config)
    pipe = GeCoCogVideoXPipeline(**components)
    pipe.set_progress_bar_config(disable=True)
    return pipe


def run_pipeline(pipe, estimators, seeds=(0,), search=None, guidance=UNGUIDED, run=None, search_seed=7, prompt=PROMPT,
                 **changes):
    kwargs = dict(T.TINY_CALL_KWARGS, num_frames=NUM_FRAMES, **{"output_type": "latent", **changes})
    return pipe(prompt, generator=gens(*seeds) if search is not None else torch.Generator().manual_seed(seeds[0]),
                guidance=guidance, estimators=estimators, run_options=run or T.tiny_run_options(),
                search=search, search_generator=torch.Generator().manual_seed(search_seed), **kwargs)


@pytest.mark.parametrize("guidance", [UNGUIDED, GUIDED], ids=["unguided", "guided"])
def test_pipeline_one_particle_without_resampling_is_the_plain_video(guidance, estimators):
    pipe = cogvideox()
    plain = run_pipeline(pipe, estimators, guidance=guidance).frames
    searched = run_pipeline(pipe, estimators, search=SearchConfig(particles=1, resample_steps=[]), guidance=guidance)
    assert torch.equal(searched.frames, plain)
    assert searched.report.search["resamplings"] == [] and searched.report.search["lineages"] == [[0]]


def test_pipeline_particles_of_one_per_call_are_their_seeds_videos_and_reproducible(estimators):
    pipe = cogvideox()
    search = SearchConfig(particles=2, resample_steps=[1, 2], temperature=0.001)
    run = T.tiny_run_options(particle_batch=1)
    alone = [run_pipeline(pipe, estimators, seeds=(s,)).frames for s in (3, 4)]
    unresampled = run_pipeline(pipe, estimators, seeds=(3, 4), run=run,
                               search=SearchConfig(particles=2, resample_steps=[]))
    assert torch.equal(unresampled.frames, torch.cat(alone))  # each particle is its seed's video, bit for bit
    a, b = (run_pipeline(pipe, estimators, seeds=(3, 4), run=run, search=search) for _ in range(2))
    assert torch.equal(a.frames, b.frames) and records(a) == records(b)  # the same seeds: the same search
    assert records(a)[0]["ancestors"] == [0, 0]  # (a resampling that changes something)


def records(output):
    """A search's resampling records without their wall times."""
    return [{key: value for key, value in r.items() if key != "seconds"} for r in output.report.search["resamplings"]]


@pytest.mark.parametrize("scheduler", ["ddim", "dpm"])
def test_pipeline_resampling_carries_every_particles_state(scheduler, estimators, monkeypatch):
    # one particle per call: a particle's numbers are then its own (in a batch, CPU kernels round
    # a row by where it sits: the last rows fall in the remainder tiles)
    pipe = cogvideox(scheduler)
    run = T.tiny_run_options(particle_batch=1)
    plain = run_pipeline(pipe, estimators, seeds=(0, 1), run=run, search=SearchConfig(particles=2, resample_steps=[]))
    at = dict(particles=2, resample_steps=[2], renoise=False)
    identity = run_pipeline(pipe, estimators, seeds=(0, 1), run=run,
                            search=SearchConfig(**at, scheme=fixed_scheme(monkeypatch, "identity", [0, 1])))
    assert torch.equal(identity.frames, plain.frames)
    if scheduler == "ddim":  # deterministic: a swap swaps the videos (DPM draws each slot's noise from its own seed)
        swapped = run_pipeline(pipe, estimators, seeds=(0, 1), run=run,
                               search=SearchConfig(**at, scheme=fixed_scheme(monkeypatch, "swap", [1, 0])))
        assert torch.equal(swapped.frames, plain.frames.flip(0))
    copies = run_pipeline(pipe, estimators, seeds=(0, 0), run=run,
                          search=SearchConfig(**at, scheme=fixed_scheme(monkeypatch, "copy", [0, 0])))
    assert torch.equal(copies.frames[0], copies.frames[1])  # identical noise: the copies' futures are identical
    assert copies.report.search["lineages"] == [[0, 0], [0, 1]]


def test_pipeline_renoised_copies_explore_with_their_own_noise(estimators, monkeypatch):
    pipe = cogvideox()
    scheme = fixed_scheme(monkeypatch, "copy", [0, 0, 0])
    search = SearchConfig(particles=3, resample_steps=[1], scheme=scheme)
    out = run_pipeline(pipe, estimators, seeds=(0, 1, 1), search=search)
    assert out.report.search["resamplings"][0]["renoised"] == [1, 2]
    assert not torch.equal(out.frames[0], out.frames[1])  # moved off their ancestor
    assert torch.equal(out.frames[1], out.frames[2])  # the same noise (seeds 1, 1): the same move


class RecordingVae(torch.nn.Module):
    """A VAE whose decode doubles its latents and records, per call, its batch, its timestep rows,
    its replica and whether autograd was recording."""

    def __init__(self):
        super().__init__()
        self.weight = torch.nn.Parameter(torch.tensor(2.0))
        self.calls = []

    def decode(self, latents, temb=None, return_dict=True):
        self.calls.append((latents.shape[0], None if temb is None else temb.tolist(), id(self), torch.is_grad_enabled()))
        frames = latents * self.weight
        return (frames,) if not return_dict else type("DecoderOutput", (), {"sample": frames})()


def test_the_final_decode_dealt_over_devices_decodes_each_video_alone_in_order_and_goes_back():
    vae = RecordingVae()
    latents, temb = torch.arange(5.0).view(5, 1, 1), torch.tensor([10.0, 11.0, 12.0, 13.0, 14.0])
    restore = P.deal_final_decode(vae, [torch.device("cpu")] * 2)
    with torch.no_grad():
        dealt = vae.decode(latents, temb, return_dict=False)[0]
    assert torch.equal(dealt, latents * 2) and not dealt.requires_grad
    home = [call for call in vae.calls if call[2] == id(vae)]
    assert [call[1] for call in home] == [[10.0], [12.0], [14.0]]  # videos 0, 2, 4 here; 1 and 3 on the copy
    assert all(call[0] == 1 and not call[3] for call in vae.calls)  # one video a call, no graph in the threads
    assert len(vae.calls) == 3
    restore()
    assert "decode" not in vae.__dict__ and vae.decode(latents).sample.shape == (5, 1, 1)


def test_dealt_work_keeps_the_order_and_raises_what_an_item_raises():
    assert list(dealt_work(5, 2, lambda k, place: (k, place))) == [(0, 0), (1, 1), (2, 0), (3, 1), (4, 0)]

    def failing(k, place):
        if k == 3:
            raise ValueError("item 3")
        return k

    with pytest.raises(ValueError, match="item 3"):
        list(dealt_work(4, 2, failing))


@pytest.mark.slow
def test_pipeline_sub_batches_and_devices_give_the_same_frames(estimators):
    pipe = cogvideox()
    search = SearchConfig(particles=3, resample_steps=[1, 2], temperature=0.001)
    one_batch = run_pipeline(pipe, estimators, seeds=(0, 1, 2), search=search, guidance=GUIDED,
                             run=T.tiny_run_options(particle_batch=3), output_type="pt")
    singles = run_pipeline(pipe, estimators, seeds=(0, 1, 2), search=search, guidance=GUIDED,
                           run=T.tiny_run_options(particle_batch=1), output_type="pt")
    dealt = run_pipeline(pipe, estimators, seeds=(0, 1, 2), search=search, guidance=GUIDED,
                         run=T.tiny_run_options(particle_batch=1, devices=["cpu", "cpu"]), output_type="pt")
    assert torch.equal(dealt.frames, singles.frames)  # a sub-batch and a video's decode: the same on any replica
    assert dealt.report.search["final_decode_devices"] == ["cpu", "cpu"]
    assert "final_decode_devices" not in singles.report.search and "decode" not in pipe.vae.__dict__
    # batches of another size sum in another order: the same resamplings, frames to float rounding
    ancestors = [r["ancestors"] for r in one_batch.report.search["resamplings"]]
    assert ancestors == [r["ancestors"] for r in singles.report.search["resamplings"]]
    torch.testing.assert_close(one_batch.frames, singles.frames, rtol=0, atol=1e-3)
    assert {tuple(r["particles"]) for r in singles.report.log} == {(0, 0), (1, 1), (2, 2)}


def test_pipeline_counts_the_forwards_and_scorings_it_predicts(estimators, monkeypatch):
    pipe = cogvideox()
    forwards = CountingHook()
    HookRegistry.check_if_exists_or_initialize(pipe.transformer).register_hook(forwards, "count")
    scored = []
    estimate = estimators.geometry.estimate_geometry
    monkeypatch.setattr(estimators.geometry, "estimate_geometry", lambda frames: scored.append(len(frames)) or
                        estimate(frames))
    search = SearchConfig(particles=3, resample_steps=[1, 2], scheme=fixed_scheme(monkeypatch, "copy", [0, 0, 2]))
    out = run_pipeline(pipe, estimators, seeds=(0, 1, 2), search=search, run=T.tiny_run_options(particle_batch=1))
    counts = S.search_counts(search, 4)
    renoised = sum(len(r["renoised"]) for r in out.report.search["resamplings"])
    assert renoised == 2 <= counts.renoise_forwards_max
    assert forwards.n == counts.denoiser_forwards + renoised  # one particle per call
    assert sum(scored) == counts.scorings and set(scored) == {1}  # each particle's anchors, one at a time


def test_pipeline_search_errors_are_one_line_before_any_work(estimators):
    pipe = cogvideox()
    forwards = CountingHook()
    HookRegistry.check_if_exists_or_initialize(pipe.transformer).register_hook(forwards, "count")
    cases = [
        (dict(search=SearchConfig(particles=2, resample_steps=[4])), "outside the 4 denoising steps"),
        (dict(search={"particles": 2, "temperature": float("nan")}), "search: temperature must be a finite number"),
        (dict(search={"particles": 0}), "search: particles must be a whole number"),
        (dict(search=SearchConfig(particles=2), seeds=(0,)), "needs one generator per particle, got a list of 1"),
        (dict(search=SearchConfig(particles=2), run=T.tiny_run_options(split_cfg=True)), "run.split_cfg"),
    ]
    for changes, match in cases:
        with pytest.raises(ValueError, match=match) as err:
            run_pipeline(pipe, estimators, **changes)
        assert "\n" not in str(err.value)
    with pytest.raises(ValueError, match="search_generator"):
        pipe(PROMPT, generator=gens(0, 1), guidance=UNGUIDED, estimators=estimators, search=SearchConfig(particles=2),
             **dict(T.TINY_CALL_KWARGS, num_frames=NUM_FRAMES))
    with pytest.raises(ValueError, match="makes 2"):
        run_pipeline(pipe, estimators, seeds=(0, 1), search=SearchConfig(particles=2), prompt=[PROMPT, PROMPT])
    with pytest.raises(ValueError, match="a search scores its particles with GeCo"):
        run_pipeline(pipe, None, seeds=(0, 1), search=SearchConfig(particles=2))
    assert forwards.n == 0


# ---- the hooks ----------------------------------------------------------------------------------


HOOKED = {
    "wan": T.tiny_wan_pipeline,  # UniPC: model_outputs and last_sample
    "ltx": T.tiny_ltx_pipeline,
    "hunyuan": T.tiny_hunyuan_pipeline,
}


def run_hooked(pipe, estimators, seeds, search=None, guidance=UNGUIDED, run=None, search_seed=7):
    kwargs = T.tiny_call_kwargs(pipe, num_frames=NUM_FRAMES, output_type="pt")
    if search is None:
        return pipe(prompt=PROMPT, generator=torch.Generator().manual_seed(seeds[0]), **kwargs).frames, None
    with attach_geco_guidance(pipe, guidance, estimators, run or T.tiny_run_options()) as handle:
        handle.enable_search(search, torch.Generator().manual_seed(search_seed))
        frames = pipe(prompt=PROMPT, generator=gens(*seeds), num_videos_per_prompt=len(seeds), **kwargs).frames
    return frames, handle.last


@pytest.mark.parametrize("family", sorted(HOOKED))
def test_hooks_one_particle_without_resampling_is_the_plain_video(family, estimators):
    pipe = HOOKED[family](0)
    plain, _ = run_hooked(pipe, estimators, (0,))
    searched, report = run_hooked(pipe, estimators, (0,), SearchConfig(particles=1, resample_steps=[]))
    assert torch.equal(searched, plain) and report.search["lineages"] == [[0]]


@pytest.mark.slow
def test_hooks_guided_particles_of_one_per_call_are_their_seeds_guided_videos(estimators):
    pipe = T.tiny_wan_pipeline(0)
    with attach_geco_guidance(pipe, GUIDED, estimators, T.tiny_run_options()):
        alone = [pipe(prompt=PROMPT, generator=torch.Generator().manual_seed(s),
                      **T.tiny_call_kwargs(pipe, num_frames=NUM_FRAMES, output_type="pt")).frames for s in (0, 1)]
    searched, report = run_hooked(pipe, estimators, (0, 1), SearchConfig(particles=2, resample_steps=[]), GUIDED,
                                  T.tiny_run_options(particle_batch=1))
    assert torch.equal(searched, torch.cat(alone))
    assert [tuple(r["particles"]) for r in report.log] == [(0, 0), (1, 1), (0, 0), (1, 1)]


@pytest.mark.slow
def test_hooks_resampling_carries_the_multistep_history(estimators, monkeypatch):
    pipe = T.tiny_wan_pipeline(0)  # UniPC: the next steps read model_outputs and last_sample
    run = T.tiny_run_options(particle_batch=1)  # one particle per call: its numbers its own
    at = dict(particles=2, resample_steps=[2], renoise=False)
    plain, _ = run_hooked(pipe, estimators, (0, 1), SearchConfig(particles=2, resample_steps=[]), run=run)
    identity, _ = run_hooked(pipe, estimators, (0, 1), SearchConfig(**at, scheme=fixed_scheme(monkeypatch, "i", [0, 1])),
                             run=run)
    assert torch.equal(identity, plain)
    swap = SearchConfig(**at, scheme=fixed_scheme(monkeypatch, "swap", [1, 0]))
    swapped, report = run_hooked(pipe, estimators, (0, 1), swap, run=run)
    assert torch.equal(swapped, plain.flip(0)) and report.search["carried_state"] == ["last_sample", "model_outputs"]
    copies, _ = run_hooked(pipe, estimators, (0, 1), SearchConfig(**at, scheme=fixed_scheme(monkeypatch, "c", [1, 1])),
                           run=run)
    assert torch.equal(copies[0], plain[1]) and torch.equal(copies[1], plain[1])
    # the history is what makes it so: left behind, the swapped slots continue from the wrong past
    monkeypatch.setattr(S, "reorder_scheduler_state", lambda *args: [])
    unswapped_history, _ = run_hooked(pipe, estimators, (0, 1), swap, run=run)
    assert not torch.equal(unswapped_history, plain.flip(0))


def test_hooks_carry_the_steps_per_particle_arguments(estimators, monkeypatch):
    pipe = T.tiny_cogvideox_pipeline(0, scheduler="dpm")  # old_pred_original_sample: an argument of step
    kwargs = T.tiny_call_kwargs(pipe, num_frames=NUM_FRAMES, output_type="pt")
    outputs = []
    for scheme, ancestors in (("none", None), ("copy", [0, 0])):
        search = SearchConfig(particles=2, resample_steps=[] if ancestors is None else [2], renoise=False,
                              **({} if ancestors is None else {"scheme": fixed_scheme(monkeypatch, scheme, ancestors)}))
        with attach_geco_guidance(pipe, UNGUIDED, estimators, T.tiny_run_options(particle_batch=1)) as h:
            h.enable_search(search, torch.Generator().manual_seed(0))
            # stock CogVideoX makes one video per prompt: the particles are two prompts; both slots the same seed
            outputs.append(pipe(prompt=[PROMPT, PROMPT], generator=gens(5, 5), **kwargs).frames)
    plain, copies = outputs
    assert torch.equal(copies[0], copies[1]) and torch.equal(copies[0], plain[0])


@pytest.mark.slow
def test_hooks_sub_batches_and_devices_give_the_same_frames(estimators):
    pipe = T.tiny_wan_pipeline(0)
    search = SearchConfig(particles=3, resample_steps=[1, 2], temperature=0.001)
    one_batch, a = run_hooked(pipe, estimators, (0, 1, 2), search, GUIDED, T.tiny_run_options(particle_batch=3))
    singles, b = run_hooked(pipe, estimators, (0, 1, 2), search, GUIDED, T.tiny_run_options(particle_batch=1))
    dealt, c = run_hooked(pipe, estimators, (0, 1, 2), search, GUIDED,
                          T.tiny_run_options(particle_batch=1, devices=["cpu", "cpu"]))
    assert torch.equal(dealt, singles)
    assert c.search["final_decode_devices"] == ["cpu", "cpu"] and "final_decode_devices" not in b.search
    assert "decode" not in pipe.vae.__dict__  # the dealt final decode went with the handle
    assert [r["ancestors"] for r in a.search["resamplings"]] == [r["ancestors"] for r in b.search["resamplings"]]
    # to float rounding, grown by the guided updates: far below an 8-bit level (1/255)
    torch.testing.assert_close(one_batch, singles, rtol=0, atol=1e-3)
    assert not hasattr(pipe.transformer, "_diffusers_hook")  # the hooks and the replicas' making left nothing


def test_hooks_search_errors_are_one_line_before_any_denoising_step(estimators):
    pipe = T.tiny_wan_pipeline(0)
    forwards = CountingHook()
    HookRegistry.check_if_exists_or_initialize(pipe.transformer).register_hook(forwards, "count")
    kwargs = T.tiny_call_kwargs(pipe, num_frames=NUM_FRAMES, output_type="pt")
    with attach_geco_guidance(pipe, UNGUIDED, estimators) as handle:
        with pytest.raises(TypeError, match=r"^attach_geco_guidance\(search=...\) is the earlier spelling: a search is "
                                            r"handle.enable_search"):
            attach_geco_guidance(pipe, UNGUIDED, estimators, search=SearchConfig(particles=2))
        with pytest.raises(ValueError, match="enable_search needs search.particles"):
            handle.enable_search(SearchConfig(), torch.Generator())
        with pytest.raises(ValueError, match="pass a torch.Generator, got int"):
            handle.enable_search(SearchConfig(particles=2), 0)
        handle.enable_search(SearchConfig(particles=2), torch.Generator().manual_seed(0))
        with pytest.raises(ValueError, match="num_videos_per_prompt=2"):
            pipe(prompt=PROMPT, generator=torch.Generator().manual_seed(0), **kwargs)
        handle.enable_search({"particles": 2, "resample_steps": [9]}, torch.Generator().manual_seed(0))
        with pytest.raises(ValueError, match=r"search.resample_steps \[9\] are outside the 4 denoising steps"):
            pipe(prompt=PROMPT, generator=gens(0, 1), num_videos_per_prompt=2, **kwargs)
        handle.disable_search()
        assert handle.search is None and handle.search_generator is None
    assert forwards.n == 0  # refused at prepare_latents; the steps at the first denoiser call, before it runs


class LeftHalf:
    """A mask source that masks the left half of every frame, and counts the clips it was asked for."""

    source_name = "left half"

    def __init__(self):
        self.clips = 0

    def dynamic_masks(self, frames, geometry=None, flow=None, pairs=None):
        self.clips += 1
        masks = torch.zeros(frames.shape[0], *frames.shape[-2:], dtype=torch.bool)
        masks[..., : frames.shape[-1] // 2] = True
        return masks


@pytest.mark.slow
def test_search_with_dynamic_masks_scores_without_what_moves_and_guides_each_particle(estimators, monkeypatch):
    pipe = cogvideox()
    search = SearchConfig(particles=2, resample_steps=[2], scheme=fixed_scheme(monkeypatch, "copy", [1, 1]))
    plain = run_pipeline(pipe, estimators, seeds=(0, 1), search=search)
    source = LeftHalf()
    with_masks = estimators.with_segmenter(source)
    masked = run_pipeline(pipe, with_masks, seeds=(0, 1), search=search,
                          guidance=T.tiny_guidance_config(anchors=ANCHORS, enabled=False, dynamic="the dog"))
    assert source.clips == 2  # each particle's anchors, at the one resampling
    assert masked.report.search["resamplings"][0]["scores"] != plain.report.search["resamplings"][0]["scores"]
    assert masked.report.mask_source == "left half" and plain.report.mask_source is None
    unguided_masks = T.tiny_guidance_config(anchors=ANCHORS, enabled=False, dynamic="the dog")
    _, hooked = run_hooked(T.tiny_wan_pipeline(0), with_masks, (0, 1), search, unguided_masks)
    assert hooked.mask_source == "left half"  # under the hooks too
    guided = T.tiny_guidance_config(anchors=ANCHORS, repeats="0x1,1x3", time_travel=[], step_size=1.0,
                                    denoiser_grad=False, dynamic="the dog", dynamic_refresh=2)
    source.clips = 0
    report = run_pipeline(pipe, with_masks, seeds=(0, 1), search=search, guidance=guided,
                          run=T.tiny_run_options(particle_batch=1)).report
    # guided steps 1 and 3 refresh each particle's masks (2 x 2), step 2 reuses them, the scoring asks afresh (2)
    assert source.clips == 6 and report.mask_source == "left half"
    assert [tuple(r["particles"]) for r in report.log] == [(0, 0), (1, 1)] * 3
    assert all(r["masked_fraction"] == pytest.approx(0.5) for r in report.log)
