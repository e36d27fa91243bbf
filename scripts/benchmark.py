"""Time and memory benchmarks of geco_guide.

Subcommands:

* ``loss`` — the fused GeCo loss core (:func:`geco_from_geometry`) forward and forward+backward,
  geometry and correspondences as random-but-valid leaf tensors requiring grad.
* ``estimators`` — VGGT ``estimate_geometry`` and UFM ``estimate_flow`` forward and
  forward+backward (gradient w.r.t. the input frames; parameters frozen), tiny and/or full-size
  architectures with random weights.
* ``vae`` — the anchor decode of one guided update (:func:`decode_anchor_frames`: the paper's
  3-latent causal chunks, equal-length chunks batched in one call) forward and forward+backward
  w.r.t. the latents, through the CogVideoX-5B VAE (random weights) or the tiny one.
* ``sampling`` — :class:`GeCoCogVideoXPipeline` sampling without and with GeCo guidance from the
  same seed (one subprocess per arm): wall time, time per denoising step, a per-stage breakdown
  of the guided arm (denoiser forward/backward, VAE slice decode forward/backward, VGGT and UFM
  forward/backward, loss), denoiser pass counts and peak memory. ``--preset tiny`` (tiny random
  models, 17x32x48) or ``--full-size`` (CogVideoX-5B transformer + VAE, VGGT-1B, UFM-Base, random
  weights, random ``[1, 226, 4096]`` text embeddings instead of T5, 49x480x720; refused on CPU
  without ``--allow-cpu``). ``--steps N < 50`` runs the paper's guidance schedule compressed to N
  steps (step i takes R_t and time travel of paper step ``floor(i * 50 / N)``; the scheduler's
  own N-step table) and extrapolates to 50 steps and the paper's 111 updates
  (``extrapolated: true``).

  Stage timing (:class:`StageProfiler`) wraps, on the instances only, ``transformer.forward``,
  ``vae.decode``, ``geometry_estimator.estimate_geometry`` and ``flow_estimator.estimate_flow``:
  forward = the call's duration; backward = from the first execution of an output's ``grad_fn``
  (node pre-hook) to the gradient w.r.t. the last input (an identity autograd function on the
  inputs). ``loss`` = the guided updates' own seconds (``guidance_log``) minus every stage
  interval inside them: the GeCo loss math and its backward, resizing, the normalised update.
  On CUDA every timing point synchronises the device, so CUDA timings include syncs added by
  the harness.

* ``cost`` — a cost model of sampling, no weights and no GPU needed: the real pipeline call of one
  step (unguided, or guided with one update of ``--mode``) runs on fake tensors
  (``FakeTensorMode``; full size: CogVideoX-5B transformer + VAE, VGGT-1B, UFM-Base, 49x480x720)
  under :class:`CostTracker`, which counts per stage (denoiser with / without gradients, anchor
  decode, VGGT, UFM, loss, final decode; forward and backward) the FLOPs
  (``torch.utils.flop_counter`` formulas), bytes moved, ATen ops and the live memory (weights +
  activations at the peak). The units are combined with the schedule's counts (the real
  ``guided_step`` driven by counting stubs over R_t and time travel) into whole-run FLOPs, the
  guided / unguided FLOP ratio, peak memory and a roofline time on H100/H200 (one efficiency,
  calibrated on the measured unguided H200 step). About a minute per mode on a 2-core CPU.

Every case (one workload in one mode) runs in its own subprocess (the internal ``worker``
subcommand), so peak memory is per case: ``torch.cuda.max_memory_allocated`` on a GPU, peak RSS
(``ru_maxrss``) on CPU, reported in total and as the increase over the child's post-import
baseline; the peak is then restarted after setup, so that the timed runs' own peak over the
memory in use when they start (activations) is reported too. Each case also records the
1-minute load average at its start and its CPU time per wall-clock second: on a shared machine
timings are only comparable at similar CPU shares.
Results are printed as a Markdown table and written as JSON with ``--json PATH``.

A new benchmark adds a workload builder to :data:`WORKLOADS` and a subcommand that lists its
cases; the timing, memory, subprocess and report utilities below are shared.

Examples::

    python scripts/benchmark.py loss --frames 4 --height 480 --width 720 --repeats 3
    python scripts/benchmark.py estimators --size both --frames 2 --height 140 --width 210
    python scripts/benchmark.py vae --size full --height 64 --width 96
    python scripts/benchmark.py sampling --preset tiny --mode faithful --json out.json
    python scripts/benchmark.py sampling --full-size --device cuda --mode fast --steps 10
    python scripts/benchmark.py cost --mode faithful --json cost.json
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import resource
import statistics
import subprocess
import sys
import time
import weakref
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable, Sequence

import torch
import torch.nn.functional as F
from torch import Tensor

from geco_guide.bench.synthetic import default_intrinsics, orbit_cameras
from geco_guide.config import COGVIDEOX_TEMPORAL_COMPRESSION
from geco_guide.estimators.ufm import UFM, UFMConfig, choose_resolution
from geco_guide.estimators.vggt import VGGT, VGGTConfig, plan_preprocess
from geco_guide.loss.geco import (
    PAIR_MODES,
    GeCoLossConfig,
    frame_pairs,
    geco_from_geometry,
)
from geco_guide.sampler.slicing import default_anchors
from geco_guide.types import Correspondences, SceneGeometry

MODES = ("forward", "forward_backward")
#: ``--rss-exact``: allocations from 64 KiB up are mapped on their own and unmapped when freed.
RSS_EXACT_MMAP_THRESHOLD = 64 * 1024
MIB = 2**20

# ----------------------------------------------------------------------------------------------
# Shared utilities: timing, memory, one subprocess per case, reports
# ----------------------------------------------------------------------------------------------


def synchronize(device: torch.device) -> None:
    """Wait for queued GPU work so wall-clock times cover it (no-op on CPU)."""
    if device.type == "cuda":
        torch.cuda.synchronize(device)


def time_callable(
    fn: Callable[[], object], device: torch.device, warmup: int, repeats: int
) -> dict[str, Any]:
    """Run ``fn`` ``warmup`` times untimed, then ``repeats`` times timed.

    Returns:
        ``times_s`` (every timed run), ``time_median_s``, ``time_min_s`` and ``cpu_per_wall``:
        this process's CPU time over the timed wall time, about the thread count on an idle
        machine and lower when other processes take the cores.
    """
    if repeats < 1:
        raise ValueError(f"repeats must be >= 1, got {repeats}")
    for _ in range(warmup):
        fn()
    synchronize(device)
    times = []
    cpu_start = time.process_time()
    for _ in range(repeats):
        start = time.perf_counter()
        fn()
        synchronize(device)
        times.append(time.perf_counter() - start)
    return {"times_s": times, "time_median_s": statistics.median(times), "time_min_s": min(times),
            "cpu_per_wall": (time.process_time() - cpu_start) / sum(times)}


def peak_memory_bytes(device: torch.device) -> int:
    """Peak memory of this process so far: CUDA ``max_memory_allocated`` on a GPU, else peak RSS."""
    if device.type == "cuda":
        return torch.cuda.max_memory_allocated(device)
    peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    return peak if sys.platform == "darwin" else peak * 1024  # bytes on macOS, KiB on Linux


def current_memory_bytes(device: torch.device) -> int | None:
    """Memory in use now: CUDA ``memory_allocated`` on a GPU, else resident set size (Linux only)."""
    if device.type == "cuda":
        return torch.cuda.memory_allocated(device)
    try:
        status = Path("/proc/self/status").read_text()
    except OSError:
        return None
    kib = next((line.split()[1] for line in status.splitlines() if line.startswith("VmRSS:")), None)
    return int(kib) * 1024 if kib is not None else None


def reset_peak_memory(device: torch.device) -> bool:
    """Restart :func:`peak_memory_bytes` from the current use (CUDA peak stats; on Linux the
    process's RSS high-water mark via ``/proc/self/clear_refs``). False where that is impossible."""
    if device.type == "cuda":
        torch.cuda.reset_peak_memory_stats(device)
        return True
    try:
        Path("/proc/self/clear_refs").write_text("5")
    except OSError:
        return False
    return True


def memory_kind(device: torch.device) -> str:
    """What :func:`peak_memory_bytes` measures on ``device``."""
    return "cuda_max_memory_allocated" if device.type == "cuda" else "peak_rss"


def run_case_subprocess(spec: dict[str, Any]) -> dict[str, Any]:
    """Run one case in a fresh Python process (``worker`` subcommand) and return its result.

    The child prints its result as JSON on its last stdout line; a failing child raises with its
    stderr.
    """
    command = [sys.executable, str(Path(__file__).resolve()), "worker", json.dumps(spec)]
    env = dict(os.environ)
    if spec.get("rss_exact"):
        # glibc otherwise raises its mmap threshold to 32 MiB after the first large free and keeps
        # freed blocks below it in the heap, so peak RSS overstates the live tensors.
        env["MALLOC_MMAP_THRESHOLD_"] = str(RSS_EXACT_MMAP_THRESHOLD)
    proc = subprocess.run(command, capture_output=True, text=True, env=env)
    if proc.returncode != 0:
        raise RuntimeError(f"case {spec['case']} / {spec['mode']} failed:\n{proc.stderr}")
    return json.loads(proc.stdout.strip().splitlines()[-1])


def run_cases(specs: Sequence[dict[str, Any]]) -> list[dict[str, Any]]:
    """Run every case in its own subprocess, logging progress to stderr."""
    results = []
    for spec in specs:
        print(f"running {spec['case']} / {spec['mode']} ...", file=sys.stderr, flush=True)
        result = run_case_subprocess(spec)
        print(f"  median {result['time_median_s']:.4g} s, peak {result['peak_mib']:.0f} MiB",
              file=sys.stderr, flush=True)
        results.append(result)
    return results


def environment_info(threads: int) -> dict[str, Any]:
    """Machine and software facts for the report (the children use ``threads`` threads)."""
    return {
        "platform": platform.platform(),
        "processor": _cpu_model(),
        "cpu_count": os.cpu_count(),
        "python": platform.python_version(),
        "torch": torch.__version__,
        "torch_threads": threads,
        "cuda": torch.cuda.get_device_name() if torch.cuda.is_available() else None,
    }


def _cpu_model() -> str:
    """CPU model name from ``/proc/cpuinfo`` (Linux), else :func:`platform.processor`."""
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor()


# Report columns: header, result key, format.
COLUMNS: tuple[tuple[str, str, str], ...] = (
    ("case", "case", "{}"),
    ("mode", "mode", "{}"),
    ("input", "input", "{}"),
    ("network input", "network", "{}"),
    ("params (M)", "params_m", "{:.1f}"),
    ("dtype", "dtype", "{}"),
    ("checkpointing", "checkpointing", "{}"),
    ("tiling", "tiling", "{}"),
    ("setup (s)", "setup_s", "{:.1f}"),
    ("median (s)", "time_median_s", "{:.4g}"),
    ("min (s)", "time_min_s", "{:.4g}"),
    ("peak mem (MiB)", "peak_mib", "{:.0f}"),
    ("after setup (MiB)", "after_setup_mib", "{:.0f}"),
    ("increase over import (MiB)", "peak_increase_mib", "{:.0f}"),
    ("runs: peak over in use after setup (MiB)", "run_increase_mib", "{:.0f}"),
    ("load (1 min)", "load_avg_1m", "{:.1f}"),
    ("CPU/wall", "cpu_per_wall", "{:.2f}"),
)


def markdown_table(
    results: Sequence[dict[str, Any]], columns: Sequence[tuple[str, str, str]] = COLUMNS
) -> str:
    """A Markdown table of ``results``, one row each; missing values are shown as ``-``."""
    lines = ["| " + " | ".join(header for header, _, _ in columns) + " |",
             "|" + "|".join("---" for _ in columns) + "|"]
    for result in results:
        cells = [fmt.format(result[key]) if result.get(key) is not None else "-" for _, key, fmt in columns]
        lines.append("| " + " | ".join(cells) + " |")
    return "\n".join(lines)


def run_and_report(subcommand: str, specs: Sequence[dict[str, Any]], json_path: str | None) -> None:
    """Run ``specs``, print the Markdown table and write the JSON report to ``json_path``."""
    results = run_cases(specs)
    print(markdown_table(results))
    if json_path:
        payload = {
            "subcommand": subcommand,
            "argv": sys.argv[1:],
            "environment": environment_info(results[0]["threads"]),
            "results": results,
        }
        path = Path(json_path)
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_text(json.dumps(payload, indent=2) + "\n")


# ----------------------------------------------------------------------------------------------
# Workloads: what one case runs
# ----------------------------------------------------------------------------------------------


@dataclass
class Workload:
    """A case's timed step and the facts worth reporting (input size, network size, ...)."""

    step: Callable[[], None]
    info: dict[str, Any]


def make_step(mode: str, scalar_fn: Callable[[], Tensor], leaves: Sequence[Tensor]) -> Callable[[], None]:
    """The timed step: ``forward`` evaluates ``scalar_fn`` under ``no_grad``;
    ``forward_backward`` evaluates it with autograd and back-propagates to ``leaves``
    (whose gradients are cleared first, so runs do not accumulate)."""
    if mode == "forward":
        def step() -> None:
            with torch.no_grad():
                scalar_fn()
    elif mode == "forward_backward":
        def step() -> None:
            for leaf in leaves:
                leaf.grad = None
            scalar_fn().backward()
    else:
        raise ValueError(f"mode must be one of {MODES}, got {mode!r}")
    return step


def _smooth_field(shape: tuple[int, ...], height: int, width: int, gen: torch.Generator) -> Tensor:
    """Seeded smooth random field ``[*shape, H, W]`` in ``[0, 1]``: a 6x8 grid upsampled bilinearly."""
    coarse = torch.rand(*shape, 6, 8, generator=gen).flatten(0, -3)[:, None]
    fine = F.interpolate(coarse, size=(height, width), mode="bilinear", align_corners=False)
    return fine.reshape(*shape, height, width)


def loss_workload(spec: dict[str, Any], device: torch.device) -> Workload:
    """GeCo loss core on random-but-valid geometry and correspondences.

    Leaf tensors requiring grad: smooth depth in ``[3, 6]``, K of a 60-degree camera, orbiting
    camera-from-world extrinsics (:mod:`geco_guide.synthetic`), smooth flow of up to +-4 px and
    covisibility in ``[0.4, 1]``. A confidence map in ``[1, 2]`` (>= 1 like VGGT's, no grad)
    exercises the confidence-percentile mask as in guidance. All maps are dense, so the cost
    does not depend on the values; nothing is rendered, which keeps the setup's memory small.
    """
    frames, height, width = spec["frames"], spec["height"], spec["width"]
    pairs = frame_pairs(frames, spec["pairs"])
    gen = torch.Generator().manual_seed(spec["seed"])
    depth = 3 + 3 * _smooth_field((1, frames), height, width, gen)
    intrinsics = default_intrinsics(height, width, dtype=torch.float32).expand(1, frames, 3, 3).clone()
    extrinsics = orbit_cameras(frames, dtype=torch.float32)[None]
    flow = 8 * _smooth_field((len(pairs), 2), height, width, gen) - 4
    covisibility = 0.4 + 0.6 * torch.rand(len(pairs), height, width, generator=gen)
    confidence = 1 + torch.rand(1, frames, height, width, generator=gen)
    leaves = [t.to(device).requires_grad_() for t in (depth, intrinsics, extrinsics, flow, covisibility)]
    geometry = SceneGeometry(depth=leaves[0], intrinsics=leaves[1], extrinsics=leaves[2],
                             confidence=confidence.to(device))
    correspondences = Correspondences(flow=leaves[3], covisibility=leaves[4])
    config = GeCoLossConfig(pairs=spec["pairs"])

    def scalar() -> Tensor:
        return geco_from_geometry(geometry, correspondences, pairs, config).loss

    info = {"input": f"{frames}x{height}x{width}, {len(pairs)} {spec['pairs']} pairs"}
    return Workload(make_step(spec["mode"], scalar, leaves), info)


def _random_frames(spec: dict[str, Any], device: torch.device) -> Tensor:
    """Seeded uniform frames ``[1, S, 3, H, W]`` in ``[0, 1]`` requiring grad."""
    gen = torch.Generator().manual_seed(spec["seed"])
    frames = torch.rand(1, spec["frames"], 3, spec["height"], spec["width"], generator=gen)
    return frames.to(device).requires_grad_()


def _num_params(model: torch.nn.Module) -> float:
    """Parameter count in millions."""
    return sum(p.numel() for p in model.parameters()) / 1e6


def vggt_workload(spec: dict[str, Any], device: torch.device) -> Workload:
    """``VGGT.estimate_geometry`` on ``[1, S, 3, H, W]``; the scalar sums the means of depth,
    confidence, K and extrinsics so backward runs through the depth and camera heads."""
    config = VGGTConfig.tiny() if spec["size"] == "tiny" else VGGTConfig()
    model = VGGT.random(config, seed=spec["seed"]).trunk_to(getattr(torch, spec["dtype"])).to(device)
    frames = _random_frames(spec, device)

    def scalar() -> Tensor:
        geometry = model.estimate_geometry(frames)
        outputs = (geometry.depth, geometry.confidence, geometry.intrinsics, geometry.extrinsics)
        return sum(t.mean() for t in outputs)

    plan = plan_preprocess(spec["height"], spec["width"], config.img_size, config.patch_size)
    info = {"input": "x".join(map(str, frames.shape)), "network": "{}x{}".format(*plan.network_hw),
            "params_m": _num_params(model), "dtype": spec["dtype"]}
    return Workload(make_step(spec["mode"], scalar, [frames]), info)


def ufm_workload(spec: dict[str, Any], device: torch.device) -> Workload:
    """``UFM.estimate_flow`` on the ``S - 1`` adjacent pairs of ``[1, S, 3, H, W]`` in one batch;
    the scalar is mean flow + mean covisibility. Weights: ``UFM.random(config, seed)``."""
    config = UFMConfig.tiny() if spec["size"] == "tiny" else UFMConfig()
    model = UFM.random(config, seed=spec["seed"]).trunk_to(getattr(torch, spec["dtype"])).to(device)
    frames = _random_frames(spec, device)

    def scalar() -> Tensor:
        source, target = frames[0, :-1], frames[0, 1:]
        correspondences = model.estimate_flow(source, target)
        return correspondences.flow.mean() + correspondences.covisibility.mean()

    hw = (spec["height"], spec["width"])
    info = {"input": f"{spec['frames'] - 1} pair(s) {hw[0]}x{hw[1]}",
            "network": "{}x{}".format(*choose_resolution(config.inference_resolution, hw, hw)),
            "params_m": _num_params(model), "dtype": spec["dtype"]}
    return Workload(make_step(spec["mode"], scalar, [frames]), info)


def _tiles_like_full_size(height: int, width: int) -> dict[str, Any]:
    """``enable_tiling`` arguments that cut a ``height x width`` video into the tiles the
    CogVideoX VAE uses at 480x720 (half-size tiles, its default overlaps), so that a small
    benchmark shows the tiles' effect at full size."""
    return {"tile_sample_min_height": height // 2, "tile_sample_min_width": width // 2,
            "tile_overlap_factor_height": 1 / 6, "tile_overlap_factor_width": 1 / 5}


def vae_workload(spec: dict[str, Any], device: torch.device) -> Workload:
    """The guided update's anchor decode alone: :func:`decode_anchor_frames` of seeded random
    clean latents ``[1, L, C, H/8, W/8]`` (``spec["frames"] = 4L - 3`` pixel frames) at
    :func:`default_anchors` with 3-latent chunks, through the CogVideoX-5B VAE (``full``) or the
    tiny one, in ``spec["dtype"]``; the scalar is the frames' mean, back-propagated to the latents."""
    from functools import partial

    from geco_guide.sampler.slicing import (
        anchor_latent_chunks,
        decode_anchor_frames,
        decode_chunk,
    )

    dtype = getattr(torch, spec["dtype"])
    if spec["size"] == "tiny":
        from geco_guide.tiny import tiny_cogvideox_components

        vae = tiny_cogvideox_components(spec["seed"])["vae"].to(device=device, dtype=dtype)
    else:
        from diffusers import AutoencoderKLCogVideoX

        vae = _materialise(AutoencoderKLCogVideoX, COGVIDEOX_5B_VAE, device, dtype, spec["seed"])
    vae.requires_grad_(False)
    if spec["vae_checkpointing"]:
        vae.enable_gradient_checkpointing()
    if spec["vae_tiling"]:
        vae.enable_tiling(**_tiles_like_full_size(spec["height"], spec["width"]))
    r = vae.config.temporal_compression_ratio
    spatial = 2 ** (len(vae.config.block_out_channels) - 1)
    chunks = anchor_latent_chunks(default_anchors(spec["frames"], r), spec["frames"], r, 3)
    num_latents = (spec["frames"] - 1) // r + 1
    gen = torch.Generator().manual_seed(spec["seed"])
    shape = (1, num_latents, vae.config.latent_channels, spec["height"] // spatial, spec["width"] // spatial)
    latents = torch.randn(*shape, generator=gen).to(device).requires_grad_()

    def scalar() -> Tensor:
        return decode_anchor_frames(partial(decode_chunk, vae, scaling_factor=vae.config.scaling_factor), latents,
                                    chunks, checkpoint_chunks=spec["vae_checkpointing"]).mean()

    spans = {(c.start, c.stop) for c in chunks}
    # checkpointed: one decode per chunk; otherwise equal-length chunks share a decode call
    calls = len(spans) if spec["vae_checkpointing"] else len({stop - start for start, stop in spans})
    info = {"input": "x".join(map(str, shape)),
            "network": f"{len(spans)} chunks in {calls} decode call(s), anchors {[c.anchor for c in chunks]}",
            "params_m": _num_params(vae), "dtype": spec["dtype"],
            "checkpointing": spec["vae_checkpointing"], "tiling": spec["vae_tiling"]}
    return Workload(make_step(spec["mode"], scalar, [latents]), info)


WORKLOADS: dict[str, Callable[[dict[str, Any], torch.device], Workload]] = {
    "loss": loss_workload,
    "vggt": vggt_workload,
    "ufm": ufm_workload,
    "vae": vae_workload,
}


def run_worker(spec: dict[str, Any]) -> dict[str, Any]:
    """Build and time one case in this process; memory figures are this process's peaks."""
    device = torch.device(spec["device"])
    if spec["threads"]:
        torch.set_num_threads(spec["threads"])
    torch.manual_seed(spec["seed"])
    baseline = peak_memory_bytes(device)
    start = time.perf_counter()
    workload = WORKLOADS[spec["workload"]](spec, device)
    synchronize(device)
    setup_s = time.perf_counter() - start
    after_setup = peak_memory_bytes(device)
    # The peak of the runs alone: building a model can peak higher than running it (fp32
    # random init before trunk_to(bfloat16), for one), which would hide the activations.
    in_use = current_memory_bytes(device)
    reset = in_use is not None and reset_peak_memory(device)
    load_avg_1m = os.getloadavg()[0]
    timing = time_callable(workload.step, device, spec["warmup"], spec["repeats"])
    run_peak = peak_memory_bytes(device) if reset else None
    peak = max(after_setup, run_peak) if reset else peak_memory_bytes(device)
    return {
        **spec,
        **workload.info,
        "threads": torch.get_num_threads(),
        "setup_s": setup_s,
        **timing,
        "memory_kind": memory_kind(device),
        "baseline_mib": baseline / MIB,
        "after_setup_mib": after_setup / MIB,
        "peak_mib": peak / MIB,
        "peak_increase_mib": (peak - baseline) / MIB,
        "in_use_after_setup_mib": in_use / MIB if reset else None,
        "run_peak_mib": run_peak / MIB if reset else None,
        "run_increase_mib": (run_peak - in_use) / MIB if reset else None,
        "load_avg_1m": load_avg_1m,
    }


# ----------------------------------------------------------------------------------------------
# Sampling: guided vs unguided CogVideoX denoising, per-stage breakdown
# ----------------------------------------------------------------------------------------------

#: Published ``THUDM/CogVideoX-5b`` configs (``transformer/config.json``, ``vae/config.json``,
#: ``scheduler/scheduler_config.json``), written out so nothing is downloaded. The checkpoint ships
#: ``CogVideoXDPMScheduler``; the GeCo pipeline samples with DDIM from the same settings.
COGVIDEOX_5B_TRANSFORMER: dict[str, Any] = {
    "activation_fn": "gelu-approximate",
    "attention_bias": True,
    "attention_head_dim": 64,
    "dropout": 0.0,
    "flip_sin_to_cos": True,
    "freq_shift": 0,
    "in_channels": 16,
    "max_text_seq_length": 226,
    "norm_elementwise_affine": True,
    "norm_eps": 1e-5,
    "num_attention_heads": 48,
    "num_layers": 42,
    "out_channels": 16,
    "patch_size": 2,
    "sample_frames": 49,
    "sample_height": 60,
    "sample_width": 90,
    "spatial_interpolation_scale": 1.875,
    "temporal_compression_ratio": 4,
    "temporal_interpolation_scale": 1.0,
    "text_embed_dim": 4096,
    "time_embed_dim": 512,
    "timestep_activation_fn": "silu",
    "use_learned_positional_embeddings": False,
    "use_rotary_positional_embeddings": True,
}
COGVIDEOX_5B_VAE: dict[str, Any] = {
    "act_fn": "silu",
    "block_out_channels": (128, 256, 256, 512),
    "down_block_types": ("CogVideoXDownBlock3D",) * 4,
    "force_upcast": True,
    "in_channels": 3,
    "latent_channels": 16,
    "layers_per_block": 3,
    "norm_eps": 1e-6,
    "norm_num_groups": 32,
    "out_channels": 3,
    "sample_height": 480,
    "sample_width": 720,
    "scaling_factor": 0.7,
    "temporal_compression_ratio": 4,
    "up_block_types": ("CogVideoXUpBlock3D",) * 4,
    "use_post_quant_conv": False,
    "use_quant_conv": False,
}
COGVIDEOX_5B_SCHEDULER: dict[str, Any] = {
    "beta_end": 0.012,
    "beta_schedule": "scaled_linear",
    "beta_start": 0.00085,
    "clip_sample": False,
    "num_train_timesteps": 1000,
    "prediction_type": "v_prediction",
    "rescale_betas_zero_snr": True,
    "set_alpha_to_one": True,
    "snr_shift_scale": 1.0,
    "steps_offset": 0,
    "timestep_spacing": "trailing",
}
#: The paper's setting: 49 frames of 480x720, 50 DDIM steps, CFG 6; T5 embeddings are [1, 226, 4096].
FULL_SIZE_VIDEO = {"frames": 49, "height": 480, "width": 720}
NOMINAL_STEPS = 50
TEXT_EMBED_SHAPE = (1, 226, 4096)
SAMPLING_MODES = ("faithful", "fast", "unguided")
#: Breakdown stages (keys of the profiler) in report order.
STAGES = ("denoiser", "vae_decode", "vggt", "ufm")
GIB = 2**30


def _init_weights_(model: torch.nn.Module, seed: int) -> None:
    """Cheap random init of a model materialised with ``to_empty``: weight matrices / kernels
    ``N(0, 1 / fan_in)``, other weights (norm scales) 1, biases and other 1-D tensors 0; buffers
    must not exist (their values would be garbage)."""
    device = next(model.parameters()).device
    gen = torch.Generator(device=device).manual_seed(seed)
    with torch.no_grad():
        for name, param in model.named_parameters():
            if param.ndim >= 2:
                fan_in = param[0].numel()
                param.normal_(0.0, fan_in**-0.5, generator=gen)
            elif name.endswith("weight"):
                param.fill_(1.0)
            else:
                param.zero_()
    buffers = [name for name, _ in model.named_buffers()]
    if buffers:
        raise RuntimeError(f"{type(model).__name__} has buffers {buffers[:5]}; _init_weights_ cannot fill them")


def build_full_size_components(device: str | torch.device, dtype: torch.dtype, seed: int = 0) -> dict[str, Any]:
    """CogVideoX-5B transformer and VAE (random weights, ``dtype``, on ``device``), DDIM scheduler.

    Built on the meta device and materialised with ``to_empty`` directly in ``dtype``; with
    ``device="meta"`` nothing is allocated (for tests). No tokenizer or text encoder.
    """
    from diffusers import (
        AutoencoderKLCogVideoX,
        CogVideoXDDIMScheduler,
        CogVideoXTransformer3DModel,
    )

    return {"tokenizer": None, "text_encoder": None,
            "vae": _materialise(AutoencoderKLCogVideoX, COGVIDEOX_5B_VAE, device, dtype, seed + 1),
            "transformer": _materialise(CogVideoXTransformer3DModel, COGVIDEOX_5B_TRANSFORMER, device, dtype, seed),
            "scheduler": CogVideoXDDIMScheduler(**COGVIDEOX_5B_SCHEDULER)}


def _materialise(cls: type, config: dict[str, Any], device: str | torch.device, dtype: torch.dtype, seed: int) -> Any:
    """``cls(**config)`` built on the meta device, then allocated in ``dtype`` on ``device`` with
    :func:`_init_weights_` (left on meta when ``device`` is meta), in eval mode."""
    with torch.device("meta"):
        model = cls(**config)
    model.to(dtype)
    if torch.device(device).type != "meta":
        model.to_empty(device=device)
        _init_weights_(model, seed)
    return model.eval()


def compressed_paper_schedule(num_steps: int) -> tuple[list[int], list[int] | None]:
    """The paper's 50-step guidance schedule compressed to ``num_steps`` steps.

    Step ``i`` of ``num_steps`` takes ``R_t`` (and time travel) of paper step
    ``floor(i * 50 / num_steps)``; the sampler uses the scheduler's own ``num_steps``-step
    timestep table (trailing spacing), so the steps span the whole trajectory. Identity at 50.
    """
    from geco_guide.sampler.schedule import (
        PAPER_REPEATS,
        PAPER_TIME_TRAVEL,
        parse_repeats,
    )

    paper = parse_repeats(PAPER_REPEATS)
    index = [i * NOMINAL_STEPS // num_steps for i in range(num_steps)]
    repeats = [paper[j] for j in index]
    first, last = PAPER_TIME_TRAVEL
    window = [i for i, j in enumerate(index) if first <= j <= last]
    return repeats, ([window[0], window[-1]] if window else None)


def _tensors(obj: Any) -> list[Tensor]:
    """Tensors in a (nested) output: tensors, tuples/lists, dicts (diffusers outputs), dataclasses."""
    if isinstance(obj, Tensor):
        return [obj]
    if isinstance(obj, (tuple, list)):
        return [t for item in obj for t in _tensors(item)]
    if isinstance(obj, dict):
        return [t for item in obj.values() for t in _tensors(item)]
    if hasattr(obj, "__dataclass_fields__"):
        return [t for name in obj.__dataclass_fields__ for t in _tensors(getattr(obj, name))]
    return []


class _BackwardMark(torch.autograd.Function):
    """Identity whose backward calls ``callback`` (the gradient w.r.t. a stage input is done)."""

    @staticmethod
    def forward(ctx, callback, x):  # type: ignore[override]
        ctx.callback = callback
        return x.view_as(x)

    @staticmethod
    def backward(ctx, grad):  # type: ignore[override]
        ctx.callback()
        return None, grad


class StageProfiler:
    """Per-stage forward/backward times of a pipeline call, installed on the instances only.

    ``wrap(obj, name, stage)`` replaces the bound method ``obj.name`` by a wrapper that times the
    call (forward) and, when autograd is on, marks the backward: it starts at the first execution of
    an output's ``grad_fn`` (a node pre-hook) and ends when the gradient w.r.t. the last stage
    input is computed (an identity autograd function on every tensor input). The autograd engine
    runs ready nodes in decreasing creation order, so the backward of a stage runs contiguously
    between these two events. On CUDA every event synchronises the device (added by the harness).
    """

    def __init__(self, device: torch.device) -> None:
        self.device = device
        self.calls: list[dict[str, Any]] = []
        self.loop_start: float | None = None
        self.step_ends: list[float] = []

    def now(self) -> float:
        synchronize(self.device)
        return time.perf_counter()

    def reset(self) -> None:
        self.calls, self.loop_start, self.step_ends = [], None, []

    def wrap(self, obj: Any, name: str, stage: str) -> None:
        original = getattr(obj, name)

        def wrapper(*args: Any, **kwargs: Any) -> Any:
            call: dict[str, Any] = {"stage": stage, "grad": torch.is_grad_enabled(),
                                    "bwd_start": None, "bwd_end": None}

            def mark(x: Any) -> Any:
                if isinstance(x, Tensor) and x.requires_grad:
                    return _BackwardMark.apply(lambda: self._bwd_end(call), x)
                return x

            if call["grad"]:
                args = tuple(mark(a) for a in args)
                kwargs = {k: mark(v) for k, v in kwargs.items()}
            call["start"] = self.now()
            out = original(*args, **kwargs)
            call["end"] = self.now()
            if call["grad"]:
                nodes = {id(t.grad_fn): t.grad_fn for t in _tensors(out) if t.grad_fn is not None}
                for node in nodes.values():
                    node.register_prehook(lambda grad_outputs: self._bwd_start(call))
            self.calls.append(call)
            return out

        setattr(obj, name, wrapper)

    def _bwd_start(self, call: dict[str, Any]) -> None:
        if call["bwd_start"] is None:
            call["bwd_start"] = self.now()

    def _bwd_end(self, call: dict[str, Any]) -> None:
        call["bwd_end"] = self.now()

    def wrap_predict_x0(self, pipe: Any) -> None:
        """Mark the loop start: the first ``model_output`` call (every step makes at least one: the
        unguided steps call it directly, ``predict_x0`` through it); ``predict_x0`` on pipelines
        without ``model_output``."""
        name = "model_output" if hasattr(pipe, "model_output") else "predict_x0"
        original = getattr(pipe, name)

        def wrapper(*args: Any, **kwargs: Any) -> Any:
            if self.loop_start is None:
                self.loop_start = self.now()
            return original(*args, **kwargs)

        setattr(pipe, name, wrapper)

    def on_step_end(self, pipe: Any, step: int, t: Any, callback_kwargs: dict[str, Any]) -> dict[str, Any]:
        self.step_ends.append(self.now())
        return {}

    def intervals(self) -> list[dict[str, Any]]:
        """Every timed interval: ``stage, kind (forward|backward), grad, start, end``."""
        out = []
        for call in self.calls:
            out.append({"stage": call["stage"], "kind": "forward", "grad": call["grad"],
                        "start": call["start"], "end": call["end"]})
            if call["bwd_start"] is not None and call["bwd_end"] is not None:
                out.append({"stage": call["stage"], "kind": "backward", "grad": True,
                            "start": call["bwd_start"], "end": call["bwd_end"]})
        return out


def _union_seconds(spans: Sequence[tuple[float, float]]) -> float:
    """Total length of the union of ``(start, end)`` spans (overlaps counted once)."""
    total, current = 0.0, None
    for start, end in sorted(spans):
        if current is None or start > current[1]:
            if current is not None:
                total += current[1] - current[0]
            current = [start, end]
        else:
            current[1] = max(current[1], end)
    return total + (current[1] - current[0] if current is not None else 0.0)


def update_windows(loop_start: float, step_ends: Sequence[float], log: Sequence[dict[str, Any]]) -> list[tuple[float, float]]:
    """``(start, end)`` of every guided update from the step boundaries and the records.

    A step's updates run back to back from its start (the previous step's end, or the loop start)
    and each lasts its record's ``seconds``; the few microseconds of Python between them shift
    the windows slightly early, so the step's final prediction still falls after the last one.
    """
    windows, start = [], None
    step_starts = [loop_start, *step_ends]
    current_step = None
    for record in log:
        if record["step"] != current_step:
            current_step, start = record["step"], step_starts[record["step"]]
        windows.append((start, start + record["seconds"]))
        start += record["seconds"]
    return windows


def summarize_profile(profiler: StageProfiler, log: Sequence[dict[str, Any]]) -> dict[str, Any]:
    """Stage seconds split by where they happened: ``update`` (inside a guided update), ``loop``
    (the rest of the denoising loop: the final predictions of each step) and ``post`` (after the
    loop: the final VAE decode); plus counts and the ``loss`` remainder of the updates."""
    update_seconds = [r["seconds"] for r in log]
    windows = update_windows(profiler.loop_start, profiler.step_ends, log) if log else []
    loop_end = profiler.step_ends[-1] if profiler.step_ends else float("inf")

    def where(start: float) -> str:
        if any(a <= start <= b for a, b in windows):
            return "update"
        return "loop" if start <= loop_end else "post"

    spans: dict[tuple[str, str, str], list[tuple[float, float]]] = {}
    counts: dict[tuple[str, str, str], int] = {}
    for iv in profiler.intervals():
        key = (iv["stage"], iv["kind"], where(iv["start"]))
        spans.setdefault(key, []).append((iv["start"], iv["end"]))
        counts[key] = counts.get(key, 0) + 1
    seconds = {key: _union_seconds(value) for key, value in spans.items()}
    in_updates = sum(v for (_, _, w), v in seconds.items() if w == "update")
    return {
        "seconds": {"/".join(k): v for k, v in sorted(seconds.items())},
        "counts": {"/".join(k): v for k, v in sorted(counts.items())},
        "denoiser_forwards_with_grad": sum(1 for c in profiler.calls if c["stage"] == "denoiser" and c["grad"]),
        "updates_s": sum(update_seconds),
        "attributed_in_updates_s": in_updates,
        "loss_s": sum(update_seconds) - in_updates,
    }


def breakdown_of(profile: dict[str, Any], scale: dict[str, float] | None = None) -> dict[str, Any]:
    """The report's breakdown: seconds per stage and counts, optionally with the ``update`` and
    ``loop`` parts scaled (extrapolation to the nominal step count)."""
    scale = scale or {"update": 1.0, "loop": 1.0, "post": 1.0}

    def total(stage: str, kind: str, where: Sequence[str] = ("update", "loop", "post"), table: str = "seconds") -> float:
        value = sum(scale[w] * profile[table].get(f"{stage}/{kind}/{w}", 0) for w in where)
        return int(round(value)) if table == "counts" else value

    return {
        "denoiser_forward_s": total("denoiser", "forward"),
        "denoiser_backward_s": total("denoiser", "backward"),
        "vae_slice_decode_forward_s": total("vae_decode", "forward", ("update",)),
        "vae_slice_decode_backward_s": total("vae_decode", "backward", ("update",)),
        "vae_final_decode_s": total("vae_decode", "forward", ("loop", "post")),
        "vggt_forward_s": total("vggt", "forward"),
        "vggt_backward_s": total("vggt", "backward"),
        "ufm_forward_s": total("ufm", "forward"),
        "ufm_backward_s": total("ufm", "backward"),
        "loss_s": scale["update"] * profile["loss_s"],
        "guided_updates_s": scale["update"] * profile["updates_s"],
        "counts": {
            "denoiser_forwards": total("denoiser", "forward", table="counts"),
            "denoiser_forwards_in_updates": total("denoiser", "forward", ("update",), table="counts"),
            "denoiser_backwards": total("denoiser", "backward", table="counts"),
            "vae_slice_decodes": total("vae_decode", "forward", ("update",), table="counts"),
            "vggt_calls": total("vggt", "forward", table="counts"),
            "ufm_calls": total("ufm", "forward", table="counts"),
        },
    }


def _sampling_guidance(spec: dict[str, Any]) -> Any:
    """The ``guidance=`` argument of an arm: ``False`` (unguided) or a :class:`GuidanceConfig`."""
    from dataclasses import replace

    from geco_guide.sampler.config import fused_guidance_config
    from geco_guide.tiny import tiny_guidance_config

    if spec["arm"] == "unguided":
        return False
    repeats, time_travel = compressed_paper_schedule(spec["steps"])
    # the fused loss (gradients through VGGT too): the costlier of the two presets, what was measured
    base = tiny_guidance_config() if spec["preset"] == "tiny" else fused_guidance_config()
    chunk_latents = spec["chunk_latents"] or base.chunk_latents
    anchors = default_anchors(spec["frames"], COGVIDEOX_TEMPORAL_COMPRESSION)
    return replace(base, anchors=anchors, repeats=",".join(map(str, repeats)),
                   time_travel=time_travel, denoiser_grad=spec["mode"] == "faithful", chunk_latents=chunk_latents,
                   gradient_checkpointing=base.gradient_checkpointing and not spec.get("no_denoiser_checkpointing"))


def build_sampling_pipeline(spec: dict[str, Any], device: torch.device, dtype: torch.dtype) -> tuple[Any, dict[str, Any]]:
    """The pipeline of a sampling case and its call kwargs (random text embeddings for full size)."""
    from geco_guide.sampler.pipeline_cogvideox import GeCoCogVideoXPipeline

    seed = spec["seed"]
    if spec["preset"] == "tiny":
        from geco_guide.tiny import TINY_MAX_SEQUENCE_LENGTH, tiny_pipeline

        pipe = tiny_pipeline(seed).to(device=device, dtype=dtype)
        call = {"prompt": "a red cube on a table", "max_sequence_length": TINY_MAX_SEQUENCE_LENGTH}
    else:
        # trunks in the sampling dtype, heads float32: what generate's from_pretrained(dtype=...) builds
        ckpt = spec.get("estimator_checkpointing", False)
        geometry = VGGT.random(VGGTConfig(), seed=seed, gradient_checkpointing=ckpt).trunk_to(dtype)
        flow = UFM.random(UFMConfig(), seed=seed, gradient_checkpointing=ckpt).trunk_to(dtype)
        pipe = GeCoCogVideoXPipeline(**build_full_size_components(device, dtype, seed),
                                     geometry_estimator=geometry.eval(), flow_estimator=flow.eval())
        pipe.to(device)
        if spec["vae_tiling"]:  # generate's model.vae_tiling
            pipe.vae.enable_tiling()
        pipe.set_progress_bar_config(disable=True)
        gen = torch.Generator().manual_seed(seed + 1000)
        embeds = [torch.randn(*TEXT_EMBED_SHAPE, generator=gen).to(device, dtype) for _ in range(2)]
        call = {"prompt_embeds": embeds[0], "negative_prompt_embeds": embeds[1],
                "max_sequence_length": TEXT_EMBED_SHAPE[1]}
    call.update(num_frames=spec["frames"], height=spec["height"], width=spec["width"], output_type="pt")
    return pipe, call


def run_sampling_worker(spec: dict[str, Any]) -> dict[str, Any]:
    """One arm (guided or unguided) of a sampling benchmark in this process."""
    device = torch.device(spec["device"])
    dtype = getattr(torch, spec["dtype"])
    if spec["threads"]:
        torch.set_num_threads(spec["threads"])
    baseline = peak_memory_bytes(device)
    start = time.perf_counter()
    pipe, call = build_sampling_pipeline(spec, device, dtype)
    synchronize(device)
    setup_s = time.perf_counter() - start
    after_setup = peak_memory_bytes(device)

    profiler = StageProfiler(device)
    profiler.wrap(pipe.transformer, "forward", "denoiser")
    profiler.wrap(pipe.vae, "decode", "vae_decode")
    profiler.wrap(pipe.geometry_estimator, "estimate_geometry", "vggt")
    profiler.wrap(pipe.flow_estimator, "estimate_flow", "ufm")
    profiler.wrap_predict_x0(pipe)
    guidance = _sampling_guidance(spec)

    def sample(steps: int, guidance_arg: Any) -> Any:
        return pipe(**call, num_inference_steps=steps, guidance=guidance_arg, guidance_scale=6.0,
                    generator=torch.Generator().manual_seed(spec["seed"]), callback_on_step_end=profiler.on_step_end)

    for _ in range(spec["warmup"]):  # 2 steps: with guidance, step 1 has updates (compressed schedule)
        warm = _sampling_guidance({**spec, "steps": 2}) if guidance is not False else False
        sample(2, warm)
    profiler.reset()
    load_avg_1m = os.getloadavg()[0]
    cpu_start = time.process_time()
    start = profiler.now()
    out = sample(spec["steps"], guidance)
    wall = profiler.now() - start
    cpu_per_wall = (time.process_time() - cpu_start) / wall
    peak = peak_memory_bytes(device)

    log = out.guidance_log or []
    profile = summarize_profile(profiler, log)
    loop_s = profiler.step_ends[-1] - profiler.loop_start
    step_times = [b - a for a, b in zip([profiler.loop_start, *profiler.step_ends[:-1]], profiler.step_ends)]
    frames = out.frames
    return {
        **spec,
        "threads": torch.get_num_threads(),
        "setup_s": setup_s,
        "wall_s": wall,
        "loop_s": loop_s,
        "before_loop_s": profiler.loop_start - start,
        "after_loop_s": start + wall - profiler.step_ends[-1],
        "step_times_s": step_times,
        "time_per_step_s": loop_s / len(step_times),
        "guided_updates": len(log),
        "update_seconds": [r["seconds"] for r in log],
        "skipped_updates": sum(bool(r["skipped"]) for r in log),
        "losses": [r["loss"] for r in log],
        "profile": profile,
        "breakdown": breakdown_of(profile),
        "output_shape": list(frames.shape),
        "output_finite": bool(torch.isfinite(frames).all()),
        "memory_kind": memory_kind(device),
        "baseline_gb": baseline / GIB,
        "after_setup_gb": after_setup / GIB,
        "peak_memory_gb": peak / GIB,
        "load_avg_1m": load_avg_1m,
        "cpu_per_wall": cpu_per_wall,
        "guidance": None if guidance is False else {k: v for k, v in vars(guidance).items() if k != "loss"},
    }


def extrapolate_arm(arm: dict[str, Any], nominal: int, nominal_updates: int) -> dict[str, Any]:
    """Times of ``arm`` extrapolated from its ``steps`` to ``nominal`` steps with
    ``nominal_updates`` guided updates: the per-step part (final predictions, DDIM step) scales by
    ``nominal / steps``, the per-update part by ``nominal_updates / updates``; the time before and
    after the loop (text embeddings, latents, final decode) is kept."""
    steps, updates = arm["steps"], arm["guided_updates"]
    update_s = sum(arm["update_seconds"])
    per_step = (arm["loop_s"] - update_s) / steps
    per_update = update_s / updates if updates else 0.0
    if nominal_updates and not updates:
        raise ValueError(f"{steps} step(s) run no guided update: cannot extrapolate the guided time")
    loop = nominal * per_step + nominal_updates * per_update
    scale = {"update": nominal_updates / updates if updates else 0.0, "loop": nominal / steps, "post": 1.0}
    return {
        "wall_s": arm["before_loop_s"] + loop + arm["after_loop_s"],
        "loop_s": loop,
        "time_per_step_s": loop / nominal,
        "guided_updates": nominal_updates,
        "breakdown": breakdown_of(arm["profile"], scale),
    }


def sampling_report(args: argparse.Namespace) -> dict[str, Any]:
    """Run the unguided and (unless ``--mode unguided``) the guided arm; build the JSON report."""
    from geco_guide.sampler.schedule import PAPER_REPEATS, parse_repeats

    device = torch.device(args.device)
    if args.full_size and device.type == "cpu" and not args.allow_cpu:
        raise SystemExit(
            "sampling --full-size on CPU is refused: CogVideoX-5B + VGGT-1B + UFM-Base weights alone are "
            "about 30 GiB in float32 (7.4 G parameters) and a 49x480x720 step would take hours; run it on a GPU "
            "(--device cuda) or pass --allow-cpu to insist.")
    preset = "full-size" if args.full_size else "tiny"
    if preset == "tiny":
        from geco_guide.tiny import TINY_HEIGHT, TINY_NUM_FRAMES, TINY_WIDTH

        video = {"frames": TINY_NUM_FRAMES, "height": TINY_HEIGHT, "width": TINY_WIDTH}
    else:
        video = dict(FULL_SIZE_VIDEO)
    video.update({k: getattr(args, k) for k in ("frames", "height", "width") if getattr(args, k) is not None})
    steps = NOMINAL_STEPS if args.steps is None else args.steps  # 0 is an error, not the default
    if steps > NOMINAL_STEPS or steps < 1:
        raise SystemExit(f"--steps must be in [1, {NOMINAL_STEPS}], got {steps}")
    dtype = args.dtype or ("bfloat16" if preset == "full-size" and device.type == "cuda" else "float32")
    spec = {"workload": "sampling", "preset": preset, "mode": args.mode, "steps": steps, **video,
            "device": args.device, "dtype": dtype, "threads": args.threads, "seed": args.seed,
            "warmup": args.warmup, "estimator_checkpointing": args.estimator_checkpointing,
            "chunk_latents": args.chunk_latents, "vae_tiling": args.vae_tiling, "rss_exact": args.rss_exact,
            "no_denoiser_checkpointing": args.no_denoiser_checkpointing}
    arms_to_run = ("unguided",) if args.mode == "unguided" else ("unguided", "guided")
    arms = {}
    for arm in arms_to_run:
        case = {**spec, "arm": arm, "case": f"sampling-{preset}-{arm}"}
        print(f"running {case['case']} ({args.mode}, {steps} steps) ...", file=sys.stderr, flush=True)
        arms[arm] = run_case_subprocess(case)
        print(f"  wall {arms[arm]['wall_s']:.4g} s, peak {arms[arm]['peak_memory_gb']:.3f} GiB",
              file=sys.stderr, flush=True)

    extrapolated = steps < NOMINAL_STEPS
    paper_updates = sum(parse_repeats(PAPER_REPEATS))
    guided = arms.get("guided")
    main_arm = guided or arms["unguided"]
    report: dict[str, Any] = {
        "subcommand": "sampling",
        "argv": sys.argv[1:],
        "environment": environment_info(main_arm["threads"]),
        "device": f"{device.type} ({torch.cuda.get_device_name(device)})" if device.type == "cuda" else "cpu",
        "mode": args.mode,
        "preset": preset,
        "steps": steps,
        "nominal_steps": NOMINAL_STEPS,
        "extrapolated": extrapolated,
        "config": {**video, "dtype": dtype, "seed": args.seed, "warmup": args.warmup, "guidance_scale": 6.0,
                   "estimator_checkpointing": args.estimator_checkpointing, "vae_tiling": args.vae_tiling,
                   "rss_exact": args.rss_exact,
                   "guidance": guided["guidance"] if guided else None,
                   "schedule_note": "paper schedule compressed to the run's steps: step i takes R_t and time "
                                    "travel of paper step floor(i*50/steps); scheduler's own steps-step table"},
        "memory_kind": main_arm["memory_kind"],
        "peak_memory_gb": main_arm["peak_memory_gb"],
        "peak_memory_gb_unguided": arms["unguided"]["peak_memory_gb"],
        "wall_time_s": {arm: r["wall_s"] for arm, r in arms.items()},
        "time_per_step_s": {arm: r["time_per_step_s"] for arm, r in arms.items()},
        "breakdown": main_arm["breakdown"],
        "breakdown_unguided": arms["unguided"]["breakdown"],
        "arms": arms,
    }
    ratio_basis = "measured"
    if guided:
        ratio = guided["wall_s"] / arms["unguided"]["wall_s"]
    if extrapolated:
        ext = {arm: extrapolate_arm(r, NOMINAL_STEPS, paper_updates if arm == "guided" else 0)
               for arm, r in arms.items()}
        report["extrapolated_to_nominal"] = {
            "note": f"per-step and per-update times of the {steps}-step run scaled to {NOMINAL_STEPS} steps "
                    f"and the paper's {paper_updates} guided updates (not measured)",
            "wall_time_s": {arm: e["wall_s"] for arm, e in ext.items()},
            "time_per_step_s": {arm: e["time_per_step_s"] for arm, e in ext.items()},
            "breakdown": ext.get("guided", ext["unguided"])["breakdown"],
        }
        if guided:
            ratio = ext["guided"]["wall_s"] / ext["unguided"]["wall_s"]
            ratio_basis = "extrapolated"
    report["ratio_guided_over_unguided"] = ratio if guided else None
    report["ratio_basis"] = ratio_basis if guided else None
    return report


SAMPLING_COLUMNS: tuple[tuple[str, str, str], ...] = (
    ("arm", "arm", "{}"),
    ("steps", "steps", "{}"),
    ("updates", "guided_updates", "{}"),
    ("wall (s)", "wall_s", "{:.4g}"),
    ("per step (s)", "time_per_step_s", "{:.4g}"),
    ("denoiser fwd", "denoiser_forward_s", "{:.3g}"),
    ("denoiser bwd", "denoiser_backward_s", "{:.3g}"),
    ("VAE slice fwd", "vae_slice_decode_forward_s", "{:.3g}"),
    ("VAE slice bwd", "vae_slice_decode_backward_s", "{:.3g}"),
    ("VAE final", "vae_final_decode_s", "{:.3g}"),
    ("VGGT fwd", "vggt_forward_s", "{:.3g}"),
    ("VGGT bwd", "vggt_backward_s", "{:.3g}"),
    ("UFM fwd", "ufm_forward_s", "{:.3g}"),
    ("UFM bwd", "ufm_backward_s", "{:.3g}"),
    ("loss", "loss_s", "{:.3g}"),
    ("fwd / bwd", "passes", "{}"),
    ("peak mem (GiB)", "peak_memory_gb", "{:.3f}"),
)


def sampling_table(report: dict[str, Any]) -> str:
    """Markdown table of the arms (measured; the extrapolated rows are marked ``(extrap.)``)."""
    rows = []
    for arm, r in report["arms"].items():
        b = r["breakdown"]
        rows.append({**r, **b, "passes": f"{b['counts']['denoiser_forwards']} / {b['counts']['denoiser_backwards']}"})
    for arm, wall in report.get("extrapolated_to_nominal", {}).get("wall_time_s", {}).items():
        ext = report["extrapolated_to_nominal"]
        b = ext["breakdown"] if arm == ("guided" if "guided" in report["arms"] else "unguided") else {}
        rows.append({"arm": f"{arm} (extrap.)", "steps": report["nominal_steps"], "wall_s": wall,
                     "time_per_step_s": ext["time_per_step_s"][arm], **{k: v for k, v in b.items() if k != "counts"}})
    ratio = report["ratio_guided_over_unguided"]
    footer = f"\nguided / unguided wall time: {ratio:.3g} ({report['ratio_basis']})" if ratio else ""
    return markdown_table(rows, SAMPLING_COLUMNS) + footer


def run_sampling(args: argparse.Namespace) -> None:
    report = sampling_report(args)
    print(sampling_table(report))
    if args.json:
        path = Path(args.json)
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_text(json.dumps(report, indent=2) + "\n")


# ----------------------------------------------------------------------------------------------
# Cost model: FLOPs, bytes and memory of sampling on fake tensors (no weights, no GPU)
# ----------------------------------------------------------------------------------------------

#: Published dense (no sparsity) bf16 tensor-core peak and HBM bandwidth of the SXM parts
#: (NVIDIA H100 and H200 data sheets): 989.4 TFLOP/s for both; 3.35 and 4.8 TB/s.
GPU_SPECS: dict[str, dict[str, float]] = {
    "H100": {"bf16_flops_per_s": 989.4e12, "bytes_per_s": 3.35e12, "memory_gib": 80},
    "H200": {"bf16_flops_per_s": 989.4e12, "bytes_per_s": 4.8e12, "memory_gib": 141},
}
#: Measured on the H200 (docs/benchmarks/sampling_full_h200_*.json): one unguided CFG step of the
#: CogVideoX-5B transformer at 49x480x720, steady state (steps 2-4 of the three unguided arms).
H200_UNGUIDED_STEP_S = 1.78
#: Stages of the cost report; ``denoiser_cfg`` is a CFG call without gradients (the unguided step,
#: the final prediction of a guided step, fast mode's held prediction), ``denoiser`` the
#: differentiated call of a faithful update; ``loss`` is everything else inside a guided update
#: (GeCo loss, resizing, CFG combination, normalised update), ``other`` the rest of the call.
COST_STAGES = ("denoiser_cfg", "denoiser", "anchor_decode", "vggt", "ufm", "loss", "final_decode", "other")


def _register_cpu_sdpa_flops() -> None:
    """FLOP formulas for the CPU flash attention kernels (FlopCounter's registry only has the CUDA
    ones): the same counts as ``scaled_dot_product_attention`` anywhere."""
    from torch.utils import flop_counter as fc

    aten = torch.ops.aten
    if aten._scaled_dot_product_flash_attention_for_cpu in fc.flop_registry:
        return

    @fc.register_flop_formula(aten._scaled_dot_product_flash_attention_for_cpu)
    def _fwd(query_shape, key_shape, value_shape, *args, out_shape=None, **kwargs):
        return fc.sdpa_flop_count(query_shape, key_shape, value_shape)

    @fc.register_flop_formula(aten._scaled_dot_product_flash_attention_for_cpu_backward)
    def _bwd(grad_out_shape, query_shape, key_shape, value_shape, *args, out_shape=None, **kwargs):
        return fc.sdpa_backward_flop_count(grad_out_shape, query_shape, key_shape, value_shape)


def _tensor_bytes(t: Tensor) -> int:
    return t.numel() * t.element_size()


class CostTracker:
    """A ``TorchDispatchMode`` (built lazily, see :meth:`mode`) that counts, per ``(stage, kind)``
    (``kind`` = ``forward`` or ``backward``), the FLOPs of every ATen op (``torch.utils.flop_counter``
    formulas), the bytes it reads and writes (tensor arguments + outputs, views excluded) and a
    roofline time per GPU of :data:`GPU_SPECS` (``max(flops / peak, bytes / bandwidth)`` per op), and
    follows memory: every new output storage is live from its creation until a ``weakref``
    finalizer on the storage says it is freed (autograd's saved tensors keep theirs alive, so the
    graph's activations are counted); ``static`` storages (the weights) are not counted.

    Stages come from :meth:`wrap` (forward: the innermost wrapped call running; backward: from the
    first execution of an output's ``grad_fn`` to the gradient w.r.t. an input, as
    :class:`StageProfiler`); ops of the autograd engine run in ``backward``
    (``torch._C._current_graph_task_id() != -1``), including checkpoint recomputation.
    """

    def __init__(self, static: Sequence[Tensor] = ()) -> None:
        self.stack: list[str] = []
        self.bwd_stage: str | None = None
        self.in_update = 0
        self.flops: dict[tuple[str, str], int] = {}
        self.bytes: dict[tuple[str, str], int] = {}
        self.roofline_s: dict[str, dict[tuple[str, str], float]] = {gpu: {} for gpu in GPU_SPECS}
        self.ops: dict[tuple[str, str], int] = {}
        self.calls: dict[str, int] = {}
        self.static = {t.untyped_storage()._cdata for t in static}
        self.live: dict[int, int] = {}
        self.current = 0
        self.peak = 0
        self.peak_key: tuple[str, str] | None = None
        self.stage_peak: dict[tuple[str, str], int] = {}

    def key(self) -> tuple[str, str]:
        backward = torch._C._current_graph_task_id() != -1
        if self.stack:
            stage = self.stack[-1]
        elif backward and self.bwd_stage is not None:
            stage = self.bwd_stage
        else:
            stage = "loss" if self.in_update else "other"
        return stage, "backward" if backward else "forward"

    def _free(self, key: int) -> None:
        self.current -= self.live.pop(key, 0)

    def record(self, func: Any, args: tuple, kwargs: dict, out: Any) -> None:
        from torch.utils import flop_counter as fc
        from torch.utils._pytree import tree_flatten

        key = self.key()
        formula = fc.flop_registry.get(func._overloadpacket)
        flops = int(formula(*args, **kwargs, out_val=out)) if formula is not None else 0
        outputs = [t for t in tree_flatten(out)[0] if isinstance(t, Tensor)]
        moved = 0
        if not func.is_view:
            inputs = [t for t in tree_flatten((args, kwargs))[0] if isinstance(t, Tensor)]
            moved = sum(_tensor_bytes(t) for t in inputs + outputs)
        self.flops[key] = self.flops.get(key, 0) + flops
        self.bytes[key] = self.bytes.get(key, 0) + moved
        self.ops[key] = self.ops.get(key, 0) + 1
        for gpu, spec in GPU_SPECS.items():
            seconds = max(flops / spec["bf16_flops_per_s"], moved / spec["bytes_per_s"])
            self.roofline_s[gpu][key] = self.roofline_s[gpu].get(key, 0.0) + seconds
        for t in outputs:
            storage = t.untyped_storage()
            sid = storage._cdata
            if sid in self.static or sid in self.live:
                continue
            self.live[sid] = storage.nbytes()
            self.current += self.live[sid]
            weakref.finalize(storage, self._free, sid)
        if self.current > self.peak:
            self.peak, self.peak_key = self.current, key
        self.stage_peak[key] = max(self.stage_peak.get(key, 0), self.current)

    def mode(self) -> Any:
        """The dispatch mode to enter (inside a ``FakeTensorMode``, or on real tensors)."""
        from torch.utils._python_dispatch import TorchDispatchMode

        tracker = self

        class _Mode(TorchDispatchMode):
            def __torch_dispatch__(self, func, types, args=(), kwargs=None):
                kwargs = kwargs or {}
                out = func(*args, **kwargs)
                tracker.record(func, args, kwargs, out)
                return out

        return _Mode()

    def wrap(self, obj: Any, name: str, stage: str | Callable[[], str]) -> None:
        """Label the ops of ``obj.name`` (an instance attribute replaces the method) as ``stage``
        (or ``stage()``, evaluated per call), forward and backward."""
        original = getattr(obj, name)

        def wrapper(*args: Any, **kwargs: Any) -> Any:
            label = stage() if callable(stage) else stage
            if torch.is_grad_enabled():
                def end() -> None:
                    if self.bwd_stage == label:
                        self.bwd_stage = None

                def mark(x: Any) -> Any:
                    if isinstance(x, Tensor) and x.requires_grad:
                        return _BackwardMark.apply(end, x)
                    return x

                args = tuple(mark(a) for a in args)
                kwargs = {k: mark(v) for k, v in kwargs.items()}
            # a call: not a checkpoint's recomputation (backward), not nested in a call of the same stage
            new_call = torch._C._current_graph_task_id() == -1 and not (self.stack and self.stack[-1] == label)
            self.calls[label] = self.calls.get(label, 0) + new_call
            self.stack.append(label)
            try:
                out = original(*args, **kwargs)
            finally:
                self.stack.pop()
            if torch.is_grad_enabled():
                def start(grad_outputs: Any) -> None:
                    self.bwd_stage = label

                for node in {id(t.grad_fn): t.grad_fn for t in _tensors(out) if t.grad_fn is not None}.values():
                    node.register_prehook(start)
            return out

        setattr(obj, name, wrapper)

    def summary(self) -> dict[str, Any]:
        """Per-stage FLOPs, bytes, op counts, roofline seconds and peak memory (bytes)."""
        stages: dict[str, Any] = {}
        for stage, kind in sorted(self.flops):
            entry = stages.setdefault(stage, {"calls": self.calls.get(stage, 0)})
            k = (stage, kind)
            entry[kind] = {"flops": self.flops[k], "bytes": self.bytes[k], "ops": self.ops[k],
                           "peak_live_bytes": self.stage_peak[k],
                           "roofline_s": {gpu: self.roofline_s[gpu][k] for gpu in GPU_SPECS}}
        return {"stages": stages, "peak_live_bytes": self.peak,
                "peak_at": "/".join(self.peak_key) if self.peak_key else None}


def _to_fake(model: torch.nn.Module, fake_mode: Any) -> torch.nn.Module:
    """Replace the parameters and buffers of ``model`` (real or on the meta device) by fake CPU
    tensors of the same shapes and dtypes, in place."""
    memo: dict[int, Tensor] = {}
    cpu = torch.device("cpu")

    def fake(t: Tensor) -> Tensor:
        if id(t) not in memo:
            t_ = t.detach()
            memo[id(t)] = (fake_mode.fake_tensor_converter.from_meta_and_device(fake_mode, t_, cpu)
                           if t_.is_meta else fake_mode.from_tensor(t_))
        return memo[id(t)]

    for module in model.modules():
        for name, param in list(module._parameters.items()):
            if param is not None:
                module._parameters[name] = torch.nn.Parameter(fake(param), requires_grad=param.requires_grad)
        for name, buf in list(module._buffers.items()):
            if buf is not None:
                module._buffers[name] = fake(buf)
    return model


def _model_bytes(model: Any) -> int:
    if not isinstance(model, torch.nn.Module):
        return 0
    seen = {}
    for t in [*model.parameters(), *model.buffers()]:
        seen[t.untyped_storage()._cdata] = t.untyped_storage().nbytes()
    return sum(seen.values())


def build_cost_pipeline(settings: dict[str, Any], fake_mode: Any) -> tuple[Any, dict[str, Any]]:
    """The pipeline of the cost model with fake weights, and its call kwargs (fake text embeddings
    for full size; the tiny preset runs its tiny T5 on fake tensors). Full size: the CogVideoX-5B
    transformer and VAE, VGGT-1B and UFM-Base (trunks in ``dtype``, heads float32), built on the meta
    device: nothing is allocated."""
    from geco_guide.sampler.pipeline_cogvideox import GeCoCogVideoXPipeline

    dtype = getattr(torch, settings["dtype"])
    if settings["preset"] == "tiny":
        from geco_guide.tiny import TINY_MAX_SEQUENCE_LENGTH, tiny_pipeline

        pipe = tiny_pipeline(settings["seed"]).to(dtype=dtype)
        call = {"prompt": "a red cube on a table", "max_sequence_length": TINY_MAX_SEQUENCE_LENGTH}
    else:
        ckpt = settings["estimator_checkpointing"]
        with torch.device("meta"):
            geometry = VGGT(VGGTConfig(), gradient_checkpointing=ckpt)
            flow = UFM(UFMConfig(), gradient_checkpointing=ckpt)
        geometry.trunk_to(dtype).eval()
        flow.trunk_to(dtype).eval()
        pipe = GeCoCogVideoXPipeline(**build_full_size_components("meta", dtype, settings["seed"]),
                                     geometry_estimator=geometry, flow_estimator=flow)
        call = {"max_sequence_length": TEXT_EMBED_SHAPE[1]}
    for name in ("text_encoder", "transformer", "vae", "geometry_estimator", "flow_estimator"):
        model = getattr(pipe, name, None)
        if isinstance(model, torch.nn.Module):
            _to_fake(model, fake_mode)
    if settings["vae_tiling"]:
        pipe.vae.enable_tiling()
    pipe.set_progress_bar_config(disable=True)
    call.update(num_frames=settings["frames"], height=settings["height"], width=settings["width"], output_type="pt")
    return pipe, call


def _cost_guidance(settings: dict[str, Any], mode: str, repeats: str, time_travel: list[int] | None) -> Any:
    """The guidance of a cost trace or count: the preset's config with the run's settings."""
    from dataclasses import replace

    from geco_guide.sampler.config import fused_guidance_config
    from geco_guide.tiny import tiny_guidance_config

    if mode == "unguided":
        return False
    # the fused loss (gradients through VGGT too): the costlier of the two presets, what was measured
    base = tiny_guidance_config() if settings["preset"] == "tiny" else fused_guidance_config()
    changes = {k: settings[k] for k in ("chunk_latents", "vae_checkpointing", "denoiser_checkpointing")
               if settings.get(k) is not None}
    anchors = default_anchors(settings["frames"], COGVIDEOX_TEMPORAL_COMPRESSION)
    return replace(base, anchors=anchors, repeats=repeats, time_travel=time_travel,
                   denoiser_grad=mode == "faithful",
                   chunk_latents=changes.get("chunk_latents", base.chunk_latents),
                   vae_checkpointing=changes.get("vae_checkpointing", base.vae_checkpointing),
                   gradient_checkpointing=changes.get("denoiser_checkpointing", base.gradient_checkpointing))


def trace_cost(settings: dict[str, Any], mode: str) -> dict[str, Any]:
    """One pipeline call of 1 step on fake tensors, counted by a :class:`CostTracker`: unguided (one
    CFG step and the final decode) or guided with ``R = 1`` (one update of ``mode``, the step's final
    prediction, the final decode). The call is the real ``GeCoCogVideoXPipeline.__call__``, with
    three shims for fake tensors (values do not exist): the scheduler's timestep table is built
    outside the fake mode and ``scheduler.step`` gets the real timestep, and the guided update's
    record reads no scalars (``_read_scalars`` returns zeros)."""
    from unittest import mock

    from torch._subclasses.fake_tensor import FakeTensorMode, unset_fake_temporarily

    import geco_guide.sampler.config as guidance_module
    import geco_guide.sampler.pipeline_cogvideox as pipeline_module

    _register_cpu_sdpa_flops()
    fake_mode = FakeTensorMode(allow_non_fake_inputs=True)
    pipe, call = build_cost_pipeline(settings, fake_mode)
    models = {name: getattr(pipe, name, None) for name in
              ("transformer", "vae", "geometry_estimator", "flow_estimator", "text_encoder")}
    weights = [t for m in models.values() if isinstance(m, torch.nn.Module) for t in [*m.parameters(), *m.buffers()]]
    tracker = CostTracker(static=weights)

    tracker.wrap(pipe.transformer, "forward", lambda: "denoiser" if torch.is_grad_enabled() else "denoiser_cfg")
    tracker.wrap(pipe.vae, "decode", lambda: "final_decode" if "final_decode" in tracker.stack else "anchor_decode")
    tracker.wrap(pipe, "decode_latents", "final_decode")
    if mode != "unguided":
        tracker.wrap(pipe.geometry_estimator, "estimate_geometry", "vggt")
        tracker.wrap(pipe.flow_estimator, "estimate_flow", "ufm")

    scheduler, table = pipe.scheduler, {"timesteps": [], "i": 0}
    set_timesteps, step = scheduler.set_timesteps, scheduler.step

    def set_timesteps_real(*args: Any, **kwargs: Any) -> Any:
        with unset_fake_temporarily():
            out = set_timesteps(*args, **kwargs)
        table.update(timesteps=scheduler.timesteps.tolist(), i=0)
        return out

    def step_real(model_output: Tensor, timestep: Any, *args: Any, **kwargs: Any) -> Any:
        t = table["timesteps"][table["i"]]
        table["i"] += 1
        return step(model_output, t, *args, **kwargs)

    scheduler.set_timesteps, scheduler.step = set_timesteps_real, step_real
    guided_step = pipeline_module.guided_step

    def counted_guided_step(*args: Any, **kwargs: Any) -> Any:
        tracker.in_update += 1
        try:
            return guided_step(*args, **kwargs)
        finally:
            tracker.in_update -= 1

    def no_scalars(values: dict[str, Tensor], device: Any) -> dict[str, float]:
        return {**{name: 0.0 for name in values}, "finite": 1.0}

    guidance = _cost_guidance(settings, mode, "1", None)
    start = time.perf_counter()
    with (mock.patch.object(pipeline_module, "guided_step", counted_guided_step),
          mock.patch.object(guidance_module, "_read_scalars", no_scalars),
          fake_mode, tracker.mode()):
        if settings["preset"] != "tiny":
            dtype = getattr(torch, settings["dtype"])
            call["prompt_embeds"], call["negative_prompt_embeds"] = (
                torch.empty(TEXT_EMBED_SHAPE, dtype=dtype) for _ in range(2))
        out = pipe(**call, num_inference_steps=1, guidance=guidance, guidance_scale=6.0)
        frames_shape = list(out.frames.shape)
        del out
    summary = tracker.summary()
    summary.update(trace_s=time.perf_counter() - start, output_shape=frames_shape,
                   weights_bytes={name: _model_bytes(m) for name, m in models.items()},
                   guided_updates=1 if mode != "unguided" else 0)
    return summary


def count_schedule_calls(mode: str, settings: dict[str, Any]) -> dict[str, int]:
    """How often each unit of work runs in a whole sampling call (``settings["steps"]`` steps, the
    guidance schedule of the preset with the run's time travel): the real :func:`guided_step`
    driven by counting stubs (R_t = 0 steps make the pipeline's single CFG call). Returns
    ``steps``, ``updates``, ``denoiser_cfg`` (calls without gradients) and ``denoiser_grad``."""
    from geco_guide.sampler.levels import VPLevels
    from geco_guide.sampler.step import guided_step

    steps = settings["steps"]
    counts = {"steps": steps, "updates": 0, "denoiser_cfg": 0, "denoiser_grad": 0, "time_travel_updates": 0}
    if mode == "unguided":
        counts["denoiser_cfg"] = steps
        return counts
    config = _cost_guidance(settings, mode, settings["repeats"], settings["time_travel"])
    schedule = config.schedule(steps)

    def predict_x0(z: Tensor, differentiate: bool) -> Tensor:
        counts["denoiser_grad" if differentiate and torch.is_grad_enabled() else "denoiser_cfg"] += 1
        return z * 0.5

    for i in range(steps):
        repeats = schedule.repeats_at(i)
        if repeats == 0:
            counts["denoiser_cfg"] += 1
            continue
        tt = schedule.time_travel_at(i)
        _, _, records = guided_step(torch.ones(1, 4), predict_x0=predict_x0, decode_anchors=lambda x0: x0,
                                    loss_fn=lambda frames: (frames**2).sum(), levels=VPLevels(0.5, 0.6),
                                    repeats=repeats, eta=config.eta, time_travel=tt,
                                    denoiser_grad=config.denoiser_grad, take_step=False)
        counts["updates"] += len(records)
        counts["time_travel_updates"] += len(records) if tt else 0
    return counts


def _flops(stage: dict[str, Any], kind: str | None = None) -> int:
    kinds = (kind,) if kind else ("forward", "backward")
    return sum(stage.get(k, {}).get("flops", 0) for k in kinds)


def _ops(stage: dict[str, Any]) -> int:
    return sum(stage.get(k, {}).get("ops", 0) for k in ("forward", "backward"))


def _roofline(stage: dict[str, Any], gpu: str) -> float:
    return sum(stage.get(k, {}).get("roofline_s", {}).get(gpu, 0.0) for k in ("forward", "backward"))


def whole_run_costs(unguided: dict[str, Any], guided: dict[str, Any] | None, counts: dict[str, int],
                    counts_unguided: dict[str, int]) -> dict[str, Any]:
    """Whole-run totals from the traced units and the schedule counts.

    Units: a CFG call without gradients (``denoiser_cfg``, per call, from the unguided trace), one
    guided update (every stage of the guided trace's update except its ``denoiser_cfg`` calls: the
    differentiated denoiser call, anchor decode, VGGT, UFM, loss, forward and backward), and per
    call once: ``final_decode`` and ``other`` (latents, rotary tables, scheduler step; tiny).
    """
    cfg = unguided["stages"]["denoiser_cfg"]
    cfg_calls = cfg["calls"]
    per_call = {"flops": _flops(cfg) / cfg_calls, "ops": _ops(cfg) / cfg_calls,
                "roofline_s": {gpu: _roofline(cfg, gpu) / cfg_calls for gpu in GPU_SPECS}}
    once = {s: unguided["stages"].get(s, {}) for s in ("final_decode", "other")}

    def totals(trace: dict[str, Any] | None, c: dict[str, int]) -> dict[str, Any]:
        stages: dict[str, dict[str, Any]] = {}
        stages["denoiser_cfg"] = {"count": c["denoiser_cfg"], "flops_forward": c["denoiser_cfg"] * per_call["flops"],
                                  "flops_backward": 0, "ops": c["denoiser_cfg"] * per_call["ops"],
                                  "roofline_s": {g: c["denoiser_cfg"] * per_call["roofline_s"][g] for g in GPU_SPECS}}
        if trace is not None:
            for name in ("denoiser", "anchor_decode", "vggt", "ufm", "loss"):
                s = trace["stages"].get(name, {})
                stages[name] = {"count": c["updates"], "flops_forward": c["updates"] * _flops(s, "forward"),
                                "flops_backward": c["updates"] * _flops(s, "backward"), "ops": c["updates"] * _ops(s),
                                "roofline_s": {g: c["updates"] * _roofline(s, g) for g in GPU_SPECS}}
        for name, s in once.items():
            stages[name] = {"count": 1, "flops_forward": _flops(s, "forward"), "flops_backward": _flops(s, "backward"),
                            "ops": _ops(s),
                            "roofline_s": {g: _roofline(s, g) for g in GPU_SPECS}}
        total = sum(s["flops_forward"] + s["flops_backward"] for s in stages.values())
        return {"stages": stages, "flops": total, "ops": sum(s["ops"] for s in stages.values()),
                "roofline_s": {g: sum(s["roofline_s"][g] for s in stages.values()) for g in GPU_SPECS}}

    return {"unguided": totals(None, counts_unguided), "guided": totals(guided, counts) if guided else None,
            "cfg_call": per_call}


def cost_report(settings: dict[str, Any], mode: str) -> dict[str, Any]:
    """Trace the units, count the schedule, combine; the JSON report of ``cost``."""
    start = time.perf_counter()
    unguided = trace_cost(settings, "unguided")
    guided = trace_cost(settings, mode) if mode != "unguided" else None
    counts_unguided = count_schedule_calls("unguided", settings)
    counts = count_schedule_calls(mode, settings) if mode != "unguided" else counts_unguided
    run = whole_run_costs(unguided, guided, counts, counts_unguided)
    main = guided or unguided
    weights = sum(main["weights_bytes"].values())
    calibration = settings["calibration_step_s"]
    # one efficiency for every op, from the measured unguided step on the H200
    efficiency = run["cfg_call"]["roofline_s"]["H200"] / calibration
    wall = {}
    for gpu in GPU_SPECS:
        wall[gpu] = {arm: (r["roofline_s"][gpu] / efficiency if r else None) for arm, r in
                     (("unguided", run["unguided"]), ("guided", run["guided"]))}
    per_stage = {}
    for name, s in (run["guided"] or run["unguided"])["stages"].items():
        per_stage[name] = {**{k: v for k, v in s.items() if k != "roofline_s"},
                           "flops": s["flops_forward"] + s["flops_backward"],
                           "time_s": {gpu: s["roofline_s"][gpu] / efficiency for gpu in GPU_SPECS}}
    unit = {}
    for arm, trace in (("unguided", unguided), ("guided", guided)):
        if trace is None:
            continue
        unit[arm] = {name: {kind: {k: v[k] for k in ("flops", "bytes", "ops", "peak_live_bytes")}
                            for kind, v in s.items() if kind in ("forward", "backward")} | {"calls": s["calls"]}
                     for name, s in trace["stages"].items()}
    flops_u, flops_g = run["unguided"]["flops"], (run["guided"] or run["unguided"])["flops"]
    report = {
        "subcommand": "cost",
        "argv": sys.argv[1:],
        "mode": mode,
        "settings": settings,
        "flops_unguided": flops_u,
        "flops_guided": flops_g if guided else None,
        "flops_ratio_guided_over_unguided": flops_g / flops_u if guided else None,
        "ops_unguided": run["unguided"]["ops"],
        "ops_guided": run["guided"]["ops"] if guided else None,
        "ops_ratio_guided_over_unguided": run["guided"]["ops"] / run["unguided"]["ops"] if guided else None,
        "peak_memory_gb": (weights + main["peak_live_bytes"]) / GIB,
        "peak_memory_gb_unguided": (sum(unguided["weights_bytes"].values()) + unguided["peak_live_bytes"]) / GIB,
        "peak_at": main["peak_at"],
        "weights_gb": {k: v / GIB for k, v in main["weights_bytes"].items()},
        "activations_peak_gb": main["peak_live_bytes"] / GIB,
        "per_stage": per_stage,
        "counts": counts,
        "unit_traces": unit,
        "roofline": {
            "gpus": GPU_SPECS,
            "efficiency": efficiency,
            "efficiency_note": (f"one efficiency for all ops: the roofline time of one unguided CFG call on the "
                                f"H200 over the measured {calibration} s (docs/benchmarks/sampling_full_h200_*.json)"),
            "roofline_s_at_peak": {gpu: {arm: (r["roofline_s"][gpu] if r else None) for arm, r in
                                         (("unguided", run["unguided"]), ("guided", run["guided"]))} for gpu in GPU_SPECS},
            "wall_time_s": wall,
            "ratio_guided_over_unguided": {gpu: (wall[gpu]["guided"] / wall[gpu]["unguided"] if guided else None)
                                           for gpu in GPU_SPECS},
        },
        "trace_s": {"unguided": unguided["trace_s"], "guided": guided["trace_s"] if guided else None},
        "elapsed_s": time.perf_counter() - start,
        "environment": environment_info(torch.get_num_threads()),
    }
    return report


#: Measured breakdown keys (``sampling`` JSON) of each cost stage; the denoiser's calls with and
#: without gradients are one measured stage.
MEASURED_STAGES: dict[str, tuple[str, ...]] = {
    "denoiser": ("denoiser_forward_s", "denoiser_backward_s"),
    "anchor_decode": ("vae_slice_decode_forward_s", "vae_slice_decode_backward_s"),
    "vggt": ("vggt_forward_s", "vggt_backward_s"),
    "ufm": ("ufm_forward_s", "ufm_backward_s"),
    "loss": ("loss_s",),
    "final_decode": ("vae_final_decode_s",),
}


def compare_with_measured(report: dict[str, Any], measured_path: str, gpu: str = "H200") -> dict[str, Any]:
    """Predicted vs measured: a ``sampling`` report of the same mode on ``gpu`` (times extrapolated to
    the nominal run when the run was shorter). Stage times: the measured breakdown's seconds per
    stage (forward + backward; the harness's forward of a checkpointed decode includes its
    recomputation, so the measured stage sums can exceed the measured updates a little)."""
    measured = json.loads(Path(measured_path).read_text())
    ext = measured.get("extrapolated_to_nominal") or {}
    walls = ext.get("wall_time_s") or measured["wall_time_s"]
    breakdown = ext.get("breakdown") or measured["breakdown"]
    predicted_wall = report["roofline"]["wall_time_s"][gpu]
    stages = {}
    for name, keys in MEASURED_STAGES.items():
        parts = ("denoiser_cfg", "denoiser") if name == "denoiser" else (name,)
        predicted = sum(report["per_stage"][p]["time_s"][gpu] for p in parts if p in report["per_stage"])
        stages[name] = {"predicted_s": predicted, "measured_s": sum(breakdown.get(k, 0.0) for k in keys)}
    return {
        "measured_json": measured_path,
        "gpu": gpu,
        "wall_time_s": {"predicted": predicted_wall, "measured": walls},
        "ratio_guided_over_unguided": {"predicted": report["roofline"]["ratio_guided_over_unguided"][gpu],
                                       "measured": measured.get("ratio_guided_over_unguided")},
        "peak_memory_gb": {"predicted": report["peak_memory_gb"], "measured": measured["peak_memory_gb"]},
        "peak_memory_gb_unguided": {"predicted": report["peak_memory_gb_unguided"],
                                    "measured": measured.get("peak_memory_gb_unguided")},
        "stages": stages,
    }


def cost_table(report: dict[str, Any]) -> str:
    """Markdown: per stage FLOPs and predicted seconds on the GPUs, then the run's totals."""
    lines = ["| stage | count | TFLOP forward | TFLOP backward | TFLOP total | share | "
             + " | ".join(f"{g} (s)" for g in GPU_SPECS) + " |",
             "|---|---|---|---|---|---|" + "---|" * len(GPU_SPECS)]
    total = sum(s["flops"] for s in report["per_stage"].values()) or 1
    for name, s in report["per_stage"].items():
        lines.append(f"| {name} | {s['count']} | {s['flops_forward'] / 1e12:.1f} | {s['flops_backward'] / 1e12:.1f} | "
                     f"{s['flops'] / 1e12:.1f} | {100 * s['flops'] / total:.1f} % | "
                     + " | ".join(f"{s['time_s'][g]:.1f}" for g in GPU_SPECS) + " |")
    ratio = report["flops_ratio_guided_over_unguided"]
    wall = report["roofline"]["wall_time_s"]
    lines.append("")
    lines.append(f"mode {report['mode']}: FLOPs unguided {report['flops_unguided'] / 1e15:.2f} PFLOP"
                 + (f", guided {report['flops_guided'] / 1e15:.2f} PFLOP, ratio {ratio:.2f}" if ratio else ""))
    lines.append(f"peak memory {report['peak_memory_gb']:.1f} GiB (at {report['peak_at']}; weights "
                 f"{sum(report['weights_gb'].values()):.1f} GiB), unguided {report['peak_memory_gb_unguided']:.1f} GiB")
    if report["ops_ratio_guided_over_unguided"]:
        lines.append(f"ATen ops: unguided {report['ops_unguided']:.0f}, guided {report['ops_guided']:.0f}, "
                     f"ratio {report['ops_ratio_guided_over_unguided']:.1f} (what a launch-bound device pays for)")
    if report["settings"]["preset"] == "tiny":
        return "\n".join(lines)  # the calibration is a full-size measurement: no GPU times for tiny models
    validation = report.get("validation")
    if validation:
        v = validation
        lines.append(f"vs measured ({v['measured_json']}): ratio {v['ratio_guided_over_unguided']['predicted']:.2f} "
                     f"predicted / {v['ratio_guided_over_unguided']['measured']:.2f} measured; peak "
                     f"{v['peak_memory_gb']['predicted']:.1f} / {v['peak_memory_gb']['measured']:.1f} GiB; "
                     + ", ".join(f"{k} {x['predicted_s']:.0f} / {x['measured_s']:.0f} s" for k, x in v["stages"].items()))
    for gpu in GPU_SPECS:
        g = wall[gpu]["guided"]
        lines.append(f"{gpu}: unguided {wall[gpu]['unguided']:.0f} s" + (f", guided {g:.0f} s" if g else "")
                     + f" (efficiency {report['roofline']['efficiency']:.2f})")
    return "\n".join(lines)


def run_cost(args: argparse.Namespace) -> None:
    from geco_guide.sampler.schedule import PAPER_REPEATS, PAPER_TIME_TRAVEL

    if args.threads:
        torch.set_num_threads(args.threads)
    if args.preset == "tiny":
        from geco_guide.tiny import (
            TINY_HEIGHT,
            TINY_NUM_FRAMES,
            TINY_WIDTH,
            tiny_guidance_config,
        )

        video = {"frames": TINY_NUM_FRAMES, "height": TINY_HEIGHT, "width": TINY_WIDTH}
        base = tiny_guidance_config()
        repeats, time_travel, dtype = base.repeats, base.time_travel, args.dtype or "float32"
        steps = 4 if args.steps is None else args.steps
        if args.paper_schedule:
            repeats, time_travel = PAPER_REPEATS, list(PAPER_TIME_TRAVEL)
            steps = NOMINAL_STEPS if args.steps is None else args.steps
    else:
        video = dict(FULL_SIZE_VIDEO)
        repeats, time_travel = PAPER_REPEATS, list(PAPER_TIME_TRAVEL)
        steps, dtype = NOMINAL_STEPS if args.steps is None else args.steps, args.dtype or "bfloat16"
    if steps < 1:
        raise SystemExit(f"--steps must be >= 1, got {steps}")
    video.update({k: getattr(args, k) for k in ("frames", "height", "width") if getattr(args, k) is not None})
    settings = {"preset": args.preset, **video, "dtype": dtype, "steps": steps, "repeats": repeats,
                "time_travel": None if args.no_time_travel else time_travel, "seed": args.seed,
                "chunk_latents": args.chunk_latents,
                "vae_checkpointing": None if args.vae_checkpointing is None else args.vae_checkpointing == "on",
                "denoiser_checkpointing": None if args.denoiser_checkpointing is None else args.denoiser_checkpointing == "on",
                "estimator_checkpointing": args.estimator_checkpointing, "vae_tiling": args.vae_tiling,
                "calibration_step_s": args.calibration_step_s, "guidance_scale": 6.0,
                "note": "shape-only: fake tensors (FakeTensorMode), no weights; estimator trunks in dtype, heads float32"}
    report = cost_report(settings, args.mode)
    if args.measured:
        report["validation"] = compare_with_measured(report, args.measured)
    print(cost_table(report))
    if args.json:
        path = Path(args.json)
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_text(json.dumps(report, indent=2) + "\n")


# ----------------------------------------------------------------------------------------------
# GeCo-Eval: what scoring one video costs under each pair mode
# ----------------------------------------------------------------------------------------------

#: The H200 sampling run whose estimator calls give the per-call times of the full-size estimate.
H200_FAST_RUN = Path(__file__).resolve().parents[1] / "docs" / "benchmarks" / "sampling_full_h200_fast.json"


def _counting(estimator: Any, method: str, counts: dict[str, int], calls: str, items: str, dim: int) -> None:
    """Count ``estimator.method``'s calls and the size of its first argument along ``dim``."""
    original = getattr(estimator, method)

    def wrapper(first: Tensor, *args: Any, **kwargs: Any) -> Any:
        counts[calls] += 1
        counts[items] += first.shape[dim]
        return original(first, *args, **kwargs)

    setattr(estimator, method, wrapper)


def geco_eval_cost(args: argparse.Namespace) -> dict[str, Any]:
    """Score one random clip of ``args.frames`` frames at ``args.fps`` with the tiny estimators
    under each pair mode (estimator calls counted, wall time measured), and scale the counts to
    VGGT-1B / UFM-Base on an H200 with per-call times of the measured full-size sampling run."""
    from geco_guide.config import load_config
    from geco_guide.estimators import load_estimators
    from geco_guide.metric.evaluate import evaluate_video

    if args.threads:
        torch.set_num_threads(args.threads)
    video = torch.rand(args.frames, 3, args.height, args.width, generator=torch.Generator().manual_seed(args.seed))
    geometry, flow = load_estimators(load_config(preset="tiny").estimators, "cpu")
    counts = {"vggt_calls": 0, "vggt_frames": 0, "ufm_calls": 0, "ufm_pairs": 0}
    _counting(geometry, "estimate_geometry", counts, "vggt_calls", "vggt_frames", dim=1)
    _counting(flow, "estimate_flow", counts, "ufm_calls", "ufm_pairs", dim=0)
    h200 = json.loads(H200_FAST_RUN.read_text())["arms"]["guided"]
    seconds, calls = h200["profile"]["seconds"], h200["profile"]["counts"]
    # guidance's UFM call holds the anchors' adjacent pairs, its VGGT call the anchors
    anchors = len(h200["guidance"]["anchors"])
    ufm_pair_s = seconds["ufm/forward/update"] / (calls["ufm/forward/update"] * (anchors - 1))
    vggt_frame_s = seconds["vggt/forward/update"] / (calls["vggt/forward/update"] * anchors)
    modes = {}
    for pairs in args.pairs:
        cfg = load_config(preset="tiny", overrides=[f"evaluation.loss.pairs={pairs}"])
        evaluate_video(video, geometry=geometry, flow=flow, config=cfg, fps=args.fps)  # warm-up
        counts.update(dict.fromkeys(counts, 0))
        start = time.perf_counter()
        result = evaluate_video(video, geometry=geometry, flow=flow, config=cfg, fps=args.fps)
        wall = time.perf_counter() - start
        estimate = counts["ufm_pairs"] * ufm_pair_s + counts["vggt_frames"] * vggt_frame_s
        modes[pairs] = {**counts, "windows": len(result.windows), "tiny_cpu_wall_s": wall,
                        "h200_estimate_s": estimate, "h200_estimate_suite_h": estimate * args.videos / 3600}
    return {
        "subcommand": "geco-eval", "argv": sys.argv[1:], "environment": environment_info(torch.get_num_threads()),
        "clip": {"frames": args.frames, "fps": args.fps, "height": args.height, "width": args.width},
        "videos_per_model": args.videos, "modes": modes,
        "h200_per_call": {"ufm_pair_s": ufm_pair_s, "vggt_frame_s": vggt_frame_s, "source": H200_FAST_RUN.name},
        "estimate_note": ("UFM's network runs at a fixed working resolution whatever the input size, so its "
                          "per-pair time from the H200 guidance run (forward with autograd bookkeeping) "
                          "applies; VGGT is scaled per frame from 4-frame calls, a lower bound for 24-frame "
                          "windows (its global attention grows with the square of the frames). Generation "
                          "not included."),
    }


def run_geco_eval_cost(args: argparse.Namespace) -> None:
    report = geco_eval_cost(args)
    header = "| pairs | windows | VGGT calls (frames) | UFM calls (pairs) | tiny CPU wall (s) | H200 estimate per video (s) | per model, {} videos (h) |"
    lines = [header.format(report["videos_per_model"]), "|---|---|---|---|---|---|---|"]
    for pairs, m in report["modes"].items():
        lines.append(f"| {pairs} | {m['windows']} | {m['vggt_calls']} ({m['vggt_frames']}) | {m['ufm_calls']} "
                     f"({m['ufm_pairs']}) | {m['tiny_cpu_wall_s']:.3g} | {m['h200_estimate_s']:.3g} | "
                     f"{m['h200_estimate_suite_h']:.3g} |")
    print("\n".join(lines))
    if args.json:
        path = Path(args.json)
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_text(json.dumps(report, indent=2) + "\n")


# ----------------------------------------------------------------------------------------------
# Subcommands
# ----------------------------------------------------------------------------------------------


def common_spec(args: argparse.Namespace) -> dict[str, Any]:
    """Options every case shares."""
    return {"device": args.device, "threads": args.threads, "warmup": args.warmup,
            "repeats": args.repeats, "seed": args.seed, "rss_exact": args.rss_exact}


def loss_specs(args: argparse.Namespace) -> list[dict[str, Any]]:
    """Cases of ``loss``: the GeCo loss core, forward and forward+backward."""
    base = {**common_spec(args), "workload": "loss", "case": "geco_from_geometry",
            "frames": args.frames, "height": args.height, "width": args.width, "pairs": args.pairs}
    return [{**base, "mode": mode} for mode in MODES]


def vae_specs(args: argparse.Namespace) -> list[dict[str, Any]]:
    """Cases of ``vae``: the anchor-chunk decode, forward and forward+backward."""
    base = {**common_spec(args), "workload": "vae", "case": f"vae-{args.size}", "size": args.size,
            "frames": args.frames, "height": args.height, "width": args.width, "dtype": args.dtype,
            "vae_checkpointing": args.vae_checkpointing, "vae_tiling": args.vae_tiling}
    return [{**base, "mode": mode} for mode in MODES]


def estimator_specs(args: argparse.Namespace) -> list[dict[str, Any]]:
    """Cases of ``estimators``: VGGT and UFM per size, forward and forward+backward."""
    sizes = ("tiny", "full") if args.size == "both" else (args.size,)
    base = {**common_spec(args), "frames": args.frames, "height": args.height, "width": args.width,
            "dtype": args.dtype}
    return [
        {**base, "workload": model, "case": f"{model}-{size}", "size": size, "mode": mode}
        for size in sizes for model in ("vggt", "ufm") for mode in MODES
    ]


def _add_common_options(parser: argparse.ArgumentParser, repeats: int) -> None:
    parser.add_argument("--device", default="cpu", help="torch device, e.g. cpu or cuda (default: cpu)")
    parser.add_argument("--threads", type=int, default=None,
                        help="torch.set_num_threads in every case (default: torch's default)")
    parser.add_argument("--warmup", type=int, default=1, help="untimed runs before timing (default: 1)")
    parser.add_argument("--repeats", type=int, default=repeats, help=f"timed runs (default: {repeats})")
    parser.add_argument("--seed", type=int, default=0, help="seed of weights and inputs (default: 0)")
    parser.add_argument("--json", metavar="PATH", help="also write the results as JSON to PATH")
    _add_rss_exact_option(parser)


def _add_rss_exact_option(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--rss-exact", action="store_true",
                        help="CPU memory: run the workers with glibc's MALLOC_MMAP_THRESHOLD_="
                             f"{RSS_EXACT_MMAP_THRESHOLD}, so that freed tensors leave the resident set at once "
                             "and peak RSS follows the live tensors (slower: every allocation maps fresh pages)")


def _frame_count(value: str) -> int:
    """argparse type of ``--frames``: GeCo and UFM need at least one pair."""
    frames = int(value)
    if frames < 2:
        raise argparse.ArgumentTypeError(f"needs at least 2 frames, got {frames}")
    return frames


def build_parser() -> argparse.ArgumentParser:
    """The CLI: ``loss``, ``estimators`` and the internal ``worker`` subcommand."""
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    sub = parser.add_subparsers(dest="command", required=True)

    loss = sub.add_parser("loss", help="GeCo loss core (geco_from_geometry) forward / forward+backward")
    loss.add_argument("--frames", type=_frame_count, default=4, help="frames S (default: 4)")
    loss.add_argument("--height", type=int, default=480, help="frame height (default: 480)")
    loss.add_argument("--width", type=int, default=720, help="frame width (default: 720)")
    loss.add_argument("--pairs", choices=PAIR_MODES, default="adjacent", help="frame pairs (default: adjacent)")
    _add_common_options(loss, repeats=3)
    loss.set_defaults(specs=loss_specs)

    est = sub.add_parser("estimators", help="VGGT and UFM forward / forward+backward w.r.t. the frames")
    est.add_argument("--size", choices=("tiny", "full", "both"), default="tiny",
                     help="tiny configs, the VGGT-1B / UFM-Base architectures (random weights), or both")
    est.add_argument("--frames", type=_frame_count, default=2,
                     help="frames S; UFM gets the S - 1 adjacent pairs (default: 2)")
    est.add_argument("--height", type=int, default=140, help="input frame height (default: 140)")
    est.add_argument("--width", type=int, default=210, help="input frame width (default: 210)")
    est.add_argument("--dtype", choices=("float32", "bfloat16"), default="float32",
                     help="storage dtype of the ViT trunks (trunk_to); heads stay float32 (default: float32)")
    _add_common_options(est, repeats=3)
    est.set_defaults(specs=estimator_specs)

    vae = sub.add_parser("vae", help="the anchor-chunk VAE decode of one guided update, forward / forward+backward")
    vae.add_argument("--size", choices=("tiny", "full"), default="tiny",
                     help="the tiny VAE or the CogVideoX-5B VAE architecture (random weights)")
    vae.add_argument("--frames", type=int, default=49, help="video frames 4k+1, anchors spread as in sampling (default: 49)")
    vae.add_argument("--height", type=int, default=480, help="video height, a multiple of 8 (default: 480)")
    vae.add_argument("--width", type=int, default=720, help="video width, a multiple of 8 (default: 720)")
    vae.add_argument("--dtype", choices=("float32", "bfloat16"), default="bfloat16",
                     help="VAE dtype (default: bfloat16, as the pipeline on a GPU)")
    vae.add_argument("--vae-checkpointing", action="store_true",
                     help="guidance.vae_checkpointing: one checkpointed decode per chunk, and the VAE's own "
                          "block checkpointing inside")
    vae.add_argument("--vae-tiling", action="store_true",
                     help="vae.enable_tiling with tiles of half the video size, as at 480x720")
    _add_common_options(vae, repeats=1)
    vae.set_defaults(specs=vae_specs)

    samp = sub.add_parser("sampling", help="guided vs unguided CogVideoX sampling, same seed, per-stage breakdown")
    size = samp.add_mutually_exclusive_group()
    size.add_argument("--preset", choices=("tiny",), default="tiny",
                      help="tiny random models (default; 17 frames of 32x48, runs anywhere)")
    size.add_argument("--full-size", action="store_true",
                      help="CogVideoX-5B transformer + VAE, VGGT-1B, UFM-Base with random weights, 49x480x720")
    samp.add_argument("--mode", choices=SAMPLING_MODES, default="faithful",
                      help="faithful: backprop through the denoiser (paper); fast: denoiser output held "
                           "constant; unguided: only the unguided arm (default: faithful)")
    samp.add_argument("--steps", type=int, default=None,
                      help=f"denoising steps run (default {NOMINAL_STEPS}); fewer compress the paper schedule "
                           f"and extrapolate the times to {NOMINAL_STEPS} steps")
    samp.add_argument("--frames", type=int, default=None, help="frames (default: 17 tiny, 49 full size)")
    samp.add_argument("--height", type=int, default=None, help="height (default: 32 tiny, 480 full size)")
    samp.add_argument("--width", type=int, default=None, help="width (default: 48 tiny, 720 full size)")
    samp.add_argument("--dtype", choices=("bfloat16", "float32"), default=None,
                      help="transformer/VAE dtype; estimators autocast to it (default: bfloat16 for full size "
                           "on CUDA, else float32)")
    samp.add_argument("--estimator-checkpointing", action="store_true",
                      help="gradient checkpointing in VGGT and UFM (less memory, more backward time)")
    samp.add_argument("--vae-tiling", action="store_true",
                      help="full size: the VAE's spatial tiles (generate's model.vae_tiling), both arms")
    samp.add_argument("--chunk-latents", type=int, default=None,
                      help="latents per anchor chunk (default: the paper's 3; 2 decodes 5 frames per anchor instead of 9)")
    samp.add_argument("--no-denoiser-checkpointing", action="store_true",
                      help="faithful mode: backpropagate through the transformer without gradient checkpointing "
                           "(guidance.gradient_checkpointing=false: one forward less per update, more memory)")
    samp.add_argument("--allow-cpu", action="store_true",
                      help="allow --full-size on CPU (the weights alone are ~30 GiB in float32)")
    samp.add_argument("--device", default="cpu", help="torch device, e.g. cpu or cuda (default: cpu)")
    samp.add_argument("--threads", type=int, default=None, help="torch.set_num_threads in both arms")
    samp.add_argument("--warmup", type=int, default=1,
                      help="untimed 2-step calls of the same arm before the timed one (default: 1)")
    samp.add_argument("--seed", type=int, default=0, help="seed of weights, text embeddings and noise (default: 0)")
    samp.add_argument("--json", metavar="PATH", help="also write the report as JSON to PATH")
    _add_rss_exact_option(samp)

    cost = sub.add_parser("cost", help="FLOPs, memory and a roofline time of sampling at full size, on fake tensors "
                                       "(no weights, no GPU)")
    cost.add_argument("--preset", choices=("full", "tiny"), default="full",
                      help="full: CogVideoX-5B, VGGT-1B, UFM-Base at 49x480x720 (default); tiny: the tiny pipeline")
    cost.add_argument("--mode", choices=SAMPLING_MODES, default="faithful",
                      help="guided mode to model beside the unguided run (default: faithful)")
    cost.add_argument("--steps", type=int, default=None, help="denoising steps (default: 50 full, 4 tiny)")
    cost.add_argument("--frames", type=int, default=None, help="frames (default: 49 full, 17 tiny)")
    cost.add_argument("--height", type=int, default=None, help="height (default: 480 full, 32 tiny)")
    cost.add_argument("--width", type=int, default=None, help="width (default: 720 full, 48 tiny)")
    cost.add_argument("--dtype", choices=("bfloat16", "float32"), default=None,
                      help="transformer/VAE dtype and the estimators' trunks (default: bfloat16 full, float32 tiny)")
    cost.add_argument("--chunk-latents", type=int, default=None, help="latents per anchor chunk (default: the preset's)")
    cost.add_argument("--vae-checkpointing", choices=("on", "off"), default=None,
                      help="guidance.vae_checkpointing (default: the preset's: on full, off tiny)")
    cost.add_argument("--denoiser-checkpointing", choices=("on", "off"), default=None,
                      help="guidance.gradient_checkpointing (default: the preset's: on full, off tiny)")
    cost.add_argument("--estimator-checkpointing", action="store_true", help="VGGT and UFM gradient checkpointing")
    cost.add_argument("--vae-tiling", action="store_true", help="the VAE's spatial tiles (model.vae_tiling)")
    cost.add_argument("--no-time-travel", action="store_true", help="the schedule without its time-travel window")
    cost.add_argument("--paper-schedule", action="store_true",
                      help="tiny preset: the paper's 50-step schedule instead of the tiny 4-step one (as `sampling`)")
    cost.add_argument("--calibration-step-s", type=float, default=H200_UNGUIDED_STEP_S,
                      help=f"measured seconds of one unguided CFG step on the H200 (default {H200_UNGUIDED_STEP_S})")
    cost.add_argument("--measured", metavar="JSON",
                      help="a `sampling` report of the same settings on an H200: add predicted vs measured")
    cost.add_argument("--threads", type=int, default=None, help="torch.set_num_threads")
    cost.add_argument("--seed", type=int, default=0, help="seed (shapes only; default: 0)")
    cost.add_argument("--json", metavar="PATH", help="also write the report as JSON to PATH")

    geval = sub.add_parser("geco-eval", help="estimator calls and time of scoring one video under each pair mode "
                                             "(tiny on CPU, estimated at full size on an H200)")
    geval.add_argument("--frames", type=int, default=49, help="frames of the clip (default: 49, CogVideoX)")
    geval.add_argument("--fps", type=float, default=16.0, help="its native frame rate (default: 16, CogVideoX)")
    geval.add_argument("--height", type=int, default=32, help="height of the tiny run (default: 32)")
    geval.add_argument("--width", type=int, default=48, help="width of the tiny run (default: 48)")
    geval.add_argument("--pairs", nargs="+", choices=PAIR_MODES, default=["all", "center", "adjacent"])
    geval.add_argument("--videos", type=int, default=320, help="videos per model (default: 320 = 80 prompts x 4 seeds)")
    geval.add_argument("--threads", type=int, default=None, help="torch.set_num_threads")
    geval.add_argument("--seed", type=int, default=0, help="seed of the random clip (default: 0)")
    geval.add_argument("--json", metavar="PATH", help="also write the report as JSON to PATH")

    worker = sub.add_parser("worker", help="internal: run one case given as JSON, print its result as JSON")
    worker.add_argument("spec")
    return parser


def main(argv: Sequence[str] | None = None) -> None:
    args = build_parser().parse_args(argv)
    if args.command == "worker":
        spec = json.loads(args.spec)
        print(json.dumps(run_sampling_worker(spec) if spec["workload"] == "sampling" else run_worker(spec)))
    elif args.command == "sampling":
        run_sampling(args)
    elif args.command == "cost":
        run_cost(args)
    elif args.command == "geco-eval":
        run_geco_eval_cost(args)
    else:
        run_and_report(args.command, args.specs(args), args.json)


if __name__ == "__main__":
    main()
