"""decoder-agreement: both decoders at every guidance update, on the tiny random models."""

from __future__ import annotations

import json
import math
import subprocess
import sys
from pathlib import Path

import pytest
import torch

from geco_guide.perf.decoder_agreement import (
    agreement_summary,
    gradient_cosine,
    psnr_db,
)

REPO = Path(__file__).resolve().parents[2]
ROW_KEYS = {"update", "step", "t", "guided_by", "loss_vae", "loss_tiny", "cosine", "psnr_db"}


@pytest.fixture(scope="module")
def report(tmp_path_factory: pytest.TempPathFactory) -> dict:
    path = tmp_path_factory.mktemp("agreement") / "agreement.json"
    proc = subprocess.run([sys.executable, "-m", "geco_guide.cli.bench", "decoder-agreement", "--preset", "tiny",
                           "--threads", "1", "--json", str(path)], capture_output=True, text=True, timeout=300,
                          check=False, cwd=REPO)
    assert proc.returncode == 0, proc.stderr
    return {**json.loads(path.read_text()), "stdout": proc.stdout}


@pytest.mark.slow
def test_every_update_has_both_losses_a_cosine_and_a_psnr(report):
    rows = report["rows"]
    # the tiny preset's schedule 0x1,2x2,1x1 with time travel at step 2: 5 updates
    assert len(rows) == report["summary"]["updates"] == 5
    assert [r["step"] for r in rows] == [1, 1, 2, 2, 3] and [r["update"] for r in rows] == list(range(5))
    for row in rows:
        assert set(row) == ROW_KEYS and row["guided_by"] == "vae"
        assert -1 <= row["cosine"] <= 1
        assert math.isfinite(row["psnr_db"]) and 0 < row["psnr_db"] <= 100
        assert row["loss_vae"] > 0 and row["loss_tiny"] > 0 and row["loss_vae"] != row["loss_tiny"]


@pytest.mark.slow
def test_the_summary_and_the_record(report):
    s, rows = report["summary"], report["rows"]
    cosines = sorted(r["cosine"] for r in rows)
    assert s["cosine_median"] == pytest.approx(cosines[2]) and s["cosine_min"] == pytest.approx(cosines[0])
    assert s["psnr_mean_db"] == pytest.approx(sum(r["psnr_db"] for r in rows) / 5)
    assert s["non_finite_cosines"] == 0
    assert report["tiny_decoder"] == "TinyDecoder(cogvideox) from tiny-random(seed=0)"
    assert "say nothing about the published decoder" in report["note"]
    assert report["config"]["estimators"]["tiny_decoder"] == "tiny-random"
    assert "gradient cosine median" in report["stdout"]


@pytest.mark.slow
def test_guiding_with_the_tiny_decoder_swaps_the_roles():
    from geco_guide.config import load_config
    from geco_guide.perf.decoder_agreement import decoder_agreement

    torch.set_num_threads(1)
    cfg = load_config(preset="tiny", overrides=["guidance.decoder=tiny", "guidance.repeats=0x3,1x1"])
    result = decoder_agreement(cfg, "a marble bust")
    assert result["guided_by"] == "tiny" and len(result["rows"]) == 1
    assert all(r["guided_by"] == "tiny" and -1 <= r["cosine"] <= 1 for r in result["rows"])


@pytest.mark.slow
def test_rows_of_loaded_models_leave_them_as_they_were():
    from geco_guide import tiny as T
    from geco_guide.config import load_config
    from geco_guide.generation import Models, sample
    from geco_guide.perf.decoder_agreement import agreement_rows
    from geco_guide.sampler.pipelines.loading import LoadedPipeline

    torch.set_num_threads(1)
    pipe = T.tiny_pipeline(0)
    decoder = T.tiny_guidance_decoder("cogvideox")
    cfg = load_config(preset="tiny", overrides=["guidance.repeats=0x3,1x1"])
    models = Models(LoadedPipeline(pipe, cfg.model.video_model, "the tiny pipeline's"),
                    T.tiny_estimators(0, tiny_decoder=decoder))
    sample(models, cfg, "a marble bust", progress=False)  # an unwatched call: the pipeline's own per-call state
    state = (set(pipe.__dict__), set(pipe.scheduler.__dict__), [p.requires_grad for p in decoder.parameters()])
    rows = agreement_rows(models, cfg, "a marble bust")
    assert len(rows) == 1 and rows[0]["step"] == 3 and -1 <= rows[0]["cosine"] <= 1
    # the rows are watched through the call's observer: nothing of the measurement stays behind
    assert (set(pipe.__dict__), set(pipe.scheduler.__dict__), [p.requires_grad for p in decoder.parameters()]) == state


def test_cosine_and_psnr():
    g = torch.randn(2, 3, 4, generator=torch.Generator().manual_seed(0))
    assert gradient_cosine(g, 2 * g) == pytest.approx(1.0) and gradient_cosine(g, -g) == pytest.approx(-1.0)
    for broken in (None, torch.zeros_like(g), torch.full_like(g, math.nan)):
        assert math.isnan(gradient_cosine(g, broken))
    frames = torch.rand(1, 4, 3, 8, 8, generator=torch.Generator().manual_seed(1))
    assert psnr_db(frames, frames) == pytest.approx(100.0)
    assert psnr_db(frames.clamp(0.1, 0.9), frames) < 100
    rows = [{"cosine": 0.5, "psnr_db": 20.0}, {"cosine": math.nan, "psnr_db": 30.0}]
    assert agreement_summary(rows) == {"updates": 2, "non_finite_cosines": 1, "cosine_median": 0.5,
                                       "cosine_min": 0.5, "psnr_mean_db": 25.0}


# ---- bad input: one line, before any model loads -------------------------------------------------


@pytest.fixture(scope="module")
def cli():
    from geco_guide.cli import bench

    return bench


@pytest.mark.parametrize(("argv", "expected"), [
    (["decoder-agreement", "--preset", "tiny", "estimators.tiny_decoder=null"],
     "estimators.tiny_decoder=/path/to/taecvx.pth"),
    (["decoder-agreement", "--preset", "tiny", "estimators.tiny_decoder=/nowhere/taecvx.pth"], "no such file"),
    (["decoder-agreement", "--preset", "tiny", "guidance.enabled=false"], "guidance.enabled must be true"),
    (["decoder-agreement", "--preset", "tiny", "guidance.step_size=-1"], "guidance.step_size"),
    (["decoder-agreement", "--preset", "tiny", "no.such=1"], "unknown config key"),
    (["decoder-agreement", "--preset", "tiny", "--prompt", " "], "--prompt must not be empty"),
    (["decoder-agreement", "--preset", "nope"], "unknown preset 'nope'"),
    (["decoder-agreement", "--preset", "tiny", "--threads", "0"], "--threads: must be >= 1"),
    (["cost", "--decoder", "taesd"], "--decoder must be one of vae, tiny, got 'taesd'"),
    (["cost", "--decoder", "tiny", "--mode", "unguided"], "use --mode fast or faithful"),
])
def test_bad_input_is_one_error_line_before_any_work(cli, monkeypatch, capsys, argv, expected):
    def no_work(*args, **kwargs):
        raise AssertionError(f"{argv}: work started before the options were checked")

    from geco_guide.perf import cost, decoder_agreement

    monkeypatch.setattr(decoder_agreement, "decoder_agreement", no_work)
    monkeypatch.setattr(cost, "cost_report", no_work)
    try:
        code = cli.main(argv)
    except SystemExit as exit_info:
        code = exit_info.code
    assert code == 2
    err = capsys.readouterr().err.strip()
    assert err.count("\n") == 0 and "error:" in err and expected in err, err
