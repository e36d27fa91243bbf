"""Every number GeCo computes on fixed inputs with ``movers="drop"`` (the default), for the
before/after check of tests/loss/test_movers_drop.py: ``python tests/drop_reference.py``
rewrote ``tests/fixtures/drop_reference.pt`` with the code before
``movers`` existed. The automatic masks' cases (``auto``) were rewritten when those masks changed
(the target's depth read on one surface, movers followed into their unmatched pixels); the
others are still the first run's."""

from __future__ import annotations

from pathlib import Path

import torch

from geco_guide.estimators.bundle import Estimators
from geco_guide.bench.synthetic import inject_deformation, moving_clip
from geco_guide.estimators.motion_masks import MotionMasks
from geco_guide.estimators.oracle import OracleFlow, OracleGeometry
from geco_guide.loss.geco import GeCoLoss, GeCoLossConfig
from geco_guide.loss.presets import evaluation_loss, guidance_loss
from geco_guide.metric.evaluate import evaluate_video

FIXTURE = Path(__file__).resolve().parent / "fixtures" / "drop_reference.pt"


def reference_clip():
    """A moving scene (two boxes moving on their own) with a deformation, 5 frames of 24x32."""
    return inject_deformation(moving_clip(5, 24, 32), amplitude=2.0, seed=3)


def _masks(clip, kind):
    return {"none": None, "true": clip.dynamic_mask, "auto": MotionMasks()}[kind]


def _result_numbers(result) -> dict:
    numbers = {name: getattr(result, name).detach() for name in ("loss", "motion", "structure", "fused")}
    for group in ("pair_maps", "frame_maps"):
        maps = getattr(result, group)
        for name in ("motion", "motion_valid", "structure", "structure_valid", "fused", "fused_valid"):
            numbers[f"{group}.{name}"] = getattr(maps, name).detach()
    for name, value in result.frame_scores.items():
        numbers[f"frame_scores.{name}"] = value.detach()
        numbers[f"frame_has_valid.{name}"] = result.frame_has_valid[name]
    if result.dynamic_masks is not None:
        numbers["dynamic_masks"] = result.dynamic_masks
        numbers["masked_fraction"] = result.masked_fraction
    return numbers


def loss_numbers(tiny=None) -> dict:
    """``{case: {name: tensor}}``: GeCoLoss with the oracle estimators (evaluation and guidance
    options; no, true and automatic masks) and, given ``tiny``, the tiny estimators' bundle, the tiny
    estimators' loss and its gradient on the frames."""
    clip = reference_clip()
    frames = clip.frames.float()[None]
    out = {}
    for options_name, options in (("evaluation", evaluation_loss()), ("guidance", guidance_loss()), ("default", GeCoLossConfig())):
        loss = GeCoLoss(Estimators(OracleGeometry(clip), OracleFlow(clip)), options)
        for kind in ("none", "true", "auto"):
            out[f"oracle/{options_name}/{kind}"] = _result_numbers(loss(frames, dynamic_masks=_masks(clip, kind)))
    if tiny is not None:
        loss = GeCoLoss(tiny, GeCoLossConfig(pairs="adjacent"))
        for kind in ("none", "true"):
            x = frames.clone().requires_grad_(True)
            result = loss(x, dynamic_masks=_masks(clip, kind))
            result.loss.backward()
            out[f"tiny/{kind}"] = {**_result_numbers(result), "grad": x.grad.detach()}
    return out


def evaluation_numbers() -> dict:
    """``{kind: (to_dict(), {map name: tensor})}``: evaluate_video with the oracle estimators at 8
    fps with maps, with no, true and automatic masks."""
    clip = reference_clip()
    out = {}
    for kind in ("none", "true", "auto"):
        result = evaluate_video(clip.frames.float(), Estimators(OracleGeometry(clip), OracleFlow(clip)), fps=8.0,
                                maps=True, dynamic_masks=_masks(clip, kind))
        maps = {name: getattr(result.maps, name) for name in ("motion", "motion_valid", "structure", "structure_valid",
                                                              "fused", "fused_valid", "frames")}
        if result.maps.dynamic_masks is not None:
            maps["dynamic_masks"] = result.maps.dynamic_masks
        out[kind] = (result.to_dict(), maps)
    return out


if __name__ == "__main__":
    from geco_guide.tiny import tiny_estimators

    torch.save({"loss": loss_numbers(tiny_estimators(0)), "evaluation": evaluation_numbers()}, FIXTURE)
    print(f"wrote {FIXTURE}")
