"""Memory plans: every plan gives the same video, the planner's choice, the OOM fallback, bad input."""

from __future__ import annotations

import json
import math
from functools import partial
from pathlib import Path

import pytest
import torch

from geco_guide.config import load_config
from geco_guide.perf.plans import KNOWN_MODELS, MODES, anchor_decoders, card_plan, offload_peak
from geco_guide.sampler.algorithm.config import GuidanceConfig
from geco_guide.sampler.running.context import GuidanceContext
from geco_guide.sampler.running.run_options import RUN_KEYS, RunOptions
from geco_guide.sampler.running.memory_plan import (
    DEVICE_HEADROOM,
    ESTIMATES_PATH,
    PLAN_NAMES,
    PLANS,
    SAFE_PLAN,
    choose_plan,
    explicit_plan,
    load_estimates,
    plan_named,
    process_peak,
)
from geco_guide.sampler.algorithm.slicing import (
    anchor_latent_chunks,
    decode_anchor_frames,
    decode_chunk,
)
from geco_guide.tiny import TINY_CALL_KWARGS, tiny_estimators, tiny_pipeline, tiny_run_options

PROMPT = "a marble bust on a table"
#: Two guided steps, one update each: short, and the second update runs after the first's plan.
SCHEDULE = {"repeats": "0x1,1x2,0x1", "time_travel": []}
#: Today's default (GuidanceConfig(), the paper's preset): the chunks decoded one at a time in
#: checkpointed regions, with the VAE's block checkpointing, the denoiser checkpointed.
EXPLICIT_DEFAULT = {"memory_plan": "explicit", "vae_checkpointing": True, "gradient_checkpointing": True}
ESTIMATORS = tiny_estimators(0)


@pytest.fixture(scope="module")
def pipe():
    return tiny_pipeline(0)


def run(pipe, mode: str, seed: int = 3, **options):
    """A call in ``mode`` with ``options``: the run options (``memory_plan``, ...; over the tiny
    ones) and guidance's."""
    args = dict(TINY_CALL_KWARGS, output_type="pt", estimators=ESTIMATORS)
    run_options = tiny_run_options(**{key: value for key, value in options.items() if key in RUN_KEYS})
    guidance = {key: value for key, value in options.items() if key not in RUN_KEYS}
    return pipe(PROMPT, generator=torch.Generator().manual_seed(seed), **args, run_options=run_options,
                guidance={**SCHEDULE, "denoiser_grad": mode == "faithful", **guidance})


# ---- every plan gives the same video ------------------------------------------------------------


@pytest.mark.parametrize("mode", ["fast", "faithful"])
@pytest.mark.slow
def test_every_plan_gives_the_same_frames_as_the_explicit_default(pipe, mode):
    reference = run(pipe, mode, **EXPLICIT_DEFAULT)
    assert reference.report.memory_plan["name"] == "explicit" and len(reference.report.log) == 2
    variants = [{"memory_plan": name} for name in PLAN_NAMES if name != "explicit"]
    variants.append({"memory_plan": "explicit", "vae_checkpointing": True, "vae_block_checkpointing": False,
                     "gradient_checkpointing": False})
    for guidance in variants:
        out = run(pipe, mode, **guidance)
        assert torch.equal(out.frames, reference.frames), guidance
        assert [r["loss"] for r in out.report.log] == [r["loss"] for r in reference.report.log], guidance
    # every switch restored after the calls
    assert not pipe.transformer.is_gradient_checkpointing and not pipe.vae.is_gradient_checkpointing
    assert not ESTIMATORS.geometry.gradient_checkpointing and not ESTIMATORS.flow.gradient_checkpointing


@pytest.mark.slow
def test_one_call_per_chunk_is_the_checkpointed_decode_to_the_last_bit(pipe):
    """The named plans' decode without checkpointing (one call per chunk) gives the checkpointed
    decode's numbers and gradient exactly; the explicit plan without ``vae_checkpointing`` batches
    the chunks of one length, as before the plans."""
    decode = partial(decode_chunk, pipe.vae, scaling_factor=pipe.vae_scaling_factor_image)
    chunks = anchor_latent_chunks([4, 8, 12, 16], 17, 4, 3)
    latents = torch.randn(1, 5, pipe.transformer.config.in_channels, 4, 6, generator=torch.Generator().manual_seed(0))
    results = []

    def counted(calls: list[int], x):
        calls.append(len(x))
        return decode(x)

    for kwargs in ({"checkpoint_chunks": True}, {"batch_chunks": False}, {}):
        z = latents.clone().requires_grad_(True)
        calls: list[int] = []
        frames = decode_anchor_frames(partial(counted, calls), z, chunks, **kwargs)
        frames.square().sum().backward()
        results.append((frames.detach(), z.grad, calls))
    (ckpt, ckpt_grad, _), (single, single_grad, single_calls), (_, _, batched_calls) = results
    assert torch.equal(single, ckpt) and torch.equal(single_grad, ckpt_grad)
    assert single_calls == [1, 1, 1, 1] and sorted(batched_calls) == [1, 3]


@pytest.mark.slow
def test_the_plan_switches_are_on_during_the_call_and_reported(pipe, monkeypatch):
    seen = []
    objective = GuidanceContext.objective

    def spy(self, x0):
        seen.append((pipe.transformer.is_gradient_checkpointing, pipe.vae.is_gradient_checkpointing,
                     ESTIMATORS.geometry.gradient_checkpointing, self.memory_plan.plan.chunk_checkpointing))
        return objective(self, x0)

    monkeypatch.setattr(GuidanceContext, "objective", spy)
    out = run(pipe, "faithful", memory_plan="leanest")
    assert seen[0] == (True, True, True, True)
    assert out.report.memory_plan["name"] == "leanest"
    assert not hasattr(pipe, "geco_memory_plan")  # the plan is the call's: in its report, not on the pipeline
    seen.clear()
    run(pipe, "fast", memory_plan="chunked")
    assert seen[0] == (False, False, False, True)  # the denoiser is not differentiated in fast mode


@pytest.mark.slow
def test_partial_checkpoints_all_denoiser_blocks_but_every_fourth_and_changes_nothing():
    """``partial`` on a 6-block tiny transformer: blocks 1-3 and 5 checkpointed one by one during the
    faithful call (the model's own checkpointing off), blocks 0 and 4 kept; the frames are the
    default's exactly, and the blocks are restored after the call."""
    from geco_guide.sampler.pipelines.pipeline_cogvideox import GeCoCogVideoXPipeline
    from geco_guide.tiny import (
        TinySizes,
        tiny_cogvideox_components,
        tiny_guidance_config,
    )

    deep = GeCoCogVideoXPipeline(**tiny_cogvideox_components(0, TinySizes(layers=6)),
                                 guidance_config=tiny_guidance_config())
    deep.set_progress_bar_config(disable=True)
    blocks = deep.transformer.transformer_blocks
    seen = []
    objective = GuidanceContext.objective

    def spy(self, x0):
        wrapped = [i for i, b in enumerate(blocks) if "forward" in b.__dict__]
        seen.append((wrapped, deep.transformer.is_gradient_checkpointing))
        return objective(self, x0)

    reference = run(deep, "faithful", **EXPLICIT_DEFAULT)
    GuidanceContext.objective = spy
    try:
        partial_out = run(deep, "faithful", memory_plan="partial")
    finally:
        GuidanceContext.objective = objective
    assert seen[0] == ([1, 2, 3, 5], False)
    assert torch.equal(partial_out.frames, reference.frames)
    assert not any("forward" in b.__dict__ for b in blocks)


# ---- the planner ------------------------------------------------------------------------------


def estimates(peaks: dict[str, float], times: dict[str, float]) -> dict:
    """A one-model estimates table: ``cogvideox-5b`` fast/vae, weights 10 GiB, no offload savings
    but half the activations under offload."""
    table = {name: {"weights_gb": 10.0, "activations_gb": peaks[name] - 10.0, "offload_weights_gb": 2.0,
                    "offload_activations_gb": (peaks[name] - 10.0) / 2, "time_s": times[name]} for name in peaks}
    return {"models": {"cogvideox-5b": {"signature": {"num_layers": 42}, "model_ids": ["THUDM/CogVideoX-5b"],
                                        "video": {"frames": 49, "height": 480, "width": 720},
                                        "estimates": {"fast/vae": table}}}}


TABLE = estimates({"fastest": 300, "partial": 120, "chunked": 80, "checkpointed": 30, "leanest": 28},
                  {"fastest": 500, "partial": 560, "chunked": 600, "checkpointed": 800, "leanest": 810})


def choose(budget=None, device_gb=None, offload=False, frames=49, **run):
    return choose_plan(GuidanceConfig(denoiser_grad=False), RunOptions(memory_budget_gb=budget, **run), model_id="THUDM/CogVideoX-5b", frames=frames, height=480, width=720,
                       device_gb=device_gb, offload=offload, estimates=TABLE)


def test_auto_picks_the_least_time_that_fits_and_falls_back_in_order():
    assert choose(budget=400).plan.name == "fastest"
    assert [p.name for p in choose(budget=400).fallbacks] == ["partial", "chunked", "checkpointed", "leanest"]
    assert choose(budget=120).plan.name == "partial"
    choice = choose(budget=100)
    assert choice.plan.name == "chunked" and choice.predicted_peak_gb == 80
    assert [p.name for p in choice.fallbacks] == ["checkpointed", "leanest"]
    assert choose(budget=29).plan.name == "leanest"
    # the device's memory, with headroom: 0.94 * 90 = 84.6 fits chunked, 0.94 * 85 = 79.9 does not
    assert choose(device_gb=90).plan.name == "chunked"
    assert choose(device_gb=85).plan.name == "checkpointed"
    # activations scale with frames x pixels: 10 + 70 * 25 / 49 = 45.7 for 25 frames
    assert choose(budget=46, frames=25).plan.name == "chunked"
    assert choose(budget=20, offload=True).plan.name == "checkpointed"  # 2 + 20 / 2 = 12


def test_unknown_model_or_budget_gets_the_safe_plan_and_named_plans_are_kept():
    cfg = GuidanceConfig(denoiser_grad=False)
    unknown = choose_plan(cfg, RunOptions(), model_id="someone/other-model", frames=49, height=480, width=720, device_gb=80,
                          estimates=TABLE)
    assert unknown.plan == SAFE_PLAN and "no estimates" in unknown.reason and unknown.fallbacks == ()
    assert choose().plan == SAFE_PLAN  # no budget known
    faithful = choose_plan(GuidanceConfig(), RunOptions(), model_id="THUDM/CogVideoX-5b", frames=49, height=480, width=720,
                           device_gb=80, estimates=TABLE)
    assert faithful.plan == SAFE_PLAN  # the table has no faithful estimates
    named = choose(budget=1, memory_plan="chunked")
    assert named.plan == plan_named("chunked") and named.fallbacks == () and named.predicted_peak_gb == 80


def test_under_context_parallel_a_plan_fits_one_process_share_of_the_denoiser():
    """Faithful peaks 60 GiB over the fast ones (the differentiated denoiser's activations): over
    4 processes each holds 15 of them, so ``fastest`` (300 + 60 / 4) fits 320 GiB per process."""
    fast = {"fastest": 300, "partial": 120, "chunked": 80, "checkpointed": 30, "leanest": 28}
    faithful = estimates({name: peak + 60 for name, peak in fast.items()},
                         {"fastest": 900, "partial": 960, "chunked": 1000, "checkpointed": 1200, "leanest": 1210})
    model = faithful["models"]["cogvideox-5b"]["estimates"]
    model["faithful/vae"], model["fast/vae"] = model["fast/vae"], TABLE["models"]["cogvideox-5b"]["estimates"]["fast/vae"]

    def plan(**run):
        return choose_plan(GuidanceConfig(), RunOptions(memory_budget_gb=320, **run), model_id="THUDM/CogVideoX-5b",
                           frames=49, height=480, width=720, device_gb=None, estimates=faithful)

    one, split = plan(), plan(context_parallel=4)
    assert one.plan.name == "partial" and one.predicted_peak_gb == 180
    assert split.plan.name == "fastest" and split.predicted_peak_gb == 315
    assert split.reason.startswith("auto: least recomputation predicted to fit 320.0 GiB per process of 4")
    assert process_peak(360, 300, 4) == 315 and process_peak(300, 310, 4) == 300  # nothing divided below the fast peak


def test_no_plan_fits_is_one_line_naming_the_smallest_peak_and_offload():
    with pytest.raises(ValueError) as err:
        choose(budget=25)
    message = str(err.value)
    assert "\n" not in message and "'leanest'" in message and "28.0 GiB" in message
    assert "enable_model_cpu_offload() it is predicted at 11.0 GiB" in message
    with pytest.raises(ValueError, match="no memory plan fits 5.0 GiB") as err:
        choose(budget=5)
    assert "offload" not in str(err.value)  # 11 GiB with offload does not fit 5 either


def test_explicit_plan_reproduces_the_one_flag_of_before():
    for flag in (True, False):
        plan = explicit_plan(RunOptions(vae_checkpointing=flag, gradient_checkpointing=flag))
        assert plan.chunk_checkpointing is plan.vae_block_checkpointing is plan.denoiser_checkpointing is flag
        assert plan.estimator_checkpointing is None  # the estimators as loaded
    split = explicit_plan(RunOptions(vae_checkpointing=True, vae_block_checkpointing=False))
    assert split.chunk_checkpointing and not split.vae_block_checkpointing
    # the named plans, least recomputation first: each adds one
    flags = [sum((p.chunk_checkpointing, p.vae_block_checkpointing, p.denoiser_checkpointing,
                  bool(p.estimator_checkpointing))) for p in PLANS]
    assert flags == sorted(flags) and PLANS[-1] == SAFE_PLAN


# ---- bad input ----------------------------------------------------------------------------------


@pytest.mark.parametrize("value", [0, -1.5, math.nan, math.inf])
def test_a_budget_that_is_not_a_positive_finite_number_is_one_line(value):
    with pytest.raises(ValueError, match="memory_budget_gb") as err:
        RunOptions(memory_budget_gb=value)
    assert "\n" not in str(err.value)


def test_an_unknown_plan_is_one_line_listing_the_plans():
    with pytest.raises(ValueError) as err:
        load_config(preset="tiny", overrides=["run.memory_plan=smallest"])
    message = str(err.value)
    assert "\n" not in message and all(name in message for name in PLAN_NAMES)
    assert load_config(preset="tiny", overrides=["run.memory_budget_gb=12.5"]).run.memory_budget_gb == 12.5


def test_a_call_whose_budget_no_plan_fits_stops_before_any_step(pipe, monkeypatch):
    def no_step(*args, **kwargs):
        raise AssertionError("the call started denoising")

    monkeypatch.setattr(type(pipe), "model_output", no_step)
    with pytest.raises(ValueError, match="no memory plan fits 0.0 GiB"):
        run(pipe, "fast", memory_plan="auto", memory_budget_gb=1e-6)


# ---- out of memory at the first update -----------------------------------------------------------


def fake_oom_at_calls(monkeypatch, calls: set[int]):
    """Make the objective raise ``torch.cuda.OutOfMemoryError`` at the given 0-based calls."""
    objective, count = GuidanceContext.objective, {"n": 0}

    def failing(self, x0):
        count["n"] += 1
        if count["n"] - 1 in calls:
            raise torch.cuda.OutOfMemoryError("CUDA out of memory (injected)")
        return objective(self, x0)

    monkeypatch.setattr(GuidanceContext, "objective", failing)


@pytest.mark.parametrize("mode", ["fast", "faithful"])
@pytest.mark.slow
def test_oom_at_the_first_update_falls_back_to_the_next_plan(pipe, monkeypatch, caplog, mode):
    budget = {"memory_plan": "auto", "memory_budget_gb": 1000.0}  # the tiny models' least-recompute plan
    plain = run(pipe, mode, **budget)
    first = plain.report.memory_plan["name"]
    expected = plain.report.memory_plan["fallbacks"][0]
    assert PLANS.index(plan_named(expected)) > PLANS.index(plan_named(first))
    fake_oom_at_calls(monkeypatch, {0})
    with caplog.at_level("WARNING", logger="geco_guide.sampler.running.context"):
        out = run(pipe, mode, **budget)
    assert out.report.memory_plan["name"] == expected and first in out.report.memory_plan["reason"]
    assert f"memory plan {first!r}; retrying it with {expected!r}" in caplog.text
    torch.testing.assert_close(out.frames, plain.frames, rtol=0, atol=1e-6)
    assert len(out.report.log) == len(plain.report.log)


def test_oom_after_the_first_update_or_with_a_named_plan_is_raised(pipe, monkeypatch):
    fake_oom_at_calls(monkeypatch, {1})
    with pytest.raises(torch.cuda.OutOfMemoryError):
        run(pipe, "fast", memory_plan="auto", memory_budget_gb=1000.0)
    fake_oom_at_calls(monkeypatch, {0})
    with pytest.raises(torch.cuda.OutOfMemoryError):
        run(pipe, "fast", memory_plan="chunked")


# ---- the shipped estimates and the cards -------------------------------------------------------


def test_the_shipped_estimates_know_the_models_and_are_package_data():
    data = load_estimates()
    assert set(data["models"]) == set(KNOWN_MODELS)
    for key, entry in data["models"].items():
        assert set(entry["estimates"]) == {f"{mode}/{decoder}" for mode in MODES for decoder in anchor_decoders(key)}
        for table in entry["estimates"].values():
            assert [name for name in table] == [p.name for p in PLANS]
    full = data["models"]["cogvideox-5b"]["estimates"]["fast/vae"]
    assert full["fastest"]["peak_gb"] > full["chunked"]["peak_gb"] > full["checkpointed"]["peak_gb"]
    assert full["fastest"]["time_s"] < full["chunked"]["time_s"] < full["checkpointed"]["time_s"]
    pyproject = (Path(__file__).resolve().parents[2] / "pyproject.toml").read_text()
    assert '"geco_guide.sampler.running" = ["data/*.json"]' in pyproject and ESTIMATES_PATH.parent.name == "data"
    assert '"geco_guide.families" = ["data/*.json"]' in pyproject  # the published configs they are traced from


def test_every_traced_family_is_known_by_its_signature_and_its_hub_id():
    """A stock pipeline is known by its denoiser's config and how many denoisers take turns: Wan
    2.2 A14B's two experts share Wan 2.1 14B's config, and the estimates tell them apart."""
    from geco_guide.families import model_named
    from geco_guide.families.published import published_configs, traced_models
    from geco_guide.sampler.running.memory_plan import known_model, model_signature

    data = load_estimates()
    signatures = [json.dumps(data["models"][name]["signature"], sort_keys=True) for name in traced_models()]
    assert len(set(signatures)) == len(signatures)
    for name in traced_models():
        published = published_configs(name)
        experts = 2 if published.transformer_2 is not None else 1
        assert known_model(data, signature=model_signature(published.transformer, experts)) == name
        assert known_model(data, model_id=model_named(name).hub_id) == name
    wan22 = published_configs("wan2.2-t2v-a14b").transformer
    assert known_model(data, signature=model_signature(wan22)) == "wan2.1-t2v-14b"
    assert known_model(data, signature=model_signature(wan22, experts=2)) == "wan2.2-t2v-a14b"


def test_each_family_gets_its_own_plans_on_a_card():
    """The plan of each family on the H200 comes from its own estimates (the planner's reason names
    it); a size the planner scales to reads LTX's 32x VAE right (the hooks' pixels of its latents)."""
    from geco_guide import tiny as T
    from geco_guide.families import model_named
    from geco_guide.families.published import traced_models
    from geco_guide.sampler.pipelines.adapters import adapter_for

    for name in traced_models():
        video = model_named(name).call
        choice = choose_plan(GuidanceConfig(denoiser_grad=False), RunOptions(), model_id=model_named(name).hub_id,
                             frames=video["num_frames"], height=video["height"], width=video["width"],
                             device_gb=1000.0)
        assert f"({name})" in choice.reason and choice.predicted_peak_gb > 0
    ltx = T.tiny_ltx_pipeline(0)  # LTX's pipelines name the factor otherwise than the others
    assert not hasattr(ltx, "vae_scale_factor_spatial") and ltx.vae_spatial_compression_ratio == 8
    ltx.vae_spatial_compression_ratio = 32  # the full-size VAE's
    wan = T.tiny_wan_pipeline(0)
    assert adapter_for(ltx).spatial_compression(ltx) == 32 and adapter_for(wan).spatial_compression(wan) == 8


def test_the_cards_get_the_plans_of_their_memory():
    h200 = card_plan("H200", "fast", "vae", 49, 480, 720)
    assert h200["plan"] == "chunked" and not h200["offload"]
    assert card_plan("H200", "faithful", "vae", 49, 480, 720)["plan"] == "partial"
    h100 = card_plan("H100", "fast", "vae", 49, 480, 720)
    assert h100["plan"] == "checkpointed" and h100["predicted_peak_gb"] < DEVICE_HEADROOM * h100["memory_gib"]
    small = card_plan("RTX4090", "fast", "vae", 49, 480, 720)
    assert small["offload"] and small["predicted_peak_gb"] <= 23


def test_offload_peak_counts_the_resident_estimators_and_the_model_at_work():
    gib = 2**30
    report = {"weights_gb": {"transformer": 10.0, "vae": 0.5, "geometry_estimator": 2.0, "flow_estimator": 1.0},
              "settings": {"decoder": "vae"},
              "unit_traces": {"guided": {"denoiser_cfg": {"forward": {"peak_live_bytes": 1 * gib}, "calls": 1},
                                         "anchor_decode": {"backward": {"peak_live_bytes": 12 * gib}, "calls": 1},
                                         "loss": {"forward": {"peak_live_bytes": 11 * gib}, "calls": 0}}}}
    peak = offload_peak(report)
    assert peak == {"weights_gb": 3.5, "activations_gb": 12.0, "at": "anchor_decode/backward"}


# ---- the hooks ----------------------------------------------------------------------------------


@pytest.mark.slow
def test_a_hooked_stock_pipeline_runs_the_plans_and_reports_them():
    """attach_geco_guidance: the stock tiny CogVideoX pipeline is a model the estimates know (auto
    picks its least-recompute plan), every plan gives the same frames there too, and the handle
    reports the plan; a Wan pipeline is not known: the safe plan."""
    from geco_guide import tiny as T
    from geco_guide.sampler.pipelines.hooks import attach_geco_guidance

    stock = T.tiny_cogvideox_pipeline(0)
    kwargs = T.tiny_call_kwargs(stock, num_frames=9, output_type="pt")
    config = {"anchors": [5, 8], "repeats": "0x3,1x1", "time_travel": []}
    frames = {}
    for plan in ("auto", "leanest", "explicit"):
        flags = {"vae_checkpointing": True, "gradient_checkpointing": True} if plan == "explicit" else {}
        run_options = {"memory_budget_gb": 1000.0, "memory_plan": plan, **flags}
        with attach_geco_guidance(stock, config, ESTIMATORS, run_options=run_options) as handle:
            frames[plan] = stock(prompt=PROMPT, generator=torch.Generator().manual_seed(0), **kwargs).frames
            frames[plan + " plan"] = handle.last.memory_plan["name"]
    assert frames["auto plan"] == "fastest" and frames["leanest plan"] == "leanest"
    assert torch.equal(frames["auto"], frames["explicit"]) and torch.equal(frames["leanest"], frames["explicit"])
    wan = T.tiny_wan_pipeline(0)
    with attach_geco_guidance(wan, {"anchors": [5, 8], "repeats": "0x3,1x1", "time_travel": []},
                              ESTIMATORS) as handle:
        wan(prompt=PROMPT, generator=torch.Generator().manual_seed(0),
            **T.tiny_call_kwargs(wan, num_frames=9, output_type="latent"))
        assert handle.last.memory_plan["name"] == SAFE_PLAN.name and "no estimates" in handle.last.memory_plan["reason"]


def test_a_command_line_can_check_the_budget_before_loading():
    from geco_guide.sampler.running.memory_plan import plan_before_loading

    cfg = load_config(preset="cogvideox-5b", overrides=["run.memory_budget_gb=20"])
    with pytest.raises(ValueError, match="the smallest, 'checkpointed', is predicted to peak at 40.3 GiB") as err:
        plan_before_loading(cfg.guidance, cfg.run, cfg.model.source, 49, 480, 720, None)
    assert "\n" not in str(err.value)
    fits = load_config(preset="cogvideox-5b", overrides=["run.memory_budget_gb=100"])
    assert plan_before_loading(fits.guidance, fits.run, "THUDM/CogVideoX-5b", 49, 480, 720, None).plan.name == "chunked"
    assert plan_before_loading(fits.guidance, fits.run, "someone/else", 49, 480, 720, None).plan == SAFE_PLAN
    off = load_config(preset="cogvideox-5b", overrides=["guidance.enabled=false"])
    assert plan_before_loading(off.guidance, off.run, "THUDM/CogVideoX-5b", 49, 480, 720, None) is None


@pytest.mark.parametrize("frames, height, width, bad", [
    (0, 480, 720, "frames=0"), (49, -32, 720, "height=-32"), (49, 480, 0, "width=0"), (49, 480.5, 720, "height=480.5"),
    (True, 480, 720, "frames=True"),
])
@pytest.mark.parametrize("enabled", [True, False])
def test_a_video_size_no_video_has_is_refused_before_any_plan(frames, height, width, bad, enabled):
    from geco_guide.sampler.running.memory_plan import plan_before_loading

    guidance = GuidanceConfig(enabled=enabled)
    with pytest.raises(ValueError, match=rf"^a memory plan needs a video size of positive integers: {bad} ") as err:
        plan_before_loading(guidance, RunOptions(), "THUDM/CogVideoX-5b", frames, height, width, None)
    assert "\n" not in str(err.value)


@pytest.mark.slow
def test_the_shipped_estimates_are_what_the_cost_model_traces_now():
    """One plan of the tiny models traced again gives the shipped numbers (regenerate the file
    with `geco bench plans` when this fails)."""
    from geco_guide.perf.cost import cost_report, cost_settings
    from geco_guide.perf.plans import plan_estimate

    settings = cost_settings(preset="tiny", steps=None, frames=None, height=None, width=None, dtype=None,
                             plan="chunked")
    estimate = plan_estimate(cost_report(settings, "fast"))
    shipped = load_estimates()["models"]["tiny"]["estimates"]["fast/vae"]["chunked"]
    for key in ("weights_gb", "activations_gb", "peak_gb", "offload_peak_gb", "time_s"):
        assert estimate[key] == pytest.approx(shipped[key], rel=1e-6), key
    assert estimate["peak_gb"] == pytest.approx(estimate["weights_gb"] + estimate["activations_gb"])
    assert estimate["offload_peak_gb"] <= estimate["peak_gb"]
