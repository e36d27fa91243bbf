"""The weights check before loading (:func:`geco_guide.estimators.check_weights`): every
model of a run at once, in the words loading each would use."""

from __future__ import annotations

from pathlib import Path

import pytest

from geco_guide.estimators import EstimatorsConfig, check_weights, estimator_weight_sources
from geco_guide.estimators.loading import WeightsNotFoundError, WeightsSource


def test_every_missing_model_is_named_in_one_line(tmp_path: Path):
    cfg = EstimatorsConfig(geometry=str(tmp_path / "VGGT-1B"), flow="tiny-random",
                           segmenter=f"{tmp_path / 'dino'},{tmp_path / 'sam2'}")
    video = WeightsSource("model.id", str(tmp_path / "CogVideoX-5b"), "CogVideoX", ("model_index.json",))
    with pytest.raises(WeightsNotFoundError) as err:
        check_weights(cfg, segmenter=True, extra=[video])
    text = str(err.value)
    assert "\n" not in text and text.startswith("4 models lack their weights: (1) CogVideoX: local path ")
    for k, (name, key, example) in enumerate([
            ("CogVideoX", "model.id", "/path/to/CogVideoX-5b"),
            ("VGGT", "estimators.geometry", "/path/to/VGGT-1B"),
            ("Grounding DINO", "estimators.segmenter", "/path/to/grounding-dino-tiny,/path/to/sam2.1-hiera-tiny"),
            ("SAM 2 video", "estimators.segmenter", "/path/to/grounding-dino-tiny,/path/to/sam2.1-hiera-tiny")], 1):
        assert f"({k}) {name}: local path " in text and f"(config: {key}={example})" in text
    # one missing model: the line loading it would end in, with its config key
    with pytest.raises(WeightsNotFoundError) as err:
        check_weights(cfg)
    assert str(err.value).startswith("VGGT: local path ") and str(err.value).endswith(
        "(config: estimators.geometry=/path/to/VGGT-1B)")


def test_models_that_are_there_or_tiny_need_no_weights(tmp_path: Path):
    (tmp_path / "vggt").mkdir()
    cfg = EstimatorsConfig(geometry=str(tmp_path / "vggt"), flow="tiny-random", segmenter="tiny-random")
    check_weights(cfg, segmenter=True)
    assert [row.key for row in estimator_weight_sources(cfg, segmenter=True)] == ["estimators.geometry"]
    assert estimator_weight_sources(EstimatorsConfig(), segmenter=False)[1].source == "infinity1096/UFM-Base"
