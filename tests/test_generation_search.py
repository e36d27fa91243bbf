"""The generation path's search (geco_guide.generation.sample_search, ``search`` section): the
video key, the selection under the GeCo protocol, the sidecar, the checks before loading."""

from __future__ import annotations

import pytest

from geco_guide import generation
from geco_guide.config import config_to_dict, load_config
from geco_guide.generation import default_name, generate, video_key

PROMPT = "a marble bust"


def tiny(*overrides, **changes):
    return load_config(preset="tiny", overrides=list(overrides), changes=changes)


def test_the_video_key_names_a_search_and_nothing_else_changes():
    plain = config_to_dict(tiny())
    without_section = {section: value for section, value in plain.items() if section != "search"}
    assert video_key(plain, PROMPT) == video_key(without_section, PROMPT)  # videos made before searches keep their name
    idle = config_to_dict(tiny("run.particle_batch=2", "search.temperature=0.5"))
    assert video_key(idle, PROMPT) == video_key(plain, PROMPT)  # no search: its options make no frame
    searched = tiny("search.particles=4")
    key = video_key(config_to_dict(searched), PROMPT)
    assert key != video_key(plain, PROMPT)
    assert video_key(config_to_dict(tiny("search.particles=4", "run.particle_batch=2")), PROMPT) != key
    assert video_key(config_to_dict(tiny("search.particles=4", "search.temperature=0.5")), PROMPT) != key
    assert default_name(searched, PROMPT).endswith("-seed0-search-4")
    # the moving-subject options act on a search's scores, guided or not
    unguided = ("search.particles=2", "guidance.enabled=false")
    assert (video_key(config_to_dict(tiny(*unguided, "guidance.dynamic=auto")), PROMPT)
            != video_key(config_to_dict(tiny(*unguided)), PROMPT))


@pytest.mark.slow
def test_one_particle_without_resampling_writes_the_plain_video(tmp_path):
    cfg = tiny("guidance.enabled=false", "output.score_anchors=false")
    models = generation.load_models(cfg)
    plain = generate(cfg, PROMPT, tmp_path / "plain.mp4", models=models)
    searched = generate(tiny("guidance.enabled=false", "output.score_anchors=false", "search.particles=1",
                             "search.resample_steps=[]"), PROMPT, tmp_path / "searched.mp4", models=models)
    assert searched.video_path.read_bytes() == plain.video_path.read_bytes()
    assert searched.sidecar["search"]["kept_lineage"] == [0] and "search" not in plain.sidecar


@pytest.mark.slow
def test_a_search_keeps_the_final_particle_of_least_protocol_score(tmp_path):
    cfg = tiny("guidance.enabled=false", "search.particles=3", "search.resample_steps=[1,2]",
               "search.temperature=0.001", seed=5)
    result = generate(cfg, PROMPT, tmp_path)
    assert result.video_path.name.endswith("-seed5-unguided-search-3.mp4")
    search = result.sidecar["search"]
    finals = search["final_particles"]
    assert [f["particle"] for f in finals] == [0, 1, 2] and len(search["resamplings"]) == 2
    assert search["kept"] == min(finals, key=lambda f: f["fused"])["particle"]
    assert search["kept_lineage"] == finals[search["kept"]]["lineage"]
    for final in finals:  # a lineage: the slot before each resampling, from the particle (and seed) it started as
        lineage = final["lineage"]
        assert final["seed"] == 5 + lineage[0] and lineage[-1] == final["particle"] and len(lineage) == 3
        assert all(search["resamplings"][r]["ancestors"][lineage[r + 1]] == lineage[r] for r in range(2))
    assert search["score"].startswith("fused (the GeCo protocol") and search["particle_batch"]["size"] == 3


@pytest.mark.slow
def test_a_search_dealt_over_devices_writes_the_same_video_and_scores(tmp_path):
    options = ("guidance.enabled=false", "search.particles=3", "search.resample_steps=[1]", "run.particle_batch=1")
    models = generation.load_models(tiny(*options))
    one = generate(tiny(*options), PROMPT, tmp_path / "one.mp4", models=models)
    dealt = generate(tiny(*options, "run.devices=[cpu,cpu]"), PROMPT, tmp_path / "dealt.mp4", models=models)
    assert dealt.video_path.read_bytes() == one.video_path.read_bytes()
    # each device decodes and scores its share of the final particles, to the same numbers
    assert dealt.sidecar["search"]["final_particles"] == one.sidecar["search"]["final_particles"]
    assert dealt.sidecar["search"]["selection_devices"] == ["cpu", "cpu"]
    assert dealt.sidecar["search"]["final_decode_devices"] == ["cpu", "cpu"]
    assert "selection_devices" not in one.sidecar["search"]
    assert one.sidecar["dynamic_masks"] is None


@pytest.mark.slow
def test_an_unguided_search_says_what_its_scores_left_out(tmp_path):
    cfg = tiny("guidance.enabled=false", "guidance.dynamic=auto", "search.particles=2", "search.resample_steps=[1]")
    assert generate(cfg, PROMPT, tmp_path).sidecar["dynamic_masks"] == "auto"


def test_search_errors_are_one_line_before_anything_loads(tmp_path, monkeypatch):
    monkeypatch.setattr(generation, "load_models", lambda *a, **k: (_ for _ in ()).throw(AssertionError("loaded")))
    cases = [
        (tiny("search.particles=2", "run.memory_budget_gb=0.0001"),
         r"search.particles=2 does not fit 0.0 GiB: .* at most 0 particles fit"),
        (tiny("search.particles=3", seed=2**64 - 2), "needs seeds up to"),
    ]
    for cfg, match in cases:
        with pytest.raises(ValueError, match=match) as err:
            generate(cfg, PROMPT, tmp_path)
        assert "\n" not in str(err.value)
    with pytest.raises(ValueError, match="--best-of and a search"):
        generation.generate_best_of(tiny("search.particles=2"), PROMPT, 2, tmp_path)
    for override, match in (("search.resample_steps=[4]", "outside the 4 denoising steps"),
                            ("run.split_cfg=true", "run.split_cfg")):
        with pytest.raises(ValueError, match=match):
            tiny("search.particles=2", override)
    assert not any(tmp_path.iterdir())
