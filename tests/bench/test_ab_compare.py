"""The A/B command (``geco ab``): the run end to end (tiny models, CPU), resuming after a kill,
bad inputs, and the best-of-N arm (the search arm: test_ab_search.py).

The end-to-end and interruption tests run the command in subprocesses with 2 sampling steps; the
statistics, report and input checks run in process (:mod:`geco_guide.cli.ab`) on hand-made results.
"""

from __future__ import annotations

import csv
import json
import os
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path
from types import SimpleNamespace

import imageio.v2 as imageio
import numpy as np
import pytest
import torch

from geco_guide.bench import ab as core
from geco_guide.bench import ab_report, ab_run, ab_stats
from geco_guide.bench.report import MIN_INTERVAL_N
from geco_guide.bench.runs import LOCK_NAME, shard, take_run_lock
from geco_guide.cli import ab
from geco_guide.cli.kit import Parser
from geco_guide.cli.prompt_files import Prompt, read_prompts
from geco_guide.config import config_to_dict, load_config
from geco_guide.io.files import write_json_atomic
from geco_guide.io.video import read_video, write_video
from geco_guide.metric.render import READABLE_HEIGHT, enlarge, panel_layout

REPO = Path(__file__).resolve().parents[2]
#: ``geco ab`` in a process of its own (``python -m geco_guide ab`` runs the same ``main``)
DRIVER = "import sys; from geco_guide.cli.ab import main; sys.exit(main(sys.argv[1:]))"
FAST = [  # the tiny preset, shortened: 9 frames, 2 steps with one guided update each, 5 scored frames
    "--preset", "tiny", "sampling.num_frames=9", "guidance.anchors=[4,8]", "sampling.num_inference_steps=2",
    "guidance.repeats=1x2", "guidance.time_travel=[]", "output.score_anchors=false", "evaluation.max_fps=4",
]
PROMPTS = 'a marble bust\n# a comment\n\n{"id": "bridge", "prompt": "a stone bridge over a river"}\n'
PAIRS = ("a-marble-bust-s0", "bridge-s0")
SCORES = ("fused", "motion", "structure", "total_motion", "mean_motion")



def _command(prompts: Path, out: Path) -> list[str]:
    return [sys.executable, "-c", DRIVER, "--prompts", str(prompts), "--seeds", "0", "--out", str(out), *FAST]


def _env() -> dict[str, str]:
    """One thread per process: numbers are bitwise reproducible only at a fixed thread count (guided
    sampling amplifies float summation-order differences), and torchrun uses one thread too."""
    return dict(os.environ, HF_HUB_OFFLINE="1", PYTHONPATH=str(REPO), OMP_NUM_THREADS="1")


def _assert_same_scores(rows: list[dict[str, str]], expected: list[dict[str, str]]) -> None:
    assert [(r["pair"], r["arm"]) for r in rows] == [(r["pair"], r["arm"]) for r in expected]
    for row, ref in zip(rows, expected):
        assert {k: row[k] for k in SCORES} == {k: ref[k] for k in SCORES}, row["pair"]


def _rows(out: Path) -> list[dict[str, str]]:
    with open(out / "results.csv", newline="") as fh:
        return list(csv.DictReader(fh))


def _temporaries(out: Path) -> list[Path]:
    return [p for p in out.rglob("*") if p.name.startswith(".")]


@pytest.fixture(scope="module")
def prompts_file(tmp_path_factory: pytest.TempPathFactory) -> Path:
    path = tmp_path_factory.mktemp("prompts") / "prompts.txt"
    path.write_text(PROMPTS)
    return path


@pytest.fixture(scope="module")
def reference(prompts_file: Path, tmp_path_factory: pytest.TempPathFactory) -> Path:
    """An uninterrupted A/B run of 2 prompts x 1 seed; its output folder."""
    out = tmp_path_factory.mktemp("ab") / "reference"
    proc = subprocess.run(_command(prompts_file, out), env=_env(), capture_output=True, text=True, check=False, timeout=300)
    assert proc.returncode == 0, proc.stderr
    assert "0 of 2 pairs already complete" in proc.stdout and "2 pairs: fused guided - unguided" in proc.stdout
    # the last line is the result, one sentence; the tiny models' note is a line of its own before it
    *_, note, last = proc.stdout.strip().splitlines()
    assert note == core.TINY_GUIDANCE_NOTE
    assert last.startswith("2 pairs: fused guided - unguided") and last.endswith(str(out / "report.md"))
    # no terminal, no progress bar: a line when the models load and one per pair and arm instead
    assert "loading models: cogvideox-5b tiny-random, geometry tiny-random, flow tiny-random ..." in proc.stderr
    assert "[1/2] a-marble-bust-s0: unguided arm ...\n[1/2] a-marble-bust-s0: guided arm ...\n" in proc.stderr
    assert "[2/2] bridge-s0: guided arm ..." in proc.stderr and "it/s" not in proc.stderr
    return out


# ----------------------------------------------------------------------------------------------
# end to end


@pytest.mark.slow
def test_end_to_end_report(reference: Path):
    rows = _rows(reference)
    assert len(rows) == 4
    assert sorted((r["pair"], r["arm"]) for r in rows) == [(p, a) for p in PAIRS for a in ("guided", "unguided")]
    for row in rows:
        assert all(np.isfinite(float(row[k])) for k in SCORES)
        assert float(row["generation_s"]) > 0 and row["memory_kind"] == "cpu_peak_rss"
        assert (int(row["guidance_updates"]) > 0) == (row["arm"] == "guided")

    summary = json.loads((reference / "summary.json").read_text())
    assert {"pairs", "arms", "paired_differences", "guidance_lowered_fused", "bootstrap", "config", "versions",
            "devices", "seeds"} <= set(summary)
    assert summary["pairs"] == 2 and summary["missing_pairs"] == [] and summary["seeds"] == [0]
    assert set(summary["arms"]) == {"unguided", "guided"}
    assert {*SCORES, "generation_s_mean", "peak_memory_mib_max"} <= set(summary["arms"]["guided"])
    fused = summary["paired_differences"]["fused"]
    by_arm = {(r["pair"], r["arm"]): float(r["fused"]) for r in rows}
    diffs = [by_arm[p, "guided"] - by_arm[p, "unguided"] for p in PAIRS]
    assert fused["n"] == 2 and fused["mean_diff"] == pytest.approx(np.mean(diffs))
    assert fused["ci95"] is None  # 2 pairs: too few for an interval
    assert summary["guidance_lowered_fused"]["count"] == sum(d < 0 for d in diffs)
    assert summary["config"]["sampling"]["num_frames"] == 9 and summary["devices"] == ["cpu"]

    report = (reference / "report.md").read_text()
    assert report.count("tiny random models: the numbers show the mechanics, not quality") == 1
    assert "## Models and weights" in report
    assert f"none from 2 pairs (an interval needs {MIN_INTERVAL_N})" in report
    assert core.TINY_GUIDANCE_NOTE in report
    for text in ("## Configuration", "num_frames: 9", "## Versions", "| torch |", "pareto.png",
                 "seeds [0]", "95% CI (paired bootstrap)"):
        assert text in report, text

    image = imageio.imread(reference / "pareto.png")
    assert image.ndim == 3 and image.shape[2] == 3 and image.shape[0] > 100 and image.std() > 0

    pair = reference / "pairs" / "bridge-s0"
    unguided, _ = read_video(pair / "unguided.mp4")
    both, _ = read_video(pair / "side_by_side.mp4")
    # enlarged to a readable height as the maps are (the tiny models' videos are 16 pixels high)
    enlarged = tuple(enlarge(unguided).shape[-2:])
    assert enlarged[0] >= READABLE_HEIGHT
    (height, width), _ = panel_layout([enlarged] * 2)  # labels above, a gap between
    even = (height + height % 2, width + width % 2)  # mp4 (yuv420p) pads odd sizes by one
    assert both.shape == (unguided.shape[0], 3, *even) and width >= 2 * enlarged[1]
    result = json.loads((pair / "result.json").read_text())
    assert result["prompt"] == "a stone bridge over a river" and result["seed"] == 0
    assert {"unguided.json", "guided.json", "guided.mp4"} <= {p.name for p in pair.iterdir()}
    assert not _temporaries(reference)


@pytest.mark.slow
def test_the_first_pair_of_a_process_is_timed_apart_as_the_warm_up(reference: Path):
    rows = _rows(reference)
    assert {(r["pair"], r["warm_up"]) for r in rows} == {(PAIRS[0], "True"), (PAIRS[1], "False")}
    summary = json.loads((reference / "summary.json").read_text())
    assert summary["warm_up_pairs"] == [PAIRS[0]]
    timed = {r["arm"]: float(r["generation_s"]) for r in rows if r["pair"] == PAIRS[1]}
    for arm in ("unguided", "guided"):
        record = summary["arms"][arm]
        assert record["timed_pairs"] == 1 and not record["timing_includes_warm_up"]
        assert record["generation_s_mean"] == pytest.approx(timed[arm])  # the warm-up pair left out
        assert record["generation_s_total"] > record["generation_s_mean"]  # the total has both
    report = (reference / "report.md").read_text()
    assert f"The means leave out the arms made with the models' warm-up (in {PAIRS[0]}: each process's first " \
           "pair, and its first search arm)" in report
    # every pair a warm-up (one pair per process): the means include it, and say so
    results = [_result("p0-s0", 0.2, 0.1)]
    for record in results[0]["arms"].values():
        record["warm_up"] = True
    cfg = load_config(preset="tiny")
    summary = ab_stats.summarize(results, core.plan_pairs([Prompt("p0", "p0")], [0]), cfg, {})
    assert summary["arms"]["guided"]["timing_includes_warm_up"] and summary["arms"]["guided"]["generation_s_mean"] == 1.0
    assert "Every pair was made with the models' warm-up (p0-s0" in ab_report.report_markdown(summary, results, "", "cmd")


@pytest.mark.slow
def test_arms_differ_only_in_guidance(reference: Path):
    """Both arms ran `generate` with the same seed and config but guidance.enabled, so from the same
    initial noise (generate seeds its generator from the config); the unguided arm logged no update."""
    pair = reference / "pairs" / "a-marble-bust-s0"
    sidecars = {arm: json.loads((pair / f"{arm}.json").read_text()) for arm in ("unguided", "guided")}
    configs = {arm: sidecar["config"] for arm, sidecar in sidecars.items()}
    assert configs["unguided"]["guidance"].pop("enabled") is False and configs["guided"]["guidance"].pop("enabled")
    assert configs["unguided"] == configs["guided"] and configs["guided"]["seed"] == 0
    assert sidecars["unguided"]["guidance_log"] == [] and sidecars["guided"]["guidance_log"]


# ----------------------------------------------------------------------------------------------
# interruption


@pytest.mark.slow
def test_rerun_after_kill_finishes_with_the_same_results(reference: Path, prompts_file: Path, tmp_path: Path):
    out = tmp_path / "killed"
    first = out / "pairs" / PAIRS[0] / "result.json"
    proc = subprocess.Popen(_command(prompts_file, out), env=_env(), stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)
    deadline = time.monotonic() + 240
    while not first.exists() and proc.poll() is None and time.monotonic() < deadline:
        time.sleep(0.02)
    proc.send_signal(signal.SIGKILL)
    proc.wait()
    assert first.exists(), proc.stderr.read().decode()
    assert not (out / "pairs" / PAIRS[1] / "result.json").exists()  # killed mid-way through the second pair
    assert not (out / "results.csv").exists()
    for path in out.rglob("*"):  # whatever the kill left is complete, or a hidden temporary
        if path.suffix == ".json" and not path.name.startswith("."):
            json.loads(path.read_text())
        elif path.suffix == ".mp4" and not path.name.startswith("."):
            read_video(path)
    completed = first.read_bytes()

    rerun = subprocess.run(_command(prompts_file, out), env=_env(), capture_output=True, text=True, check=False, timeout=300)
    assert rerun.returncode == 0, rerun.stderr
    assert "1 of 2 pairs already complete" in rerun.stdout
    assert first.read_bytes() == completed  # the complete pair was skipped, not redone
    rows = _rows(out)
    assert len(rows) == 4 and len({(r["pair"], r["arm"]) for r in rows}) == 4
    _assert_same_scores(rows, _rows(reference))
    assert not _temporaries(out)


@pytest.mark.slow
def test_sharded_run_matches_the_single_process_run(reference: Path, prompts_file: Path, tmp_path: Path):
    """Two processes (torchrun, as ``accelerate launch`` starts them) share the pairs; the main one merges."""
    out = tmp_path / "sharded"
    launcher = [sys.executable, "-m", "torch.distributed.run", "--standalone", "--nproc_per_node", "2", "--no-python"]
    proc = subprocess.run([*launcher, *_command(prompts_file, out)], env=_env(), capture_output=True, text=True,
                          check=False, timeout=300)
    assert proc.returncode == 0, proc.stderr
    assert "[rank 0 of 2] 0 of 1 pair already" in proc.stdout and "[rank 1 of 2] 0 of 1 pair already" in proc.stdout
    _assert_same_scores(_rows(out), _rows(reference))


@pytest.mark.slow
def test_rerun_redoes_a_damaged_pair_and_maps_the_complete_ones(reference: Path, prompts_file: Path, tmp_path: Path):
    """A resumed folder with ``--maps``: the pair whose result.json is damaged is redone (a warning
    names the file), the complete pair gets its maps without being generated again."""
    out = tmp_path / "resumed"
    shutil.copytree(reference, out)
    damaged = out / "pairs" / "bridge-s0" / "result.json"
    damaged.write_text('{"pair": "bridge-s0", "arms": {')  # e.g. edited by hand
    complete = out / "pairs" / "a-marble-bust-s0"
    video = (complete / "guided.mp4").read_bytes()
    rerun = subprocess.run([*_command(prompts_file, out), "--maps"], env=_env(), capture_output=True, text=True, check=False,
                           timeout=300)
    assert rerun.returncode == 0, rerun.stderr
    assert f"warning: {damaged} is damaged; pair bridge-s0 is redone" in rerun.stderr
    assert "1 of 2 pairs already complete" in rerun.stdout
    assert "making the maps of 1 complete pair(s) that have none" in rerun.stdout
    for pair in PAIRS:
        result = json.loads((out / "pairs" / pair / "result.json").read_text())
        for arm in ("unguided", "guided"):
            assert result["arms"][arm]["maps_video"] == f"{arm}_maps.mp4"
            assert read_video(out / "pairs" / pair / f"{arm}_maps.mp4")[0].shape[0] > 1
    assert (complete / "guided.mp4").read_bytes() == video  # scored again for the maps, not generated again
    _assert_same_scores(_rows(out), _rows(reference))
    assert not _temporaries(out)


# ----------------------------------------------------------------------------------------------
# statistics and report on hand-made results


def _result(name: str, unguided: float, guided: float) -> dict:
    def arm(fused: float) -> dict:
        return {"video": "v.mp4", "sidecar": "v.json", "fused": fused, "motion": fused / 2, "structure": fused / 2, "total_motion": 5.0,
                "mean_motion": 40.0, "generation_s": 1.0, "evaluation_s": 0.1, "peak_memory_mib": 10.0,
                "memory_kind": "cpu_peak_rss", "guidance_updates": 0}

    return {"pair": name, "prompt_id": name, "prompt": name, "seed": 0, "device": "cpu",
            "side_by_side": "side_by_side.mp4", "arms": {"unguided": arm(unguided), "guided": arm(guided)}}


def test_bootstrap_ci():
    assert ab_stats.bootstrap_ci(np.array([0.1])) is None
    diffs = np.array([-0.02, -0.01, 0.0, -0.03, 0.01])
    low, high = ab_stats.bootstrap_ci(diffs)
    assert low < diffs.mean() < high and (low, high) == ab_stats.bootstrap_ci(diffs)  # seeded
    assert ab_stats.bootstrap_ci(np.full(4, 0.5)) == (0.5, 0.5)
    # the report's interval needs MIN_INTERVAL_N finite pairs
    results = [_result(f"p{i}-s0", 0.2, 0.1 + 0.01 * i) for i in range(MIN_INTERVAL_N)]
    assert ab_stats.paired_difference(results[:-1], "fused")["ci95"] is None
    low, high = ab_stats.paired_difference(results, "fused")["ci95"]
    assert low <= ab_stats.paired_difference(results, "fused")["mean_diff"] <= high


def test_single_pair_reports_an_undefined_interval():
    cfg = load_config(preset="tiny")
    pairs = core.plan_pairs([Prompt("one", "one"), Prompt("two", "two")], [0])
    results = [_result("one-s0", 0.2, 0.1)]
    summary = ab_stats.summarize(results, pairs, cfg, {})
    assert summary["paired_differences"]["fused"] == {"n": 1, "mean_diff": pytest.approx(-0.1), "ci95": None}
    assert summary["guidance_lowered_fused"] == {"count": 1, "n": 1, "fraction": 1.0}
    assert summary["missing_pairs"] == ["two-s0"]
    report = ab_report.report_markdown(summary, results, "config: yaml", "cmd")
    assert "none from 1 pair (an interval needs 10)" in report and "Missing pairs" in report and "two-s0" in report
    assert ab_report.plot_png(results).startswith(b"\x89PNG")


def test_a_video_without_valid_pixels_is_left_out_of_the_statistics():
    cfg = load_config(preset="tiny")
    results = [_result("nan-s0", float("nan"), 0.1)]
    summary = ab_stats.summarize(results, core.plan_pairs([Prompt("nan", "nan")], [0]), cfg, {})
    assert summary["arms"]["unguided"]["fused"] is None and summary["arms"]["guided"]["fused"] == 0.1
    assert summary["paired_differences"]["fused"] == {"n": 0, "mean_diff": None, "ci95": None}
    assert summary["guidance_lowered_fused"] == {"count": 0, "n": 0, "fraction": None}
    assert "in **0 of 0** pairs (-)" in ab_report.report_markdown(summary, results, "", "cmd")
    assert ab_report.plot_png(results).startswith(b"\x89PNG")


def test_non_finite_scores_are_counted_and_named():
    cfg = load_config(preset="tiny")
    results = [_result("nan-s0", float("nan"), 0.1), _result("ok-s0", 0.2, 0.1)]
    pairs = core.plan_pairs([Prompt("nan", "nan"), Prompt("ok", "ok")], [0])
    summary = ab_stats.summarize(results, pairs, cfg, {})
    assert summary["non_finite_scores"] == {"nan-s0": ["unguided fused", "unguided motion", "unguided structure"]}
    assert summary["arms"]["unguided"]["fused"] == pytest.approx(0.2)  # the finite one: not a NaN mean
    assert summary["paired_differences"]["fused"]["n"] == 1
    report = ab_report.report_markdown(summary, results, "", "cmd")
    assert ("**Non-finite scores** in 1 pair(s), left out of the means, differences and counts (no valid pixels "
            "to measure): nan-s0 (unguided fused, unguided motion, unguided structure)") in report
    assert "Non-finite" not in ab_report.report_markdown(ab_stats.summarize(results[1:], pairs[1:], cfg, {}), results[1:], "", "cmd")


def test_a_pair_with_a_deleted_video_or_a_damaged_result_is_not_complete(tmp_path: Path, capsys):
    pair = core.Pair(Prompt("cat", "a cat"), 0)
    folder = core.pair_dir(tmp_path, pair)
    result = _result(pair.name, 0.2, 0.1)
    write_json_atomic(folder / "result.json", result)
    for name in core.PAIR_OUTPUTS:
        (folder / name).write_bytes(b"x")
    assert core.read_result(tmp_path, pair, warn=True) == result and capsys.readouterr().err == ""
    (folder / "guided.mp4").unlink()
    assert core.read_result(tmp_path, pair) is None and capsys.readouterr().err == ""  # the report reads quietly
    assert core.read_result(tmp_path, pair, warn=True) is None
    assert capsys.readouterr().err == f"warning: {folder / 'guided.mp4'} is missing; pair cat-s0 is redone\n"
    (folder / "guided.mp4").write_bytes(b"x")
    (folder / "result.json").write_bytes(b"\xff{")
    assert core.read_result(tmp_path, pair, warn=True) is None
    assert capsys.readouterr().err == f"warning: {folder / 'result.json'} is damaged; pair cat-s0 is redone\n"


def _whole_pair(folder: Path, frames: int = 3) -> dict:
    """A complete pair folder of real (tiny) videos and its result; the result."""
    video = torch.rand(frames, 3, 16, 16)
    for arm in core.ARMS:
        write_video(folder / f"{arm}.mp4", video, fps=8)
        write_json_atomic(folder / f"{arm}.json", {"num_frames": frames})
    write_video(folder / "side_by_side.mp4", video, fps=8)
    result = _result(folder.name, 0.2, 0.1)
    write_json_atomic(folder / "result.json", result)
    return result


@pytest.mark.slow
def test_resume_checks_the_fields_and_the_videos_of_a_pair(tmp_path: Path, capsys):
    pair = core.Pair(Prompt("cat", "a cat"), 0)
    folder = core.pair_dir(tmp_path, pair)
    result = _whole_pair(folder)
    assert core.read_result(tmp_path, pair, warn=True, verify=True) == result and capsys.readouterr().err == ""

    guided = (folder / "guided.mp4").read_bytes()
    (folder / "guided.mp4").write_bytes(guided[: len(guided) // 2])  # a copy cut short
    assert core.read_result(tmp_path, pair, warn=True) == result  # without verify: only that it is there
    assert core.read_result(tmp_path, pair, warn=True, verify=True) is None
    err = capsys.readouterr().err
    assert err.startswith(f"warning: cannot read video {str(folder / 'guided.mp4')!r}") and err.count("\n") == 1
    assert err.endswith("; pair cat-s0 is redone\n")

    write_video(folder / "guided.mp4", torch.rand(2, 3, 16, 16), fps=8)
    assert core.read_result(tmp_path, pair, warn=True, verify=True) is None
    assert f"{folder / 'guided.mp4'} holds 2 frame(s), not 3" in capsys.readouterr().err

    _whole_pair(folder)
    del result["arms"]["guided"]["fused"]
    write_json_atomic(folder / "result.json", result)
    assert core.read_result(tmp_path, pair, warn=True, verify=True) is None
    assert f"{folder / 'result.json'} lacks 'arms.guided.fused'" in capsys.readouterr().err
    del result["arms"]
    write_json_atomic(folder / "result.json", result)
    assert core.read_result(tmp_path, pair, warn=True) is None
    assert "lacks 'arms'" in capsys.readouterr().err

    result = _whole_pair(folder)
    result["arms"]["guided"]["fused"] = None  # a score that was not finite, written as null
    write_json_atomic(folder / "result.json", result)
    assert np.isnan(core.read_result(tmp_path, pair, verify=True)["arms"]["guided"]["fused"])


def test_shards_cover_every_pair_once():
    pairs = core.plan_pairs([Prompt(f"p{i}", f"p{i}") for i in range(3)], [0, 1])
    shards = [shard(pairs, rank, 4) for rank in range(4)]
    assert sorted(p.name for s in shards for p in s) == sorted(p.name for p in pairs)


# ----------------------------------------------------------------------------------------------
# bad inputs: one error line, before any model is loaded


@pytest.fixture
def no_models(monkeypatch: pytest.MonkeyPatch) -> None:
    def fail(*args, **kwargs):
        raise AssertionError("models must not be loaded for bad inputs")

    monkeypatch.setattr(ab_run, "process_state", fail)
    monkeypatch.setattr(ab_run, "execute", fail)


def _args(argv: list[str]):
    """``argv`` parsed as ``geco ab`` parses it."""
    return ab.register_subcommand(Parser(prog="geco ab")).parse_args(argv)


def _write(path: Path, text: str) -> Path:
    path.write_text(text)
    return path


@pytest.mark.parametrize(
    "prompts, seeds, extra, message",
    [
        (None, ["0"], [], "does not exist"),
        ("# only a comment\n\n", ["0"], [], "holds no prompts"),
        ("a cat\nA cat!\n", ["0"], [], "prompt id 'a-cat' already used on line 1"),
        ('{"id": "../up", "prompt": "x"}\n', ["0"], [], "not filesystem-safe"),
        ('{"id": "x"}\n', ["0"], [], "needs a non-empty string 'prompt'"),
        ("{not json\n", ["0"], [], "not valid JSON"),
        ("a cat\n", ["zero"], [], "--seeds takes integers, got 'zero'"),
        ("a cat\n", ["-1"], [], "must be in [0, 2**63)"),
        ("a cat\n", ["1", "1"], [], "lists 1 twice"),
        # an override typed after --seeds is read as one, not as a seed
        ("a cat\n", ["0", "sampling.nope=1"], [], "unknown config key 'sampling.nope'"),
        ("a cat\n", ["0"], ["sampling.nope=1"], "unknown config key 'sampling.nope'"),
        ("a cat\n", ["0"], ["sampling.num_frames=10"], "sampling.num_frames"),
        ("a cat\n", ["0"], ["guidance.enabled=false"], "nothing to compare"),
        ("a cat\n", ["0"], ["--config", "missing.yaml"], "config file"),
    ],
)
def test_bad_inputs_are_one_line(prompts, seeds, extra, message, tmp_path, capsys, no_models):
    path = _write(tmp_path / "p.txt", prompts) if prompts is not None else tmp_path / "missing.txt"
    rc = ab.main(["--prompts", str(path), "--out", str(tmp_path / "out"), "--preset", "tiny", *extra, "--seeds", *seeds])
    err = capsys.readouterr().err.strip()
    assert rc == 2 and err.startswith("error:") and "\n" not in err, err
    assert message in err, err


def test_reusing_an_output_folder_for_other_work_is_refused(tmp_path, capsys, no_models):
    out = tmp_path / "out"
    argv = ["--prompts", str(_write(tmp_path / "p.txt", "a cat\n")), "--seeds", "0", "--out", str(out), "--preset", "tiny"]
    write_json_atomic(out / "pairs" / "a-cat-s0" / "result.json", {"prompt": "a black cat"})
    assert ab.main(argv) == 2
    err = capsys.readouterr().err.strip()
    assert "was made for the prompt 'a black cat', not 'a cat'" in err and "\n" not in err

    write_json_atomic(out / "run.json", {"config_sha": "0123456789abcdef"})
    assert ab.main(argv) == 2
    err = capsys.readouterr().err.strip()
    assert "holds results of another config" in err and "\n" not in err


def test_a_damaged_run_file_or_a_non_utf8_prompts_file_is_one_line_naming_it(tmp_path, capsys, no_models):
    prompts = _write(tmp_path / "p.txt", "a cat\n")
    out = tmp_path / "out"
    argv = ["--seeds", "0", "--out", str(out), "--preset", "tiny"]
    (out / "pairs" / "a-cat-s0").mkdir(parents=True)
    (out / "pairs" / "a-cat-s0" / "result.json").write_text("{")  # damaged: redone later, no reason to stop
    (out / "run.json").write_text('{"config_sha": ')
    assert ab.main(["--prompts", str(prompts), *argv]) == 2
    err = capsys.readouterr().err.strip()
    assert err == f"error: {out / 'run.json'} is damaged; remove it to reuse the folder with this config"
    (tmp_path / "latin1.txt").write_bytes("a caf\xe9\n".encode("latin-1"))
    assert ab.main(["--prompts", str(tmp_path / "latin1.txt"), *argv]) == 2
    err = capsys.readouterr().err.strip()
    assert err == f"error: prompts file {str(tmp_path / 'latin1.txt')!r} is not UTF-8 text (byte 5: invalid continuation byte)"


def test_outputs_of_another_run_in_a_pair_folder_are_refused_unless_overwrite(tmp_path, capsys, no_models):
    out = tmp_path / "out"
    argv = ["--prompts", str(_write(tmp_path / "p.txt", "a cat\n")), "--seeds", "0", "--out", str(out), "--preset", "tiny"]
    cfg = load_config(preset="tiny")
    pair = core.Pair(Prompt("a-cat", "a cat"), 0)
    sidecar = {"prompt": "a cat", "config": config_to_dict(core.arm_config(cfg, pair, "guided"))}
    write_json_atomic(core.pair_dir(out, pair) / "guided.json", sidecar)  # this run's, unfinished: redone
    assert ab.validate_inputs(_args(argv)).pairs == [pair]
    sidecar["config"]["guidance"]["step_size"] = 123.0
    write_json_atomic(core.pair_dir(out, pair) / "guided.json", sidecar)
    assert ab.main(argv) == 2
    err = capsys.readouterr().err.strip()
    assert err == (f"error: {core.pair_dir(out, pair) / 'guided.json'} was made by another run (its prompt or config "
                   "differ); pass --overwrite to replace it, or use a new --out folder")
    assert ab.validate_inputs(_args([*argv, "--overwrite"])).pairs == [pair]


def test_a_second_run_in_one_folder_is_refused_while_the_first_holds_the_lock(tmp_path, capsys, no_models):
    out = tmp_path / "out"
    out.mkdir()
    argv = ["--prompts", str(_write(tmp_path / "p.txt", "a cat\n")), "--seeds", "0", "--out", str(out), "--preset", "tiny"]
    (out / LOCK_NAME).write_text(f"{os.getppid()}\n")  # a live process
    assert ab.main(argv) == 2
    err = capsys.readouterr().err.strip()
    assert err == (f"error: another A/B run (pid {os.getppid()}) is writing to {out}; wait for it to end or use "
                   "another --out folder")
    dead = subprocess.Popen([sys.executable, "-c", "pass"])
    dead.wait()
    (out / LOCK_NAME).write_text(f"{dead.pid}\n")  # left by a killed run
    lock = take_run_lock(out, "A/B")
    assert lock.read_text() == f"{os.getpid()}\n"


def test_a_lock_of_an_impossible_pid_is_taken_over_and_a_folder_in_its_place_is_one_line(tmp_path, capsys,
                                                                                         no_models):
    out = tmp_path / "out"
    out.mkdir()
    (out / LOCK_NAME).write_text("99999999999999\n")  # beyond any pid: no process holds it
    assert take_run_lock(out, "A/B").read_text() == f"{os.getpid()}\n"
    (out / LOCK_NAME).unlink()
    (out / LOCK_NAME).mkdir()
    argv = ["--prompts", str(_write(tmp_path / "p.txt", "a cat\n")), "--seeds", "0", "--out", str(out), "--preset", "tiny"]
    assert ab.main(argv) == 2
    assert capsys.readouterr().err == (f"error: {out / LOCK_NAME} is a folder, not a run lock; remove it (or use "
                                       "another --out folder)\n")


def test_ctrl_c_is_one_line_exit_130_and_releases_the_lock(tmp_path, capsys, monkeypatch):
    def interrupted(*args, **kwargs):
        raise KeyboardInterrupt

    state = SimpleNamespace(process_index=0, num_processes=1, is_main_process=True, wait_for_everyone=lambda: None)
    monkeypatch.setattr(ab_run, "process_state", lambda cfg: state)
    monkeypatch.setattr(ab_run, "make_pairs", interrupted)
    out = tmp_path / "out"
    argv = ["--prompts", str(_write(tmp_path / "p.txt", "a cat\n")), "--seeds", "0", "--out", str(out), "--preset", "tiny"]
    assert ab.main(argv) == 130
    assert capsys.readouterr().err == ("interrupted: finished pairs and arms are kept (each is written whole or not "
                                       "at all); rerun the same command to resume\n")
    assert not (out / LOCK_NAME).exists()


def test_a_folder_as_prompts_file_is_named_a_folder(tmp_path, capsys, no_models):
    rc = ab.main(["--prompts", str(tmp_path), "--out", str(tmp_path / "out"), "--preset", "tiny", "--seeds", "0"])
    assert rc == 2 and "is a folder, not a prompt file" in capsys.readouterr().err


def test_missing_weights_leave_no_run_file(tmp_path, capsys):
    out = tmp_path / "out"
    argv = ["--prompts", str(_write(tmp_path / "p.txt", "a cat\n")), "--out", str(out), "--preset", "tiny",
            f"estimators.geometry={tmp_path / 'no-such-vggt'}", "--seeds", "0"]
    assert ab.main(argv) == 2
    assert "no-such-vggt" in capsys.readouterr().err
    assert not (out / "run.json").exists()


def test_missing_argument_is_one_line(capsys):
    with pytest.raises(SystemExit) as exit_info:
        ab.main(["--prompts", "p.txt", "--out", "o"])
    err = capsys.readouterr().err.strip()
    assert exit_info.value.code == 2 and err.startswith("error:") and "--seeds" in err and "\n" not in err


@pytest.mark.skipif(torch.cuda.is_available(), reason="needs a machine without CUDA")
def test_cuda_without_cuda_is_one_line(tmp_path, capsys, no_models):
    prompts = _write(tmp_path / "p.txt", "a cat\n")
    argv = ["--prompts", str(prompts), "--out", str(tmp_path / "out"), "--preset", "tiny", "model.device=cuda", "--seeds", "0"]
    assert ab.main(argv) == 2
    err = capsys.readouterr().err.strip()
    assert "device 'cuda' is not available" in err and "\n" not in err


def test_the_geco_eval_suite_as_prompts(tmp_path, capsys, no_models):
    prompts = read_prompts("geco-eval:indoor:fast")
    assert [p.id for p in prompts] == [f"b{k}" for k in range(11, 21)] and prompts[0].text.startswith(("A", "T", "I"))
    assert len(read_prompts("geco-eval")) == 80
    assert ab.main(["--prompts", "geco-eval:underwater", "--seeds", "0", "--out", str(tmp_path / "o"),
                    "--preset", "tiny"]) == 2
    err = capsys.readouterr().err
    assert "unknown filter 'underwater'" in err and err.count("\n") == 1


@pytest.mark.slow
def test_a_run_guided_by_the_tiny_decoder_measures_it_against_the_vae(tmp_path: Path, capsys):
    out = tmp_path / "out"
    argv = ["--prompts", str(_write(tmp_path / "p.txt", "a cat\n")), "--seeds", "0", "--out", str(out),
            *FAST, "guidance.decoder=tiny"]
    assert ab.main(argv) == 0
    measured = json.loads((out / core.AGREEMENT_FILE).read_text())
    assert measured["pair"] == "a-cat-s0" and measured["summary"]["updates"] == len(measured["updates"]) > 0
    assert -1 <= measured["summary"]["cosine_min"] <= measured["summary"]["cosine_median"] <= 1
    summary = json.loads((out / "summary.json").read_text())
    assert summary["decoder_agreement"]["pair"] == "a-cat-s0"
    assert "**Tiny decoder vs VAE**" in (out / "report.md").read_text()
    assert "measuring the tiny decoder against the VAE on a-cat-s0" in capsys.readouterr().err


@pytest.mark.slow
def test_a_resumed_run_measures_the_agreement_that_an_interrupted_run_did_not(tmp_path: Path, capsys):
    out = tmp_path / "out"
    argv = ["--prompts", str(_write(tmp_path / "p.txt", "a cat\n")), "--seeds", "0", "--out", str(out),
            *FAST, "guidance.decoder=tiny"]
    assert ab.main(argv) == 0
    first = json.loads((out / core.AGREEMENT_FILE).read_text())
    (out / core.AGREEMENT_FILE).unlink()  # what a run killed while measuring it leaves: every pair complete
    capsys.readouterr()
    assert ab.main(argv) == 0
    captured = capsys.readouterr()
    assert "1 of 1 pair" in captured.out and "already complete" in captured.out  # no pair is redone
    assert "measuring the tiny decoder against the VAE on a-cat-s0" in captured.err
    assert json.loads((out / core.AGREEMENT_FILE).read_text())["summary"] == first["summary"]
    assert "**Tiny decoder vs VAE**" in (out / "report.md").read_text()
    (out / core.AGREEMENT_FILE).write_text('{"pair": "a-cat-s0"')  # cut short
    assert ab.main(argv) == 0
    assert f"warning: {out / core.AGREEMENT_FILE} is damaged; it is measured again" in capsys.readouterr().err
    assert json.loads((out / core.AGREEMENT_FILE).read_text())["summary"] == first["summary"]
    assert ab.main(argv) == 0  # nothing missing: nothing loads, nothing is measured
    captured = capsys.readouterr()
    assert "measuring" not in captured.err and "loading models" not in captured.err


@pytest.mark.parametrize("overrides, message", [
    (["run.memory_plan=auto", "run.memory_budget_gb=0.001"], "no memory plan fits 0.0 GiB"),
    (["guidance.repeats=1,1,1"], "repeats"),  # 3 per-step values for 4 steps
    (["guidance.decoder=tiny", "estimators.tiny_decoder=null"], "guidance.decoder=tiny needs the tiny decoder's weights"),
])
def test_what_generate_checks_before_loading_is_checked_before_the_run_starts(tmp_path, capsys, no_models, overrides,
                                                                             message):
    out = tmp_path / "out"
    argv = ["--prompts", str(_write(tmp_path / "p.txt", "a cat\n")), "--seeds", "0", "--out", str(out), "--preset",
            "tiny", *overrides]
    assert ab.main(argv) == 2
    # a renamed key's deprecation may precede it: the error itself is one line
    (err,) = [line for line in capsys.readouterr().err.splitlines() if not line.startswith("warning: ")]
    assert err.startswith("error: ") and message in err, err
    assert not out.exists()  # no run.json pinned, no video written


# ----------------------------------------------------------------------------------------------
# the best-of arm: selection among unguided seeds


@pytest.fixture(scope="module")
def best_of_2(reference: Path, prompts_file: Path, tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, str]:
    """The reference folder rerun with ``--best-of 2``: the arm added to its complete pairs; the
    folder and the run's stderr."""
    out = tmp_path_factory.mktemp("ab") / "best-of-2"
    shutil.copytree(reference, out)
    proc = subprocess.run([*_command(prompts_file, out), "--best-of", "2"], env=_env(), capture_output=True, text=True,
                          check=False, timeout=300)
    assert proc.returncode == 0, proc.stderr
    assert "best-of-2: N = 2, given (--best-of)" in proc.stdout
    assert "0 of 2 pairs already complete" in proc.stdout
    assert "adding the best-of-2 arm to 2 complete pair(s) that lack it" in proc.stdout
    last = proc.stdout.strip().splitlines()[-1]
    assert "fused guided - unguided = " in last and "; best-of-2 - unguided = " in last
    return out, proc.stderr


@pytest.mark.slow
def test_the_best_of_arm_keeps_the_candidate_of_least_fused_score(best_of_2, reference: Path):
    out, stderr = best_of_2
    assert "[1/2] a-marble-bust-s0: best-of-2 arm, candidate 2/2 (seed 1) ..." in stderr
    assert "unguided arm ..." not in stderr  # the complete pairs' arms are not made again
    _assert_same_scores([r for r in _rows(out) if r["arm"] != "best_of"], _rows(reference))
    for name in PAIRS:
        folder = out / "pairs" / name
        result = json.loads((folder / "result.json").read_text())
        arm = result["arms"]["best_of"]
        chosen = arm["best_of"]
        candidates = chosen["candidates"]
        assert [c["seed"] for c in candidates] == [0, 1] and chosen["n"] == 2
        assert candidates[0]["fused"] == result["arms"]["unguided"]["fused"]  # the first is the unguided arm
        scores = json.loads((folder / "candidates" / "seed1.scores.json").read_text())
        assert candidates[1]["fused"] == scores["fused"]
        assert chosen["kept_seed"] == min(candidates, key=lambda c: c["fused"])["seed"]
        kept = next(c for c in candidates if c["seed"] == chosen["kept_seed"])
        assert arm["fused"] == kept["fused"]
        assert (folder / "best_of.mp4").read_bytes() == (folder / kept["video"]).read_bytes()
        assert json.loads((folder / "best_of.json").read_text())["best_of"]["kept_seed"] == chosen["kept_seed"]
        # the arm's cost is every candidate's sampling
        assert arm["generation_s"] == pytest.approx(result["arms"]["unguided"]["generation_s"] + scores["generation_s"])
        both, _ = read_video(folder / "side_by_side.mp4")
        one, _ = read_video(folder / "unguided.mp4")
        assert both.shape[-1] >= 3 * one.shape[-1]  # three panels
    rows = _rows(out)
    assert sorted({r["arm"] for r in rows}) == ["best_of", "guided", "unguided"] and len(rows) == 6
    summary = json.loads((out / "summary.json").read_text())
    assert summary["best_of"]["n"] == 2 and summary["best_of"]["chosen"] == "given"
    assert summary["best_of"]["vs_unguided"]["paired_differences"]["fused"]["ci95"] is None  # 2 pairs: too few
    assert summary["best_of"]["guided_vs_best_of"]["lowered_fused"]["n"] == 2
    report = (out / "report.md").read_text()
    for text in ("unguided vs guided vs best-of-2", "| best-of-2 - unguided |", "| guided - best-of-2 |",
                 "N = 2, given (--best-of)", "kept seed (best-of-2)", "none from 2 pairs (an interval needs 10)"):
        assert text in report, text
    assert not _temporaries(out)


@pytest.mark.slow
def test_a_killed_best_of_run_resumes_with_the_candidates_it_made(best_of_2, prompts_file: Path, tmp_path: Path):
    """Killed after a candidate was scored: the rerun makes only the missing candidates and arms,
    and every output of the run is there."""
    done, _ = best_of_2
    out = tmp_path / "killed"
    shutil.copytree(done, out)
    scored = out / "pairs" / PAIRS[0] / "candidates" / "seed2.scores.json"
    proc = subprocess.Popen([*_command(prompts_file, out), "--best-of", "3"], env=_env(), stdout=subprocess.DEVNULL,
                            stderr=subprocess.PIPE)
    deadline = time.monotonic() + 240
    while not scored.exists() and proc.poll() is None and time.monotonic() < deadline:
        time.sleep(0.02)
    proc.send_signal(signal.SIGKILL)
    proc.wait()
    assert scored.exists(), proc.stderr.read().decode()
    assert "best_of" in json.loads((out / "pairs" / PAIRS[1] / "result.json").read_text())["arms"]  # still best-of-2
    made = {path: path.read_bytes() for path in (out / "pairs").rglob("seed*.mp4")}

    rerun = subprocess.run([*_command(prompts_file, out), "--best-of", "3"], env=_env(), capture_output=True, text=True,
                           check=False, timeout=300)
    assert rerun.returncode == 0, rerun.stderr
    assert "candidate 3/3 (seed 2)" in rerun.stderr and "candidate 2/3" not in rerun.stderr
    assert f"{PAIRS[0]}: best-of-3 arm, candidate 3/3" not in rerun.stderr  # its candidates were all made
    assert all(path.read_bytes() == data for path, data in made.items())  # kept, not made again
    for name in PAIRS:
        folder = out / "pairs" / name
        chosen = json.loads((folder / "result.json").read_text())["arms"]["best_of"]["best_of"]
        assert [c["seed"] for c in chosen["candidates"]] == [0, 1, 2]
        assert chosen["kept_seed"] == min(chosen["candidates"], key=lambda c: c["fused"])["seed"]
        assert {p.name for p in folder.iterdir()} >= {"best_of.mp4", "best_of.json", "side_by_side.mp4", "result.json"}
    assert len(_rows(out)) == 6 and json.loads((out / "summary.json").read_text())["best_of"]["n"] == 3
    assert (out / "report.md").is_file() and (out / "pareto.png").is_file() and not _temporaries(out)


@pytest.mark.slow
def test_matched_best_of_takes_n_from_the_cost_model_on_the_named_card():
    """N = round of the guided / unguided time ratio of ``geco bench cost --gpu``'s model:
    the card's memory plan, the run's size, steps and schedule."""
    from geco_guide.perf.cost import cost_report, cost_settings
    from geco_guide.perf.plans import card_plan

    cfg = load_config(preset="tiny", overrides=FAST[2:])
    chosen = ab.choose_best_of("matched", "L40S", cfg, [0, 100])  # seeds far apart: N uncapped
    s = cfg.sampling
    plan = card_plan("L40S", "faithful", "vae", s.num_frames, s.height, s.width)["plan"]
    settings = cost_settings(preset="tiny", steps=2, frames=9, height=s.height, width=s.width, dtype=None, plan=plan)
    settings.update(repeats="1x2", time_travel=None)
    ratio = cost_report(settings, "faithful")["roofline"]["ratio_guided_over_unguided"]["L40S"]
    assert chosen == core.BestOf(max(2, round(ratio)), "L40S", pytest.approx(ratio))
    assert "matched: round(" in chosen.how and "on the L40S" in chosen.how


def test_the_candidate_kept_is_the_least_finite_score_the_earlier_on_ties():
    from geco_guide.generation import best_candidate

    assert best_candidate([float("nan"), 0.3, 0.2, 0.2]) == 2
    assert best_candidate([float("nan"), float("nan")]) == 0


@pytest.mark.parametrize("extra, message", [
    (["--best-of", "1"], "--best-of takes an integer >= 2 or 'matched', got 1"),
    (["--best-of", "two"], "--best-of takes an integer >= 2 or 'matched', got 'two'"),
    (["--best-of", "matched", "--gpu", "V100"], "--gpu must be one of H200, H100"),
    (["--gpu", "H200"], "pass --best-of matched too"),
    (["--best-of", "3", "--gpu", "H200"], "an integer --best-of N needs no card"),
    (["--best-of", "3", "--seeds", "0", str(2**63 - 2)], "--best-of 3 from seed 9223372036854775806 runs past"),
])
def test_bad_best_of_values_are_one_line_before_any_work(extra, message, tmp_path, capsys, no_models):
    out = tmp_path / "out"
    argv = ["--prompts", str(_write(tmp_path / "p.txt", "a cat\n")), "--out", str(out), "--preset", "tiny",
            "--seeds", "0", *extra]
    assert ab.main(argv) == 2
    err = capsys.readouterr().err
    assert err.startswith("error: ") and err.count("\n") == 1 and message in err, err
    assert not out.exists()


def test_matched_for_a_model_the_cost_model_does_not_know_is_refused():
    cfg = load_config(preset="hunyuanvideo-1.5", overrides=["model.id=my/model"])
    with pytest.raises(ValueError, match="does not trace 'hunyuanvideo-1.5' .*; pass an integer --best-of N"):
        ab.choose_best_of("matched", "H200", cfg, [0])


@pytest.mark.slow
def test_matched_predicts_for_another_family_from_its_published_configs():
    """Wan 2.1 1.3B's preset: N from a trace of its own denoiser and VAE (fake tensors)."""
    torch.set_num_threads(1)
    best_of = ab.choose_best_of("matched", "H200", load_config(preset="wan2.1-t2v-1.3b"), [0])
    assert best_of.gpu == "H200" and best_of.n == max(2, round(best_of.predicted_ratio)) and best_of.predicted_ratio > 1


@pytest.mark.skipif(torch.cuda.is_available(), reason="needs a machine without CUDA")
def test_matched_on_a_cpu_asks_for_a_card(tmp_path, capsys, no_models):
    argv = ["--prompts", str(_write(tmp_path / "p.txt", "a cat\n")), "--out", str(tmp_path / "out"), "--preset", "tiny",
            "--best-of", "matched", "--seeds", "0"]
    assert ab.main(argv) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "the device here (cpu) is none: pass --gpu NAME or an integer --best-of N" in err


def test_a_three_arm_report_from_hand_made_results():
    cfg = load_config(preset="tiny")
    best_of = core.BestOf(7, "H200", 6.55)
    results = []
    for i in range(MIN_INTERVAL_N):
        result = _result(f"p{i}-s0", 0.2, 0.1 + 0.001 * i)
        result["arms"]["best_of"] = {**result["arms"]["unguided"], "fused": 0.15, "best_of": {"kept_seed": 3}}
        results.append(result)
    pairs = core.plan_pairs([Prompt(f"p{i}", f"p{i}") for i in range(len(results))], [0])
    summary = ab_stats.summarize(results, pairs, cfg, {}, best_of)
    assert summary["best_of"]["chosen"] == "matched" and summary["best_of"]["predicted_ratio"] == 6.55
    assert summary["best_of"]["vs_unguided"]["paired_differences"]["fused"]["mean_diff"] == pytest.approx(-0.05)
    assert summary["best_of"]["vs_unguided"]["lowered_fused"]["count"] == len(results)
    low, high = summary["best_of"]["guided_vs_best_of"]["paired_differences"]["fused"]["ci95"]
    assert low <= high < 0
    report = ab_report.report_markdown(summary, results, "", "cmd")
    assert "N = 7, matched: round(6.55), the guided / unguided sampling time ratio the cost model predicts" in report
    assert "on the H200 (predicted, not measured); measured here:" in report
    assert ab_report.plot_png(results, best_of).startswith(b"\x89PNG")
    assert "best_of" in ab_report.csv_text(results, core.run_arms(best_of))
