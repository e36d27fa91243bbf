"""Time and memory benchmarks of geco_guide.

Subcommands:

* ``loss`` — the fused GeCo loss core (:func:`geco_from_geometry`) forward and forward+backward,
  geometry and correspondences as random-but-valid leaf tensors requiring grad.
* ``estimators`` — VGGT ``estimate_geometry`` and UFM ``estimate_flow`` forward and
  forward+backward (gradient w.r.t. the input frames; parameters frozen), tiny and/or full-size
  architectures with random weights.

Every case (one workload in one mode) runs in its own subprocess (the internal ``worker``
subcommand), so peak memory is per case: ``torch.cuda.max_memory_allocated`` on a GPU, peak RSS
(``ru_maxrss``) on CPU, reported in total and as the increase over the child's post-import
baseline. Each case also records the 1-minute load average at its start and its CPU time per
wall-clock second: on a shared machine timings are only comparable at similar CPU shares.
Results are printed as a Markdown table and written as JSON with ``--json PATH``.

A new benchmark adds a workload builder to :data:`WORKLOADS` and a subcommand that lists its
cases; the timing, memory, subprocess and report utilities below are shared.

Examples::

    python scripts/benchmark.py loss --frames 4 --height 480 --width 720 --repeats 3
    python scripts/benchmark.py estimators --size both --frames 2 --height 140 --width 210
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
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable, Sequence

import torch
import torch.nn.functional as F
from torch import Tensor

from geco_guide.estimators.base import Correspondences, SceneGeometry
from geco_guide.estimators.ufm import UFM, UFMConfig, choose_resolution
from geco_guide.estimators.vggt import VGGT, VGGTConfig, plan_preprocess
from geco_guide.loss.geco import PAIR_MODES, GeCoLossConfig, frame_pairs, geco_from_geometry
from geco_guide.synthetic import default_intrinsics, orbit_cameras

MODES = ("forward", "forward_backward")
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


def memory_kind(device: torch.device) -> str:
    """What :func:`peak_memory_bytes` measures on ``device``."""
    return "cuda_max_memory_allocated" if device.type == "cuda" else "peak_rss"


def run_case_subprocess(spec: dict[str, Any]) -> dict[str, Any]:
    """Run one case in a fresh Python process (``worker`` subcommand) and return its result.

    The child prints its result as JSON on its last stdout line; a failing child raises with its
    stderr.
    """
    command = [sys.executable, str(Path(__file__).resolve()), "worker", json.dumps(spec)]
    proc = subprocess.run(command, capture_output=True, text=True)
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
    ("setup (s)", "setup_s", "{:.1f}"),
    ("median (s)", "time_median_s", "{:.4g}"),
    ("min (s)", "time_min_s", "{:.4g}"),
    ("peak mem (MiB)", "peak_mib", "{:.0f}"),
    ("after setup (MiB)", "after_setup_mib", "{:.0f}"),
    ("increase over import (MiB)", "peak_increase_mib", "{:.0f}"),
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
    model = VGGT.random(config, seed=spec["seed"]).to(device)
    frames = _random_frames(spec, device)

    def scalar() -> Tensor:
        geometry = model.estimate_geometry(frames)
        outputs = (geometry.depth, geometry.confidence, geometry.intrinsics, geometry.extrinsics)
        return sum(t.mean() for t in outputs)

    plan = plan_preprocess(spec["height"], spec["width"], config.img_size, config.patch_size)
    info = {"input": "x".join(map(str, frames.shape)), "network": "{}x{}".format(*plan.network_hw),
            "params_m": _num_params(model)}
    return Workload(make_step(spec["mode"], scalar, [frames]), info)


def ufm_workload(spec: dict[str, Any], device: torch.device) -> Workload:
    """``UFM.estimate_flow`` on the ``S - 1`` adjacent pairs of ``[1, S, 3, H, W]`` in one batch;
    the scalar is mean flow + mean covisibility. Weights: ``UFM.random(config, seed)``."""
    config = UFMConfig.tiny() if spec["size"] == "tiny" else UFMConfig()
    model = UFM.random(config, seed=spec["seed"]).to(device)
    frames = _random_frames(spec, device)

    def scalar() -> Tensor:
        source, target = frames[0, :-1], frames[0, 1:]
        correspondences = model.estimate_flow(source, target)
        return correspondences.flow.mean() + correspondences.covisibility.mean()

    hw = (spec["height"], spec["width"])
    info = {"input": f"{spec['frames'] - 1} pair(s) {hw[0]}x{hw[1]}",
            "network": "{}x{}".format(*choose_resolution(config.inference_resolution, hw, hw)),
            "params_m": _num_params(model)}
    return Workload(make_step(spec["mode"], scalar, [frames]), info)


WORKLOADS: dict[str, Callable[[dict[str, Any], torch.device], Workload]] = {
    "loss": loss_workload,
    "vggt": vggt_workload,
    "ufm": ufm_workload,
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
    load_avg_1m = os.getloadavg()[0]
    timing = time_callable(workload.step, device, spec["warmup"], spec["repeats"])
    peak = peak_memory_bytes(device)
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
        "load_avg_1m": load_avg_1m,
    }


# ----------------------------------------------------------------------------------------------
# Subcommands
# ----------------------------------------------------------------------------------------------


def common_spec(args: argparse.Namespace) -> dict[str, Any]:
    """Options every case shares."""
    return {"device": args.device, "threads": args.threads, "warmup": args.warmup,
            "repeats": args.repeats, "seed": args.seed}


def loss_specs(args: argparse.Namespace) -> list[dict[str, Any]]:
    """Cases of ``loss``: the GeCo loss core, forward and forward+backward."""
    base = {**common_spec(args), "workload": "loss", "case": "geco_from_geometry",
            "frames": args.frames, "height": args.height, "width": args.width, "pairs": args.pairs}
    return [{**base, "mode": mode} for mode in MODES]


def estimator_specs(args: argparse.Namespace) -> list[dict[str, Any]]:
    """Cases of ``estimators``: VGGT and UFM per size, forward and forward+backward."""
    sizes = ("tiny", "full") if args.size == "both" else (args.size,)
    base = {**common_spec(args), "frames": args.frames, "height": args.height, "width": args.width}
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
    _add_common_options(est, repeats=3)
    est.set_defaults(specs=estimator_specs)

    worker = sub.add_parser("worker", help="internal: run one case given as JSON, print its result as JSON")
    worker.add_argument("spec")
    return parser


def main(argv: Sequence[str] | None = None) -> None:
    args = build_parser().parse_args(argv)
    if args.command == "worker":
        print(json.dumps(run_worker(json.loads(args.spec))))
    else:
        run_and_report(args.command, args.specs(args), args.json)


if __name__ == "__main__":
    main()
