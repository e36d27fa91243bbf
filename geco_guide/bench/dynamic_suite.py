"""Dynamic masks checked against ground truth on synthetic scenes with objects that move on their own
(the command is ``geco validate --dynamic``; numbers in docs/validation.md).

The scene is :func:`~geco_guide.bench.synthetic.moving_clip` (the gallery, an orbiting camera, two
boxes that move on their own), next to the same scene with the boxes still. GeCo runs with the
oracle estimators (exact depth, cameras and flow) and the evaluation loss (all ordered pairs),
with no mask, the true mask of the moving boxes, and the automatic mask
(:class:`~geco_guide.estimators.motion_masks.MotionMasks`). Three questions:

* **false positives**: the scores of the clip without artifacts, against the still clip's (with
  no mask, and with the boxes masked alike);
* **artifact detection**: the paper's per-frame localisation AP (the fused map against the
  artifact's pixels, macro-averaged over the frames that hold some) of a WarpBench deformation and
  an OccluBench swap placed on the static background, against the still clip with the same edit;
* **the automatic mask**: its IoU with the true mask of the moving boxes, and the fraction of the
  deformation's pixels it hides.

And with ``movers="rigid"`` (:func:`movers_validation`), on one box (the first of
:func:`~geco_guide.bench.synthetic.moving_boxes` at seed 0, else the seed's
:func:`~geco_guide.bench.synthetic.drawn_mover`) in the same gallery:

* **a rigid mover**: with automatic masks, how much of what the moving box adds to the score with
  nothing masked ``rigid`` removes; with the true mask, its score over the still box's;
* **a mover that changes shape** (:func:`~geco_guide.bench.synthetic.deform_mover`, a thin-plate
  spline on the box alone): the deformation's localisation AP with ``rigid`` and automatic masks,
  over the same warp's on the still box (no mask), and with ``drop`` (near chance);
* **a non-rigid mover** (the box stretching, its parts moving apart) under its true mask: judged
  non-rigid and left out, so its score is ``drop``'s.

And on :data:`MOVER_SEEDS` scenes of one box drawn at random (size, place, velocity;
:func:`~geco_guide.bench.synthetic.drawn_mover`, :func:`drawn_movers_validation`), the two measures of
``rigid`` with automatic masks on every seed: the false positive it removes and the share of a
deformation's score on the box it recovers (:func:`mover_measures`).
"""

from __future__ import annotations

import logging
import math
import time
from dataclasses import dataclass, replace
from typing import Any

import torch
from torch import Tensor

from ..estimators.bundle import Estimators
from ..estimators.motion_masks import MotionMasks
from ..estimators.oracle import OracleFlow, OracleGeometry
from ..loss.cues import CUES, MAP_ORDER
from ..loss.geco import GeCoResult
from ..loss.presets import evaluation_loss
from ..metric.evaluate import mean_or_nan, score_frames
from .datasets import scene_track
from .occlusion import OcclusionParams, composite_occlusion
from .synthetic import MovingBox, SyntheticClip, deform_mover, drawn_mover, moving_boxes, moving_clip, with_overlay, with_warp
from .validate import cue_map, localisation
from .warp import WarpParams, warp_clip

__all__ = ["MOVER_SEEDS", "DynamicScenes", "drawn_movers_markdown", "drawn_movers_validation", "dynamic_validation",
           "edited_clips", "markdown_report", "mover_clips", "mover_measures", "movers_validation"]

logger = logging.getLogger(__name__)

MASKS = ("none", "true", "auto")

#: The issue's targets on these scenes.
TARGETS = {
    "auto_iou": 0.7,  # automatic mask vs true moving-object mask, at least
    "hidden_deformation": 0.1,  # fraction of deformation pixels the automatic mask hides, below
    "score_ratio": 2.0,  # masked fused score of the moving clip over the still clip's, at most
    "ap_ratio": 0.9,  # detection AP with automatic masks over the still clip's AP, at least
    "movers_removed": 0.8,  # share of the moving box's added score that rigid + auto removes, at least
    "movers_score_ratio": 2.0,  # rigid + true mask score over the still box's, at most
    "movers_ap_ratio": 0.9,  # AP of a deformation on the moving box (rigid + auto) over the still box's, at least
    "movers_false_positive_removed": 0.9,  # on every drawn scene: share of the box's added score rigid + auto removes
    "movers_deformation_recovered": 0.5,  # on every drawn scene: the deformation's added score (rigid + auto) over the still box's
}

#: How many drawn mover scenes (:func:`~geco_guide.bench.synthetic.drawn_mover`, seeds ``seed`` to
#: ``seed + MOVER_SEEDS - 1``) the two measures of :func:`mover_measures` are checked on.
MOVER_SEEDS = 8

#: How the box of :func:`mover_clips` stretches (per frame, along x) when it is the non-rigid mover.
STRETCH = (0.1, 0.0, 0.0)

#: Size (pixels, standard deviation) of the control displacements of the warp on the box.
MOVER_WARP_AMPLITUDE = 1.5


@dataclass(frozen=True)
class DynamicScenes:
    """Size of the validation clips (frames, height, width) and the edits' seed."""

    num_frames: int = 9
    height: int = 96
    width: int = 128
    seed: int = 0

    def __post_init__(self) -> None:
        if self.num_frames < 4 or self.height < 24 or self.width < 32:
            raise ValueError(f"dynamic validation clips need >= 4 frames of >= 24x32 pixels, got "
                             f"{self.num_frames}x{self.height}x{self.width}")


def background_warp_region(clip: SyntheticClip) -> Tensor:
    """``[H, W]`` bool: an ellipse on the right wall, minus every pixel a mover ever covers, where
    the deformation goes (on the static background)."""
    height, width = clip.frames.shape[-2:]
    v, u = torch.meshgrid(torch.arange(height, dtype=torch.float64), torch.arange(width, dtype=torch.float64), indexing="ij")
    ellipse = ((u - 0.86 * width) / (0.1 * width)) ** 2 + ((v - 0.45 * height) / (0.25 * height)) ** 2 <= 1.0
    return ellipse & ~clip.dynamic_mask.any(0)


def background_occlusion_region(height: int, width: int) -> tuple[int, int, int, int]:
    """``(left, top, right, bottom)`` of the swap on the left wall, clear of the movers."""
    return round(0.03 * width), round(0.25 * height), round(0.2 * width), round(0.6 * height)


def edited_clips(scenes: DynamicScenes) -> dict[str, dict[str, SyntheticClip]]:
    """``{"clean" | "deformation" | "occlusion": {"still" | "moving": clip}}``: the same edit,
    placed on the static background, in the still and the moving scene."""
    size = (scenes.num_frames, scenes.height, scenes.width)
    base = {"still": moving_clip(*size, still=True), "moving": moving_clip(*size)}
    region = background_warp_region(base["moving"]) & background_warp_region(base["still"])
    params = WarpParams(seed=scenes.seed, amplitude=3.0 * scenes.width / 128)
    box = background_occlusion_region(scenes.height, scenes.width)
    clips: dict[str, dict[str, SyntheticClip]] = {"clean": base, "deformation": {}, "occlusion": {}}
    for motion, clip in base.items():
        frames = clip.frames.float()
        clips["deformation"][motion] = with_warp(clip, warp_clip(frames, region, params))
        edit = composite_occlusion(frames, OcclusionParams(region=box, seed=scenes.seed), region_track=scene_track(clip, box))
        clips["occlusion"][motion] = with_overlay(clip, edit)
    return clips


def score_clip(clip: SyntheticClip, masks: str, movers: str = "drop") -> GeCoResult:
    """GeCo of ``clip`` with the oracle estimators and the evaluation loss, with ``masks``:
    ``none``, ``true`` (the moving boxes) or ``auto``, and ``movers`` (``drop`` or ``rigid``)."""
    dynamic = {"none": None, "true": clip.dynamic_mask, "auto": MotionMasks()}[masks]
    frames = clip.frames.float()
    loss = replace(evaluation_loss(), movers=movers)
    return score_frames(frames, Estimators(OracleGeometry(clip), OracleFlow(clip)), loss, dynamic_masks=dynamic)[1]


def detection_ap(clip: SyntheticClip, result: GeCoResult) -> float:
    """The paper's localisation AP of the fused map against the artifact's pixels, macro-averaged
    over the frames that hold some (masked pixels score 0, as invalid ones); NaN without any."""
    values, valid = cue_map(result, "fused")
    frames = [t for t in range(clip.num_frames) if bool(clip.mask[t].any())]
    return mean_or_nan([localisation(values[t], valid[t], clip.mask[t])["ap"] for t in frames])


def iou(predicted: Tensor, truth: Tensor) -> float:
    """Intersection over union of two bool masks (1 when both are empty)."""
    union = int((predicted | truth).sum())
    return int((predicted & truth).sum()) / union if union else 1.0


def _scores(result: GeCoResult) -> dict[str, float]:
    """The cues' scores as shown to a user: NaN over no valid pixel, never the loss's 0."""
    return {name: value for name, value in result.scalars().items() if name != "loss"}


def dynamic_validation(scenes: DynamicScenes = DynamicScenes()) -> dict[str, Any]:
    """Every number of the report (JSON-ready): ``false_positives``, ``detection``,
    ``auto_mask``, ``movers`` (:func:`movers_validation`), ``drawn_movers``
    (:func:`drawn_movers_validation`) and ``targets`` (each target's value and whether it is met)."""
    clips = edited_clips(scenes)
    # each (kind, key) scored in turn, with a log line as it finishes: the whole takes minutes
    planned = [(kind, key) for kind in clips for key in ("still", *(f"moving/{m}" for m in MASKS))]
    planned.append(("clean", "still/true"))  # the boxes' edges, masked alike
    results: dict[str, dict[str, GeCoResult]] = {kind: {} for kind in clips}
    for k, (kind, key) in enumerate(planned, start=1):
        motion, _, masks = key.partition("/")
        started = time.perf_counter()
        results[kind][key] = score_clip(clips[kind][motion], masks or "none")
        logger.info("[%d/%d] scored the %s %s clip with %s mask (%.1f s)", k, len(planned), motion, kind,
                    masks or "no", time.perf_counter() - started)
    false_positives = {key: _scores(result) for key, result in results["clean"].items()}
    detection = {kind: {key: detection_ap(clips[kind]["still" if key == "still" else "moving"], result)
                        for key, result in results[kind].items()} for kind in ("deformation", "occlusion")}
    auto_iou = {kind: iou(results[kind]["moving/auto"].dynamic_masks[0].cpu(), clips[kind]["moving"].dynamic_mask)
                for kind in clips}
    deformation = clips["deformation"]["moving"].mask
    hidden = int((results["deformation"]["moving/auto"].dynamic_masks[0].cpu() & deformation).sum()) / int(deformation.sum())
    moving = clips["clean"]["moving"]
    ratio = false_positives["moving/auto"]["fused"] / false_positives["still"]["fused"]
    ap_ratio = {kind: detection[kind]["moving/auto"] / detection[kind]["still"] for kind in detection}
    # The swap's sprites are rigid movers in 3-D (flat cards sliding at a fixed depth): the mask of
    # the boxes alone is not the truth there, so the IoU target is judged without that clip.
    judged_iou = min(auto_iou["clean"], auto_iou["deformation"])
    targets = {
        "auto_iou": {"value": judged_iou, "target": f">= {TARGETS['auto_iou']}", "met": judged_iou >= TARGETS["auto_iou"]},
        "hidden_deformation": {"value": hidden, "target": f"< {TARGETS['hidden_deformation']}",
                               "met": hidden < TARGETS["hidden_deformation"]},
        "score_ratio": {"value": ratio, "target": f"<= {TARGETS['score_ratio']}", "met": ratio <= TARGETS["score_ratio"]},
        **{f"ap_ratio_{kind}": {"value": value, "target": f">= {TARGETS['ap_ratio']}", "met": value >= TARGETS["ap_ratio"]}
           for kind, value in ap_ratio.items()},
    }
    movers = movers_validation(scenes)
    drawn = drawn_movers_validation(scenes)
    return {
        "scenes": {"num_frames": scenes.num_frames, "height": scenes.height, "width": scenes.width, "seed": scenes.seed,
                   "true_masked_fraction": float(moving.dynamic_mask.float().mean()),
                   "estimators": "oracle", "loss": "evaluation (all ordered pairs)"},
        "false_positives": false_positives,
        "detection": detection,
        "auto_mask": {"iou": auto_iou, "hidden_deformation": hidden,
                      "masked_fraction": float(results["clean"]["moving/auto"].dynamic_masks.float().mean())},
        "movers": {key: value for key, value in movers.items() if key != "targets"},
        "drawn_movers": drawn["seeds"],
        "targets": {**targets, **movers["targets"], **drawn["targets"]},
    }


def drawn_movers_validation(scenes: DynamicScenes = DynamicScenes()) -> dict[str, Any]:
    """:func:`mover_measures` on the :data:`MOVER_SEEDS` drawn scenes from ``scenes.seed`` on
    (JSON-ready): ``seeds`` (each seed's measures) and ``targets`` (each measure's worst seed
    against its target)."""
    seeds = {}
    for k, seed in enumerate(range(scenes.seed, scenes.seed + MOVER_SEEDS), start=1):
        started = time.perf_counter()
        seeds[str(seed)] = mover_measures(replace(scenes, seed=seed))
        logger.info("[%d/%d] scored the drawn mover scene of seed %d (%.1f s)", k, MOVER_SEEDS, seed,
                    time.perf_counter() - started)
    targets = {}
    for measure in ("false_positive_removed", "deformation_recovered"):
        values = [row[measure] for row in seeds.values()]
        worst = min(values) if all(math.isfinite(v) for v in values) else math.nan  # NaN: not met
        wanted = TARGETS[f"movers_{measure}"]
        targets[f"movers_{measure}"] = {"value": worst, "target": f">= {wanted} on every seed", "met": worst >= wanted}
    return {"seeds": seeds, "targets": targets}


def mover_clips(scenes: DynamicScenes) -> dict[str, SyntheticClip]:
    """The movers' scenes: one box in the gallery (:func:`drawn_mover` of the scenes' seed; seed
    0: the sliding box of :func:`moving_boxes`), ``still`` / ``moving``, ``deformed_still`` /
    ``deformed_moving`` (the same warp on it, :func:`deform_mover` with the scenes' seed) and
    ``stretching`` (the sliding box standing, its size growing along x: non-rigid)."""
    size = (scenes.num_frames, scenes.height, scenes.width)
    box = drawn_mover(scenes.seed)
    still, moving = moving_clip(*size, movers=[box], still=True), moving_clip(*size, movers=[box])
    amplitude = MOVER_WARP_AMPLITUDE * scenes.width / 128

    def deformed(clip: SyntheticClip) -> SyntheticClip:
        return deform_mover(clip, amplitude=amplitude, seed=scenes.seed)

    return {"still": still, "moving": moving, "deformed_still": deformed(still), "deformed_moving": deformed(moving),
            "stretching": moving_clip(*size, movers=[MovingBox(moving_boxes()[0].box, (0.0, 0.0, 0.0), stretch=STRETCH)])}


def mover_measures(scenes: DynamicScenes) -> dict[str, float]:
    """The two measures of ``movers="rigid"`` with automatic masks on the drawn scene of
    ``scenes.seed`` (M_geo of five runs, and):

    * ``false_positive_removed``: the share of what the moving box adds to M_geo with nothing
      masked that rigid + auto removes (1: the still scene's score);
    * ``deformation_recovered``: what the warp on the box adds to M_geo with rigid + auto, over what
      the same warp adds to the still box with nothing masked (1: found as on a still object);
    * ``still_ratio``: rigid + auto on the moving box over the still box;
    * ``auto_recall``: the share of the box's true pixels the automatic masks cover (moving box).
    """
    clips = mover_clips(scenes)
    runs = {"still": ("still", "none", "drop"), "moving": ("moving", "none", "drop"),
            "moving/rigid": ("moving", "auto", "rigid"), "deformed_still": ("deformed_still", "none", "drop"),
            "deformed_moving/rigid": ("deformed_moving", "auto", "rigid")}
    results = {key: score_clip(clips[clip], masks, movers) for key, (clip, masks, movers) in runs.items()}
    fused = {key: float(result.fused) for key, result in results.items()}
    truth = clips["moving"].dynamic_mask
    covered = int((results["moving/rigid"].dynamic_masks[0].cpu() & truth).sum()) / max(int(truth.sum()), 1)
    return {**fused,
            "false_positive_removed": _ratio(fused["moving"] - fused["moving/rigid"], fused["moving"] - fused["still"]),
            "deformation_recovered": _ratio(fused["deformed_moving/rigid"] - fused["moving/rigid"],
                                            fused["deformed_still"] - fused["still"]),
            "still_ratio": _ratio(fused["moving/rigid"], fused["still"]), "auto_recall": covered}


def _ratio(numerator: float, denominator: float) -> float:
    """``numerator / denominator``, NaN over 0 (a box that never shows adds nothing to divide by)."""
    return numerator / denominator if denominator != 0 else math.nan


def _mover_rows(result: GeCoResult) -> list[dict[str, Any]]:
    return [] if result.movers is None else result.movers.records()


def movers_validation(scenes: DynamicScenes = DynamicScenes()) -> dict[str, Any]:
    """The movers' checks (JSON-ready): ``rigid`` (scores), ``deformed`` (APs and the chance
    level), ``non_rigid`` (scores and the verdict), each mover's record, and ``targets``."""
    clips = mover_clips(scenes)
    runs = {"still/none/drop": ("still", "none", "drop"), "moving/none/drop": ("moving", "none", "drop"),
            "moving/auto/drop": ("moving", "auto", "drop"), "moving/auto/rigid": ("moving", "auto", "rigid"),
            "moving/true/rigid": ("moving", "true", "rigid")}
    deformed_runs = {"still/none/drop": ("deformed_still", "none", "drop"),
                     "moving/auto/drop": ("deformed_moving", "auto", "drop"),
                     "moving/auto/rigid": ("deformed_moving", "auto", "rigid"),
                     "moving/true/rigid": ("deformed_moving", "true", "rigid")}
    stretching_runs = {f"{m}/{mv}": ("stretching", m, mv)
                       for m, mv in (("none", "drop"), ("true", "drop"), ("true", "rigid"), ("auto", "drop"), ("auto", "rigid"))}
    planned = [(group, key, run) for group, group_runs in (("rigid", runs), ("deformed", deformed_runs),
                                                          ("non_rigid", stretching_runs)) for key, run in group_runs.items()]
    scored: dict[str, dict[str, GeCoResult]] = {"rigid": {}, "deformed": {}, "non_rigid": {}}
    for k, (group, key, (clip, masks, movers)) in enumerate(planned, start=1):  # a log line as each finishes
        started = time.perf_counter()
        scored[group][key] = score_clip(clips[clip], masks, movers)
        logger.info("[%d/%d] scored the movers' %s clip with %s mask, movers %s (%.1f s)", k, len(planned), clip, masks,
                    movers, time.perf_counter() - started)
    rigid, non_rigid = scored["rigid"], scored["non_rigid"]
    deformed = {key: (clips[deformed_runs[key][0]], result) for key, result in scored["deformed"].items()}
    fused = {key: float(result.fused) for key, result in rigid.items()}
    added = fused["moving/none/drop"] - fused["still/none/drop"]
    removed = (fused["moving/none/drop"] - fused["moving/auto/rigid"]) / added
    score_ratio = fused["moving/true/rigid"] / fused["still/none/drop"]
    aps = {key: detection_ap(clip, result) for key, (clip, result) in deformed.items()}
    ap_ratio = aps["moving/auto/rigid"] / aps["still/none/drop"]
    verdicts = [row["verdict"] for row in _mover_rows(non_rigid["true/rigid"])]
    left_out = verdicts == ["non-rigid"] and float(non_rigid["true/rigid"].fused) == float(non_rigid["true/drop"].fused)
    targets = {
        "movers_removed": {"value": removed, "target": f">= {TARGETS['movers_removed']}", "met": removed >= TARGETS["movers_removed"]},
        "movers_score_ratio": {"value": score_ratio, "target": f"<= {TARGETS['movers_score_ratio']}",
                               "met": score_ratio <= TARGETS["movers_score_ratio"]},
        "movers_ap_ratio": {"value": ap_ratio, "target": f">= {TARGETS['movers_ap_ratio']}", "met": ap_ratio >= TARGETS["movers_ap_ratio"]},
        "movers_non_rigid_left_out": {"value": float(left_out), "target": "non-rigid, scored as drop", "met": left_out},
    }
    return {
        "box_fraction": float(clips["moving"].dynamic_mask.float().mean()),
        "rigid": {**fused, "removed": removed, "score_ratio": score_ratio},
        "deformed": {**aps, "chance": float(clips["deformed_moving"].mask.float().mean()), "ap_ratio": ap_ratio,
                     "deformed_fraction_of_box": float(clips["deformed_moving"].mask.sum() / clips["deformed_moving"].dynamic_mask.sum())},
        "non_rigid": {**{key: float(result.fused) for key, result in non_rigid.items()},
                      "auto_masked_fraction": float(non_rigid["auto/drop"].masked_fraction.mean())},
        "movers": {"moving/auto/rigid": _mover_rows(rigid["moving/auto/rigid"]),
                   "moving/true/rigid": _mover_rows(rigid["moving/true/rigid"]),
                   "deformed/auto/rigid": _mover_rows(deformed["moving/auto/rigid"][1]),
                   "stretching/true/rigid": _mover_rows(non_rigid["true/rigid"]),
                   "stretching/auto/rigid": _mover_rows(non_rigid["auto/rigid"])},
        "targets": targets,
    }


def _number(value: float) -> str:
    return "-" if not math.isfinite(value) else (f"{value:.3g}" if abs(value) < 1e-2 else f"{value:.3f}")


def markdown_report(report: dict[str, Any]) -> str:
    """The report's three tables and its targets, in Markdown."""
    s = report["scenes"]
    fp, det, auto = report["false_positives"], report["detection"], report["auto_mask"]
    lines = [f"Scenes: {s['num_frames']} frames of {s['height']}x{s['width']}, oracle estimators, "
             f"all ordered pairs; the moving boxes cover {100 * s['true_masked_fraction']:.1f} % of a frame.", "",
             "False positives (clip without artifacts):", "",
             "| Clip | Mask | " + " | ".join(CUES[c].symbol for c in MAP_ORDER) + " |",
             "|---|---|" + "---|" * len(MAP_ORDER)]
    rows = (("still", "still boxes / none"), ("still/true", "still boxes / true"), *((f"moving/{m}", f"moving boxes / {m}") for m in MASKS))
    for key, name in rows:
        clip, mask = name.split(" / ")
        lines.append(f"| {clip} | {mask} | " + " | ".join(_number(fp[key][c]) for c in MAP_ORDER) + " |")
    lines += ["", "Artifact detection on the static background (localisation AP of M_geo):", "",
              "| Artifact | still, no mask | moving, no mask | moving, true mask | moving, auto mask |", "|---|---|---|---|---|"]
    for kind, row in det.items():
        lines.append(f"| {kind} | " + " | ".join(f"{row[k]:.3f}" for k in ("still", "moving/none", "moving/true", "moving/auto")) + " |")
    lines += ["", "Automatic mask: IoU with the true mask of the moving boxes "
              + ", ".join(f"{kind} {value:.3f}" for kind, value in auto["iou"].items())
              + f"; hides {100 * auto['hidden_deformation']:.2f} % of the deformation's pixels.", "",
              *_movers_markdown(report["movers"]), "", *drawn_movers_markdown(report["drawn_movers"]), "",
              "| Target | Value | Wanted | Met |", "|---|---|---|---|"]
    for name, t in report["targets"].items():
        lines.append(f"| {name} | {_number(t['value'])} | {t['target']} | {'yes' if t['met'] else 'no'} |")
    return "\n".join(lines) + "\n"


def _movers_markdown(movers: dict[str, Any]) -> list[str]:
    """The movers' three tables (one box, ``movers="rigid"``)."""
    rigid, deformed, non_rigid = movers["rigid"], movers["deformed"], movers["non_rigid"]
    lines = [f"Movers scored against their own motion (one box, {100 * movers['box_fraction']:.1f} % of a frame):", "",
             "| Rigid box | still, none | moving, none | moving, auto, drop | moving, auto, rigid | moving, true, rigid |",
             "|---|---|---|---|---|---|",
             "| M_geo | " + " | ".join(_number(rigid[k]) for k in ("still/none/drop", "moving/none/drop", "moving/auto/drop",
                                                                     "moving/auto/rigid", "moving/true/rigid")) + " |",
             "", f"rigid + auto removes {100 * rigid['removed']:.1f} % of what the moving box adds; rigid + true "
                 f"mask scores {_number(rigid['score_ratio'])}x the still box.", "",
             "| Deformed box (AP of M_geo) | still, none | moving, auto, drop | moving, auto, rigid | moving, true, rigid | chance |",
             "|---|---|---|---|---|---|",
             "| deformation | " + " | ".join(_number(deformed[k]) for k in ("still/none/drop", "moving/auto/drop", "moving/auto/rigid",
                                                                         "moving/true/rigid", "chance")) + " |",
             "", "| Non-rigid box (stretching), M_geo | none | true, drop | true, rigid | auto, drop | auto, rigid |",
             "|---|---|---|---|---|---|",
             "| M_geo | " + " | ".join(_number(non_rigid[k]) for k in ("none/drop", "true/drop", "true/rigid", "auto/drop",
                                                                     "auto/rigid")) + " |",
             "", "Verdicts: " + "; ".join(f"{key}: " + (", ".join(f"{row['verdict']} (inliers {_number(row['inlier_fraction'] or math.nan)})"
                                                             for row in rows) or "no mover")
                                        for key, rows in movers["movers"].items()) + "."]
    return lines


def drawn_movers_markdown(seeds: dict[str, dict[str, float]]) -> list[str]:
    """The drawn scenes' table: per seed, the two measures of :func:`mover_measures` and more."""
    lines = [f"Drawn mover scenes (rigid + automatic masks, {len(seeds)} seeds):", "",
             "| seed | false positive removed | deformation recovered | rigid / still | automatic mask recall |",
             "|---|---|---|---|---|"]
    for seed, row in seeds.items():
        lines.append(f"| {seed} | {_number(row['false_positive_removed'])} | {_number(row['deformation_recovered'])} | "
                     f"{_number(row['still_ratio'])} | {_number(row['auto_recall'])} |")
    return lines
