"""``geco ab --best-of matched``: N capped at the spacing of the run's seeds, and the candidates
that pairs share said before the run (not only in its report)."""

from __future__ import annotations

import pytest

from geco_guide.bench import ab as core
from geco_guide.bench import ab_run
from geco_guide.cli import ab
from geco_guide.perf import guided_ratio


@pytest.mark.parametrize("seeds, n, matched_n", [
    ([0], 48, None),  # one pair: nothing to share
    ([0, 100], 48, None),  # far enough apart
    ([0, 25, 10], 10, 48),  # the least spacing, in any order
    ([0, 1], 2, 48),  # adjacent seeds: a best-of arm's least N
    ([0, 1], 2, None),  # the ratio's N is no more than that: no cap
])
def test_matched_n_is_capped_at_the_least_spacing_of_the_seeds(seeds, n, matched_n):
    ratio = 48.2 if matched_n or n == 48 else 1.6
    best_of = core.matched_best_of(ratio, "H100", seeds)
    assert (best_of.n, best_of.matched_n, best_of.predicted_ratio, best_of.gpu) == (n, matched_n, ratio, "H100")
    assert ("capped at" in best_of.how) == (matched_n is not None)


def test_shared_candidates_name_the_closest_seeds_and_the_spacing_to_give():
    assert core.shared_candidates([0, 10], 10) is None and core.shared_candidates([7], 100) is None
    assert core.shared_candidates([0, 100, 1], 2) == (
        "seeds less than 2 apart share best-of-2 candidates (seed 1 is a candidate of seed 0's pair and the unguided "
        "video of its own): for independent pairs give seeds at least 2 apart")


def test_the_cap_and_the_shared_candidates_are_said_before_anything_is_generated(tmp_path, capsys, monkeypatch):
    chosen = []
    monkeypatch.setattr(guided_ratio, "predicted_ratio", lambda cfg, gpu: 48.2)  # the tiny models on an H100
    monkeypatch.setattr(ab_run, "execute", lambda inputs, *args, **kwargs: chosen.append(inputs.best_of))
    prompts = tmp_path / "p.txt"
    prompts.write_text("a cat\n")
    argv = ["--prompts", str(prompts), "--out", str(tmp_path / "out"), "--preset", "tiny", "--seeds", "0", "1",
            "--best-of", "matched", "--gpu", "H100"]
    assert ab.main(argv) == 0
    assert chosen == [core.BestOf(2, "H100", 48.2, matched_n=48)]
    assert capsys.readouterr().err.splitlines() == [
        "note: --best-of matched: N = 48 predicted on the H100, capped at 2, the least spacing of --seeds: give seeds "
        "at least 48 apart for N = 48",
        "warning: --best-of 2: seeds less than 2 apart share best-of-2 candidates (seed 1 is a candidate of seed 0's "
        "pair and the unguided video of its own): for independent pairs give seeds at least 2 apart"]
