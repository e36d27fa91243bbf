"""Choosing the geometry backbone: ``estimators.geometry`` / ``--geometry-estimator`` names
VGGT-1B (the default), DA3-SMALL or DA3-BASE; ``load_estimators`` builds the one named, offline
without its weights ends in one line naming the hub id, and results record which backbone scored
them.

The end-to-end case puts a tiny random Depth Anything 3 where the hub cache keeps
``depth-anything/DA3-BASE`` (the cache layout: ``models--owner--name/refs/main`` naming a
snapshot folder holding ``config.json`` and ``model.safetensors``) and runs ``geco evaluate
--preset tiny --geometry-estimator da3-base`` offline: the same code path the published weights
take, at the tiny stand-in's cost.
"""

from __future__ import annotations

import json
from pathlib import Path

import huggingface_hub.constants as hub_constants
import pytest
import torch

from geco_guide.cli import evaluate as evaluate_cli
from geco_guide.estimators import (
    TINY_RANDOM_DA3,
    EstimatorsConfig,
    estimator_ids,
    geometry_architecture,
    load_estimators,
)
from geco_guide.estimators.da3 import DA3, DA3Config
from geco_guide.estimators.loading import WeightsNotFoundError
from geco_guide.io.video import write_video

SNAPSHOT = "0" * 40


@pytest.fixture
def offline_cache(tmp_path: Path, monkeypatch) -> Path:
    """An empty hub cache, offline."""
    cache = tmp_path / "hub"
    cache.mkdir()
    monkeypatch.setattr(hub_constants, "HF_HUB_CACHE", str(cache))
    monkeypatch.setattr(hub_constants, "HF_HUB_OFFLINE", True)
    return cache


def _cache_tiny_da3(cache: Path, repo_id: str) -> None:
    """A tiny random DA3 as the cached snapshot of ``repo_id``."""
    repo = cache / f"models--{repo_id.replace('/', '--')}"
    DA3.random(DA3Config.tiny(), seed=3).save_pretrained(repo / "snapshots" / SNAPSHOT)
    (repo / "refs").mkdir()
    (repo / "refs" / "main").write_text(SNAPSHOT)


def test_default_stays_vggt_and_names_resolve_to_hub_ids() -> None:
    assert EstimatorsConfig().geometry == "facebook/VGGT-1B"
    assert geometry_architecture(EstimatorsConfig().geometry) == "vggt"
    for name, repo in (("vggt-1b", "facebook/VGGT-1B"), ("da3-small", "depth-anything/DA3-SMALL"),
                       ("da3-base", "depth-anything/DA3-BASE")):
        assert estimator_ids(EstimatorsConfig(geometry=name))["geometry"] == repo
    assert geometry_architecture("da3-small") == geometry_architecture("depth-anything/DA3-BASE") == "da3"
    assert estimator_ids(EstimatorsConfig(geometry=TINY_RANDOM_DA3))["geometry"] == "tiny-random-da3(seed=0)"


@pytest.mark.slow
def test_a_saved_folder_is_read_as_what_it_holds(tmp_path: Path) -> None:
    folder = DA3.random(DA3Config.tiny(), seed=0).save_pretrained(tmp_path / "mine")
    assert geometry_architecture(str(folder)) == "da3"
    (tmp_path / "published").mkdir()
    (tmp_path / "published" / "config.json").write_text(json.dumps({"model_name": "da3-small"}))
    assert geometry_architecture(str(tmp_path / "published")) == "da3"
    assert geometry_architecture(str(tmp_path / "nothing")) == "vggt"


def test_tiny_random_da3_loads_as_the_geometry_estimator() -> None:
    cfg = EstimatorsConfig(geometry=TINY_RANDOM_DA3, flow="tiny-random", dtype="float32")
    estimators = load_estimators(cfg, "cpu")
    assert isinstance(estimators.geometry, DA3)
    assert estimators.ids() == {"geometry": "tiny-random-da3(seed=0)", "flow": "tiny-random(seed=0)"}


def test_offline_without_weights_is_one_line_naming_the_hub_id(offline_cache: Path) -> None:
    cfg = EstimatorsConfig(geometry="da3-base", flow="tiny-random", dtype="float32")
    with pytest.raises(WeightsNotFoundError) as info:
        load_estimators(cfg, "cpu")
    message = str(info.value)
    assert "\n" not in message and message.startswith("DA3: could not load weights for 'depth-anything/DA3-BASE'")
    assert "(config: estimators.geometry=/path/to/DA3-BASE)" in message


def test_geco_evaluate_without_the_weights_says_so_before_loading(tmp_path: Path, offline_cache: Path,
                                                                  capsys) -> None:
    video = write_video(tmp_path / "v.mp4", torch.rand(9, 3, 24, 32, generator=torch.Generator().manual_seed(0)),
                        fps=8)
    code = evaluate_cli.main(["--preset", "tiny", str(video), "--out", str(tmp_path / "out"),
                              "--geometry-estimator", "da3-small"])
    err = capsys.readouterr().err.strip().splitlines()
    assert code == 2 and "'depth-anything/DA3-SMALL'" in err[-1], err
    assert "(config: estimators.geometry=/path/to/DA3-SMALL)" in err[-1], err


@pytest.mark.slow
def test_geco_evaluate_scores_with_da3_base_end_to_end(tmp_path: Path, offline_cache: Path, capsys) -> None:
    _cache_tiny_da3(offline_cache, "depth-anything/DA3-BASE")
    video = write_video(tmp_path / "v.mp4", torch.rand(9, 3, 24, 32, generator=torch.Generator().manual_seed(0)),
                        fps=8)
    code = evaluate_cli.main(["--preset", "tiny", str(video), "--out", str(tmp_path / "out"),
                              "--geometry-estimator", "da3-base"])
    assert code == 0, capsys.readouterr().err
    data = json.loads((tmp_path / "out" / "v.geco.json").read_text())
    assert data["estimators"]["geometry"] == "depth-anything/DA3-BASE"
    assert data["fused"] is not None
