"""The shipped presets run as a user runs them, with only the weights swapped.

A user's first command is ``--preset cogvideox-5b``: ``model.device: auto``, ``run.memory_plan: auto``,
bfloat16, hub ids, the estimators' and the pipeline's real loading. Here each preset runs exactly
as shipped (device, memory plan, dtypes, schedule, loss), except that ``model.id``,
``estimators.geometry`` and ``estimators.flow`` name local folders written with
``save_pretrained`` from the tiny random models (so ``from_pretrained`` of a folder, the planner on
the resolved device, the dtype casts and the sidecar all run) and the video is small. Offline
without weights, every command with a real preset ends in the one missing-weights line and exit
code 2.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
import textwrap
from pathlib import Path

import pytest
import torch

from geco_guide.cli import ab
from geco_guide.cli import generate as generate_module
from geco_guide.config import CONFIG_DIR, load_config, preset_path
from geco_guide.estimators.tiny_decoder import TinyDecoder
from geco_guide.estimators.ufm import UFM
from geco_guide.estimators.vggt import VGGT
from geco_guide.sampler.pipelines.pipeline_cogvideox import GeCoCogVideoXPipeline
from geco_guide.tiny import tiny_cogvideox_components, tiny_estimators

ROOT = Path(__file__).resolve().parents[2]
SHIPPED = sorted(p.stem for p in CONFIG_DIR.glob("*.yaml"))
REAL_PRESETS = [name for name in SHIPPED if name != "tiny"]
#: The real presets whose model has the checkpoint layout of the local CogVideoX-5b folder below
#: (CogVideoX 1.0, text to video): the ones that run from it as shipped. The other models'
#: presets load and validate here; their families run on their tiny stand-ins in test_hooks.py.
FOLDER_PRESETS = [name for name in REAL_PRESETS
                  if load_config(preset=name).model.video_model.tiny == "tiny_cogvideox_pipeline"]
PROMPT = "a stone bridge over a river, slow orbit"
# A small video with the presets' 49 frames (their anchors 12..48 need them), 16x16 pixels, and the
# tiny text encoder's sequence length.
SMALL_VIDEO = ["sampling.height=16", "sampling.width=16", "sampling.max_sequence_length=16"]


def test_every_preset_is_shipped_with_the_package_and_real_presets_are_tested():
    assert {"tiny", "cogvideox-5b", "cogvideox-5b-fused"} <= set(SHIPPED)
    assert REAL_PRESETS, "no real preset found"
    assert {"cogvideox-5b", "cogvideox-5b-fused"} <= set(FOLDER_PRESETS)


@pytest.mark.parametrize("name", SHIPPED)
def test_every_shipped_preset_loads_and_validates(name):
    # a preset cannot ship with a key the schema rejects or a value its checks refuse
    cfg = load_config(preset=name)
    assert preset_path(name).is_file() and cfg.guidance.anchors
    if name != "tiny":
        assert (cfg.model.device, cfg.run.memory_plan, cfg.model.dtype) == ("auto", "auto", "bfloat16")


@pytest.fixture(scope="module")
def local_weights(tmp_path_factory) -> dict[str, str]:
    """Folders as a user downloads them: the pipeline (with the DPM scheduler CogVideoX-5b ships),
    VGGT-1B and UFM-Base, written with ``save_pretrained`` from the tiny random models."""
    root = tmp_path_factory.mktemp("weights")
    components = tiny_cogvideox_components(0)
    from diffusers import CogVideoXDPMScheduler

    components["scheduler"] = CogVideoXDPMScheduler.from_config(components["scheduler"].config)
    GeCoCogVideoXPipeline(**components).save_pretrained(root / "CogVideoX-5b")
    tiny = tiny_estimators(0)
    tiny.geometry.save_pretrained(root / "VGGT-1B")
    tiny.flow.save_pretrained(root / "UFM-Base")
    return {"model": str(root / "CogVideoX-5b"), "geometry": str(root / "VGGT-1B"), "flow": str(root / "UFM-Base")}


def weights_overrides(weights: dict[str, str]) -> list[str]:
    return [f"model.id={weights['model']}", f"estimators.geometry={weights['geometry']}",
            f"estimators.flow={weights['flow']}"]


@pytest.mark.slow
def test_estimators_round_trip_through_save_pretrained_with_their_config(tmp_path):
    tiny = tiny_estimators(3)
    for model, cls in ((tiny.geometry, VGGT), (tiny.flow, UFM)):
        folder = model.save_pretrained(tmp_path / cls.model_name)
        assert sorted(p.name for p in folder.iterdir()) == ["config.json", "model.safetensors"]
        # no config= given: the folder's config.json says it is a tiny model, not the default 1B
        loaded = cls.from_pretrained(folder)
        assert loaded.config == model.config != cls.config_class()
        for key, value in model.state_dict().items():
            assert torch.equal(loaded.state_dict()[key], value), key
    # the upstream VGGT config.json (its constructor arguments) is read too
    (tmp_path / "VGGT" / "config.json").write_text(json.dumps({"img_size": 518, "patch_size": 14, "embed_dim": 1024}))
    assert VGGT.config_from_json(json.loads((tmp_path / "VGGT" / "config.json").read_text())) == VGGT.config_class()
    # a VGGT folder without config.json is the default architecture (VGGT-1B): the tiny weights do not fit it
    (tmp_path / "VGGT" / "config.json").unlink()
    with pytest.raises(ValueError, match="VGGT checkpoint does not fit"):
        VGGT.from_pretrained(tmp_path / "VGGT")
    (tmp_path / "VGGT" / "config.json").write_text("{not json")
    with pytest.raises(ValueError, match="not a readable VGGT config.json"):
        VGGT.from_pretrained(tmp_path / "VGGT")


@pytest.mark.parametrize("preset", FOLDER_PRESETS)
@pytest.mark.slow
def test_a_real_preset_generates_from_local_folders_as_shipped(preset, local_weights, tmp_path, capsys):
    out = tmp_path / "video.mp4"
    rc = generate_module.main(["--preset", preset, "--prompt", PROMPT, "--out", str(out),
                               *weights_overrides(local_weights), *SMALL_VIDEO])
    captured = capsys.readouterr()
    assert rc == 0, captured.err
    sidecar = json.loads(out.with_suffix(".json").read_text())
    shipped = load_config(preset=preset)
    config = sidecar["config"]
    # auto resolved once: the planner, the loaders and the sidecar saw the same real device
    assert config["model"]["device"] == sidecar["device"] == ("cuda:0" if torch.cuda.is_available() else "cpu")
    assert config["model"]["dtype"] == "bfloat16" and config["estimators"]["dtype"] == "bfloat16"
    guidance = config["guidance"]
    assert config["run"]["memory_plan"] == "auto" and guidance["repeats"] == shipped.guidance.repeats
    assert guidance["loss"]["cue"] == shipped.guidance.loss.cue
    assert config["sampling"]["num_inference_steps"] == shipped.sampling.num_inference_steps
    # the planner knew the folder's denoiser by its stored config (the tiny model's estimates)
    assert sidecar["memory_plan"]["reason"].startswith("auto:") and "(tiny)" in sidecar["memory_plan"]["reason"]
    assert sidecar["scheduler"].startswith("CogVideoXDDIMScheduler (sampling.scheduler=ddim, built from the "
                                           "checkpoint's CogVideoXDPMScheduler config)")
    expected_updates = sum(shipped.guidance.schedule(shipped.sampling.num_inference_steps).repeats)
    assert len(sidecar["guidance_log"]) == expected_updates
    assert sidecar["geco_scores"] is not None and "loading models" in captured.err


def test_the_paper_preset_without_guidance_from_local_folders(local_weights, tmp_path, capsys):
    out = tmp_path / "plain.mp4"
    rc = generate_module.main(["--preset", "cogvideox-5b", "--no-guidance", "--prompt", PROMPT, "--out", str(out),
                               *weights_overrides(local_weights), *SMALL_VIDEO])
    assert rc == 0, capsys.readouterr().err
    sidecar = json.loads(out.with_suffix(".json").read_text())
    assert sidecar["guidance_log"] == [] and sidecar["memory_plan"] is None and sidecar["device"] == "cpu"


def test_the_planner_knows_a_local_folder_by_its_denoiser_config(tmp_path, capsys):
    # a folder holding only the CogVideoX-5b configs: the refusal comes before any weights would be
    # read, with the 5B model's own estimates
    folder = tmp_path / "CogVideoX-5b"
    (folder / "transformer").mkdir(parents=True)
    (folder / "vae").mkdir()
    (folder / "model_index.json").write_text(json.dumps({"_class_name": "CogVideoXPipeline"}))
    (folder / "transformer" / "config.json").write_text(json.dumps(
        {"_class_name": "CogVideoXTransformer3DModel", "num_layers": 42, "num_attention_heads": 48,
         "attention_head_dim": 64, "in_channels": 16, "patch_size": 2, "patch_size_t": None}))
    (folder / "vae" / "config.json").write_text(json.dumps({"_class_name": "AutoencoderKLCogVideoX",
                                                            "latent_channels": 16}))
    rc = generate_module.main(["--preset", "cogvideox-5b", "--prompt", PROMPT, "--out", str(tmp_path),
                               f"model.id={folder}", "estimators.geometry=tiny-random", "estimators.flow=tiny-random",
                               "run.memory_budget_gb=1"])
    err = capsys.readouterr().err.strip()
    assert rc == 2 and "\n" not in err
    assert err.startswith("error: no memory plan fits 1.0 GiB: the smallest, 'checkpointed', is predicted to peak "
                          "at 40.3 GiB (cogvideox-5b, faithful mode, 49x480x720)"), err


def test_an_unusable_device_is_one_line_naming_the_key(tmp_path, capsys):
    missing = "cuda:7" if torch.cuda.is_available() else "cuda"
    rc = generate_module.main(["--preset", "cogvideox-5b", "--prompt", PROMPT, "--out", str(tmp_path),
                               f"model.device={missing}", "model.id=tiny-random", "estimators.geometry=tiny-random",
                               "estimators.flow=tiny-random"])  # weights there: missing ones are named first
    err = capsys.readouterr().err.strip()
    assert rc == 2 and "\n" not in err and "model.device" in err and repr(missing) in err


def test_the_memory_planner_resolves_auto_and_refuses_a_missing_device():
    from geco_guide.sampler.algorithm.config import paper_guidance_config
    from geco_guide.io.devices import device_memory_gb
    from geco_guide.sampler.running.memory_plan import plan_before_loading
    from geco_guide.sampler.running.run_options import RunOptions

    assert device_memory_gb("auto") == device_memory_gb("cuda" if torch.cuda.is_available() else "cpu")
    choice = plan_before_loading(paper_guidance_config(), RunOptions(memory_budget_gb=200.0), "THUDM/CogVideoX-5b",
                                 49, 480, 720, device_memory_gb("auto"))
    assert choice is not None and choice.plan.name
    if not torch.cuda.is_available():
        with pytest.raises(ValueError, match="device 'cuda' is not available"):
            device_memory_gb("cuda")


@pytest.mark.slow
def test_geco_ab_runs_the_paper_preset_from_local_folders(local_weights, tmp_path, capsys):
    prompts = tmp_path / "prompts.txt"
    prompts.write_text(PROMPT + "\n")
    out = tmp_path / "ab"
    # the runner's own path (pairs, run.json, scores, report) is what this adds to the generate tests,
    # which run the shipped schedule: 10 steps, the preset's repeats and time travel scaled to them
    rc = ab.main(["--prompts", str(prompts), "--seeds", "0", "--out", str(out), "--preset", "cogvideox-5b",
                  *weights_overrides(local_weights), *SMALL_VIDEO, "sampling.num_inference_steps=10"])
    captured = capsys.readouterr()
    assert rc == 0, captured.err
    run = json.loads((out / "run.json").read_text())
    assert run["config"]["model"]["dtype"] == "bfloat16" and run["config"]["run"]["memory_plan"] == "auto"
    assert (out / "report.md").is_file()


@pytest.mark.slow
def test_geco_eval_runs_cogvideox_5b_from_local_folders(local_weights, tmp_path, capsys, monkeypatch):
    from dataclasses import replace

    from geco_guide import families
    from geco_guide.cli import geco_eval

    small = {**families.MODELS["cogvideox-5b"].call, "height": 16, "width": 16}
    monkeypatch.setitem(families.MODELS, "cogvideox-5b", replace(families.MODELS["cogvideox-5b"], call=small))
    out = tmp_path / "bench"
    rc = geco_eval.main(["--models", "cogvideox-5b", "--limit", "1", "--seeds", "0", "--out", str(out),
                         "--weights", f"cogvideox-5b={local_weights['model']}",
                         "--geometry-estimator", local_weights["geometry"], "--flow-estimator", local_weights["flow"]])
    captured = capsys.readouterr()
    assert rc == 0, captured.err
    assert (out / "report.md").is_file() and "1 video" in captured.out


OFFLINE_DRIVER = textwrap.dedent("""
    import contextlib, io, json, sys, traceback
    root, out, video, decoder = sys.argv[1:]
    sys.path.insert(0, root)  # this checkout's package, wherever the driver runs, not an installed one
    sys.argv = ["driver"]
    results = []
    def run(name, main, argv):
        err = io.StringIO()
        try:
            with contextlib.redirect_stderr(err), contextlib.redirect_stdout(io.StringIO()):
                try:
                    rc = main(argv)
                except SystemExit as exit:
                    rc = exit.code
        except BaseException:
            rc, err = "traceback", io.StringIO(traceback.format_exc())
        results.append({"name": name, "rc": rc, "err": err.getvalue()})
    from geco_guide.cli import ab, evaluate, generate, geco_eval
    prompt = ["--prompt", "a stone bridge over a river, slow orbit"]
    run("generate", generate.main, ["--preset", "cogvideox-5b", *prompt, "--out", out + "/g.mp4"])
    run("generate --no-guidance", generate.main, ["--preset", "cogvideox-5b", "--no-guidance", *prompt, "--out", out + "/u.mp4"])
    run("generate fused", generate.main, ["--preset", "cogvideox-5b-fused", *prompt, "--out", out + "/f.mp4"])
    run("evaluate", evaluate.main, ["--preset", "cogvideox-5b", video, "--out", out + "/scores"])
    run("geco_eval", geco_eval.main, ["--models", "cogvideox-5b", "--limit", "1", "--seeds", "0", "--out", out + "/bench"])
    prompts = out + "/prompts.txt"
    open(prompts, "w").write("a stone bridge over a river, slow orbit\\n")
    run("ab", ab.main, ["--prompts", prompts, "--seeds", "0", "--out", out + "/ab", "--preset", "cogvideox-5b"])
    from geco_guide.cli import bench
    run("bench decoder-agreement", bench.main, ["decoder-agreement", "--preset", "cogvideox-5b",
                                                "estimators.tiny_decoder=" + decoder])
    print(json.dumps(results))
""")


@pytest.mark.slow
def test_offline_without_weights_every_command_with_a_real_preset_is_the_missing_weights_line(tmp_path):
    # one process for all (a process per command would pay the imports each time); offline and an
    # empty hub cache, as on a fresh machine without network
    from geco_guide.io.video import write_video

    video = tmp_path / "clip.mp4"
    write_video(video, torch.rand(9, 3, 32, 48), fps=8)
    decoder = tmp_path / "taecvx.pth"
    torch.save(TinyDecoder.tiny("cogvideox", 0).state_dict(), decoder)
    out = tmp_path / "out"
    out.mkdir()
    env = {**os.environ, "HF_HUB_OFFLINE": "1", "HF_HOME": str(tmp_path / "hf-home"), "OMP_NUM_THREADS": "1"}
    done = subprocess.run([sys.executable, "-c", OFFLINE_DRIVER, str(ROOT), str(out), str(video), str(decoder)],
                          capture_output=True, text=True, env=env, cwd=tmp_path, timeout=600)
    assert done.returncode == 0, done.stderr[-3000:]
    results = json.loads(done.stdout.strip().splitlines()[-1])
    assert [r["name"] for r in results] == ["generate", "generate --no-guidance", "generate fused", "evaluate",
                                            "geco_eval", "ab", "bench decoder-agreement"]
    for result in results:
        lines = [line for line in result["err"].splitlines() if line.strip()]
        assert result["rc"] == 2, result
        error = lines[-1]
        assert "Traceback" not in result["err"], result
        assert "could not load weights" in error and "(offline and not in the cache)" in error, result
        assert "(config: " in error and "=/path/to/" in error or "--weights cogvideox-5b=/path/to/" in error, result
        assert "hf download" in error, result
