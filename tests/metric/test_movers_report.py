"""evaluate_video with ``evaluation.loss.movers="rigid"``: the movers named in the result and its JSON,
their share of the fused score, the maps outlining them, and the option checked before any model
loads."""

from __future__ import annotations

import json
from dataclasses import replace

import pytest
import torch

from geco_guide.estimators.bundle import Estimators
from geco_guide.bench.synthetic import moving_clip
from geco_guide.config import to_config
from geco_guide.estimators.oracle import OracleFlow, OracleGeometry
from geco_guide.loss.presets import evaluation_loss
from geco_guide.metric.evaluate import evaluate_video, render_maps
from geco_guide.metric.protocol import EvaluationConfig
from geco_guide.metric.render import OUTLINE_COLOR, outline


@pytest.fixture(scope="module")
def clip():
    return moving_clip(5, 32, 48)


def _evaluate(clip, movers, masks, **kwargs):
    return evaluate_video(clip.frames.float(), Estimators(OracleGeometry(clip), OracleFlow(clip)),
                          EvaluationConfig(loss=replace(evaluation_loss(), movers=movers)), fps=8.0, dynamic_masks=masks, **kwargs)


def test_the_report_names_every_mover(clip):
    result = _evaluate(clip, "rigid", "auto", maps=True)
    data = json.loads(json.dumps(result.to_dict()))
    movers = data["movers"]
    assert movers["mode"] == "rigid" and movers["rigid"] == 2 and movers["non_rigid"] == 0
    for row in movers["movers"]:
        assert set(row) == {"window", "id", "frames", "pixels", "inlier_fraction", "residual", "verdict", "share"}
        assert row["window"] == 0 and row["frames"] == [0, 1, 2, 3, 4] and row["pixels"] > 50
        assert row["verdict"] == "rigid" and row["inlier_fraction"] >= 0.8 and 0 <= row["share"] < 1
    assert movers["share"] == pytest.approx(sum(row["share"] for row in movers["movers"]))
    assert data["config"]["loss"]["movers"] == "rigid" and "movers" not in data["config"]
    # scored against their own motion, the boxes are as consistent as the background
    dropped = _evaluate(clip, "drop", "auto")
    assert "movers" not in dropped.to_dict()
    assert result.fused < 5 * dropped.fused
    assert result.fused < 0.01 * _evaluate(clip, "drop", None).fused


def test_the_maps_outline_each_mover_on_the_static_colour_scale(clip):
    result = _evaluate(clip, "rigid", clip.dynamic_mask, maps=True)
    maps = result.maps
    assert maps.movers is not None and torch.equal(maps.movers > 0, clip.dynamic_mask)
    assert not maps.dynamic_masks.any()  # every mover rigid: nothing left out, nothing striped
    assert maps.fused_valid[clip.dynamic_mask].any()  # the movers' residual is on the map
    video = render_maps(result)
    white = (video == torch.tensor(OUTLINE_COLOR)[:, None, None]).all(1)
    plain = render_maps(_evaluate(clip, "drop", clip.dynamic_mask, maps=True))
    assert int(white.sum()) > int((plain == torch.tensor(OUTLINE_COLOR)[:, None, None]).all(1).sum())
    image = outline(torch.zeros(3, 6, 6), torch.tensor([[0, 0, 0, 0, 0, 0]] + [[0, 1, 1, 1, 2, 0]] * 3 + [[0] * 6] * 2))
    assert image[0].tolist()[1:4] == [[0, 1, 1, 1, 1, 0], [0, 1, 0, 1, 1, 0], [0, 1, 1, 1, 1, 0]]


def test_rigid_movers_need_masks_and_a_known_mode(clip):
    with pytest.raises(ValueError, match="movers='rigid' scores the movers of dynamic masks"):
        evaluate_video(clip.frames.float(), fps=8.0, config=EvaluationConfig(loss=replace(evaluation_loss(), movers="rigid")))  # before any model loads
    assert to_config({"evaluation": {"loss": {"movers": "rigid"}}}).evaluation.loss.movers == "rigid"
    with pytest.raises(ValueError, match=r"invalid value for config key 'evaluation.loss.movers': .*must be one of \('drop', 'rigid'\)"):
        to_config({"evaluation": {"loss": {"movers": "score"}}})
    # the earlier spelling, refused in one line naming the one key
    with pytest.raises(ValueError, match=r"^evaluation.movers is the earlier name of evaluation.loss.movers: use "
                                         r"evaluation.loss.movers instead \(config\)$"):
        to_config({"evaluation": {"movers": "rigid"}})
    with pytest.raises(TypeError, match=r"EvaluationConfig\(movers=...\) is the earlier spelling of "
                                        r"EvaluationConfig\(loss=GeCoLossConfig\(movers=...\)\)"):
        EvaluationConfig(movers="rigid")
