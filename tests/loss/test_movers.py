"""Movers scored against their own rigid motion (``movers="rigid"``): the movers found and linked,
the verdicts, the scores of rigid and non-rigid movers, the fit reused, the options checked, and
the loss as a guidance loss: gradient descent on the frames of a deforming mover lowers its residual."""

from __future__ import annotations

from dataclasses import replace

import pytest
import torch
import torch.nn.functional as F

from geco_guide.estimators.bundle import Estimators
from geco_guide.bench.synthetic import MovingBox, moving_boxes, moving_clip
from geco_guide.estimators.oracle import OracleFlow, OracleGeometry
from geco_guide.loss.geco import GeCoLoss, GeCoLossConfig, frame_pairs, geco_from_geometry
from geco_guide.loss.movers import MoverFit, RefreshedMovers, link_movers
from geco_guide.loss.presets import evaluation_loss, guidance_loss
from geco_guide.metric.protocol import EvaluationConfig
from geco_guide.types import Correspondences, OptionError


@pytest.fixture(scope="module")
def moving():
    return moving_clip(5, 48, 64)


@pytest.fixture(scope="module")
def stretching():
    box = moving_boxes()[0]
    return moving_clip(5, 48, 64, movers=[MovingBox(box.box, (0.0, 0.0, 0.0), stretch=(0.1, 0.0, 0.0))])


def _score(clip, masks, movers="rigid", mode="all", fit=None):
    pairs = frame_pairs(clip.num_frames, mode)
    config = replace(evaluation_loss(), pairs=mode, movers=movers)
    return geco_from_geometry(clip.geometry(), clip.pair_correspondences(pairs), pairs, config, masks, movers=fit)


def test_movers_are_the_mask_regions_linked_along_the_flow(moving):
    pairs = frame_pairs(5, "adjacent")
    labels = link_movers(moving.dynamic_mask, moving.pair_correspondences(pairs).flow, pairs)
    assert labels.shape == moving.dynamic_mask.shape and torch.equal(labels > 0, moving.dynamic_mask)
    # one id per box, the same in every frame: the ids follow the true objects
    for box in (0, 1):
        assert len(labels[moving.objects == box].unique()) == 1
    assert labels[moving.objects == 0].unique() != labels[moving.objects == 1].unique()


def test_rigid_movers_are_scored_against_their_own_motion(moving):
    result = _score(moving, moving.dynamic_mask)
    rows = result.movers.records()
    assert [row["verdict"] for row in rows] == ["rigid", "rigid"] and all(row["inlier_fraction"] > 0.9 for row in rows)
    assert all(row["frames"] == [0, 1, 2, 3, 4] and row["pixels"] > 100 for row in rows)
    # the boxes' pixels count again, and with their own motion they are as consistent as the background
    drop = _score(moving, moving.dynamic_mask, movers="drop")
    on_boxes = moving.dynamic_mask[None]
    assert not (drop.frame_maps.fused_valid & on_boxes).any() and (result.frame_maps.fused_valid & on_boxes).sum() > 500
    assert all(row["residual"] < 1e-3 for row in rows)
    nothing = _score(moving, None, movers="drop")
    assert float(result.fused) < 0.01 * float(nothing.fused)
    # the shares are each mover's part of the fused score
    static = float(result.fused) * (1 - sum(row["share"] for row in rows))
    assert 0 < static < float(result.fused)
    assert result.movers.contribution.sum() == pytest.approx(float(result.fused) * sum(row["share"] for row in rows))


def test_a_non_rigid_mover_is_left_out_as_with_drop(stretching):
    result = _score(stretching, stretching.dynamic_mask)
    rows = result.movers.records()
    assert [row["verdict"] for row in rows] == ["non-rigid"] and rows[0]["inlier_fraction"] < 0.8
    assert rows[0]["residual"] is None and rows[0]["share"] == 0.0
    assert torch.equal(result.movers.dropped[0], stretching.dynamic_mask)
    drop = _score(stretching, stretching.dynamic_mask, movers="drop")
    assert torch.equal(result.frame_maps.fused, drop.frame_maps.fused) and float(result.fused) == float(drop.fused)


def test_a_fit_is_reused_and_refreshed_on_request(moving):
    first = _score(moving, moving.dynamic_mask, mode="adjacent")
    again = _score(moving, moving.dynamic_mask, mode="adjacent", fit=first.movers.fit)
    assert again.movers.fit is first.movers.fit and float(again.fused) == float(first.fused)
    cache = RefreshedMovers(seed=0)
    pairs = frame_pairs(5, "adjacent")
    masks = moving.dynamic_mask[None]
    args = (masks, moving.geometry(), moving.pair_correspondences(pairs), pairs)
    fit = cache.fit(*args)
    assert isinstance(fit, MoverFit) and cache.fit(*args) is fit
    cache.refresh()
    refitted = cache.fit(*args)
    assert refitted is not fit and torch.equal(refitted.assignment, fit.assignment)  # seeded: the same answer
    assert cache.fit(masks[:, :4], *args[1:3], pairs[:3]) is not refitted  # other frames: fitted for them
    with pytest.raises(ValueError, match=r"unknown mover fit option\(s\) \['dilation'\]"):
        RefreshedMovers(dilation=2)


def test_movers_options_are_checked_in_one_line(moving):
    with pytest.raises(OptionError, match="movers.*must be one of"):
        GeCoLossConfig(movers="score")
    with pytest.raises(ValueError, match="movers='rigid' scores the movers of dynamic masks"):
        _score(moving, None)
    fit = _score(moving, moving.dynamic_mask).movers.fit
    with pytest.raises(ValueError, match="a movers fit was given but movers='drop'"):
        _score(moving, moving.dynamic_mask, movers="drop", fit=fit)
    # one spelling, the loss' own: the evaluation's earlier one is refused naming it
    assert EvaluationConfig(loss=GeCoLossConfig(movers="rigid")).loss.movers == "rigid"
    with pytest.raises(TypeError, match=r"EvaluationConfig\(movers=...\) is the earlier spelling"):
        EvaluationConfig(movers="rigid")
    assert EvaluationConfig().loss == evaluation_loss()


class CarriedFlow:
    """The clip's true flow plus a displacement the frames carry (a test double, differentiable):
    the first two channels of each source frame's difference from the clean frame, times
    ``scale`` pixels. Frames with such a difference on a mover show a mover that changes shape."""

    def __init__(self, clip, scale: float):
        self.oracle, self.clean, self.scale = OracleFlow(clip), clip.frames.float(), scale

    def estimate_flow(self, source, target):
        base = self.oracle.estimate_flow(source.detach(), target.detach())
        clean = F.interpolate(self.clean, size=source.shape[-2:], mode="bilinear", align_corners=False)
        carried = (source - clean[self.oracle.lookup.indices(source)])[:, :2] * self.scale
        return Correspondences(base.flow + carried, base.covisibility)


def test_gradient_descent_on_the_frames_of_a_deforming_mover_lowers_its_residual(moving):
    on_box = (moving.objects == 0)[:, None].float()  # [S, 1, H, W]
    rows = torch.arange(48, dtype=torch.float32)[:, None]
    middle = float((moving.objects == 0).nonzero()[:, 1].float().mean())
    bump = torch.exp(-((rows - middle) / 2.0) ** 2)  # a band across the box: a part of it moves on its own
    deformation = 0.006 * bump * on_box * torch.arange(5.0)[:, None, None, None]  # grows frame by frame
    frames = (moving.frames.float() + deformation.expand(-1, 3, -1, -1)).clamp(0, 1)[None]
    config = replace(guidance_loss(), flow_downscale=1.0, movers="rigid")
    loss = GeCoLoss(Estimators(OracleGeometry(moving), CarriedFlow(moving, scale=100.0)), config, check_values=False)
    cache = RefreshedMovers()  # fitted once, detached, on the deformed frames; reused by every step
    first = loss(frames, dynamic_masks=moving.dynamic_mask, movers=cache)
    box_rows = [row for row in first.movers.records() if row["verdict"] == "rigid"]
    assert len(box_rows) == 2  # both boxes keep a rigid verdict: the deformation is a part of one
    x = frames.clone().requires_grad_(True)
    residuals = []
    for _ in range(15):
        result = loss(x, dynamic_masks=moving.dynamic_mask, movers=cache)
        assert result.movers.fit is first.movers.fit
        residuals.append(float(result.movers.contribution.sum()))
        x.grad = None
        result.loss.backward()
        with torch.no_grad():
            x -= 0.03 * x.grad / x.grad.norm()
    assert residuals[-1] < 0.5 * residuals[0], residuals
    # the gradient reached the mover's pixels: with movers="drop" it could not (they are masked)
    dropped = GeCoLoss(Estimators(OracleGeometry(moving), CarriedFlow(moving, 100.0)), replace(config, movers="drop"),
                       check_values=False)
    y = frames.clone().requires_grad_(True)
    dropped(y, dynamic_masks=moving.dynamic_mask).loss.backward()
    assert float(y.grad[0, :, :2].abs().mul(on_box).sum()) == 0.0 and float(x.grad[0, :, :2].abs().mul(on_box).sum()) > 0
