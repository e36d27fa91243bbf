"""The dynamic GeCo-Eval suite (ours, not the paper's): its prompts, ``geco_eval --suite dynamic``
and ``geco ab``'s subject column, on the tiny models with a tiny random segmenter."""

from __future__ import annotations

import csv
import json
import re
from collections import Counter
from pathlib import Path

import pytest

from geco_guide.bench.geco_eval import CAMERAS, SCENARIOS, csv_text, load_prompts, movers_cell, select_prompts
from geco_guide.bench.ab import SEARCH, Pair, SearchArm, arm_config
from geco_guide.cli import ab
from geco_guide.cli.geco_eval import main
from geco_guide.cli.kit import Parser, config_from_args
from geco_guide.cli.prompt_files import read_prompts
from geco_guide.estimators.segmenters import subjects_of

REPO = Path(__file__).resolve().parents[2]
#: Grounding DINO + SAM 2 tiny random models: their masks cover part of a frame (SAM 3's tiny
#: detector keeps every query and masks nearly all of it).
SEGMENTER = "estimators.segmenter=tiny-random-grounding-sam2"
CAMERA_WORDS = re.compile(r"\b(camera|orbit|pan|dolly|tracks?|tracking|drone|crane|arc|push-in|shot)\b", re.I)


def test_the_dynamic_suite_covers_the_scenarios_and_speeds_with_named_subjects():
    prompts = load_prompts(suite="dynamic")
    assert [p["id"] for p in prompts] == [f"m{i}" for i in range(1, 25)]
    assert Counter((p["scenario"], p["camera"]) for p in prompts) == {(s, c): 3 for s in SCENARIOS for c in CAMERAS}
    papers = {p["prompt"] for p in load_prompts()}
    for p in prompts:
        assert subjects_of(p["subjects"]) and CAMERA_WORDS.search(p["prompt"]), p["id"]
        assert p["prompt"] not in papers
    assert len(select_prompts("dynamic:indoor:fast")) == 3 and len(select_prompts("geco-eval:indoor")) == 20
    with pytest.raises(ValueError, match="a prompt suite is named geco-eval or dynamic"):
        select_prompts("moving")
    with pytest.raises(ValueError, match="unknown prompt suite"):
        load_prompts(suite="moving")


def test_results_csv_has_a_subjects_column_for_the_dynamic_suite_only():
    row = {"model": "m", "guided": False, "prompt_id": "a1", "scenario": "indoor", "camera": "slow", "seed": 0}
    assert "subjects" not in csv_text([row]).splitlines()[0]
    assert csv_text([{**row, "subjects": "a dog"}]).splitlines()[0].endswith(",subjects")


def test_results_csv_has_a_movers_column_when_movers_are_scored():
    row = {"model": "m", "guided": False, "prompt_id": "m1", "scenario": "indoor", "camera": "slow", "seed": 0,
           "subjects": "a car"}
    assert "movers" not in csv_text([row]).splitlines()[0]
    cell = movers_cell({"mode": "rigid", "rigid": 2, "non_rigid": 1, "share": 0.3104, "movers": []})
    assert cell == "2 rigid, 1 non-rigid, 31.0 % of fused"
    header, line = csv_text([{**row, "movers": cell}]).splitlines()
    assert header.endswith(",subjects,movers") and line.endswith(',a car,"2 rigid, 1 non-rigid, 31.0 % of fused"')


@pytest.mark.slow
def test_geco_eval_dynamic_scores_and_guides_with_the_subjects_masks(tmp_path: Path, capsys):
    out = tmp_path / "run"
    argv = ["--preset", "tiny", "--suite", "dynamic", "--models", "cogvideox-5b", "--guided", "--limit", "1",
            "--seeds", "0", "--out", str(out), SEGMENTER]
    assert main(argv) == 0
    assert "loading segmenter: tiny-random-grounding-sam2" in capsys.readouterr().err
    for arm in ("cogvideox-5b", "cogvideox-5b-guided"):
        result = json.loads((out / "videos" / arm / "m1-s0.json").read_text())
        assert result["subjects"] == "a dog" and result["prompt_id"] == "m1"
        masks = result["evaluation"]["dynamic_masks"]
        assert masks["source"] == "grounding-sam2: a dog" and 0 <= masks["masked_fraction"] < 1
    assert json.loads((out / "videos" / "cogvideox-5b-guided" / "m1-s0.json").read_text())["guidance_updates"] > 0
    summary = json.loads((out / "summary.json").read_text())
    assert summary["suite"] == {"name": "dynamic", "ours": True, "segmenter": "tiny-random-grounding-sam2"}
    # the ids the loaded estimators carry (a report rebuilt without loading them says the same)
    assert summary["estimators"] == {"geometry": "tiny-random(seed=0)", "flow": "tiny-random(seed=0)",
                                     "segmenter": "tiny-random-grounding-sam2(seed=0)"}
    assert "24 prompts of our own with moving subjects, not the paper's" in (out / "report.md").read_text()
    rows = list(csv.DictReader((out / "results.csv").open()))
    assert [r["subjects"] for r in rows] == ["a dog", "a dog"]


@pytest.mark.slow
def test_geco_eval_dynamic_scores_the_subjects_as_movers(tmp_path: Path):
    out = tmp_path / "run"
    argv = ["--preset", "tiny", "--suite", "dynamic", "--models", "cogvideox-5b", "--limit", "1", "--seeds", "0",
            "--out", str(out), SEGMENTER, "evaluation.loss.movers=rigid"]
    assert main(argv) == 0
    result = json.loads((out / "videos" / "cogvideox-5b" / "m1-s0.json").read_text())
    movers = result["evaluation"]["movers"]
    assert movers["mode"] == "rigid" and movers["rigid"] + movers["non_rigid"] == len(movers["movers"])
    assert all(row["verdict"] in ("rigid", "non-rigid") for row in movers["movers"])
    row = next(csv.DictReader((out / "results.csv").open()))
    assert row["movers"] == result["movers"] == movers_cell(movers)


def test_ab_prompts_take_a_subject_column(tmp_path: Path):
    path = tmp_path / "prompts.jsonl"
    path.write_text('{"id": "dog", "prompt": "a dog runs on a lawn", "subjects": "a dog, a ball"}\na stone bridge\n')
    dog, bridge = read_prompts(path)
    assert dog.subjects == "a dog, a ball" and bridge.subjects is None
    path.write_text('{"id": "dog", "prompt": "a dog", "subjects": " , "}\n')
    with pytest.raises(ValueError, match=r"prompts.jsonl:1: 'subjects' subject text ' , ' names no subject"):
        read_prompts(path)
    suite = read_prompts("dynamic:outdoor:fast")
    assert [p.id for p in suite] == ["m16", "m17", "m18"] and suite[2].subjects == "a dog, a frisbee"
    parser = ab.register_subcommand(Parser(prog="geco ab"))
    cfg = config_from_args(parser.parse_args(["--prompts", "x", "--seeds", "0", "--out", "o", "--preset", "tiny"]), [])
    pair = Pair(dog, 3)
    assert arm_config(cfg, pair, "guided").guidance.dynamic == "a dog, a ball"
    assert arm_config(cfg, pair, "unguided").guidance.dynamic is None
    # the search scores its particles without the subjects, its particles guided or not
    for guided in (False, True):
        searched = arm_config(cfg, pair, SEARCH, SearchArm(3, guided))
        assert searched.guidance.dynamic == "a dog, a ball" and searched.guidance.enabled == guided
        assert searched.search.particles == 3 and searched.seed == 3


@pytest.mark.slow
def test_ab_run_masks_every_arm_s_scores_the_guidance_and_the_search(tmp_path: Path):
    prompts = tmp_path / "prompts.jsonl"
    prompts.write_text('{"id": "dog", "prompt": "a dog runs on a lawn", "subjects": "a dog"}\n')
    fast = ["sampling.num_frames=9", "guidance.anchors=[4,8]", "sampling.num_inference_steps=2", "guidance.repeats=1x2",
            "guidance.time_travel=[]", "output.score_anchors=false", "evaluation.max_fps=4"]
    out = tmp_path / "ab"
    assert ab.main(["--prompts", str(prompts), "--seeds", "0", "--out", str(out), "--preset", "tiny", SEGMENTER,
                    *fast, "--search", "2"]) == 0
    result = json.loads((out / "pairs" / "dog-s0" / "result.json").read_text())
    assert result["subjects"] == "a dog"
    arms = ("unguided", "guided", SEARCH)
    assert {arm: result["arms"][arm]["evaluation"]["dynamic_masks"]["source"] for arm in arms} == dict.fromkeys(
        arms, "grounding-sam2: a dog")
    searched = json.loads((out / "pairs" / "dog-s0" / "search.json").read_text())
    # its particles unguided, scored at the resampling steps without the subjects (guidance.dynamic)
    assert searched["config"]["guidance"]["dynamic"] == "a dog" and not searched["config"]["guidance"]["enabled"]
    assert searched["guidance_log"] == [] and searched["search"]["particles"] == 2
    guided = json.loads((out / "pairs" / "dog-s0" / "guided.json").read_text())
    unguided = json.loads((out / "pairs" / "dog-s0" / "unguided.json").read_text())
    assert guided["config"]["guidance"]["dynamic"] == "a dog" and guided["dynamic_masks"] == "grounding-sam2: a dog"
    assert all(r["mask_source"] == "grounding-sam2: a dog" for r in guided["guidance_log"])
    assert unguided["config"]["guidance"]["dynamic"] is None and unguided["dynamic_masks"] is None
    assert list(csv.DictReader((out / "results.csv").open()))[0]["subjects"] == "a dog"
    models = json.loads((out / "summary.json").read_text())["models"]
    assert models["segmenter"] == "tiny-random-grounding-sam2(seed=0)" and models["geometry"] == "tiny-random(seed=0)"
