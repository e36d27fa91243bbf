"""Guidance and search per card and per number of GPUs, and the per-family table of
docs/performance.md: arithmetic on the shipped estimates, checked against the formulas, the
document and a fresh trace of one family."""

from __future__ import annotations

import math
from pathlib import Path

import pytest

from geco_guide.families.published import traced_models
from geco_guide.perf import cost, search_cost
from geco_guide.perf.family_table import family_table
from geco_guide.sampler.running.memory_plan import load_estimates
from geco_guide.sampler.search.particle_search import default_resample_steps

DOCS = Path(__file__).resolve().parents[2] / "docs" / "performance.md"
BEGIN, END = "<!-- family table: geco bench cost --all-models -->", "<!-- end of the family table -->"


def test_every_traced_model_has_estimates_a_search_needs():
    models = load_estimates()["models"]
    for name in traced_models():
        entry = models[name]
        assert set(entry["search_units"]) >= {"prediction_s", "scoring_s", "scoring_decode_s", "final_decode_s",
                                              "vggt_frame_s", "ufm_pair_s"}
        units = entry["search_units"]
        assert 0 < units["scoring_decode_s"]["H200"] < units["scoring_s"]["H200"]
        assert entry["unguided"]["time_s"]["H200"] == pytest.approx(
            entry["schedule"]["steps"] * units["prediction_s"]["H200"] + units["final_decode_s"]["H200"], rel=0.02)


def test_the_documented_table_is_what_the_command_prints():
    text = DOCS.read_text()
    assert BEGIN in text and END in text
    documented = text.split(BEGIN, 1)[1].split(END, 1)[0].strip()
    assert documented == family_table()


@pytest.mark.parametrize("name", ["cogvideox-5b", "wan2.1-t2v-1.3b"])
def test_matched_particles_take_no_longer_than_guidance(name):
    guided = search_cost.guidance_cost(name, "H200", "faithful")
    k = search_cost.matched_particles(name, "H200")
    assert k >= 1 and guided["plan"] is not None
    assert search_cost.search_cost(name, k, "H200")["time_s"] <= guided["time_s"]
    assert search_cost.search_cost(name, k + 1, "H200")["time_s"] > guided["time_s"]


def test_a_search_is_k_predictions_a_step_plus_its_scorings():
    name, k = "cogvideox-5b", 8
    entry = load_estimates()["models"][name]
    units, steps = entry["search_units"], entry["schedule"]["steps"]
    resamplings = len(default_resample_steps(steps))
    one = search_cost.search_cost(name, k, "H200", measured=None)  # the estimators' rates predicted
    assert one["resamplings"] == resamplings == 5
    assert one["denoiser_s"] == pytest.approx((steps * k + (k - 1) * resamplings) * units["prediction_s"]["H200"])
    assert one["scoring_s"] == pytest.approx(k * resamplings * units["scoring_s"]["H200"])
    assert one["final_decode_s"] == pytest.approx(k * units["final_decode_s"]["H200"])
    assert one["protocol_s"] == pytest.approx(k * search_cost.protocol_seconds(name, "H200", measured=None))
    assert one["time_s"] == pytest.approx(one["denoiser_s"] + one["scoring_s"] + one["final_decode_s"]
                                          + one["protocol_s"])
    four = search_cost.search_cost(name, k, "H200", num_gpus=4, measured=None)
    assert four["denoiser_s"] == pytest.approx(
        (steps * 2 + math.ceil((k - 1) * resamplings / 4)) * units["prediction_s"]["H200"])
    # each GPU decodes and scores its share of the final particles: two of eight
    assert four["final_decode_s"] == pytest.approx(2 * units["final_decode_s"]["H200"])
    assert four["protocol_s"] == pytest.approx(2 * search_cost.protocol_seconds(name, "H200", measured=None))
    assert four["time_s"] < one["time_s"]


def test_guidance_on_several_gpus_spreads_the_anchor_decode_and_a_24_gb_card_says_what_does_not_fit():
    one = search_cost.guidance_cost("cogvideox-5b", "H200", "fast")
    four = search_cost.guidance_cost("cogvideox-5b", "H200", "fast", num_gpus=4)
    assert one["plan"] == four["plan"] == "chunked" and four["time_s"] < one["time_s"]
    assert one["peak_gb"] == four["peak_gb"]  # each card held to the one-GPU peak
    small = search_cost.guidance_cost("cogvideox-5b", "RTX4090", "faithful")
    assert small["plan"] is None and "no memory plan fits" in small["reason"]
    assert search_cost.guidance_cost("ltx-video", "H200", "faithful", "tiny")["plan"] is None
    with pytest.raises(ValueError, match="do not hold 'hunyuanvideo-1.5'"):
        search_cost.guidance_cost("hunyuanvideo-1.5", "H200")


@pytest.mark.slow
def test_the_estimates_of_one_family_are_what_the_cost_model_traces_now(monkeypatch):
    """One plan of Wan 2.1 1.3B traced again (its published configs, fake tensors) gives the shipped
    numbers (regenerate the file with `geco bench plans` when this fails); the calibrating trace of
    CogVideoX-5B is the shipped efficiency's."""
    import torch

    from geco_guide.perf.cards import H200_UNGUIDED_STEP_S
    from geco_guide.perf.plans import plan_estimate

    torch.set_num_threads(1)
    name, plan = "wan2.1-t2v-1.3b", "chunked"
    shipped = load_estimates()["models"][name]
    monkeypatch.setattr(cost, "calibration_call_roofline_s", lambda: shipped["efficiency"] * H200_UNGUIDED_STEP_S)
    settings = cost.cost_settings(preset="full", model=name, steps=None, frames=None, height=None, width=None,
                                  dtype=None, plan=plan)
    fresh = plan_estimate(cost.cost_report(settings, "fast"))
    for key in ("weights_gb", "activations_gb", "peak_gb", "offload_peak_gb", "time_s"):
        assert fresh[key] == pytest.approx(shipped["estimates"]["fast/vae"][plan][key], rel=1e-6), key


def test_four_particles_on_four_h200s_are_predicted_within_one_and_a_half_unguided_videos_at_the_roofline():
    """At the estimators' rates the H200 runs measured CogVideoX-5B's and Wan 2.1 1.3B's reach
    1.5x or pass it (tests/perf/test_parallel_cost.py)."""
    for name in ("cogvideox-5b", "wan2.1-t2v-1.3b", "hunyuanvideo"):
        unguided = load_estimates()["models"][name]["unguided"]["time_s"]["H200"]
        assert search_cost.search_cost(name, 4, "H200", num_gpus=4, measured=None)["time_s"] < 1.5 * unguided
    unguided = load_estimates()["models"]["hunyuanvideo"]["unguided"]["time_s"]["H200"]
    assert search_cost.search_cost("hunyuanvideo", 4, "H200", num_gpus=4)["time_s"] < 1.5 * unguided


def test_the_estimates_answer_to_every_hub_id_of_the_registry():
    from geco_guide.families import model_named

    for name, entry in load_estimates()["models"].items():
        if name != "tiny":
            model = model_named(name)
            assert entry["model_ids"] == [model.hub_id, *model.hub_aliases]
