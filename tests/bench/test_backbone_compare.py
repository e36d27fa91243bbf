"""``geco compare``: two GeCo-Eval runs of the same videos scored by different geometry
backbones, compared by Spearman over videos and over models (:mod:`geco_guide.bench.backbone_compare`).

End to end on tiny models (the tiny random VGGT, then the tiny random DA3 over the first run's
videos, one prompt, two seeds, two models); the statistics on hand-made run folders written by
GeCo-Eval's own CSV writer, checked against rank correlations computed here by hand.
"""

from __future__ import annotations

import csv
import json
import math
from pathlib import Path

import pytest

from geco_guide.__main__ import main as geco
from geco_guide.bench.backbone_compare import LABELS, compare_runs, comparison_markdown, read_run
from geco_guide.bench.geco_eval import csv_text
from geco_guide.loss.geco import CUES

MODELS = ("cogvideox-5b", "wan2.1-t2v-1.3b")
SUBSET = ["--preset", "tiny", "--limit", "1", "--seeds", "0", "1"]


def pearson_of_ranks(first: list[float], second: list[float]) -> float:
    """Spearman for samples without ties, written out: Pearson's correlation of the ranks."""
    ranks = [[sorted(values).index(v) + 1.0 for v in values] for values in (first, second)]
    means = [sum(r) / len(r) for r in ranks]
    centred = [[x - m for x in r] for r, m in zip(ranks, means)]
    product = sum(x * y for x, y in zip(*centred))
    return product / math.sqrt(sum(x * x for x in centred[0]) * sum(y * y for y in centred[1]))


@pytest.fixture(scope="module")
def two_backbones(tmp_path_factory) -> tuple[Path, Path, Path]:
    """(run scored by the tiny VGGT, the same videos scored by the tiny DA3, the comparison folder)."""
    root = tmp_path_factory.mktemp("backbones")
    vggt, da3, out = root / "vggt", root / "da3", root / "compare"
    assert geco(["geco-eval", *SUBSET, "--models", *MODELS, "--out", str(vggt)]) == 0
    videos = [f"{m}={vggt / 'videos' / m}" for m in MODELS]
    assert geco(["geco-eval", *SUBSET, "--videos", *videos, "--geometry-estimator", "tiny-random-da3",
                 "--out", str(da3)]) == 0
    assert geco(["compare", str(vggt), str(da3), "--out", str(out)]) == 0
    return vggt, da3, out


def csv_scores(run: Path, score: str) -> dict[tuple[str, str], float]:
    with open(run / "results.csv", encoding="utf-8") as fh:
        return {(row["model"], row["seed"]): float(row[score]) for row in csv.DictReader(fh)}


@pytest.mark.slow
def test_two_tiny_backbones_compared_end_to_end(two_backbones, capsys):
    vggt, da3, out = two_backbones
    comparison = json.loads((out / "comparison.json").read_text())
    assert set(comparison) == {"runs", "config_differences", "tiny_models", "videos", "spearman", "models", "created"}
    # the backbone of each run, as its summary.json records it
    assert comparison["runs"]["A"] == {"folder": str(vggt), "estimators": {"geometry": "tiny-random(seed=0)",
                                                                           "flow": "tiny-random(seed=0)"}}
    assert comparison["runs"]["B"]["estimators"]["geometry"] == "tiny-random-da3(seed=0)"
    assert comparison["config_differences"] == ['estimators.geometry: "tiny-random" -> "tiny-random-da3"']
    assert comparison["videos"] == {"paired": 4, "only_in_A": [], "only_in_B": [], "same_bytes": 4,
                                    "different_bytes": 0, "not_found": 0}
    for score in CUES:
        first, second = csv_scores(vggt, score), csv_scores(da3, score)
        assert first.keys() == second.keys() and first != second  # two backbones, two sets of scores
        keys = sorted(first)
        expected = pearson_of_ranks([first[k] for k in keys], [second[k] for k in keys])
        assert comparison["spearman"][score]["videos"] == pytest.approx(expected, abs=1e-12)
        assert comparison["spearman"][score]["n_videos"] == 4 and comparison["spearman"][score]["n_models"] == 2
        # per-model means: GeCo-Eval's own summary of each run (all its videos are paired)
        for label, run in zip(LABELS, (vggt, da3)):
            arms = json.loads((run / "summary.json").read_text())["arms"]
            for model in MODELS:
                assert comparison["models"][model][score][label] == pytest.approx(
                    arms[model]["groups"]["all"][score]["mean"], rel=1e-12)
    markdown = (out / "comparison.md").read_text()
    assert "geometry `tiny-random-da3(seed=0)`" in markdown and "| fused | " in markdown
    assert "| cogvideox-5b | 2 | " in markdown
    # a second run refuses to replace the comparison, --overwrite replaces it
    assert geco(["compare", str(vggt), str(da3), "--out", str(out)]) == 2
    assert "already exists" in capsys.readouterr().err
    assert geco(["compare", str(vggt), str(da3), "--out", str(out), "--overwrite"]) == 0


def write_run(folder: Path, geometry: str, rows: list[dict]) -> Path:
    """A GeCo-Eval folder with the report files the comparison reads, the CSV by GeCo-Eval's writer."""
    folder.mkdir()
    (folder / "results.csv").write_text(csv_text(rows), encoding="utf-8")
    (folder / "summary.json").write_text(json.dumps({"estimators": {"geometry": geometry, "flow": "ufm-base"},
                                                     "tiny_models": False}))
    (folder / "run.json").write_text(json.dumps({"config": {"estimators": {"geometry": geometry}}}))
    return folder


def row(model: str, seed: int, fused: float | None, *, guided: bool = False, error: str | None = None) -> dict:
    return {"model": model, "guided": guided, "prompt_id": "a1", "scenario": "object-centric", "camera": "slow",
            "seed": seed, "fused": fused, "motion": fused, "structure": fused, "video": f"videos/{model}/a1-s{seed}.mp4",
            "error": error}


def test_spearman_and_means_come_from_the_paired_scores(tmp_path):
    first = [row("m1", 0, 0.1), row("m1", 1, 0.2), row("m2", 0, 0.3), row("m2", 1, 0.4), row("m3", 0, 0.5),
             row("m3", 1, None, error="too short"), row("m1", 2, 0.9)]
    second = [row("m1", 0, 0.4), row("m1", 1, 0.3), row("m2", 0, 0.25), row("m2", 1, 0.2), row("m3", 0, 0.1),
              row("m3", 1, 0.05), row("m3", 0, 0.7, guided=True), row("m1", 2, None)]
    comparison = compare_runs(read_run(write_run(tmp_path / "a", "vggt-1b", first)),
                              read_run(write_run(tmp_path / "b", "da3-base", second)))
    # paired: the six videos both runs scored (m3 s1 failed in A, the guided one only B has); m1 s2
    # has no score in B, so five count
    assert comparison["videos"]["paired"] == 6 and comparison["videos"]["only_in_A"] == []
    assert comparison["videos"]["only_in_B"] == ["m3/a1-s1", "m3-guided/a1-s0"]
    assert comparison["videos"]["not_found"] == 6
    fused = comparison["spearman"]["fused"]
    assert fused["n_videos"] == 5 and fused["videos"] == pytest.approx(-1.0)  # B reverses A's ranking
    assert fused["n_models"] == 3 and fused["models"] == pytest.approx(-1.0)
    assert comparison["models"]["m1"]["fused"] == {"A": pytest.approx(0.15), "B": pytest.approx(0.35), "n": 2}
    assert comparison["models"]["m3"]["fused"] == {"A": pytest.approx(0.5), "B": pytest.approx(0.1), "n": 1}
    assert comparison["config_differences"] == ['estimators.geometry: "vggt-1b" -> "da3-base"']
    markdown = comparison_markdown(comparison)
    assert "- A: " in markdown and "geometry `da3-base`" in markdown and "| fused | -1 | 5 | -1 | 3 |" in markdown


def test_runs_that_cannot_be_compared_are_one_line(tmp_path, capsys):
    left = write_run(tmp_path / "a", "vggt-1b", [row("m1", 0, 0.1)])
    right = write_run(tmp_path / "b", "da3-base", [row("m1", 1, 0.1)])
    empty = tmp_path / "empty"
    empty.mkdir()
    for runs, problem in (([left, right], "share no scored video"), ([left, empty], "holds no GeCo-Eval report"),
                          ([left, tmp_path / "nowhere"], "no such folder")):
        assert geco(["compare", *map(str, runs), "--out", str(tmp_path / "out")]) == 2
        err = capsys.readouterr().err
        assert err.startswith("error: ") and problem in err and err.count("\n") == 1, err
    assert not (tmp_path / "out").exists()
