"""What scoring one video with GeCo-Eval costs under each pair mode: estimator calls counted on
the tiny estimators, and scaled to VGGT-1B / UFM-Base on an H200 with per-call times from a
measured full-size guided sampling run; another geometry backbone's per-frame time is VGGT-1B's
scaled by their FLOPs (predicted: no backbone but VGGT-1B was timed on a GPU)."""

from __future__ import annotations

import json
import time
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import torch
from torch import Tensor

from .measure import environment_info

__all__ = ["geco_eval_cost", "geco_eval_table"]


def _counting(estimator: Any, method: str, counts: dict[str, int], calls: str, items: str, dim: int) -> None:
    """Count ``estimator.method``'s calls and the size of its first argument along ``dim``."""
    original = getattr(estimator, method)

    def wrapper(first: Tensor, *args: Any, **kwargs: Any) -> Any:
        counts[calls] += 1
        counts[items] += first.shape[dim]
        return original(first, *args, **kwargs)

    setattr(estimator, method, wrapper)


def geco_eval_cost(*, frames: int, fps: float, height: int, width: int, pairs: Sequence[str], videos: int,
                   seed: int, h200_run: str | Path, argv: Sequence[str] = (), geometry: str = "vggt-1b") -> dict[str, Any]:
    """Score one random clip ``[frames, 3, height, width]`` at ``fps`` with the tiny estimators
    under each pair mode of ``pairs`` (estimator calls counted, wall time measured), and scale the
    counts to the ``geometry`` backbone (``vggt-1b``, ``da3-small``, ``da3-base``) and UFM-Base on
    an H200 with per-call times of the measured full-size guided sampling run ``h200_run`` (a
    ``sampling`` JSON report; a DA3 backbone's per-frame time is VGGT-1B's times their forward
    FLOPs' ratio on the run's anchors, :func:`~.geometry_backbones.geometry_flops`); ``videos`` per
    model for the suite."""
    from .geometry_backbones import geometry_flops
    from ..config import load_config
    from ..estimators import load_estimators
    from ..metric.evaluate import evaluate_video

    video = torch.rand(frames, 3, height, width, generator=torch.Generator().manual_seed(seed))
    estimators = load_estimators(load_config(preset="tiny").estimators, "cpu")
    counts = {"vggt_calls": 0, "vggt_frames": 0, "ufm_calls": 0, "ufm_pairs": 0}
    _counting(estimators.geometry, "estimate_geometry", counts, "vggt_calls", "vggt_frames", dim=1)
    _counting(estimators.flow, "estimate_flow", counts, "ufm_calls", "ufm_pairs", dim=0)
    h200 = json.loads(Path(h200_run).read_text())["arms"]["guided"]
    seconds, calls = h200["profile"]["seconds"], h200["profile"]["counts"]
    # guidance's UFM call holds the anchors' adjacent pairs, its VGGT call the anchors
    anchors = len(h200["guidance"]["anchors"])
    ufm_pair_s = seconds["ufm/forward/update"] / (calls["ufm/forward/update"] * (anchors - 1))
    vggt_frame_s = seconds["vggt/forward/update"] / (calls["vggt/forward/update"] * anchors)
    flop_ratio = 1.0
    if geometry != "vggt-1b":  # the run's anchors are frames of CogVideoX-5B's 480x720 video
        flop_ratio = (geometry_flops(geometry, anchors, 480, 720)["forward_tflop"]
                      / geometry_flops("vggt-1b", anchors, 480, 720)["forward_tflop"])
    geometry_frame_s = vggt_frame_s * flop_ratio
    modes = {}
    for mode in pairs:
        cfg = load_config(preset="tiny", overrides=[f"evaluation.loss.pairs={mode}"])
        evaluate_video(video, estimators, cfg.evaluation, fps=fps)  # warm-up
        counts.update(dict.fromkeys(counts, 0))
        start = time.perf_counter()
        result = evaluate_video(video, estimators, cfg.evaluation, fps=fps)
        wall = time.perf_counter() - start
        estimate = counts["ufm_pairs"] * ufm_pair_s + counts["vggt_frames"] * geometry_frame_s
        modes[mode] = {**counts, "windows": len(result.windows), "tiny_cpu_wall_s": wall,
                        "h200_estimate_s": estimate, "h200_estimate_suite_h": estimate * videos / 3600}
    return {
        "subcommand": "geco-eval", "argv": list(argv), "environment": environment_info(torch.get_num_threads()),
        "clip": {"frames": frames, "fps": fps, "height": height, "width": width},
        "videos_per_model": videos, "modes": modes,
        "geometry": geometry,
        "h200_per_call": {"ufm_pair_s": ufm_pair_s, "vggt_frame_s": vggt_frame_s, "geometry_frame_s": geometry_frame_s,
                          "geometry_flop_ratio": flop_ratio, "source": Path(h200_run).name},
        "estimate_note": ("UFM's network runs at a fixed working resolution whatever the input size, so its "
                          "per-pair time from the H200 guidance run (forward with autograd bookkeeping) "
                          "applies; VGGT is scaled per frame from 4-frame calls, a lower bound for 24-frame "
                          "windows (its global attention grows with the square of the frames). Generation "
                          "not included."),
    }


def geco_eval_table(report: dict[str, Any]) -> str:
    """Markdown: per pair mode, the windows, estimator calls, tiny CPU wall and the H200 estimate."""
    header = ("| pairs | windows | {} calls (frames) | UFM calls (pairs) | tiny CPU wall (s) | "
              "H200 estimate per video (s) | per model, {} videos (h) |")
    lines = [header.format(report["geometry"], report["videos_per_model"]), "|---|---|---|---|---|---|---|"]
    for pairs, m in report["modes"].items():
        lines.append(f"| {pairs} | {m['windows']} | {m['vggt_calls']} ({m['vggt_frames']}) | {m['ufm_calls']} "
                     f"({m['ufm_pairs']}) | {m['tiny_cpu_wall_s']:.3g} | {m['h200_estimate_s']:.3g} | "
                     f"{m['h200_estimate_suite_h']:.3g} |")
    return "\n".join(lines)
