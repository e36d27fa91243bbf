"""``generate --best-of N``: N seeds, each scored with the GeCo protocol, the least inconsistent kept."""

from __future__ import annotations

import json

import pytest

from geco_guide import generation
from geco_guide.cli import generate as generate_cli

TINY = ["--preset", "tiny", "--prompt", "a marble bust"]


@pytest.mark.slow
def test_best_of_keeps_the_candidate_of_least_protocol_score(tmp_path, capsys):
    out = tmp_path / "best"
    assert generate_cli.main([*TINY, "--no-guidance", "--best-of", "3", "--seed", "5", "--out", str(out)]) == 0
    (video,) = out.glob("*.mp4")
    assert video.name.endswith("-seed5-unguided-best-of-3.mp4")
    assert sorted(p.name for p in out.iterdir()) == sorted([video.name, video.with_suffix(".json").name])  # no candidates left
    best_of = json.loads(video.with_suffix(".json").read_text())["best_of"]
    candidates = best_of["candidates"]
    assert [c["seed"] for c in candidates] == [5, 6, 7] and best_of["n"] == 3
    assert best_of["kept_seed"] == min(candidates, key=lambda c: c["fused"])["seed"]
    err = capsys.readouterr().err
    assert err.count("protocol fused=") == 3 and "candidate 3/3 (seed 7): protocol fused=" in err
    # a line as each candidate starts and as its scoring starts: no silence over a candidate's work
    assert err.count(": sampling ...") == 3 and err.count(": scoring it with the GeCo protocol ...") == 3
    # the kept video is the one that seed makes on its own
    single = tmp_path / "single.mp4"
    assert generate_cli.main([*TINY, "--no-guidance", "--seed", str(best_of["kept_seed"]), "--out", str(single)]) == 0
    assert single.read_bytes() == video.read_bytes()


@pytest.mark.slow
def test_best_of_guided_videos_is_allowed(tmp_path):
    out = tmp_path / "guided.mp4"
    assert generate_cli.main([*TINY, "--best-of", "2", "--out", str(out), "output.score_anchors=false"]) == 0
    sidecar = json.loads(out.with_suffix(".json").read_text())
    assert len(sidecar["best_of"]["candidates"]) == 2 and sidecar["guidance_log"]  # selection over guided seeds


def test_best_of_below_one_is_one_line_before_loading(tmp_path, capsys, monkeypatch):
    monkeypatch.setattr(generation, "load_models", lambda cfg, estimators=True: (_ for _ in ()).throw(AssertionError("loaded")))
    for count in ("0", "-2", "2.5"):
        with pytest.raises(SystemExit) as stop:
            generate_cli.main([*TINY, "--best-of", count, "--out", str(tmp_path)])
        err = capsys.readouterr().err.strip()
        assert stop.value.code == 2 and err.startswith("error: argument --best-of: must be a whole number >= 1"), err
        assert "\n" not in err and not any(tmp_path.iterdir())


@pytest.mark.slow
def test_best_of_loads_the_models_once_for_every_candidate(tmp_path, monkeypatch):
    loads = []
    real = generation.load_models

    def counted(cfg, estimators=True):
        loads.append(1)
        return real(cfg, estimators=estimators)

    monkeypatch.setattr(generation, "load_models", counted)
    out = tmp_path / "moving.mp4"
    assert generate_cli.main([*TINY, "--best-of", "2", "--dynamic", "auto", "--out", str(out),
                              "output.score_anchors=false"]) == 0
    sidecar = json.loads(out.with_suffix(".json").read_text())
    assert len(loads) == 1 and len(sidecar["best_of"]["candidates"]) == 2 and sidecar["dynamic_masks"] == "auto"


@pytest.mark.slow
def test_the_selection_leaves_out_what_the_guidance_leaves_out(tmp_path, monkeypatch):
    from geco_guide.metric import evaluate

    seen = []
    real = evaluate.evaluate_video

    def recorded(video, estimators=None, config=None, **kwargs):
        seen.append(kwargs.get("dynamic_masks"))
        return real(video, estimators, config, **kwargs)

    monkeypatch.setattr(evaluate, "evaluate_video", recorded)
    common = [*TINY, "output.score_anchors=false", "sampling.num_inference_steps=2", "guidance.repeats=1x2",
              "guidance.time_travel=[]"]
    assert generate_cli.main([*common, "--best-of", "2", "--dynamic", "auto", "--out", str(tmp_path / "a.mp4")]) == 0
    assert seen == ["auto", "auto"]  # each candidate scored without what moves on its own, as guided
    seen.clear()
    assert generate_cli.main([*common, "--search", "2", "--dynamic", "auto", "--out", str(tmp_path / "b.mp4")]) == 0
    assert seen == ["auto", "auto"]
    seen.clear()
    assert generate_cli.main([*common, "--best-of", "2", "--out", str(tmp_path / "c.mp4")]) == 0
    assert seen == [None, None]  # the paper's protocol
