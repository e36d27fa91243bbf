"""GeCo-Eval: the prompt suite, the model registry, and the benchmark runner end to end (tiny)."""

from __future__ import annotations

import csv
import json
import shutil
from pathlib import Path

import pytest

from geco_guide.bench import geco_eval
from geco_guide.bench.geco_eval import load_prompts, select_prompts
from geco_guide.families import MODELS, SCORED_ONLY, default_anchors, video_models
from geco_guide.cli.evaluate import main as evaluate_main
from geco_guide.cli.geco_eval import main

TINY_RUN = ["--preset", "tiny", "--models", "cogvideox-5b", "wan2.1-t2v-1.3b", "--seeds", "0", "--limit", "1", "--guided"]


def test_the_suite_is_the_papers_80_prompts():
    prompts = load_prompts()
    assert len(prompts) == 80 and [p["id"] for p in prompts[:3]] == ["a1", "a2", "a3"] and prompts[-1]["id"] == "d20"
    assert {p["scenario"] for p in prompts} == set(geco_eval.SCENARIOS)
    indoor_fast = load_prompts("indoor", "fast")
    assert [p["id"] for p in indoor_fast] == [f"b{k}" for k in range(11, 21)]
    assert select_prompts("geco-eval:fast:indoor") == indoor_fast and len(select_prompts("geco-eval:slow")) == 40
    with pytest.raises(ValueError, match="unknown scenario"):
        load_prompts("underwater")
    with pytest.raises(ValueError, match="unknown filter"):
        select_prompts("geco-eval:underwater")


def test_registry_anchors_and_frame_rates():
    cfg_fps = {"cogvideox-5b": 16.0, "ltx-video": 30.0, "hunyuanvideo": 24.0}
    from geco_guide.metric.protocol import EvaluationConfig

    assert {name: EvaluationConfig().fps_of_model(name) for name in cfg_fps} == cfg_fps
    assert set(MODELS) <= set(EvaluationConfig().model_fps)  # every model has its native rate
    assert default_anchors(49, 4) == [12, 24, 36, 48]  # the paper's
    assert default_anchors(81, 4) == [20, 40, 60, 80] and default_anchors(161, 8) == [40, 80, 120, 160]
    for model in (MODELS[name] for name in video_models()):
        assert (model.call["num_frames"] - 1) % model.temporal_compression == 0


def test_one_registry_whose_frame_rates_are_the_metrics_table():
    from geco_guide.metric.protocol import PAPER_MODEL_FPS

    assert {name: model.eval_fps for name, model in MODELS.items()} == PAPER_MODEL_FPS
    assert set(video_models()) | set(SCORED_ONLY) == set(PAPER_MODEL_FPS) and not set(video_models()) & set(SCORED_ONLY)
    assert all(name == model.name for name, model in MODELS.items())


@pytest.fixture(scope="module")
def tiny_run(tmp_path_factory):
    out = tmp_path_factory.mktemp("geco-eval") / "bench"
    assert main([*TINY_RUN, "--out", str(out)]) == 0
    return out


@pytest.mark.slow
def test_tiny_run_writes_videos_results_and_a_consistent_report(tiny_run: Path):
    out = tiny_run
    arms = ["cogvideox-5b", "cogvideox-5b-guided", "wan2.1-t2v-1.3b", "wan2.1-t2v-1.3b-guided"]
    assert sorted(p.name for p in (out / "videos").iterdir()) == sorted(arms)
    results = {arm: json.loads((out / "videos" / arm / "a1-s0.json").read_text()) for arm in arms}
    for arm, result in results.items():
        assert (out / "videos" / arm / "a1-s0.mp4").is_file()
        assert result["evaluation"]["fps"] == 16.0 and result["evaluation"]["fps_source"].startswith("model ")
        assert result["guided"] == arm.endswith("guided") and (result["guidance_updates"] > 0) == result["guided"]
    rows = list(csv.DictReader((out / "results.csv").open()))
    assert len(rows) == 4
    for row in rows:
        arm = row["model"] + ("-guided" if row["guided"] == "True" else "")
        for metric in ("fused", "motion", "structure", "total_motion", "mean_motion"):
            assert float(row[metric]) == pytest.approx(results[arm][metric])
    summary = json.loads((out / "summary.json").read_text())
    assert summary["videos"] == 4 and summary["missing"] == []
    stats = summary["arms"]["wan2.1-t2v-1.3b"]["groups"]
    assert stats["all"]["fused"]["mean"] == pytest.approx(results["wan2.1-t2v-1.3b"]["fused"])
    assert stats["object-centric"]["fused"]["n"] == 1 and "indoor" not in stats
    report = (out / "report.md").read_text()
    assert "## cogvideox-5b-guided" in report and "fused (M_geo)" in report
    assert (out / "pareto.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    # the report names what it ran with, and that tiny random models say nothing about quality
    assert report.count("tiny random models: the numbers show the mechanics, not quality") == 1
    assert "## Models and weights" in report and "tiny-random (wan family" in report
    assert summary["tiny_models"] and set(summary["models"]) == {"cogvideox-5b", "wan2.1-t2v-1.3b"}


def test_pareto_draws_no_empty_scenario_panels():
    import io

    from PIL import Image

    from geco_guide.bench.geco_eval import plot_png

    stats = {"mean": 0.5, "std": None, "n": 1}
    one = {"arms": {"m": {"groups": {"all": {"mean_motion": stats, "fused": stats},
                                     "indoor": {"mean_motion": stats, "fused": stats}}}}}
    empty = {"arms": {"m": {"groups": {}}}}
    def columns_drawn(png: bytes) -> int:
        image = Image.open(io.BytesIO(png)).convert("L")
        panels = [image.crop((left, 80, left + 220, 360)) for left in range(70, image.width - 220, 290)]
        # the canvas ends a margin after the last panel: no blank room for panels not drawn
        ink = [x for x in range(image.width) if image.crop((x, 0, x + 1, image.height)).getextrema()[0] < 255]
        assert image.width - ink[-1] <= 60, (image.width, ink[-1])
        return sum(1 for panel in panels if panel.getextrema()[0] < 255)

    assert columns_drawn(plot_png(one)) == 2  # "all" and indoor; no empty object-centric/outdoor/... panels
    assert columns_drawn(plot_png(empty)) == 1  # "all", labelled "no data"
    stats = {"mean": 0.5, "std": None, "n": 1}
    five = {"arms": {"m": {"groups": {g: {"mean_motion": stats, "fused": stats} for g in ("all", *geco_eval.SCENARIOS)}}}}
    assert columns_drawn(plot_png(five)) == 5


@pytest.mark.slow
def test_rerun_resumes_and_a_redone_video_is_identical(tiny_run: Path, tmp_path: Path, capsys):
    out = tmp_path / "bench"
    shutil.copytree(tiny_run, out)
    result = out / "videos" / "wan2.1-t2v-1.3b-guided" / "a1-s0.json"
    before = json.loads(result.read_text())
    result.unlink()  # as after a kill before the job finished
    (out / "videos" / "cogvideox-5b" / "a1-s0.mp4").unlink()  # a finished job whose video was deleted
    assert main([*TINY_RUN, "--out", str(out)]) == 0
    text = capsys.readouterr()
    assert "2 of 4 videos already done" in text.err and "a1-s0.mp4 is missing" in text.err
    after = json.loads(result.read_text())
    for metric in ("fused", "motion", "structure", "total_motion"):
        assert after[metric] == before[metric]  # same seed, same device: the same video
    assert main([*TINY_RUN, "--out", str(out)]) == 0 and "4 of 4 videos already done" in capsys.readouterr().err


@pytest.mark.slow
def test_score_existing_videos_at_the_models_native_rate(tiny_run: Path, tmp_path: Path):
    downloads = tmp_path / "sora"
    (downloads / "a1").mkdir(parents=True)
    shutil.copy(tiny_run / "videos" / "cogvideox-5b" / "a1-s0.mp4", downloads / "a1" / "take.mp4")
    out = tmp_path / "scores"
    assert main(["--preset", "tiny", "--videos", f"sora-2={downloads}", "--limit", "1", "--out", str(out)]) == 0
    result = json.loads((out / "videos" / "sora-2" / "a1-s0.json").read_text())
    assert result["evaluation"]["fps"] == 30.0 and result["evaluation"]["fps_source"] == "model sora-2"
    assert result["generation_s"] is None and result["video"] == str(downloads / "a1" / "take.mp4")


@pytest.mark.slow
def test_bad_inputs_are_one_line_before_any_model_loads(tmp_path: Path, tiny_run: Path, monkeypatch, capsys):
    def no_loading(*args, **kwargs):
        raise AssertionError("a model was loaded")

    monkeypatch.setattr(geco_eval, "load_models", no_loading)
    monkeypatch.setattr(geco_eval, "load_estimators", no_loading)
    cases = [
        (["--models", "sora-3"], "unknown model 'sora-3'"),
        (["--models", "cogvideox-5b", "--limit", "0"], "--limit must be >= 1"),
        (["--videos", f"veo-3.1={tmp_path / 'none'}"], "no such folder"),
        (["--videos", "nonsense"], "NAME=DIR"),
        ([], "nothing to do"),
        (["--models", "cogvideox-5b", "--seeds", "0", "0"], "distinct"),
        (["--models", "cogvideox-5b", "--seeds", "0", str(2**64)], f"--seeds takes integers from 0 to {2**64 - 1}"),
        (["--models", "cogvideox-5b", "--seeds", "-1"], "--seeds takes integers from 0"),
    ]
    for args, message in cases:
        assert main(["--preset", "tiny", *args, "--out", str(tmp_path / "x")]) == 2
        err = capsys.readouterr().err
        assert message in err and err.count("\n") == 1, err
    # a folder made with another config is refused
    assert main([*TINY_RUN, "--out", str(tiny_run), "evaluation.loss.pairs=center"]) == 2
    assert "another config" in capsys.readouterr().err


@pytest.mark.slow
def test_evaluate_cli_uses_the_models_native_rate(tiny_run: Path, tmp_path: Path, capsys):
    video = tiny_run / "videos" / "wan2.1-t2v-1.3b" / "a1-s0.mp4"
    out = tmp_path / "scores"
    assert evaluate_main([str(video), "--preset", "tiny", "--model", "ltx-video", "--out", str(out)]) == 0
    scored = json.loads((out / "a1-s0.geco.json").read_text())
    assert scored["fps"] == 30.0 and scored["fps_source"] == "model ltx-video"
    assert evaluate_main([str(video), "--preset", "tiny", "--model", "ltx-video", "--fps", "12", "--out", str(out),
                          "--overwrite"]) == 0
    assert json.loads((out / "a1-s0.geco.json").read_text())["fps_source"] == "--fps"
    capsys.readouterr()
    assert evaluate_main([str(video), "--preset", "tiny", "--model", "nope"]) == 2
    assert "unknown model 'nope'" in capsys.readouterr().err


def test_console_scripts_and_version(capsys):
    from importlib.metadata import entry_points

    import geco_guide

    scripts = {ep.name: ep.value for ep in entry_points(group="console_scripts")
               if ep.name == "geco" or ep.name.startswith("geco-")}
    assert scripts == {"geco": "geco_guide.__main__:main", "geco-generate": "geco_guide.cli.generate:main",
                       "geco-evaluate": "geco_guide.cli.evaluate:main", "geco-eval": "geco_guide.cli.geco_eval:main"}
    from geco_guide.cli.generate import main as generate_main

    for cli in (main, evaluate_main, generate_main):
        with pytest.raises(SystemExit) as exit_info:
            cli(["--version"])
        assert exit_info.value.code == 0 and capsys.readouterr().out.strip() == f"geco_guide {geco_guide.__version__}"


def test_unavailable_weights_are_one_line_naming_the_repo_and_the_weights_option(monkeypatch, tmp_path: Path):
    import diffusers.utils.constants
    import huggingface_hub.constants

    from geco_guide.config import load_config
    from geco_guide.estimators.loading import WeightsNotFoundError

    monkeypatch.setenv("HF_HUB_OFFLINE", "1")
    monkeypatch.setenv("HF_HOME", str(tmp_path / "hf"))  # an empty cache
    monkeypatch.setattr(huggingface_hub.constants, "HF_HUB_OFFLINE", True)
    monkeypatch.setattr(diffusers.utils.constants, "HF_HUB_OFFLINE", True, raising=False)
    cfg = load_config(overrides=["model.device=cpu", "estimators.geometry=tiny-random", "estimators.flow=tiny-random"])
    with pytest.raises(WeightsNotFoundError) as err:
        geco_eval.check_model_weights(cfg, ["ltx-video"], {})
    message = str(err.value)
    assert "\n" not in message and "`hf download Lightricks/LTX-Video`" in message
    assert "--weights ltx-video=/path/to/LTX-Video" in message
    with pytest.raises(WeightsNotFoundError, match="does not exist"):
        geco_eval.check_model_weights(cfg, ["ltx-video"], {"ltx-video": str(tmp_path / "missing")})
