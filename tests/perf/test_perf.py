"""The performance harness: geco_guide.perf and its command line, geco bench.

The subcommands run at a tiny size and write sane JSON; no timing thresholds, only the report's
structure and that the numbers are positive. The micro-benchmarks run concurrently to keep the
test short (every case imports torch in its own process). Bad options are one error line before
any work (checked in-process: nothing runs).
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest
import torch

from geco_guide.cli import bench
from geco_guide.perf import cards, cost, full_size, mask_cost, profile, sampling, tracing
from geco_guide.sampler.running.context import GuidanceObserver
from geco_guide.sampler.algorithm.schedule import PAPER_STEPS

REPO = Path(__file__).resolve().parents[2]
#: geco bench in its own process (the checkout's package: run from the repository's root)
BENCH = (sys.executable, "-m", "geco_guide.cli.bench")
FAST = ["--threads", "1", "--warmup", "0", "--repeats", "1"]
COMMANDS = {
    "loss": ["loss", "--frames", "2", "--height", "24", "--width", "32", *FAST],
    "estimators": ["estimators", "--size", "tiny", "--frames", "2", "--height", "28", "--width", "42", *FAST],
    "vae": ["vae", "--size", "tiny", "--frames", "17", "--height", "32", "--width", "48", "--dtype", "float32",
            "--vae-checkpointing", "--rss-exact", *FAST],
}
POSITIVE_KEYS = (
    "time_median_s", "time_min_s", "cpu_per_wall",
    "baseline_mib", "after_setup_mib", "peak_mib", "peak_increase_mib",
)


@pytest.fixture(scope="module")
def reports(tmp_path_factory: pytest.TempPathFactory) -> dict[str, dict]:
    """Run both subcommands at once; name -> parsed JSON report (and the printed table)."""
    tmp = tmp_path_factory.mktemp("benchmark")
    procs = {
        name: subprocess.Popen(
            [*BENCH, *args, "--json", str(tmp / f"{name}.json")],
            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, cwd=REPO,
        )
        for name, args in COMMANDS.items()
    }
    out = {}
    for name, proc in procs.items():
        stdout, stderr = proc.communicate(timeout=120)
        assert proc.returncode == 0, stderr
        out[name] = {**json.loads((tmp / f"{name}.json").read_text()), "stdout": stdout}
    return out


def _check_result(result: dict) -> None:
    for key in POSITIVE_KEYS:
        assert result[key] > 0, (key, result)
    assert len(result["times_s"]) == result["repeats"] == 1
    assert result["peak_mib"] >= result["after_setup_mib"] >= result["baseline_mib"]
    # Linux: the peak restarts after setup, so the runs' own peak is measured from what is in use
    assert result["peak_mib"] >= result["run_peak_mib"] >= result["in_use_after_setup_mib"] > 0
    assert result["run_increase_mib"] == pytest.approx(result["run_peak_mib"] - result["in_use_after_setup_mib"])
    assert result["memory_kind"] == "peak_rss" and result["threads"] == 1 and result["load_avg_1m"] >= 0


@pytest.mark.slow
def test_loss_report(reports: dict[str, dict]) -> None:
    report = reports["loss"]
    assert report["subcommand"] == "loss"
    assert {"torch", "cpu_count", "processor", "torch_threads"} <= set(report["environment"])
    results = report["results"]
    assert [(r["case"], r["mode"]) for r in results] == [
        ("geco_from_geometry", "forward"), ("geco_from_geometry", "forward_backward")
    ]
    for result in results:
        _check_result(result)
        assert result["input"] == "2x24x32, 1 adjacent pairs"
    assert "| geco_from_geometry | forward_backward |" in report["stdout"]


@pytest.mark.slow
def test_estimators_report(reports: dict[str, dict]) -> None:
    results = reports["estimators"]["results"]
    assert [(r["case"], r["mode"]) for r in results] == [
        (case, mode) for case in ("vggt-tiny", "ufm-tiny") for mode in ("forward", "forward_backward")
    ]
    for result in results:
        _check_result(result)
        assert result["params_m"] > 0
    networks = {r["case"]: r["network"] for r in results}
    assert networks == {"vggt-tiny": "42x70", "ufm-tiny": "56x98"}


@pytest.mark.slow
def test_vae_report(reports: dict[str, dict]) -> None:
    results = reports["vae"]["results"]
    assert [(r["case"], r["mode"]) for r in results] == [("vae-tiny", "forward"), ("vae-tiny", "forward_backward")]
    for result in results:
        _check_result(result)
        # 17 frames -> 5 latents; anchors 4, 8, 12, 16 -> 4 chunks, each decoded alone when checkpointed
        assert result["input"] == "1x5x4x4x6" and result["dtype"] == "float32"
        assert result["checkpointing"] is True and result["tiling"] is False and result["rss_exact"] is True
        assert result["network"] == "4 chunks in 4 decode call(s), anchors [4, 8, 12, 16]"


# ---- sampling: guided vs unguided denoising ---------------------------------------------------

BREAKDOWN_KEYS = {
    "denoiser_forward_s", "denoiser_backward_s", "vae_slice_decode_forward_s", "vae_slice_decode_backward_s",
    "vae_final_decode_s", "vggt_forward_s", "vggt_backward_s", "ufm_forward_s", "ufm_backward_s", "loss_s",
    "guided_updates_s", "counts",
}


@pytest.fixture(scope="module")
def sampling_report(tmp_path_factory: pytest.TempPathFactory) -> dict:
    """2 steps of the tiny preset in fast mode (the paper schedule scaled to 2 steps gives R = 3, 2,
    time travel in step 1)."""
    path = tmp_path_factory.mktemp("sampling") / "sampling.json"
    proc = subprocess.run(
        [*BENCH, "sampling", "--preset", "tiny", "--mode", "fast", "--steps", "2",
         "--threads", "1", "--warmup", "0", "--json", str(path)],
        capture_output=True, text=True, timeout=180, cwd=REPO,
    )
    assert proc.returncode == 0, proc.stderr
    return {**json.loads(path.read_text()), "stdout": proc.stdout}


@pytest.mark.slow
def test_sampling_report(sampling_report: dict) -> None:
    report = sampling_report
    assert {"device", "mode", "ratio_guided_over_unguided", "peak_memory_gb", "breakdown", "steps",
            "extrapolated", "config", "wall_time_s", "time_per_step_s"} <= set(report)
    assert report["device"] == "cpu" and report["mode"] == "fast" and report["preset"] == "tiny"
    assert report["steps"] == 2 and report["extrapolated"] is True and report["ratio_basis"] == "extrapolated"
    assert report["config"]["guidance"]["repeats"] == "3x1,2x1" and report["config"]["guidance"]["denoiser_grad"] is False
    assert report["ratio_guided_over_unguided"] > 0
    # the tiny models' ratio comes with a sentence saying it does not carry to full size
    assert "meaningless for full size" in report["stdout"] and "geco bench cost" in report["stdout"]
    assert report["peak_memory_gb"] > 0 and report["peak_memory_gb_unguided"] > 0
    for arm in ("guided", "unguided"):
        assert report["wall_time_s"][arm] > 0 and report["time_per_step_s"][arm] > 0
        assert report["extrapolated_to_nominal"]["wall_time_s"][arm] > 0
        assert len(report["arms"][arm]["step_times_s"]) == 2 and report["arms"][arm]["output_finite"]

    breakdown = report["breakdown"]
    assert set(breakdown) == BREAKDOWN_KEYS
    for key in ("denoiser_forward_s", "vae_slice_decode_forward_s", "vae_slice_decode_backward_s",
                "vae_final_decode_s", "vggt_forward_s", "vggt_backward_s", "ufm_forward_s", "ufm_backward_s",
                "guided_updates_s"):
        assert breakdown[key] > 0, key
    # fast mode: the denoiser is never differentiated. Step 0 (R = 3) predicts once, inside its
    # first update, and the other updates and the DDIM step reuse it; step 1 (R = 2, time travel)
    # predicts in its first update, again in the second after the re-noising, and once after it:
    # 4 forwards, 3 inside updates. Per update (5), one decode of anchor 4's 2-latent chunk and one
    # of the other three 3-latent chunks together, one VGGT and one UFM call
    assert breakdown["denoiser_backward_s"] == 0
    counts = breakdown["counts"]
    assert counts == {"denoiser_forwards": 4, "denoiser_forwards_in_updates": 3, "denoiser_backwards": 0,
                      "vae_slice_decodes": 10, "vggt_calls": 5, "ufm_calls": 5}
    # the stages inside the updates never add up to more than the updates themselves
    profile = report["arms"]["guided"]["profile"]
    assert 0 < profile["attributed_in_updates_s"] <= profile["updates_s"]

    unguided = report["breakdown_unguided"]
    assert unguided["counts"]["denoiser_forwards"] == 2 and unguided["guided_updates_s"] == 0
    assert "| guided |" in report["stdout"] and "(extrap.)" in report["stdout"]


def test_full_size_pipeline_on_meta() -> None:
    """The --full-size parts build on the meta device (nothing allocated) with CogVideoX-5B's published configs."""
    from geco_guide.estimators.ufm import UFM, UFMConfig
    from geco_guide.estimators.vggt import VGGT, VGGTConfig
    from geco_guide.sampler.pipelines.pipeline_cogvideox import GeCoCogVideoXPipeline

    components = full_size.build_full_size_components("cogvideox-5b", "meta", torch.bfloat16)
    transformer, vae = components["transformer"], components["vae"]
    for model in (transformer, vae):
        assert all(p.device.type == "meta" and p.dtype == torch.bfloat16 for p in model.parameters())
    tc = transformer.config
    assert (tc.num_attention_heads, tc.attention_head_dim, tc.num_layers, tc.in_channels, tc.out_channels) == (48, 64, 42, 16, 16)
    assert (tc.text_embed_dim, tc.time_embed_dim, tc.patch_size, tc.max_text_seq_length) == (4096, 512, 2, 226)
    assert (tc.sample_frames, tc.sample_height, tc.sample_width) == (49, 60, 90)
    assert tc.use_rotary_positional_embeddings and not tc.use_learned_positional_embeddings
    vc = vae.config
    assert tuple(vc.block_out_channels) == (128, 256, 256, 512) and vc.latent_channels == 16
    assert vc.layers_per_block == 3 and vc.scaling_factor == 0.7 and vc.temporal_compression_ratio == 4
    # CogVideoX-5B: 5.57 B transformer parameters, 216 M in the VAE
    assert sum(p.numel() for p in transformer.parameters()) == 5_570_283_072
    assert sum(p.numel() for p in vae.parameters()) == 215_583_907

    sc = components["scheduler"].config
    assert (sc.prediction_type, sc.timestep_spacing, sc.rescale_betas_zero_snr) == ("v_prediction", "trailing", True)
    with torch.device("meta"):
        geometry, flow = VGGT(VGGTConfig()), UFM(UFMConfig())
    assert 1.1e9 < sum(p.numel() for p in geometry.parameters()) < 1.2e9  # VGGT-1B
    assert 4.0e8 < sum(p.numel() for p in flow.parameters()) < 4.5e8  # UFM-Base
    pipe = GeCoCogVideoXPipeline(tokenizer=None, text_encoder=None, **components)  # the estimators enter at the call
    assert set(pipe.components) == {"tokenizer", "text_encoder", "vae", "transformer", "scheduler"}
    assert pipe.tokenizer is None and pipe.text_encoder is None
    assert (pipe.vae_scale_factor_spatial, pipe.vae_scale_factor_temporal, pipe.vae_scaling_factor_image) == (8, 4, 0.7)


def test_scaled_paper_schedule() -> None:
    """The harness scales the paper schedule by the package's rule (scale_schedule: phase boundaries
    rounded, b -> round(b * N / 50)); identity at 50."""
    from geco_guide.sampler.algorithm.schedule import PAPER_REPEATS, parse_repeats

    assert sampling.paper_schedule_for(50) == (PAPER_REPEATS, [15, 20])
    repeats, window = sampling.paper_schedule_for(2)
    assert (parse_repeats(repeats), window) == ([3, 2], [1, 1])
    repeats, window = sampling.paper_schedule_for(10)
    assert (parse_repeats(repeats), window) == ([0, 3, 3, 3, 2, 2, 2, 2, 2, 2], [3, 3])


def test_update_windows_run_back_to_back_from_each_step_start() -> None:
    log = [{"step": 1, "seconds": 0.5}, {"step": 1, "seconds": 0.25}, {"step": 2, "seconds": 1.0}]
    windows = profile.update_windows(10.0, [11.0, 13.0, 16.0], log)
    assert windows == [(11.0, 11.5), (11.5, 11.75), (13.0, 14.0)]


@pytest.mark.slow
def test_full_size_refused_on_cpu() -> None:
    proc = subprocess.run([*BENCH, "sampling", "--full-size", "--steps", "1"],
                          capture_output=True, text=True, timeout=60, cwd=REPO)
    assert proc.returncode != 0 and "--allow-cpu" in proc.stderr


def test_stage_profiler_backward_intervals() -> None:
    """Two chained stages: each gets one forward and one backward interval; the backward of the
    later stage runs (and is attributed) before the earlier one's, without overlap."""
    first, second = torch.nn.Linear(8, 8), torch.nn.Linear(8, 8)
    for p in [*first.parameters(), *second.parameters()]:
        p.requires_grad_(False)
    profiler = profile.StageProfiler(torch.device("cpu"))
    profiler.wrap(first, "forward", "a")
    profiler.wrap(second, "forward", "b")
    x = torch.randn(4, 8, requires_grad=True)
    with torch.no_grad():
        second(first(x))  # no autograd: forward intervals only
    y = second(torch.tanh(first(x))).square().sum()
    (grad,) = torch.autograd.grad(y, x)
    assert grad.shape == x.shape
    calls = profiler.calls
    assert [(c["stage"], c["grad"]) for c in calls] == [("a", False), ("b", False), ("a", True), ("b", True)]
    assert all(c["bwd_start"] is None for c in calls[:2])
    a, b = calls[2], calls[3]
    assert b["bwd_start"] <= b["bwd_end"] <= a["bwd_start"] <= a["bwd_end"]
    kinds = sorted((iv["stage"], iv["kind"]) for iv in profiler.intervals())
    assert kinds == [("a", "backward"), ("a", "forward"), ("a", "forward"), ("b", "backward"), ("b", "forward"), ("b", "forward")]
    assert profile.union_seconds([(0.0, 2.0), (1.0, 3.0), (5.0, 6.0)]) == 4.0


# ---- cost: FLOPs and memory on fake tensors ----------------------------------------------------


def test_cost_tracker_counts_flops_and_live_memory() -> None:
    """On real tensors: a matmul's FLOPs, and memory that follows allocations and frees."""
    tracker = tracing.CostTracker()
    with tracker.mode():
        a = torch.ones(1024)  # 4 KiB
        b = a * 2  # 8 KiB live
        del a  # 4 KiB
        c = b + 1  # 8 KiB again
        x, y = torch.ones(4, 8), torch.ones(8, 16)
        z = x @ y
    assert tracker.flops[("other", "forward")] == 2 * 4 * 8 * 16
    assert tracker.peak == 8192 + 4 * (32 + 128 + 64)
    assert tracker.current == 8192 + 4 * (32 + 128 + 64)
    del b, c, x, y, z
    assert tracker.current == 0


def test_cost_schedule_counts_at_paper_schedule() -> None:
    """The real guided_step driven by counting stubs: 111 updates; faithful makes 111
    differentiated denoiser calls and 50 without gradients, fast 67 (docs/performance.md)."""
    from geco_guide.sampler.algorithm.schedule import PAPER_REPEATS, PAPER_TIME_TRAVEL

    settings = {"preset": "full", "model": "cogvideox-5b", "frames": 49, "steps": 50, "repeats": PAPER_REPEATS,
                "time_travel": list(PAPER_TIME_TRAVEL), "chunk_latents": None, "vae_checkpointing": None,
                "denoiser_checkpointing": None}
    faithful = tracing.count_schedule_calls("faithful", settings)
    fast = tracing.count_schedule_calls("fast", settings)
    assert faithful == {"steps": 50, "updates": 111, "denoiser_cfg": 50, "denoiser_grad": 111, "time_travel_updates": 17}
    assert fast == {"steps": 50, "updates": 111, "denoiser_cfg": 67, "denoiser_grad": 0, "time_travel_updates": 17}
    no_tt = tracing.count_schedule_calls("fast", {**settings, "time_travel": None})
    assert no_tt["denoiser_cfg"] == 50 and no_tt["updates"] == 111
    assert tracing.count_schedule_calls("unguided", settings)["denoiser_cfg"] == 50


def test_cost_tiny_denoiser_step_equals_independent_count() -> None:
    """The cost model's FLOPs of one tiny CFG denoiser call (fake tensors, through the pipeline)
    equal FlopCounterMode's on real tensors with the math attention backend (attention as bmm)."""
    from torch.nn.attention import SDPBackend, sdpa_kernel
    from torch.utils.flop_counter import FlopCounterMode

    from geco_guide.tiny import (
        TINY_HEIGHT,
        TINY_MAX_SEQUENCE_LENGTH,
        TINY_NUM_FRAMES,
        TINY_WIDTH,
        tiny_pipeline,
    )

    settings = {"preset": "tiny", "model": None, "frames": TINY_NUM_FRAMES, "height": TINY_HEIGHT,
                "width": TINY_WIDTH, "dtype": "float32", "seed": 0, "vae_tiling": False, "estimator_checkpointing": False,
                "chunk_latents": None, "vae_checkpointing": None, "denoiser_checkpointing": None,
                "guidance_scale": 6.0}
    trace = tracing.trace_cost(settings, "unguided")
    cfg = trace["stages"]["denoiser_cfg"]
    assert cfg["calls"] == 1 and "backward" not in cfg

    pipe = tiny_pipeline(0)
    config = pipe.transformer.config
    # every block's joint attention recorded once, both CFG halves over the text and video tokens
    tokens = TINY_MAX_SEQUENCE_LENGTH + ((TINY_NUM_FRAMES - 1) // 4 + 1) * (TINY_HEIGHT // 16) * (TINY_WIDTH // 16)
    heads, head_dim = config.num_attention_heads, config.attention_head_dim
    assert trace["attention"]["denoiser_cfg/forward"] == [{"query": [2, heads, tokens, head_dim],
                                                           "key": [2, heads, tokens, head_dim],
                                                           "element_bytes": 4, "calls": config.num_layers}]
    latents = torch.randn(2, (TINY_NUM_FRAMES - 1) // 4 + 1, config.in_channels, TINY_HEIGHT // 8, TINY_WIDTH // 8)
    text = torch.randn(2, TINY_MAX_SEQUENCE_LENGTH, config.text_embed_dim)
    rotary = (pipe._prepare_rotary_positional_embeddings(TINY_HEIGHT, TINY_WIDTH, latents.shape[1], torch.device("cpu"))
              if config.use_rotary_positional_embeddings else None)
    counter = FlopCounterMode(display=False)
    with torch.no_grad(), sdpa_kernel(SDPBackend.MATH), counter:
        pipe.transformer(hidden_states=latents, encoder_hidden_states=text, timestep=torch.tensor([500, 500]),
                         image_rotary_emb=rotary, return_dict=False)
    assert counter.get_total_flops() > 0
    assert cfg["forward"]["flops"] == counter.get_total_flops()


@pytest.mark.slow
def test_cost_report_tiny(tmp_path: Path) -> None:
    """`cost --preset tiny` writes the documented keys; guided costs more than unguided."""
    path = tmp_path / "cost.json"
    proc = subprocess.run([*BENCH, "cost", "--preset", "tiny", "--mode", "fast",
                           "--threads", "1", "--json", str(path)], check=False, capture_output=True, text=True,
                          timeout=300, cwd=REPO)
    assert proc.returncode == 0, proc.stderr
    assert "kept in float32" not in proc.stderr  # diffusers' warning about an empty list of modules
    report = json.loads(path.read_text())
    assert {"mode", "flops_unguided", "flops_guided", "flops_ratio_guided_over_unguided", "peak_memory_gb",
            "per_stage", "settings"} <= set(report)
    assert report["mode"] == "fast" and report["settings"]["preset"] == "tiny"
    assert report["flops_guided"] > report["flops_unguided"] > 0
    assert report["flops_ratio_guided_over_unguided"] == pytest.approx(report["flops_guided"] / report["flops_unguided"])
    assert report["peak_memory_gb"] > report["weights_gb"]["transformer"] > 0
    stages = report["per_stage"]
    # tiny schedule 0,2,2,1 with time travel in step 2: 5 updates; fast mode differentiates no denoiser
    assert report["counts"]["updates"] == 5 and stages["denoiser"]["flops"] == 0
    for name in ("anchor_decode", "vggt", "ufm"):
        assert stages[name]["count"] == 5 and stages[name]["flops_forward"] > 0 and stages[name]["flops_backward"] > 0
    assert sum(s["flops"] for s in stages.values()) == report["flops_guided"]


def test_casting_a_model_warns_only_about_float32_modules_it_has() -> None:
    """diffusers warns at every cast about modules to keep in float32, also when there are none:
    ``cast_model`` skips that empty warning and keeps the real one."""
    import logging

    from diffusers.utils import logging as dlogging

    from geco_guide.sampler.pipelines.loading import cast_model
    from geco_guide.tiny import tiny_cogvideox_components

    said: list[str] = []
    handler = logging.Handler()
    handler.emit = lambda record: said.append(record.getMessage())
    logger, level = logging.getLogger("diffusers.models.modeling_utils"), dlogging.get_verbosity()
    logger.addHandler(handler)
    dlogging.set_verbosity_warning()
    try:
        vae = tiny_cogvideox_components(0)["vae"]
        assert not vae._keep_in_fp32_modules
        assert cast_model(vae, torch.bfloat16) is vae and next(vae.parameters()).dtype == torch.bfloat16
        assert not said
        vae._keep_in_fp32_modules = ["decoder"]
        cast_model(vae, torch.float32)
        assert len(said) == 1 and "kept in float32: ['decoder']" in said[0]
    finally:
        logger.removeHandler(handler)
        dlogging.set_verbosity(level)


@pytest.mark.slow
def test_cost_time_scales_with_the_traced_size() -> None:
    """The efficiency comes from the measured size whatever size is traced: a 9x16x16 video
    predicts a fraction of the 49x480x720 run's unguided time (not the measured step's 50 x 1.78 s),
    and the tiny models' plan times stay below the full-size model's."""
    small = cost.cost_settings(preset="full", steps=None, frames=9, height=16, width=16, dtype=None)
    assert not cost.at_calibration_size(small)
    report = cost.cost_report(small, "unguided")
    efficiency = cost.calibration_call_roofline_s() / cards.H200_UNGUIDED_STEP_S
    assert report["roofline"]["efficiency"] == pytest.approx(efficiency)
    measured_run = PAPER_STEPS * cards.H200_UNGUIDED_STEP_S
    assert report["roofline"]["wall_time_s"]["H200"]["unguided"] < 0.1 * measured_run

    plans = json.loads((Path(cost.__file__).parents[1] / "sampler" / "running" / "data" / "memory_plans.json").read_text())
    times = {model: [plan["time_s"] for table in entry["estimates"].values() for plan in table.values()]
             for model, entry in plans["models"].items()}
    assert max(times["tiny"]) < min(times["cogvideox-5b"])


@pytest.mark.slow
def test_the_dynamic_masks_overhead_follows_the_schedule_and_the_cards() -> None:
    """SAM 3's vision encoder on the anchors, predicted per card; the automatic masks' measured
    time; one refresh per guided step of the paper's schedule (steps 3-49: 47 of its 111 updates);
    the movers' fit at each refresh and their cues at each update."""
    costs = mask_cost.dynamic_mask_costs()
    assert (costs["refreshes"], costs["updates"]) == (47, 111)
    sam3 = costs["sam3"]
    assert 15e12 < mask_cost.sam3_refresh_cost()["flops"] < 25e12  # a ViT over 4 frames of 1008x1008
    assert 0 < sam3["H200"]["refresh_s"] < sam3["L40S"]["refresh_s"] < sam3["L4"]["refresh_s"]
    assert sam3["H200"]["run_s"] == pytest.approx(47 * sam3["H200"]["refresh_s"])
    assert costs["auto"]["per_update_s"] == pytest.approx(mask_cost.AUTO_MASK_REFRESH_S * 47 / 111)
    movers = costs["movers"]
    assert movers["run_s"] == pytest.approx(47 * mask_cost.MOVERS_FIT_S + 111 * mask_cost.MOVERS_UPDATE_S)
    assert mask_cost.dynamic_mask_costs(refresh=2)["refreshes"] == 24
    table = mask_cost.dynamic_masks_table(costs)
    assert f"| auto (measured, one CPU thread) | any | {mask_cost.AUTO_MASK_REFRESH_S:.2f} |" in table and "| + movers rigid (predicted" in table


def test_sampling_deals_the_guided_arms_anchor_decode_over_the_devices_asked_for() -> None:
    from geco_guide.perf.sampling import sampling_guidance, sampling_run_options, sampling_spec

    spec = sampling_spec(full_size=False, mode="fast", steps=2, frames=None, height=None, width=None, device="cpu",
                         dtype=None, threads=1, seed=0, warmup=0, devices=["cpu", "cpu"])
    assert sampling_run_options({**spec, "arm": "guided"}).devices == ["cpu", "cpu"]
    assert sampling_guidance({**spec, "arm": "unguided"}) is False
    plain = sampling_spec(full_size=False, mode="fast", steps=2, frames=None, height=None, width=None, device="cpu",
                          dtype=None, threads=1, seed=0, warmup=0)
    assert sampling_run_options({**plain, "arm": "guided"}).devices is None


def test_several_gpus_divide_the_anchor_decode_by_the_chunks_each_gpu_decodes() -> None:
    gpus = list(cards.GPU_SPECS)
    report = {"settings": {"preset": "full", "model": "cogvideox-5b", "frames": 49, "height": 480, "width": 720,
                           "chunk_latents": 3},
              "counts": {"updates": 100},
              "per_stage": {"anchor_decode": {"time_s": {gpu: 400.0 for gpu in gpus}}},
              "roofline": {"wall_time_s": {gpu: {"unguided": 100.0, "guided": 800.0} for gpu in gpus}}}
    one = cost.several_gpus(report, 1)["cards"]["H200"]
    assert one["guided_s"] == 800.0 and one["transfer_s"] == 0.0  # every chunk on the pipeline's GPU
    two, four, eight = (cost.several_gpus(report, n) for n in (2, 4, 8))
    assert (two["chunks"], two["chunks_per_gpu"], four["chunks_per_gpu"]) == (4, 2, 1)
    h200 = four["cards"]["H200"]
    chunk_bytes = 3 * 16 * 60 * 90 * 4 + 3 * 480 * 720 * 4  # a chunk's latents out, its anchor frame back
    assert h200["transfer_s"] == pytest.approx(100 * 3 * 2 * chunk_bytes / cards.INTERCONNECT_BYTES_PER_S["H200"])
    assert h200["guided_s"] == pytest.approx(800 - 400 + 100 + h200["transfer_s"])
    assert h200["over_unguided_1gpu"] == pytest.approx(h200["guided_s"] / 100)
    assert eight["cards"]["H200"]["decode_s"] == h200["decode_s"]  # four chunks: no fifth GPU to use
    assert four["cards"]["L4"]["transfer_s"] > h200["transfer_s"]  # PCIe is slower than NVLink
    assert "| H200 | " in cost.several_gpus_table(four)
    with pytest.raises(ValueError, match="--num-gpus must be >= 1"):
        cost.several_gpus(report, 0)


@pytest.mark.slow
def test_geco_eval_cost_counts_the_estimator_calls_of_each_pair_mode(tmp_path: Path):
    """9 frames at 8 fps (1.125 s): one window of floor(1.125 * 8) = 9 frames and a motion grid of
    the same 9 frames, so all pairs = 9 * 8 + 8 UFM pairs, adjacent = 8 + 8, one VGGT call."""
    out = tmp_path / "geco_eval.json"
    proc = subprocess.run([*BENCH, "geco-eval", "--frames", "9", "--fps", "8", "--pairs", "all",
                           "adjacent", "--threads", "1", "--json", str(out)], capture_output=True, text=True, timeout=300,
                          cwd=REPO)
    assert proc.returncode == 0, proc.stderr
    modes = json.loads(out.read_text())["modes"]
    assert (modes["all"]["ufm_pairs"], modes["adjacent"]["ufm_pairs"]) == (80, 16)
    assert modes["all"]["vggt_calls"] == 1 and modes["all"]["vggt_frames"] == 9 and modes["all"]["windows"] == 1
    assert modes["all"]["h200_estimate_s"] > modes["adjacent"]["h200_estimate_s"] > 0


@pytest.mark.slow
def test_geco_eval_cost_of_another_geometry_backbone_scales_its_time_by_their_flops():
    """The same calls, counted once; DA3-BASE's per-frame time is VGGT-1B's measured one times
    their forward FLOPs' ratio (about 1/9.5), so the estimate falls by the geometry's share only."""
    from geco_guide.perf.scoring_cost import geco_eval_cost, geco_eval_table

    h200_run = REPO / "docs" / "benchmarks" / "sampling_full_h200_fast.json"
    kwargs = dict(frames=9, fps=8.0, height=32, width=48, pairs=["adjacent"], videos=320, seed=0, h200_run=h200_run)
    vggt, da3 = geco_eval_cost(**kwargs), geco_eval_cost(**kwargs, geometry="da3-base")
    ratio = da3["h200_per_call"]["geometry_flop_ratio"]
    assert vggt["h200_per_call"]["geometry_flop_ratio"] == 1.0 and 0.05 < ratio < 0.2
    assert da3["h200_per_call"]["geometry_frame_s"] == pytest.approx(vggt["h200_per_call"]["vggt_frame_s"] * ratio)
    same, fewer = vggt["modes"]["adjacent"], da3["modes"]["adjacent"]
    assert fewer["vggt_frames"] == same["vggt_frames"] == 9 and fewer["ufm_pairs"] == same["ufm_pairs"]
    saved = same["vggt_frames"] * vggt["h200_per_call"]["vggt_frame_s"] * (1 - ratio)
    assert fewer["h200_estimate_s"] == pytest.approx(same["h200_estimate_s"] - saved)
    assert "| da3-base calls (frames) |" in geco_eval_table(da3)


@pytest.mark.parametrize("command", [["sampling", "--steps", "0"], ["cost", "--preset", "tiny", "--steps", "0"]])
@pytest.mark.slow
def test_zero_steps_is_one_error_line(command):
    """--steps 0 used to run the default 50 steps (0 is falsy)."""
    proc = subprocess.run([*BENCH, *command], capture_output=True, text=True, timeout=120, cwd=REPO)
    assert proc.returncode != 0 and proc.stderr.strip().count("\n") == 0 and "--steps must be" in proc.stderr


# ---- option checks: one error line, exit code 2, before any work ------------------------------


@pytest.fixture
def cli():
    """geco bench in this process."""
    return bench


def _refused(cli, monkeypatch, capsys, argv: list[str]) -> str:
    """Run ``argv`` in-process with every entry point to work replaced by a failure; return the
    one stderr line of the refusal (exit code 2: argparse's, or the command's)."""
    def no_work(*args, **kwargs):
        raise AssertionError(f"{argv}: work started before the options were checked")

    from geco_guide.perf import measure, plans, scoring_cost

    for module, name in ((measure, "run_cases"), (sampling, "sampling_report"), (cost, "cost_report"),
                         (scoring_cost, "geco_eval_cost"), (plans, "plan_estimates")):
        monkeypatch.setattr(module, name, no_work)
    try:
        code = cli.main(argv)
    except SystemExit as exit_info:
        code = exit_info.code
    assert code == 2, argv
    err = capsys.readouterr().err.strip()
    assert err.count("\n") == 0 and "error:" in err, err
    return err


@pytest.mark.parametrize(("argv", "expected"), [
    (["loss", "--height", "0"], "--height: must be >= 1, got 0"),
    (["loss", "--width", "-3"], "--width: must be >= 1, got -3"),
    (["estimators", "--frames", "1"], "--frames: must be >= 2, got 1"),
    (["vae", "--frames", "0"], "--frames: must be >= 1, got 0"),
    (["sampling", "--height", "-32"], "--height: must be >= 1"),
    (["cost", "--preset", "tiny", "--width", "0"], "--width: must be >= 1"),
    (["loss", "--repeats", "0"], "--repeats: must be >= 1, got 0"),
    (["estimators", "--threads", "0"], "--threads: must be >= 1"),
    (["vae", "--frames", "16"], "4*k + 1"),
    (["sampling", "--frames", "13"], "8k+1"),
    (["sampling", "--mode", "unguided", "--frames", "14"], "4*k + 1"),
    (["cost", "--preset", "tiny", "--frames", "21"], "8k+1"),
    (["cost", "--preset", "tiny", "--calibration-step-s", "nan"], "must be a finite number > 0"),
    (["cost", "--preset", "tiny", "--calibration-step-s", "inf"], "must be a finite number > 0"),
    (["cost", "--preset", "tiny", "--calibration-step-s", "0"], "must be a finite number > 0"),
    (["cost", "--preset", "tiny", "--calibration-step-s", "-1.5"], "must be a finite number > 0"),
    (["geco-eval", "--videos", "-5"], "--videos: must be >= 1, got -5"),
    (["geco-eval", "--fps", "0"], "--fps: must be a finite number > 0"),
    (["sampling", "--chunk-latents", "0"], "--chunk-latents: must be >= 2, got 0"),
    (["sampling", "--chunk-latents", "1"], "--chunk-latents: must be >= 2, got 1"),
    (["cost", "--preset", "tiny", "--chunk-latents", "0"], "--chunk-latents: must be >= 2"),
    (["sampling", "--steps", "51"], "--steps must be in [1, 50], got 51"),
    (["sampling", "--full-size", "--steps", "1"], "--allow-cpu"),
    (["cost", "--gpu", "H300"], "--gpu: invalid choice: 'H300'"),
    (["cost", "--preset", "tiny", "--gpu", "L4"], "use it with --preset full and --mode fast or faithful"),
    (["cost", "--gpu", "L4", "--mode", "unguided"], "use it with --preset full"),
    (["cost", "--gpu", "H100", "--vae-checkpointing", "off", "--estimator-checkpointing"],
     "without --vae-checkpointing, --estimator-checkpointing"),
    (["plans", "--models", "hunyuanvideo-1.5"], "--models: invalid choice"),
    (["cost", "--model", "ltx-2"], "--model: invalid choice"),
    (["cost", "--model", "wan2.1-t2v-14b", "--frames", "83"], "must be 4k+1 frames"),
    (["cost", "--model", "ltx-video", "--width", "720"], "--width must be a multiple of 32, got 720"),
    (["sampling", "--memory-plan", "smallest"], "--memory-plan must be one of auto, explicit, fastest"),
    (["cost", "--decoder", "taesd"], "--decoder must be one of vae, tiny"),
    (["cost", "--all-models", "--model", "wan2.1-t2v-14b"], "--all-models prints the table of the shipped "
                                                             "estimates and traces nothing: leave out --model"),
    (["plans", "--threads", "0"], "--threads: must be >= 1"),
    (["cost", "--height", "30", "--width", "30"], "--height must be a multiple of 16, got 30"),
    (["sampling", "--width", "40"], "--width must be a multiple of 16, got 40"),
    (["sampling", "--devices", "cpu", "tpu"], "invalid device 'tpu' (--devices)"),
    (["sampling", "--devices", "cuda:99"], "device 'cuda:99' is not available"),
    (["cost", "--num-gpus", "0"], "--num-gpus: must be >= 1"),
    (["cost", "--context-parallel", "1"], "--context-parallel: must be >= 2, got 1"),
    (["cost", "--context-parallel", "4", "--num-gpus", "4"], "traces nothing: leave out --num-gpus"),
    (["attention-shapes", "--models", "sora"], "--models: invalid choice"),
    (["vae", "--height", "30"], "--height must be a multiple of 8, got 30"),
])
def test_bad_option_is_one_error_line_before_any_work(cli, monkeypatch, capsys, argv, expected):
    assert expected in _refused(cli, monkeypatch, capsys, argv)


@pytest.mark.skipif(torch.cuda.is_available(), reason="a GPU is available here")
@pytest.mark.parametrize("command", [["loss"], ["sampling"], ["vae"]])
def test_cuda_without_gpu_is_refused(cli, monkeypatch, capsys, command):
    err = _refused(cli, monkeypatch, capsys, [*command, "--device", "cuda"])
    assert "no CUDA GPU" in err


def test_bad_device_is_refused(cli, monkeypatch, capsys):
    assert "not a torch device" in _refused(cli, monkeypatch, capsys, ["loss", "--device", "gpu0"])


def test_missing_or_invalid_measured_file_is_refused(cli, monkeypatch, capsys, tmp_path: Path):
    base = ["cost", "--preset", "tiny", "--measured"]
    assert "no such file" in _refused(cli, monkeypatch, capsys, [*base, str(tmp_path / "missing.json")])
    broken = tmp_path / "broken.json"
    broken.write_text("{")
    assert "not JSON" in _refused(cli, monkeypatch, capsys, [*base, str(broken)])
    other = tmp_path / "other.json"
    other.write_text(json.dumps({"subcommand": "cost"}))
    err = _refused(cli, monkeypatch, capsys, [*base, str(other)])
    assert "not a `sampling` report" in err and "wall_time_s" in err


def test_unwritable_json_path_is_refused_before_the_run(cli, monkeypatch, capsys, tmp_path: Path):
    blocker = tmp_path / "file.txt"
    blocker.write_text("")
    err = _refused(cli, monkeypatch, capsys, ["loss", "--json", str(blocker / "sub" / "out.json")])
    assert "is a file" in err
    assert "is a folder" in _refused(cli, monkeypatch, capsys, ["loss", "--json", str(tmp_path)])
    if os.geteuid() != 0:  # root writes anywhere
        locked = tmp_path / "locked"
        locked.mkdir()
        locked.chmod(0o500)
        try:
            err = _refused(cli, monkeypatch, capsys, ["loss", "--json", str(locked / "new" / "out.json")])
        finally:
            locked.chmod(0o700)
        assert "permission denied" in err
    assert not (tmp_path / "sub").exists()


def test_failed_report_write_leaves_no_file(monkeypatch, tmp_path: Path):
    """A full disk while writing --json: the atomic writer raises and leaves neither the report nor
    a 0-byte file (nor its temporary) behind."""
    import errno

    from geco_guide.perf.measure import write_report

    def disk_full(fd):
        raise OSError(errno.ENOSPC, "No space left on device")

    monkeypatch.setattr(os, "fsync", disk_full)
    target = tmp_path / "reports" / "out.json"
    with pytest.raises(OSError, match="space"):
        write_report(target, {"results": [1, 2, 3]})
    assert not target.exists() and list(target.parent.iterdir()) == []


def test_no_private_name_is_patched_in_the_cost_trace():
    """The cost trace watches the call through its public seam (a GuidanceObserver passed as
    ``observer=``), not mock.patch: the updates of a step count as inside an update."""
    source = "".join(Path(module.__file__).read_text() for module in (cost, tracing, bench))
    assert "mock" not in source and "_read_scalars" not in source and "guidance_context_class" not in source
    tracker = tracing.CostTracker()
    observer = tracing.CountingObserver(tracker)
    assert isinstance(observer, GuidanceObserver)
    with observer.step(1, 999):
        assert tracker.in_update == 1
    assert tracker.in_update == 0


@pytest.mark.slow
def test_cost_with_the_tiny_decoder_traces_it_as_the_anchor_decode() -> None:
    """`cost --decoder tiny`: the tiny decoder's decode is the anchor decode (its weights counted),
    the VAE only decodes the final video."""
    torch.set_num_threads(1)
    settings = {k: cost.cost_settings(preset="tiny", steps=None, frames=None, height=None, width=None, dtype=None,
                                      decoder=k) for k in ("vae", "tiny")}
    reports = {k: cost.cost_report(s, "fast") for k, s in settings.items()}
    tiny, vae = reports["tiny"], reports["vae"]
    assert tiny["settings"]["decoder"] == "tiny" and vae["settings"]["decoder"] == "vae"
    assert tiny["weights_gb"]["guidance_decoder"] > 0 and vae["weights_gb"]["guidance_decoder"] == 0
    decode = {k: r["unit_traces"]["guided"]["anchor_decode"] for k, r in reports.items()}
    # one update: the tiny decoder decodes each anchor's 8-latent context once, no VAE call
    assert decode["tiny"]["calls"] == 4 and decode["vae"]["calls"] == 2
    assert decode["tiny"]["forward"]["flops"] != decode["vae"]["forward"]["flops"] > 0
    assert tiny["per_stage"]["final_decode"] == vae["per_stage"]["final_decode"]
    assert "the tiny decoder (an approximation" in cost.cost_table(tiny) and "tiny decoder" not in cost.cost_table(vae)


@pytest.mark.slow
def test_cost_gpu_runs_the_planner_for_the_card_and_reports_its_plan(cli, monkeypatch, capsys, tmp_path: Path):
    """`cost --gpu RTX4090`: the plan auto picks for 24 GB (with offload: none fits without), traced with
    that plan; the tiny models stand in for the full-size trace (seconds instead of a minute)."""
    real = cost.cost_report
    traced = []

    def tiny_report(settings, mode, argv=()):
        traced.append(settings["plan"])
        tiny = cost.cost_settings(preset="tiny", steps=None, frames=None, height=None, width=None, dtype=None,
                                  plan=settings["plan"])
        return real(tiny, mode, argv)

    monkeypatch.setattr(cost, "cost_report", tiny_report)
    path = tmp_path / "cost.json"
    assert cli.main(["cost", "--gpu", "RTX4090", "--mode", "fast", "--threads", "1", "--json", str(path)]) == 0
    report = json.loads(path.read_text())
    # checkpointed and leanest peak alike (in the anchor decode's backward): the faster one
    assert traced == ["checkpointed"] and report["plan"] == "checkpointed" and report["card"]["offload"]
    assert report["peak_memory_gb_without_offload"] >= report["peak_memory_gb"] > 0
    assert set(report["roofline"]["ratio_guided_over_unguided"]) == set(cards.GPU_SPECS)
    assert "RTX4090 (22.4 GiB): memory plan checkpointed with model CPU offload" in capsys.readouterr().out


def test_sampling_measures_the_explicit_flags_unless_a_plan_is_asked_for() -> None:
    """`sampling` runs the flags it was measured with (memory plan `explicit`) by default; `--memory-plan`
    sets the guided arm's plan."""
    common = {"full_size": False, "mode": "fast", "steps": 4, "frames": None, "height": None, "width": None,
              "device": "cpu", "dtype": None, "threads": 1, "seed": 0, "warmup": 0}
    default = sampling.sampling_spec(**common)
    assert sampling.sampling_run_options({**default, "arm": "guided"}).memory_plan == "explicit"
    leanest = sampling.sampling_spec(**common, memory_plan="leanest")
    assert sampling.sampling_run_options({**leanest, "arm": "guided"}).memory_plan == "leanest"
    assert sampling.sampling_guidance({**leanest, "arm": "unguided"}) is False
