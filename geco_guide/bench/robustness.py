"""How GeCo's detection degrades with noisy depth or flow (the paper's robustness study; the
command is :mod:`geco_guide.cli.robustness`).

The metric is scored as :mod:`geco_guide.metric.evaluate` scores it (the evaluation protocol's loss
options). On synthetic scenes with exact depth, cameras and flow (:mod:`geco_guide.bench.synthetic`), Gaussian
noise is added to one input at a time, as the paper does on TartanAir with ground truth:

* depth, multiplicatively in log space, ``D exp(sigma n)`` (so errors scale with distance;
  ``sigma`` is about the relative error), ``sigma`` in :data:`DEPTH_SIGMAS`;
* flow, additively in pixels, ``sigma`` in :data:`FLOW_SIGMAS`.

At each level it reports every cue's ranking AP on a WarpBench-style clip (Task 2: every frame
warped) and an OccluBench-style clip (Task 3: re-revealed frames), and the fused score of the
clean rigid clip (the noise floor). Output: ``robustness.json``, its tables ``robustness.md``
(:func:`markdown_report`) and ``robustness.png`` (AP against sigma, one panel per input and
task), written together, atomically. Deterministic from ``--seed``.
A level so large that the noisy input is not finite (depth ``exp(sigma n)`` overflowing to inf
or 0, flow to inf) is scored NaN (null in the JSON) and left out of the plot.
"""

from __future__ import annotations

import io
import math
from collections.abc import Callable
from dataclasses import asdict, replace
from typing import Any

import torch
from PIL import Image, ImageDraw

from ..io.plots import Panel, legend, limits, text
from ..loss.cues import CUES as CUE_TABLE, PAPER_ORDER
from ..loss.geco import GeCoLossConfig, frame_pairs, geco_from_geometry
from ..metric.protocol import EvaluationConfig
from ..types import Correspondences, SceneGeometry
from .datasets import scene_track
from .occlusion import OcclusionParams, composite_occlusion, default_region
from .ranking import average_precision
from .report import fmt, markdown_table
from .synthetic import SyntheticClip, rigid_clip, with_overlay, with_warp
from .warp import WarpParams, warp_clip

__all__ = ["CUES", "DEPTH_SIGMAS", "FLOW_SIGMAS", "ROBUSTNESS_AXIS_NOTE", "ROBUSTNESS_X_LABELS", "level_line",
           "plot", "run_sweep", "sweep_memory_bytes"]

#: Relative depth errors: each depth is multiplied by ``exp(sigma n)``, ``n ~ N(0, 1)``.
DEPTH_SIGMAS = (0.0, 0.01, 0.02, 0.05, 0.1, 0.15, 0.2, 0.3, 0.5, 1.0)
#: Flow errors in pixels: ``sigma n`` is added to each flow vector.
FLOW_SIGMAS = (0.0, 0.25, 0.5, 1.0, 2.0, 5.0, 10.0, 20.0)

#: The cues in the paper's row order (their colours, markers, line widths: the loss' cue table).
CUES = PAPER_ORDER


def sweep_memory_bytes(num_frames: int, height: int, width: int, pairs: str) -> int:
    """A lower bound of the sweep's peak memory in bytes: the exact inputs it holds throughout,
    for each of the three clips of :func:`sweep_clips` float64 correspondences of every frame pair
    (flow ``[P, 2, H, W]`` and covisibility ``[P, H, W]``) and depth ``[S, H, W]``. The metric's
    per-pair maps and the noisy copies come on top of it."""
    num_pairs = len(frame_pairs(num_frames, pairs))
    return 3 * 8 * height * width * (3 * num_pairs + num_frames)


def noisy_depth(geometry: SceneGeometry, sigma: float, generator: torch.Generator) -> SceneGeometry:
    """``depth [B, S, H, W] * exp(sigma n)``, ``n ~ N(0, 1)`` per pixel; cameras untouched."""
    noise = torch.randn(geometry.depth.shape, generator=generator, dtype=torch.float64).to(geometry.depth.dtype)
    return replace(geometry, depth=geometry.depth * torch.exp(sigma * noise))


def noisy_flow(correspondences: Correspondences, sigma: float, generator: torch.Generator) -> Correspondences:
    """``flow [N, 2, H, W] + sigma n`` pixels; covisibility untouched."""
    noise = torch.randn(correspondences.flow.shape, generator=generator, dtype=torch.float64)
    return replace(correspondences, flow=correspondences.flow + sigma * noise.to(correspondences.flow.dtype))


def sweep_clips(num_frames: int, height: int, width: int, seed: int) -> dict[str, SyntheticClip]:
    """The rigid clip and its two edits (built with the benchmark builders' code)."""
    rigid = rigid_clip(num_frames, height, width)
    warped = with_warp(rigid, warp_clip(rigid.frames, params=WarpParams(seed=seed)))
    region = default_region(height, width, OcclusionParams.region_fraction)
    edit = composite_occlusion(rigid.frames, OcclusionParams(seed=seed), region_track=scene_track(rigid, region))
    return {"rigid": rigid, "warp": warped, "occlusion": with_overlay(rigid, edit)}


def usable(geometry: SceneGeometry, correspondences: Correspondences) -> bool:
    """Whether noisy inputs are still inputs: finite flow and finite positive depth (a large
    sigma overflows ``exp(sigma n)`` to inf or 0, and the metric would score that garbage)."""
    depth = geometry.depth
    return bool(torch.isfinite(depth).all() and (depth > 0).all() and torch.isfinite(correspondences.flow).all())


def detection_ap(clip: SyntheticClip, geometry: SceneGeometry, correspondences: Correspondences,
                 pairs: list[tuple[int, int]], config: GeCoLossConfig) -> dict[str, float]:
    """Per cue, the mean over frames with artifact pixels of the frame map's ranking AP."""
    result = geco_from_geometry(geometry, correspondences, pairs, config)
    frames = [t for t in range(clip.num_frames) if bool(clip.mask[t].any())]
    aps = {}
    for cue in CUES:
        values, valid = result.frame_maps.cue(cue)
        maps = torch.where(valid, values, torch.zeros_like(values))[0]
        aps[cue] = sum(average_precision(maps[t], clip.mask[t]) for t in frames) / len(frames)
    return aps


def level_line(noisy_input: str, rows: dict[str, Any], k: int) -> str:
    """One line of the sweep's results: level ``k`` of the noisy input's ``rows`` (as in the report)."""
    cells = " ".join(f"{task}/{cue} {rows[task][cue][k]:.3f}" for task in ("warp", "occlusion") for cue in CUES)
    return f"{noisy_input} sigma={rows['sigmas'][k]:g}: {cells} rigid fused {rows['rigid_fused'][k]:.4f}"


def run_sweep(num_frames: int = 9, height: int = 48, width: int = 64, seed: int = 0,
              depth_sigmas=DEPTH_SIGMAS, flow_sigmas=FLOW_SIGMAS, config: GeCoLossConfig | None = None,
              progress: Callable[[str], None] | None = None) -> dict[str, Any]:
    """The whole study as a JSON-ready dict: per input (``depth``, ``flow``) the sigmas, per task
    (``warp``, ``occlusion``) each cue's AP per sigma, and the rigid clip's fused score per sigma.
    ``config``: the metric's options (default: the evaluation protocol's, every ordered pair);
    ``progress``: called with each level's :func:`level_line` as soon as the level is scored."""
    config = config or EvaluationConfig().loss
    pair_list = frame_pairs(num_frames, config.pairs)
    clips = sweep_clips(num_frames, height, width, seed)
    exact = {name: (clip.geometry(torch.float64), clip.pair_correspondences(pair_list, torch.float64)) for name, clip in clips.items()}
    report: dict[str, Any] = {"scene": {"num_frames": num_frames, "height": height, "width": width, "seed": seed},
                              "loss": asdict(config)}
    for noisy_input, sigmas in (("depth", depth_sigmas), ("flow", flow_sigmas)):
        generator = torch.Generator().manual_seed(seed)
        rows: dict[str, Any] = {"sigmas": list(sigmas), "warp": {c: [] for c in CUES}, "occlusion": {c: [] for c in CUES},
                                "rigid_fused": []}
        for sigma in sigmas:
            for name, clip in clips.items():
                geometry, correspondences = exact[name]
                if noisy_input == "depth":
                    geometry = noisy_depth(geometry, sigma, generator)
                else:
                    correspondences = noisy_flow(correspondences, sigma, generator)
                if not usable(geometry, correspondences):  # the level overflowed: no score, not a 0
                    if name == "rigid":
                        rows["rigid_fused"].append(math.nan)
                    else:
                        for cue in CUES:
                            rows[name][cue].append(math.nan)
                    continue
                if name == "rigid":  # a score over no valid pixel is NaN, never the loss's 0
                    scored = geco_from_geometry(geometry, correspondences, pair_list, config)
                    rows["rigid_fused"].append(scored.scalars()["fused"])
                    continue
                for cue, ap in detection_ap(clip, geometry, correspondences, pair_list, config).items():
                    rows[name][cue].append(ap)
            if progress is not None:
                progress(level_line(noisy_input, rows, len(rows["rigid_fused"]) - 1))
        report[noisy_input] = rows
    return report


def markdown_report(report: dict[str, Any]) -> str:
    """The sweep's tables (:func:`run_sweep`'s ``report``), one per noisy input: a row per noise
    level, each cue's detection AP of the warp (Task 2) and the occlusion (Task 3), and the rigid
    clip's fused score; ``-`` where the level overflowed (no score)."""
    scene = report["scene"]
    lines = ["# GeCo robustness: detection AP under noisy depth and flow", "",
             f"A synthetic scene of {scene['num_frames']} frames of {scene['height']}x{scene['width']} (seed "
             f"{scene['seed']}), frame pairs {report['loss']['pairs']}; sigma: "
             f"{ROBUSTNESS_X_LABELS['depth'].removeprefix('noise sigma: ')} for depth, "
             f"{ROBUSTNESS_X_LABELS['flow'].removeprefix('noise sigma: ')} for flow.", ""]
    header = ["sigma", *(f"{task} AP {cue}" for task in ("Task 2 (warp)", "Task 3 (occlusion)") for cue in CUES),
              "rigid clip fused"]
    for noisy_input in ("depth", "flow"):
        rows = report[noisy_input]
        table = [[f"{sigma:g}", *(fmt(rows[task][cue][k], 3) for task in ("warp", "occlusion") for cue in CUES),
                  fmt(rows["rigid_fused"][k])] for k, sigma in enumerate(rows["sigmas"])]
        lines += [f"## {noisy_input} noise", "", *markdown_table(header, table), ""]
    return "\n".join(lines)


#: The x axis of each row of the robustness plot, in a reader's words: sigma is the typical
#: relative error of the depth (it is multiplied by exp(sigma n), n ~ N(0, 1)) or the flow's
#: error in pixels (sigma n added).
ROBUSTNESS_X_LABELS = {"depth": "noise sigma: relative depth error (0.1 = 10 %)",
                       "flow": "noise sigma: flow error in pixels"}
#: Under the title: the levels are spaced evenly whatever their values.
ROBUSTNESS_AXIS_NOTE = "x axes: one noise level per tick (evenly spaced, not to scale)"


def plot(report: dict[str, Any]) -> bytes:
    """PNG: AP against sigma, panels depth/flow x warp (Task 2)/occlusion (Task 3), one line per
    cue. The sigmas are evenly spaced levels on the x axis, each labelled with its value (they
    span decades and start at 0, which a log axis cannot show); non-finite APs are left out."""
    image = Image.new("RGB", (760, 760), (255, 255, 255))
    draw = ImageDraw.Draw(image)
    text(draw, (80, 8), ROBUSTNESS_AXIS_NOTE, "lt")
    for row, noisy_input in enumerate(("depth", "flow")):
        sigmas = report[noisy_input]["sigmas"]
        levels = list(range(len(sigmas)))
        what = ROBUSTNESS_X_LABELS[noisy_input]
        for column, task in enumerate(("warp", "occlusion")):
            left, top = 80 + column * 360, 80 + row * 350  # 300 wide: a tick label per level, apart
            panel = Panel((left, top, left + 300, top + 200), limits(levels), (0.0, 1.0))
            title = f"{noisy_input} noise: {'Task 2 (warp)' if task == 'warp' else 'Task 3 (occlusion)'} AP"
            panel.draw_axes(draw, title, what, "AP",
                            xticks=[(k, f"{s:.2g}") for k, s in zip(levels, sigmas)])
            for cue in sorted(CUES, key=lambda c: -CUE_TABLE[c].line_width):  # widest first
                points = [(k, ap) for k, ap in zip(levels, report[noisy_input][task][cue])
                          if ap is not None and math.isfinite(ap)]
                if len(points) > 1:
                    draw.line([panel.to_pixel(k, ap) for k, ap in points], fill=CUE_TABLE[cue].color,
                              width=CUE_TABLE[cue].line_width)
                for k, ap in points:
                    panel.dot(draw, k, ap, CUE_TABLE[cue].color, radius=3, shape=CUE_TABLE[cue].marker)
            if row == 1 and column == 0:
                legend(draw, panel, [(cue, CUE_TABLE[cue].color) for cue in CUES], [CUE_TABLE[cue].marker for cue in CUES])
    buffer = io.BytesIO()
    image.save(buffer, format="PNG")
    return buffer.getvalue()
