"""Several GPUs for one video in the cost model: context parallelism's traffic from the traced
attention shapes, its memory per GPU and time, split CFG, model CPU offload's transfers, the
H200's measured memory and estimator rates, a search's memory without a backward, and the tables
of docs/performance_records.md against the command that prints them. Arithmetic on the shipped data."""

from __future__ import annotations

from pathlib import Path

import pytest

from geco_guide.cli import bench
from geco_guide.families.published import traced_models
from geco_guide.perf import cards, parallel_cost, search_cost
from geco_guide.perf.attention_shapes import load_attention
from geco_guide.sampler.running.memory_plan import load_estimates, plan_named

RECORDS = Path(__file__).resolve().parents[2] / "docs" / "performance_records.md"
CP_END = "<!-- end of the context-parallel table -->"
#: one self-attention of 8 tokens (batch 1, 4 heads of 2) and one cross-attention to 3 text tokens, bf16
SHAPES = [{"query": [1, 4, 8, 2], "key": [1, 4, 8, 2], "element_bytes": 2, "calls": 3},
          {"query": [1, 4, 8, 2], "key": [1, 4, 3, 2], "element_bytes": 2, "calls": 3}]


def _unguided(name: str, gpu: str = "H200") -> float:
    return load_estimates()["models"][name]["unguided"]["time_s"][gpu]


def test_the_attention_traffic_follows_ulysses_and_ring_and_grows_with_the_gpus():
    q = 1 * 4 * 8 * 2 * 2 * 3  # bytes of the self-attentions' queries; the cross-attention moves nothing
    for ranks in (2, 4):
        ulysses = parallel_cost.attention_traffic(SHAPES, ranks, "ulysses")
        ring = parallel_cost.attention_traffic(SHAPES, ranks, "ring")
        assert ulysses == {"forward": 4 * q * (ranks - 1) / ranks**2, "backward": 4 * q * (ranks - 1) / ranks**2}
        assert ring == {"forward": 2 * q * (ranks - 1) / ranks, "backward": 4 * q * (ranks - 1) / ranks}
    assert parallel_cost.attention_traffic(SHAPES, 1, "ulysses") == {"forward": 0.0, "backward": 0.0}
    attention = load_attention()["models"]["cogvideox-5b"]["attention"]
    moved = [n * parallel_cost.attention_traffic(attention, n, "ulysses")["forward"] for n in (2, 4, 8)]
    assert moved[0] < moved[1] < moved[2]  # all the GPUs together move more as they grow in number
    per_gpu = [parallel_cost.attention_traffic(attention, n, "ring")["forward"] for n in (2, 4, 8)]
    assert per_gpu[0] < per_gpu[1] < per_gpu[2]


def test_every_traced_model_has_its_attention_shapes_and_weights():
    models = load_attention()["models"]
    assert set(models) == set(traced_models())
    cogvideox = models["cogvideox-5b"]["attention"]
    assert cogvideox == [{"query": [2, 48, 17776, 64], "key": [2, 48, 17776, 64], "element_bytes": 2, "calls": 42}]
    assert "transformer_2" in models["wan2.2-t2v-a14b"]["weights_gb"]
    # HunyuanVideo's text refiner attends over 256 tokens that no GPU splits: its calls move nothing
    hunyuan = models["hunyuanvideo"]["attention"]
    video = [call for call in hunyuan if call["query"][2] > 256]
    assert (parallel_cost.attention_traffic(hunyuan, 4, "ulysses")
            == parallel_cost.attention_traffic(video, 4, "ulysses"))


def test_the_denoisers_share_of_a_plan_is_what_separates_faithful_from_fast():
    name, gpu, plan = "cogvideox-5b", "H200", "partial"
    entry = load_estimates()["models"][name]
    counts = parallel_cost.schedule_counts(name, entry)
    assert counts == {"steps": 50, "updates": 111, "time_travel": 17}
    faithful = parallel_cost.denoiser_seconds(entry, counts, plan, "vae", gpu, "faithful")
    fast = parallel_cost.denoiser_seconds(entry, counts, plan, "vae", gpu, "fast")
    assert faithful["cfg_s"] == pytest.approx(cards.H200_UNGUIDED_STEP_S)
    assert 3 * faithful["cfg_s"] < faithful["grad_s"] < 6 * faithful["cfg_s"]  # forward, recomputation, backward
    seconds = {mode: entry["estimates"][f"{mode}/vae"][plan]["ratio_guided_over_unguided"][gpu] * _unguided(name)
               for mode in ("fast", "faithful")}
    rest = {mode: seconds[mode] - d["cfg_calls"] * d["cfg_s"] - d["grad_calls"] * d["grad_s"]
            for mode, d in (("fast", fast), ("faithful", faithful))}
    assert rest["fast"] == pytest.approx(rest["faithful"])  # the same decode, estimators and loss


def test_context_parallel_faithful_cogvideox_5b_on_four_h200s_within_four_and_a_half_unguided():
    name, unguided = "cogvideox-5b", _unguided("cogvideox-5b")
    one = search_cost.guidance_cost(name, "H200", "faithful")
    devices = parallel_cost.parallel_guidance(name, "H200", 4, context_parallel=False)
    split = parallel_cost.parallel_guidance(name, "H200", 4)
    composed = parallel_cost.parallel_guidance(name, "H200", 4, compose=True)
    # as run.context_parallel runs it: Ulysses over all 4, the anchor decode dealt over them
    assert split["time_s"] / unguided <= 4.5 < devices["time_s"] / unguided
    assert not split["split_cfg"] and split["context_parallel"] == 4 and split["backend"] == "ulysses"
    entry = load_estimates()["models"][name]
    whole = parallel_cost._layout_cost(name, entry, parallel_cost.schedule_counts(name, entry), "H200", 1, (4, False),
                                       plan_named(split["plan"]), False, "faithful", "vae")
    assert whole["time_s"] - split["time_s"] == pytest.approx(0.75 * 441, rel=0.05)  # 3 of 4 chunks elsewhere
    # split CFG beside it (not run) is a little faster: half the batch per collective
    assert composed["time_s"] <= split["time_s"] and composed["split_cfg"] and composed["context_parallel"] == 2
    assert split["peak_gb"] == composed["peak_gb"] < one["peak_gb"] == devices["peak_gb"]  # run.devices: one GPU's
    assert 0 < composed["traffic_s"] < split["traffic_s"] < 0.05 * split["time_s"]  # NVLink: the collectives are small
    # Ulysses needs the heads divisible: CogVideoX-2B's 30 over 4 are not; the composition takes ring or split CFG
    refused = parallel_cost.parallel_guidance("cogvideox-2b", "H200", 4)
    assert refused["plan"] is None and "Ulysses needs the heads (30) divisible by 4" in refused["reason"]
    assert parallel_cost.parallel_guidance("cogvideox-2b", "H200", 4, compose=True)["plan"] is not None


def test_wan_22_a14b_faithful_fits_four_h200s_with_context_parallelism_and_not_without():
    name = "wan2.2-t2v-a14b"
    assert search_cost.guidance_cost(name, "H200", "faithful")["plan"] is None
    assert parallel_cost.parallel_guidance(name, "H200", 4, context_parallel=False)["plan"] is None
    split = parallel_cost.parallel_guidance(name, "H200", 4)
    assert split["plan"] is not None and split["offload"] and split["context_parallel"] == 4
    # nothing to compose: the hooks leave the CFG batch whole, and 40 heads divide over 4
    assert parallel_cost.parallel_guidance(name, "H200", 4, compose=True)["time_s"] == split["time_s"]
    assert split["peak_gb"] <= 0.94 * cards.card_memory_gib("H200") and split["time_s"] > _unguided(name)
    assert split["time_s"] > search_cost.offload_transfer_s(name, "H200", 90) > 0
    assert parallel_cost.parallel_guidance(name, "RTX4090", 4)["plan"] is None


def test_the_memory_per_gpu_falls_and_the_time_with_it_as_the_gpus_grow():
    runs = [parallel_cost.parallel_guidance("wan2.2-t2v-a14b", "H200", n) for n in (2, 4, 8)]
    assert [run["plan"] for run in runs] == ["checkpointed"] * 3
    assert runs[0]["peak_gb"] > runs[1]["peak_gb"] > runs[2]["peak_gb"]
    assert runs[0]["time_s"] > runs[1]["time_s"] > runs[2]["time_s"]
    unguided = [parallel_cost.parallel_unguided("hunyuanvideo", "H200", n)["time_s"] for n in (2, 4)]
    assert _unguided("hunyuanvideo") > unguided[0] > unguided[1]
    assert parallel_cost.parallel_unguided("cogvideox-2b", "H200", 4)["time_s"] is None  # 30 heads
    with pytest.raises(ValueError, match="must be >= 1"):
        parallel_cost.parallel_guidance("cogvideox-5b", "H200", 0)


def test_the_h200_is_the_memory_the_measured_card_reported():
    assert cards.card_memory_gib("H200") == pytest.approx(140.4, abs=0.05)
    assert cards.card_memory_gib("H100") == pytest.approx(80e9 / 2**30)


def test_a_search_on_the_h200_runs_its_estimators_at_the_measured_rates():
    rates = search_cost.estimator_rates("cogvideox-5b", "H200", "fast")
    assert rates["vggt"] == pytest.approx(19.3 / 111) and rates["ufm"] == pytest.approx(8.4 / 111)
    predicted = search_cost.estimator_rates("cogvideox-5b", "H200", None)
    assert rates["loss"] == predicted["loss"] and rates["vggt"] > 2 * predicted["vggt"]
    assert search_cost.estimator_rates("cogvideox-5b", "H100", "fast") == search_cost.estimator_rates(
        "cogvideox-5b", "H100", None)
    ratios = {run: search_cost.search_cost("cogvideox-5b", 4, "H200", 4, measured=run)["time_s"]
              / _unguided("cogvideox-5b") for run in ("faithful", "fast", None)}
    assert ratios[None] < 1.4 < ratios["faithful"] < 1.5 < ratios["fast"] < 1.65
    with pytest.raises(ValueError, match="measured must be one of"):
        search_cost.estimator_rates("cogvideox-5b", "H200", "guided")


def test_a_search_needs_no_backward_so_the_14b_models_search_without_offload():
    for name in ("wan2.1-t2v-14b", "wan2.2-t2v-a14b"):
        search = search_cost.search_cost(name, 4, "H200", 4)
        assert not search["offload"] and search["offload_s"] == 0 and search["batch"] == 1
    fast = search_cost.guidance_cost("wan2.2-t2v-a14b", "H200", "fast")
    entry = load_estimates()["models"]["wan2.2-t2v-a14b"]
    without = entry["estimates"]["fast/vae"][fast["plan"]]["ratio_guided_over_unguided"]["H200"] * _unguided(
        "wan2.2-t2v-a14b")
    assert fast["offload"] and fast["time_s"] == pytest.approx(
        without + search_cost.offload_transfer_s("wan2.2-t2v-a14b", "H200", 90))


@pytest.mark.parametrize("name", ["cogvideox-5b", "wan2.2-t2v-a14b"])
def test_the_documented_context_parallel_table_is_what_the_command_prints(name, capsys):
    begin = f"<!-- context-parallel table: geco bench cost --context-parallel 4 --model {name} -->"
    text = RECORDS.read_text()
    assert begin in text
    documented = text.split(begin, 1)[1].split(CP_END, 1)[0].strip()
    assert bench.main(["cost", "--context-parallel", "4", "--model", name]) == 0
    assert capsys.readouterr().out.strip() == documented


def test_context_parallel_on_the_command_line_traces_nothing_and_refuses_tracing_options(capsys):
    assert bench.main(["cost", "--context-parallel", "4", "--gpu", "H200"]) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith("error: --context-parallel predicts from the shipped estimates") and "--gpu" in err
    assert "\n" not in err
    assert bench.main(["cost", "--context-parallel", "2", "--all-models"]) == 2
    assert "--all-models" in capsys.readouterr().err
    assert bench.main(["cost", "--context-parallel", "4", "--mode", "unguided", "--model", "ltx-video"]) == 0
    out = capsys.readouterr().out
    assert "unguided, context parallel over 4" in out and "faithful" not in out


@pytest.mark.slow
def test_the_shipped_attention_shapes_are_what_a_trace_gives_now():
    """CogVideoX-2B's step traced again (its published configs, fake tensors) gives the shipped
    attention calls and weights (regenerate the file with `geco bench attention-shapes` when this
    fails)."""
    import torch

    from geco_guide.perf.attention_shapes import denoiser_attention

    torch.set_num_threads(1)
    fresh, shipped = denoiser_attention("cogvideox-2b"), load_attention()["models"]["cogvideox-2b"]
    assert fresh["attention"] == shipped["attention"] and fresh["video"] == shipped["video"]
    assert fresh["weights_gb"] == pytest.approx(shipped["weights_gb"])


def test_a_damaged_attention_file_is_one_line_naming_it(tmp_path, monkeypatch, capsys):
    from geco_guide.perf import attention_shapes

    damaged = tmp_path / "denoiser_attention.json"
    damaged.write_text("{")
    monkeypatch.setattr(attention_shapes, "ATTENTION_PATH", damaged)
    attention_shapes.load_attention.cache_clear()
    try:
        assert bench.main(["cost", "--context-parallel", "4"]) == 2
    finally:
        attention_shapes.load_attention.cache_clear()
    err = capsys.readouterr().err.strip()
    assert str(damaged) in err and "geco bench attention-shapes" in err and "\n" not in err
