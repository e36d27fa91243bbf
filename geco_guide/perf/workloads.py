"""What one micro-benchmark case runs: the timed step of a workload, and the worker that times it.

A workload builder takes the case's spec (``frames``, ``height``, ``width``, ``mode``, ``seed``,
...) and a device and returns a :class:`Workload`: a step to time and the facts worth reporting.
:func:`run_worker` builds one and times it in the current process, which the harness starts fresh
for each case (:func:`~.measure.run_case_subprocess`) so that the peaks are the case's own.
"""

from __future__ import annotations

import os
import time
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from functools import partial
from typing import Any

import torch
from torch import Tensor

from ..estimators.ufm import UFM, UFMConfig, choose_resolution
from ..estimators.vggt import VGGT, VGGTConfig, plan_preprocess
from ..families import default_anchors
from ..sampler.algorithm.slicing import (
    anchor_latent_chunks,
    decode_anchor_frames,
    decode_chunk,
)
from .full_size import full_size_vae
from .geometry_backbones import geometry_model, network_hw
from .measure import (
    MIB,
    current_memory_bytes,
    memory_kind,
    peak_memory_bytes,
    reset_peak_memory,
    synchronize,
    time_callable,
)

__all__ = ["WORKLOADS", "Workload", "estimator_specs", "loss_specs", "make_step", "run_worker", "vae_specs"]

MODES = ("forward", "forward_backward")


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


def random_frames(spec: dict[str, Any], device: torch.device) -> Tensor:
    """Seeded uniform frames ``[1, S, 3, H, W]`` in ``[0, 1]`` requiring grad."""
    gen = torch.Generator().manual_seed(spec["seed"])
    frames = torch.rand(1, spec["frames"], 3, spec["height"], spec["width"], generator=gen)
    return frames.to(device).requires_grad_()


def num_params(model: torch.nn.Module) -> float:
    """Parameter count in millions."""
    return sum(p.numel() for p in model.parameters()) / 1e6


def vggt_workload(spec: dict[str, Any], device: torch.device) -> Workload:
    """``VGGT.estimate_geometry`` on ``[1, S, 3, H, W]``; the scalar sums the means of depth,
    confidence, K and extrinsics so backward runs through the depth and camera heads."""
    config = VGGTConfig.tiny() if spec["size"] == "tiny" else VGGTConfig()
    model = VGGT.random(config, seed=spec["seed"]).trunk_to(getattr(torch, spec["dtype"])).to(device)
    frames = random_frames(spec, device)

    def scalar() -> Tensor:
        geometry = model.estimate_geometry(frames)
        outputs = (geometry.depth, geometry.confidence, geometry.intrinsics, geometry.extrinsics)
        return sum(t.mean() for t in outputs)

    plan = plan_preprocess(spec["height"], spec["width"], config.img_size, config.patch_size)
    info = {"input": "x".join(map(str, frames.shape)), "network": "{}x{}".format(*plan.network_hw),
            "params_m": num_params(model), "dtype": spec["dtype"]}
    return Workload(make_step(spec["mode"], scalar, [frames]), info)


def da3_workload(spec: dict[str, Any], device: torch.device) -> Workload:
    """``DA3.estimate_geometry`` of ``spec["geometry"]`` (DA3-SMALL or DA3-BASE; ``tiny``: the
    tiny DA3) on ``[1, S, 3, H, W]``; the scalar as VGGT's."""
    model = geometry_model(spec["geometry"], spec["size"], spec["seed"]).trunk_to(getattr(torch, spec["dtype"]))
    model = model.to(device)
    frames = random_frames(spec, device)

    def scalar() -> Tensor:
        geometry = model.estimate_geometry(frames)
        return sum(t.mean() for t in (geometry.depth, geometry.confidence, geometry.intrinsics, geometry.extrinsics))

    info = {"input": "x".join(map(str, frames.shape)),
            "network": "{}x{}".format(*network_hw(model, spec["height"], spec["width"])),
            "params_m": num_params(model), "dtype": spec["dtype"]}
    return Workload(make_step(spec["mode"], scalar, [frames]), info)


def ufm_workload(spec: dict[str, Any], device: torch.device) -> Workload:
    """``UFM.estimate_flow`` on the ``S - 1`` adjacent pairs of ``[1, S, 3, H, W]`` in one batch;
    the scalar is mean flow + mean covisibility. Weights: ``UFM.random(config, seed)``."""
    config = UFMConfig.tiny() if spec["size"] == "tiny" else UFMConfig()
    model = UFM.random(config, seed=spec["seed"]).trunk_to(getattr(torch, spec["dtype"])).to(device)
    frames = random_frames(spec, device)

    def scalar() -> Tensor:
        source, target = frames[0, :-1], frames[0, 1:]
        correspondences = model.estimate_flow(source, target)
        return correspondences.flow.mean() + correspondences.covisibility.mean()

    hw = (spec["height"], spec["width"])
    info = {"input": f"{spec['frames'] - 1} pair(s) {hw[0]}x{hw[1]}",
            "network": "{}x{}".format(*choose_resolution(config.inference_resolution, hw, hw)),
            "params_m": num_params(model), "dtype": spec["dtype"]}
    return Workload(make_step(spec["mode"], scalar, [frames]), info)


def tiles_like_full_size(height: int, width: int) -> dict[str, Any]:
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
    dtype = getattr(torch, spec["dtype"])
    if spec["size"] == "tiny":
        from ..tiny import tiny_cogvideox_components

        vae = tiny_cogvideox_components(spec["seed"])["vae"].to(device=device, dtype=dtype)
    else:
        vae = full_size_vae(device, dtype, spec["seed"])
    vae.requires_grad_(False)
    if spec["vae_checkpointing"]:
        vae.enable_gradient_checkpointing()
    if spec["vae_tiling"]:
        vae.enable_tiling(**tiles_like_full_size(spec["height"], spec["width"]))
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
            "params_m": num_params(vae), "dtype": spec["dtype"],
            "checkpointing": spec["vae_checkpointing"], "tiling": spec["vae_tiling"]}
    return Workload(make_step(spec["mode"], scalar, [latents]), info)


WorkloadBuilder = Callable[[dict[str, Any], torch.device], Workload]

#: The package's workloads by ``spec["workload"]``; the benchmark CLI adds its own.
WORKLOADS: dict[str, WorkloadBuilder] = {
    "vggt": vggt_workload,
    "da3": da3_workload,
    "ufm": ufm_workload,
    "vae": vae_workload,
}


def run_worker(spec: dict[str, Any], workloads: Mapping[str, WorkloadBuilder] = WORKLOADS) -> dict[str, Any]:
    """Build and time one case in this process; memory figures are this process's peaks."""
    device = torch.device(spec["device"])
    if spec["threads"]:
        torch.set_num_threads(spec["threads"])
    torch.manual_seed(spec["seed"])
    baseline = peak_memory_bytes(device)
    start = time.perf_counter()
    workload = workloads[spec["workload"]](spec, device)
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


# ---- the cases of each micro-benchmark subcommand (from its parsed options) ----------------------


def common_spec(args: Any) -> dict[str, Any]:
    """Options every case shares."""
    return {"device": args.device, "threads": args.threads, "warmup": args.warmup,
            "repeats": args.repeats, "seed": args.seed, "rss_exact": args.rss_exact}


def loss_specs(args: Any) -> list[dict[str, Any]]:
    """Cases of ``loss``: the GeCo loss core, forward and forward+backward."""
    base = {**common_spec(args), "workload": "loss", "case": "geco_from_geometry",
            "frames": args.frames, "height": args.height, "width": args.width, "pairs": args.pairs}
    return [{**base, "mode": mode} for mode in MODES]


def vae_specs(args: Any) -> list[dict[str, Any]]:
    """Cases of ``vae``: the anchor-chunk decode, forward and forward+backward."""
    base = {**common_spec(args), "workload": "vae", "case": f"vae-{args.size}", "size": args.size,
            "frames": args.frames, "height": args.height, "width": args.width, "dtype": args.dtype,
            "vae_checkpointing": args.vae_checkpointing, "vae_tiling": args.vae_tiling}
    return [{**base, "mode": mode} for mode in MODES]


def estimator_specs(args: Any) -> list[dict[str, Any]]:
    """Cases of ``estimators``: the geometry backbone (``args.geometry_estimator``: VGGT-1B,
    cases ``vggt-<size>``, or DA3, cases ``da3-small-<size>`` / ``da3-base-<size>``) and UFM per
    size, forward and forward+backward."""
    sizes = ("tiny", "full") if args.size == "both" else (args.size,)
    base = {**common_spec(args), "frames": args.frames, "height": args.height, "width": args.width,
            "dtype": args.dtype}
    geometry = args.geometry_estimator
    models = {"vggt": {}} if geometry == "vggt-1b" else {geometry: {"workload": "da3", "geometry": geometry}}
    return [
        {**base, "workload": model, **models.get(model, {}), "case": f"{model}-{size}", "size": size, "mode": mode}
        for size in sizes for model in (*models, "ufm") for mode in MODES
    ]
