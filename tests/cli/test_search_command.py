"""``geco generate --search K``: a particle search through the one generation path, any registry model."""

from __future__ import annotations

import json

import pytest

from geco_guide.cli import generate as generate_cli

TINY = ["--preset", "tiny", "--prompt", "a marble bust"]


@pytest.mark.slow
def test_search_writes_the_kept_particle_and_every_particles_scores(tmp_path, capsys):
    # a model the hooks guide (Wan 2.1, UniPC): the stock pipeline's batch is the particles
    out = tmp_path / "searched.mp4"
    assert generate_cli.main([*TINY, "--model", "wan2.1-t2v-1.3b", "--no-guidance", "--search", "2", "--seed", "3",
                              "--out", str(out), "search.resample_steps=[1]", "output.score_anchors=false"]) == 0
    search = json.loads(out.with_suffix(".json").read_text())["search"]
    assert search["particles"] == 2 and search["resample_steps"] == [1] and len(search["resamplings"]) == 1
    assert [f["seed"] for f in search["final_particles"]] == [3 + f["lineage"][0] for f in search["final_particles"]]
    assert search["kept"] == min(search["final_particles"], key=lambda f: f["fused"])["particle"]
    printed = capsys.readouterr().out
    assert printed.count("protocol fused=") == 2
    assert f"search of 2 particles: resampled at 1 step [1], 1 per call; kept particle {search['kept']}" in printed
    assert "guidance: off" in printed


def test_bad_search_options_are_one_line_before_loading(tmp_path, capsys, monkeypatch):
    from geco_guide import generation

    monkeypatch.setattr(generation, "load_models", lambda *a, **k: (_ for _ in ()).throw(AssertionError("loaded")))
    cases = [
        (["--search", "0"], "error: argument --search: must be a whole number >= 1 written in digits, got '0'"),
        (["--search", "2", "search.resample_steps=[4]"],
         ("error: invalid value for config key 'search.resample_steps': search.resample_steps [4] are outside the 4 "
          "denoising steps (0 to 3)")),
        (["--search", "2", "search.temperature=0"],
         ("error: invalid value for config key 'search.temperature': temperature must be a finite number > 0, "
          "got 0")),
        (["--search", "2", "--best-of", "2"], "error: --best-of and a search (search.particles) are two ways"),
        (["--search", "2", "search.potential=max"], "error: invalid value for config key 'search.potential'"),
    ]
    for flags, expected in cases:
        code = 2
        try:
            code = generate_cli.main([*TINY, *flags, "--out", str(tmp_path)])
        except SystemExit as exit_:  # argparse's own refusal
            code = exit_.code
        assert code == 2
        err = capsys.readouterr().err.strip().splitlines()
        assert err[-1].startswith(expected), err
    assert not any(tmp_path.iterdir())
