"""What moving subjects add to guidance: the dynamic masks' refreshes (SAM 3 predicted, the
automatic masks measured) and the movers scored against their own rigid motion (measured on a CPU)."""

from __future__ import annotations

from typing import Any

import torch

from ..sampler.algorithm.schedule import PAPER_REPEATS, PAPER_STEPS, PAPER_TIME_TRAVEL
from .cards import GPU_SPECS, H200_UNGUIDED_STEP_S
from .cost import calibration_call_roofline_s
from .tracing import CostTracker

__all__ = ["AUTO_MASK_REFRESH_S", "MOVERS_FIT_S", "MOVERS_UPDATE_S", "dynamic_mask_costs", "dynamic_masks_table",
           "sam3_refresh_cost"]


def sam3_refresh_cost(num_frames: int = 4, dtype: torch.dtype = torch.bfloat16) -> dict[str, Any]:
    """Predicted cost of one refresh of ``guidance.dynamic`` subject masks by SAM 3 (the default
    segmenter): its vision encoder on the ``num_frames`` anchor frames at its input size,
    traced on fake tensors (the default ``Sam3VideoConfig``, weights in ``dtype``), seconds per
    card with the cost model's one efficiency (:func:`calibration_call_roofline_s`).

    A lower bound: the text encoder, the DETR heads and the tracker's propagation (per subject,
    per frame) make data-dependent calls that fake tensors cannot trace, and are not counted; the
    vision encoder is the bulk of a frame's work (the encoder runs once per frame,
    whatever the subjects).
    """
    from torch._subclasses.fake_tensor import FakeTensorMode
    from transformers import Sam3VideoConfig, Sam3VideoModel

    from .full_size import to_fake

    config = Sam3VideoConfig()
    with torch.device("meta"):
        model = Sam3VideoModel(config).to(dtype).eval()
    fake_mode = FakeTensorMode(allow_non_fake_inputs=True)
    to_fake(model.detector_model.vision_encoder, fake_mode)
    tracker = CostTracker()
    size = config.image_size
    with fake_mode, torch.no_grad(), tracker.mode():
        model.detector_model.vision_encoder(torch.zeros(num_frames, 3, size, size, dtype=dtype))
    stage = tracker.summary()["stages"]["other"]
    efficiency = calibration_call_roofline_s() / H200_UNGUIDED_STEP_S
    return {"frames": num_frames, "input_size": size, "flops": stage["forward"]["flops"],
            "time_s": {gpu: stage["forward"]["roofline_s"][gpu] / efficiency for gpu in GPU_SPECS},
            "counted": "SAM 3's vision encoder on the anchor frames (a lower bound; see sam3_refresh_cost)"}


#: Measured: one refresh of the automatic masks (``guidance.dynamic=auto``,
#: :class:`~geco_guide.estimators.motion_masks.MotionMasks`) on 4 anchor frames of 480x720 (the
#: synthetic ``moving_clip``, adjacent pairs), with exact depth and flow, on one thread of a 2-core
#: Intel Xeon (two runs of 9, medians 0.857 and 0.879 s; following a mover into its unmatched
#: pixels made it 20 % dearer: the masks before that took 0.72 s there, paired). It runs on what
#: GeCo already estimated: no model of its own.
AUTO_MASK_REFRESH_S = 0.87
#: Measured (docs/performance_records.md, "Movers scored against their own motion"): with
#: ``guidance.loss.movers=rigid``, the movers' fit at each refresh (``fit_movers``: RANSAC + Kabsch per
#: pair and mover, on the host whatever the device), and what scoring them adds to an update's
#: forward and backward (the fit reused), by the minima of run 1, one thread of this project's CPU
#: machine, 4 frames of 480x720 with two movers. The update part runs on the loss's device: on a
#: GPU it is an upper bound.
MOVERS_FIT_S = 0.754
MOVERS_UPDATE_S = 0.657 - 0.482


def dynamic_mask_costs(num_steps: int = PAPER_STEPS, refresh: int = 1) -> dict[str, Any]:
    """The predicted overhead of ``guidance.dynamic`` on the paper's schedule of ``num_steps``
    steps with masks refreshed every ``refresh``-th guided step: per refresh, per whole run and
    per update, for SAM 3 (:func:`sam3_refresh_cost`, per card) and the automatic masks
    (:data:`AUTO_MASK_REFRESH_S`, on the CPU whatever the card)."""
    from ..sampler.algorithm.schedule import GuidanceSchedule, scale_schedule

    repeats, time_travel = scale_schedule(PAPER_REPEATS, PAPER_TIME_TRAVEL, num_steps)
    per_step = GuidanceSchedule.build(repeats, num_steps, time_travel=time_travel).repeats
    guided_steps = [step for step, r in enumerate(per_step) if r > 0]
    refreshes, updates = len(guided_steps[::refresh]), sum(per_step)
    sam3 = sam3_refresh_cost()

    def overhead(seconds: float) -> dict[str, float]:
        return {"refresh_s": seconds, "run_s": seconds * refreshes, "per_update_s": seconds * refreshes / updates}

    return {"steps": num_steps, "refreshes": refreshes, "updates": updates,
            "sam3": {"counted": sam3["counted"], **{gpu: overhead(t) for gpu, t in sam3["time_s"].items()}},
            "auto": {"counted": "measured on one CPU thread (AUTO_MASK_REFRESH_S)", **overhead(AUTO_MASK_REFRESH_S)},
            "movers": {"counted": "guidance.loss.movers=rigid beside either masks: the fit at each refresh on the host "
                                  "and the movers' cues at each update, from one CPU thread's measurements "
                                  "(MOVERS_FIT_S, MOVERS_UPDATE_S; the update part an upper bound for a GPU)",
                       "refresh_s": MOVERS_FIT_S, "update_s": MOVERS_UPDATE_S,
                       "run_s": MOVERS_FIT_S * refreshes + MOVERS_UPDATE_S * updates,
                       "per_update_s": (MOVERS_FIT_S * refreshes + MOVERS_UPDATE_S * updates) / updates}}


def dynamic_masks_table(costs: dict[str, Any]) -> str:
    """Markdown: :func:`dynamic_mask_costs` per card (SAM 3) and for the automatic masks."""
    rows = [f"dynamic masks: {costs['refreshes']} refreshes, {costs['updates']} updates ({costs['steps']} steps)",
            "| masks | card | per refresh (s) | per run (s) | per update (s) |", "|---|---|---|---|---|"]
    rows += [f"| SAM 3 (predicted, lower bound) | {gpu} | {c['refresh_s']:.3f} | {c['run_s']:.1f} | {c['per_update_s']:.3f} |"
             for gpu, c in costs["sam3"].items() if gpu != "counted"]
    auto = costs["auto"]
    rows.append(f"| auto (measured, one CPU thread) | any | {auto['refresh_s']:.2f} | {auto['run_s']:.1f} | "
                f"{auto['per_update_s']:.3f} |")
    movers = costs["movers"]
    rows.append(f"| + movers rigid (predicted from one CPU thread's measurements) | any | {movers['refresh_s']:.2f} "
                f"+ {movers['update_s']:.3f} per update | {movers['run_s']:.1f} | {movers['per_update_s']:.3f} |")
    return "\n".join(rows)
