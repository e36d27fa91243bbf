"""``geco ab``'s search arm: particle search beside guidance and best-of-N at matched compute.

The K rule of ``--search matched`` on given times; the report's paired statistics of every arm
against the unguided one, Total Motion and its flag, on hand-made records; and end to end on the
tiny preset (2 steps, in process): the search arm added to a finished run without redoing the
others, a run stopped after a pair resumed with nothing redone, K matched from the run's own
measured times and kept for the folder, and the same noise as the other arms.
"""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import pytest

from geco_guide.bench import ab as core
from geco_guide.bench import ab_report, ab_run, ab_stats
from geco_guide.bench.report import MIN_INTERVAL_N
from geco_guide.cli import ab
from geco_guide.cli.prompt_files import Prompt
from geco_guide.config import load_config
from geco_guide.io.video import read_video

FAST = [  # the tiny preset, shortened: 9 frames, 2 steps with one guided update each, 5 scored frames
    "--preset", "tiny", "sampling.num_frames=9", "guidance.anchors=[4,8]", "sampling.num_inference_steps=2",
    "guidance.repeats=1x2", "guidance.time_travel=[]", "output.score_anchors=false", "evaluation.max_fps=4",
]
PAIRS = ("a-marble-bust-s0", "bridge-s0")


def _argv(prompts: Path, out: Path, *extra: str) -> list[str]:
    return ["--prompts", str(prompts), "--seeds", "0", "--out", str(out), *FAST, *extra]


def _files(folder: Path, arms: tuple[str, ...] = core.ARMS) -> dict[str, bytes]:
    """The videos and sidecars of ``arms`` in every pair folder of ``folder``."""
    return {str(p.relative_to(folder)): p.read_bytes() for arm in arms for ext in (".mp4", ".json")
            for p in sorted(folder.glob(f"pairs/*/{arm}{ext}"))}


@pytest.fixture(scope="module")
def prompts_file(tmp_path_factory: pytest.TempPathFactory) -> Path:
    path = tmp_path_factory.mktemp("prompts") / "prompts.txt"
    path.write_text('a marble bust\n{"id": "bridge", "prompt": "a stone bridge over a river"}\n')
    return path


@pytest.fixture(scope="module")
def two_arms(prompts_file: Path, tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A finished run of the unguided and guided arms, 2 prompts x 1 seed."""
    out = tmp_path_factory.mktemp("ab") / "two-arms"
    assert ab.main(_argv(prompts_file, out)) == 0
    return out


@pytest.fixture(scope="module")
def searched(two_arms: Path, prompts_file: Path, tmp_path_factory: pytest.TempPathFactory) -> Path:
    """``two_arms`` rerun with ``--search 2``: the arm added to its finished pairs."""
    out = tmp_path_factory.mktemp("ab") / "searched"
    shutil.copytree(two_arms, out)
    assert ab.main(_argv(prompts_file, out, "--search", "2")) == 0
    return out


# ----------------------------------------------------------------------------------------------
# the K of --search matched


def test_matched_k_is_the_largest_search_within_the_guided_arm_s_time():
    # each particle: an unguided video (1 s) and 2 scorings (0.5 s each): 2 s
    assert core.matched_particles(1.0, 10.0, 0.5, 2) == (5, True)
    assert core.matched_particles(1.0, 11.9, 0.5, 2) == (5, True)
    assert core.matched_particles(1.0, 6.0, 0.5, 2) == (3, True)  # exactly the guided arm's time
    assert core.matched_particles(1.0, 10.0, 0.0, 0) == (10, True)  # no resampling step: best-of-K in one call
    assert core.matched_particles(1.0, 3.0, 0.5, 2) == (2, False)  # even the least search costs more
    assert core.matched_particles(0.1, 0.3, 0.0, 0) == (2, True)  # 3 x 0.1 > 0.3 in floats: the expectation decides
    assert core.matched_particles(0.001, 1e6, 0.0, 3) == (core.MAX_PARTICLES, True)
    assert core.expected_search_s(5, 1.0, 0.5, 2) == 10.0
    for bad in ((0.0, 10.0, 0.0, 2), (float("nan"), 10.0, 0.5, 2), (1.0, -1.0, 0.5, 2)):
        with pytest.raises(ValueError, match="matched K needs"):
            core.matched_particles(*bad)


def test_a_recorded_choice_is_read_back_and_a_damaged_one_is_named(tmp_path: Path, capsys):
    assert core.read_matched_search(tmp_path) is None
    chosen = {"particles": 3, "pair": "p-s0", "unguided_s": 1.0, "guided_s": 7.0, "scoring_s": 0.5, "resamplings": 2,
              "expected_s": 6.0}
    (tmp_path / core.MATCHED_SEARCH_FILE).write_text(json.dumps(chosen))
    assert core.read_matched_search(tmp_path, warn=True) == chosen
    for damaged in ('{"particles": 3', json.dumps({**chosen, "particles": 1}), json.dumps({"particles": 3})):
        (tmp_path / core.MATCHED_SEARCH_FILE).write_text(damaged)
        assert core.read_matched_search(tmp_path, warn=True) is None
        assert capsys.readouterr().err == (f"warning: {tmp_path / core.MATCHED_SEARCH_FILE} is damaged; the search's "
                                           "K is matched again\n")


# ----------------------------------------------------------------------------------------------
# the report on hand-made records


def _arm(fused: float, motion: float, seconds: float) -> dict:
    return {"video": "v.mp4", "sidecar": "v.json", "fused": fused, "motion": fused / 2, "structure": fused / 2,
            "total_motion": motion, "mean_motion": 8 * motion, "generation_s": seconds, "evaluation_s": 0.1,
            "peak_memory_mib": 10.0, "memory_kind": "cpu_peak_rss", "guidance_updates": 0}


def _results(count: int) -> list[dict]:
    """Pairs where guidance lowers fused by 0.02 at the same motion, best-of by 0.01 + 0.001 k, and
    search by 0.03 while moving 40 % less."""
    results = []
    for k in range(count):
        search = {**_arm(0.17, 3.0, 9.0), "search": {"particles": 4, "kept_seed": k + 2, "resampling_s": 1.5}}
        results.append({"pair": f"p{k}-s0", "prompt_id": f"p{k}", "prompt": f"p{k}", "seed": 0, "device": "cpu",
                        "side_by_side": "side_by_side.mp4",
                        "arms": {"unguided": _arm(0.2, 5.0, 2.0), "guided": _arm(0.18, 5.0, 10.0),
                                 "best_of": {**_arm(0.19 - 0.001 * k, 5.5, 8.0), "best_of": {"kept_seed": k}},
                                 "search": search}})
    return results


def test_every_arm_against_unguided_with_paired_intervals_motion_and_cost():
    cfg = load_config(preset="tiny")
    matched = {"particles": 4, "pair": "p1-s0", "unguided_s": 2.0, "guided_s": 10.0, "scoring_s": 0.25,
               "resamplings": 2, "expected_s": 10.0, "fits": True, "warm_up": False}
    best_of, search = core.BestOf(4), core.SearchArm(4, matched=matched)
    results = _results(MIN_INTERVAL_N)
    pairs = core.plan_pairs([Prompt(f"p{k}", f"p{k}") for k in range(len(results))], [0])
    summary = ab_stats.summarize(results, pairs, cfg, {}, best_of, search)

    vs = summary["search"]["vs_unguided"]
    assert vs["paired_differences"]["fused"]["mean_diff"] == pytest.approx(-0.03)
    low, high = vs["paired_differences"]["fused"]["ci95"]
    assert low == pytest.approx(-0.03) and high == pytest.approx(-0.03)  # the same difference in every pair
    assert vs["lowered_fused"] == {"count": MIN_INTERVAL_N, "n": MIN_INTERVAL_N, "fraction": 1.0}
    assert vs["total_motion_change"] == {"n": MIN_INTERVAL_N, "relative": pytest.approx(-0.4), "flagged": True}
    assert summary["guidance_total_motion_change"] == {"n": MIN_INTERVAL_N, "relative": 0.0, "flagged": False}
    assert summary["best_of"]["vs_unguided"]["total_motion_change"]["relative"] == pytest.approx(0.1)
    head = summary["search"]["guided_vs_search"]
    assert head["paired_differences"]["fused"]["mean_diff"] == pytest.approx(0.01) and head["lowered_fused"]["count"] == 0
    assert summary["search"]["particles"] == 4 and summary["search"]["chosen"] == "matched"
    assert summary["arms"]["search"]["resampling_s_mean"] == 1.5

    report = ab_report.report_markdown(summary, results, "", "cmd")
    for text in ("# GeCo guidance A/B: unguided vs guided vs best-of-4 vs search-4",
                 "| metric | guided - unguided | 95% CI (paired bootstrap) | best-of-4 - unguided | 95% CI (paired "
                 "bootstrap) | search-4 - unguided | 95% CI (paired bootstrap) |",
                 "| fused (M_geo) | -0.02 | [-0.02, -0.02] |",
                 f"search-4 in **{MIN_INTERVAL_N} of {MIN_INTERVAL_N}** pairs (100 %)",
                 "| search-4 | 0.17 | 3 | -40 % (10 pairs) | **moves less** |",
                 "| guided | 0.18 | 5 | +0 % (10 pairs) |  |",
                 "**Moves notably less than the unguided arm**: search-4 (-40 %)",
                 "| guided - best-of-4 |", "| guided - search-4 |",
                 "| search-4 | 9 | 0.9x | 0.1 |",  # its sampling as a share of the guided arm's
                 "K = 4, matched on this machine: the largest K >= 2 with K x (unguided 2 s + 2 resampling(s) x one "
                 "particle's scoring 0.25 s) <= guided 10 s, the times of pair p1-s0; expected 10 s",
                 "of which 1.5 s at the resampling steps",
                 "kept particle's seed (search-4)"):
        assert text in report, text
    assert ab_report.plot_png(results, best_of, search).startswith(b"\x89PNG")
    rows = ab_report.csv_text(results, core.run_arms(best_of, search)).splitlines()
    assert len(rows) == 1 + 4 * MIN_INTERVAL_N and sum(",search," in row for row in rows) == MIN_INTERVAL_N


def test_no_flag_where_every_arm_moves_about_as_much():
    results = _results(2)
    for result in results:
        result["arms"]["search"]["total_motion"] = 4.6  # 8 % less: within the rule
    summary = ab_stats.summarize(results, core.plan_pairs([Prompt("p0", "p0"), Prompt("p1", "p1")], [0]),
                             load_config(preset="tiny"), {}, None, core.SearchArm(4))
    assert not summary["search"]["vs_unguided"]["total_motion_change"]["flagged"]
    report = ab_report.report_markdown(summary, results, "", "cmd")
    assert "No arm's Total Motion drops by 10 % or more" in report and "moves less" not in report
    assert "K = 4, given (--search)" in report and "none from 2 pairs (an interval needs 10)" in report


# ----------------------------------------------------------------------------------------------
# bad values: one line before any work


@pytest.mark.parametrize("extra, message", [
    (["--search", "1"], "--search takes an integer >= 2 or 'matched', got 1 (a search of one particle is the unguided"),
    (["--search", "many"], "--search takes an integer >= 2 or 'matched', got 'many'"),
    (["--search-guided"], "--search-guided guides the search arm's particles; pass --search K too"),
    (["--search", "matched", "--search-guided"], "which no K >= 2 matches: pass an integer --search K"),
    (["--search", "3", "--seeds", str(2**63 - 2)], "--search 3 from seed 9223372036854775806 runs past"),
    (["--search", "2", "search.particles=3"], "search.particles=3 would make every arm a search"),
    (["--search", "2", "search.resample_steps=[5]"], "search.resample_steps [5] are outside the 2 denoising steps"),
])
def test_bad_search_values_are_one_line_before_any_work(extra, message, tmp_path, capsys, monkeypatch):
    def fail(*args, **kwargs):
        raise AssertionError("nothing must run for bad inputs")

    monkeypatch.setattr(ab_run, "execute", fail)
    (tmp_path / "p.txt").write_text("a cat\n")
    out = tmp_path / "out"
    assert ab.main(["--prompts", str(tmp_path / "p.txt"), "--out", str(out), *FAST, "--seeds", "0", *extra]) == 2
    err = capsys.readouterr().err
    assert err.startswith("error: ") and err.count("\n") == 1 and message in err, err
    assert not out.exists()


# ----------------------------------------------------------------------------------------------
# end to end, tiny preset


@pytest.mark.slow
def test_the_search_arm_is_added_to_a_finished_run_without_redoing_its_arms(two_arms: Path, searched: Path):
    assert _files(searched) == _files(two_arms)  # the unguided and guided arms: not made again
    for name in PAIRS:
        folder = searched / "pairs" / name
        result = json.loads((folder / "result.json").read_text())
        arm = result["arms"]["search"]
        made = json.loads((folder / "search.json").read_text())
        # the same noise: particle k from the pair's seed + k, particle 0 the pair's own
        assert made["seed"] == result["seed"] == 0 and made["config"]["search"]["particles"] == 2
        assert not made["config"]["guidance"]["enabled"] and made["guidance_log"] == []  # unguided particles
        kept = made["search"]["final_particles"][made["search"]["kept"]]
        assert [p["seed"] for p in made["search"]["final_particles"]] == [
            p["lineage"][0] for p in made["search"]["final_particles"]]
        assert arm["search"]["kept_seed"] == kept["seed"] and arm["search"]["particles"] == 2
        assert arm["generation_s"] == pytest.approx(made["timings"]["sampling_s"] - made["search"]["selection_s"])
        assert arm["search"]["resampling_s"] == pytest.approx(sum(r["seconds"] for r in made["search"]["resamplings"]))
        assert arm["warm_up"] == (name == PAIRS[0])  # the first search of the process
        three, _ = read_video(folder / "side_by_side.mp4")
        one, _ = read_video(folder / "unguided.mp4")
        assert three.shape[-1] >= 3 * one.shape[-1]  # unguided | guided | search-2
    summary = json.loads((searched / "summary.json").read_text())
    assert summary["search"]["particles"] == 2 and summary["search"]["chosen"] == "given"
    assert summary["search"]["vs_unguided"]["paired_differences"]["fused"]["n"] == 2
    assert summary["arms"]["search"]["timed_pairs"] == 1  # the warm-up left out
    assert "search_matched.json" not in {p.name for p in searched.iterdir()}  # a given K needs no record
    report = (searched / "report.md").read_text()
    assert "unguided vs guided vs search-2" in report and "K = 2, given (--search)" in report


@pytest.mark.slow
def test_a_run_stopped_after_a_pair_resumes_with_nothing_redone(searched: Path, two_arms: Path, prompts_file: Path,
                                                               tmp_path: Path, capsys, monkeypatch):
    out = tmp_path / "stopped"
    shutil.copytree(two_arms, out)
    made = []

    def stopped_after_one(*args, **kwargs):
        if made:
            raise KeyboardInterrupt  # Ctrl-C while the second pair's search arm runs
        made.append(real(*args, **kwargs))
        return made[-1]

    real = ab_run.add_search
    monkeypatch.setattr(ab_run, "add_search", stopped_after_one)
    assert ab.main(_argv(prompts_file, out, "--search", "2")) == 130
    first = out / "pairs" / PAIRS[0]
    kept = {path: path.read_bytes() for path in (first / "search.mp4", first / "search.json", first / "result.json")}
    assert "search" not in json.loads((out / "pairs" / PAIRS[1] / "result.json").read_text())["arms"]
    monkeypatch.setattr(ab_run, "add_search", real)
    capsys.readouterr()

    assert ab.main(_argv(prompts_file, out, "--search", "2")) == 0
    captured = capsys.readouterr()
    assert "2 of 2 pairs already complete" in captured.out and "1 of 2 pairs already have the search-2 arm" in captured.out
    assert f"[1/1] {PAIRS[1]}: search-2 arm ..." in captured.err and f"{PAIRS[0]}: search-2" not in captured.err
    assert all(path.read_bytes() == data for path, data in kept.items())  # the first pair: not redone
    for name in PAIRS:  # as if never stopped
        assert (out / "pairs" / name / "search.mp4").read_bytes() == (searched / "pairs" / name / "search.mp4").read_bytes()
        scores = [{arm: {k: record[k] for k in ("fused", "motion", "structure", "total_motion")}
                   for arm, record in json.loads((folder / "pairs" / name / "result.json").read_text())["arms"].items()}
                  for folder in (out, searched)]
        assert scores[0] == scores[1]
    assert ab.main(_argv(prompts_file, out, "--search", "2")) == 0  # all done: nothing loads
    captured = capsys.readouterr()
    assert "loading models" not in captured.err and "2 of 2 pairs already have the search-2 arm" in captured.out


@pytest.mark.slow
def test_matched_k_comes_from_the_run_s_measured_times_and_is_kept_for_the_folder(two_arms: Path, prompts_file: Path,
                                                                                tmp_path: Path, capsys):
    out = tmp_path / "matched"
    shutil.copytree(two_arms, out)
    assert ab.main(_argv(prompts_file, out, "--search", "matched")) == 0
    captured = capsys.readouterr()
    chosen = json.loads((out / core.MATCHED_SEARCH_FILE).read_text())
    # the times of the first complete pair not timed with the warm-up, as its result.json records them
    measured = json.loads((out / "pairs" / PAIRS[1] / "result.json").read_text())["arms"]
    assert chosen["pair"] == PAIRS[1] and not chosen["warm_up"]
    assert (chosen["unguided_s"], chosen["guided_s"]) == (measured["unguided"]["generation_s"],
                                                          measured["guided"]["generation_s"])
    assert chosen["resamplings"] == 1 and chosen["resample_steps"] == [1]  # the default steps of 2
    assert chosen["scoring_s"] == chosen["probe"]["resamplings_s"][-1] > 0
    assert (chosen["particles"], chosen["fits"]) == core.matched_particles(
        chosen["unguided_s"], chosen["guided_s"], chosen["scoring_s"], chosen["resamplings"])
    k = chosen["particles"]
    assert f"search-{k}: K = {k}, matched on this machine" in captured.out
    assert "measuring one particle's scoring at a resampling step on bridge-s0" in captured.err
    for name in PAIRS:
        made = json.loads((out / "pairs" / name / "result.json").read_text())["arms"]["search"]["search"]
        assert (made["particles"], made["chosen"], made["guided"]) == (k, "matched", False)
    summary = json.loads((out / "summary.json").read_text())
    assert summary["search"]["matched"]["particles"] == k
    assert f"K = {k}, matched on this machine" in (out / "report.md").read_text()

    # a resumed run keeps the recorded K: it measures nothing again, and arms of another K are redone
    recorded = {**chosen, "particles": k + 1}
    (out / core.MATCHED_SEARCH_FILE).write_text(json.dumps(recorded))
    assert ab.main(_argv(prompts_file, out, "--search", "matched")) == 0
    captured = capsys.readouterr()
    assert "measuring" not in captured.err and f"0 of 2 pairs already have the search-{k + 1} arm" in captured.out
    assert json.loads((out / core.MATCHED_SEARCH_FILE).read_text()) == recorded
    assert {json.loads((out / "pairs" / name / "result.json").read_text())["arms"]["search"]["search"]["particles"]
            for name in PAIRS} == {k + 1}


@pytest.mark.slow
def test_without_resampling_the_search_arm_is_best_of_k_from_the_same_seeds(prompts_file: Path, tmp_path: Path):
    """No resampling step and one particle per call: particle k is the video of seed s + k bit for
    bit, so the search keeps what best-of-K keeps (the same noise as the other arms)."""
    prompts = tmp_path / "p.txt"
    prompts.write_text("a marble bust\n")
    out = tmp_path / "no-resampling"
    assert ab.main(_argv(prompts, out, "--best-of", "2", "--search", "2", "search.resample_steps=[]",
                         "run.particle_batch=1")) == 0
    folder = out / "pairs" / PAIRS[0]
    arms = json.loads((folder / "result.json").read_text())["arms"]
    assert arms["search"]["search"]["resampled"] == 0
    assert arms["search"]["search"]["kept_seed"] == arms["best_of"]["best_of"]["kept_seed"]
    assert (folder / "search.mp4").read_bytes() == (folder / "best_of.mp4").read_bytes()
    assert arms["search"]["fused"] == arms["best_of"]["fused"]
    four, _ = read_video(folder / "side_by_side.mp4")
    assert four.shape[-1] >= 4 * read_video(folder / "unguided.mp4")[0].shape[-1]  # four arms side by side
