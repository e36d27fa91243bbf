"""``generate --best-of N``: N seeds, each scored with the GeCo protocol, the least inconsistent kept."""

from __future__ import annotations

import json

from geco_guide.cli import generate as generate_cli

TINY = ["--preset", "tiny", "--prompt", "a marble bust"]


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
    assert err.count("candidate ") == 3 and "candidate 3/3 (seed 7): protocol fused=" in err
    # the kept video is the one that seed makes on its own
    single = tmp_path / "single.mp4"
    assert generate_cli.main([*TINY, "--no-guidance", "--seed", str(best_of["kept_seed"]), "--out", str(single)]) == 0
    assert single.read_bytes() == video.read_bytes()


def test_best_of_guided_videos_is_allowed(tmp_path):
    out = tmp_path / "guided.mp4"
    assert generate_cli.main([*TINY, "--best-of", "2", "--out", str(out), "output.score_anchors=false"]) == 0
    sidecar = json.loads(out.with_suffix(".json").read_text())
    assert len(sidecar["best_of"]["candidates"]) == 2 and sidecar["guidance_log"]  # selection over guided seeds


def test_best_of_below_one_is_one_line_before_loading(tmp_path, capsys, monkeypatch):
    monkeypatch.setattr(generate_cli, "build_pipeline", lambda cfg: (_ for _ in ()).throw(AssertionError("loaded")))
    for count in ("0", "-2"):
        assert generate_cli.main([*TINY, "--best-of", count, "--out", str(tmp_path)]) == 2
        err = capsys.readouterr().err.strip()
        assert err == f"error: --best-of must be an integer >= 1, got {count}" and not any(tmp_path.iterdir())


def test_best_of_loads_the_segmenter_once_for_every_candidate(tmp_path, monkeypatch):
    loads = []
    real = generate_cli.loading.load_dynamic_masks

    def counted(cfg):
        loads.append(1)
        return real(cfg)

    monkeypatch.setattr(generate_cli.loading, "load_dynamic_masks", counted)
    out = tmp_path / "moving.mp4"
    assert generate_cli.main([*TINY, "--best-of", "2", "--dynamic", "auto", "--out", str(out),
                              "output.score_anchors=false"]) == 0
    assert len(loads) == 1 and json.loads(out.with_suffix(".json").read_text())["dynamic_masks"] == "auto"
