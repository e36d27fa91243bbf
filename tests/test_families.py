"""The model registry: one table of family facts, and every registry model generated through the one
generation path from a folder as a user downloads it.

Each model runs ``geco generate --model NAME`` with its preset as shipped (``model.device: auto``,
``run.memory_plan: auto``, bfloat16, the schedule of its preset) except that ``model.id`` names a
``save_pretrained`` folder of its family's tiny random stand-in (the real diffusers classes), the
estimators are the tiny random ones, and the video is the tiny one (17 frames, a few pixels, two
steps: a full-size video of these models takes minutes per step on a CPU).
"""

from __future__ import annotations

import json
import warnings
from pathlib import Path

import pytest

from geco_guide import tiny
from geco_guide.cli import ab, generate, geco_eval
from geco_guide.config import load_config, model_preset
from geco_guide.families import MODELS, SCORED_ONLY, default_anchors, frames_problem, model_named, video_models

PACKAGE = Path(__file__).resolve().parents[1] / "geco_guide"
GENERATING = video_models()
PROMPT = "a stone bridge over a river, slow orbit"


def test_the_registry_is_the_one_table_of_family_facts():
    # a hub id written anywhere else in the package would be a second table
    registry = PACKAGE / "families" / "__init__.py"
    for path in sorted(PACKAGE.rglob("*.py")):
        if path == registry:
            continue
        text = path.read_text()
        found = [model.hub_id for model in MODELS.values() if model.hub_id and model.hub_id in text]
        assert not found, f"{path.relative_to(PACKAGE)} names {found}: read the registry instead"
    assert set(SCORED_ONLY) == {"sora-2", "veo-3.1"} and not set(SCORED_ONLY) & set(GENERATING)


def _family_words() -> set[str]:
    """What names a family: the registry's model, family and pipeline class names, its adapters',
    tiny builders' and tiny decoders' names."""
    from geco_guide.families import FAMILIES, TINY_DECODER_ALIASES, TINY_DECODERS

    words = {*MODELS, *FAMILIES, *TINY_DECODERS, *TINY_DECODER_ALIASES}
    for model in MODELS.values():
        words.update(word for word in (model.pipeline, model.adapter, model.tiny) if word)
    return {word.lower() for word in words if word}


#: A family's own code, which may name it: its adapter, its tiny builders, the CogVideoX pipeline
#: and the Wan modular blocks.
FAMILY_CODE = ("sampler/pipelines/adapters.py", "tiny/pipelines.py", "tiny/components.py", "sampler/pipelines/pipeline_cogvideox.py",
               "sampler/pipelines/modular.py")


def test_no_string_outside_the_registry_and_the_families_code_names_a_family():
    # a family's name as a string elsewhere is a table or a branch of its own; exports (__all__) are names
    import ast

    words = _family_words()
    found = []
    for path in sorted(PACKAGE.rglob("*.py")):
        relative = path.relative_to(PACKAGE).as_posix()
        if relative.startswith("families/") or relative in FAMILY_CODE:
            continue
        tree = ast.parse(path.read_text())
        exported = {id(node) for assign in ast.walk(tree) if isinstance(assign, ast.Assign)
                    and any(getattr(t, "id", None) == "__all__" for t in assign.targets) for node in ast.walk(assign)}
        found += [f"{relative}:{node.lineno} {node.value!r}" for node in ast.walk(tree)
                  if isinstance(node, ast.Constant) and isinstance(node.value, str) and id(node) not in exported
                  and node.value.lower() in words]
    assert not found, f"family names outside the registry: {found}"


@pytest.mark.parametrize("name", GENERATING)
def test_every_entry_names_an_adapter_a_tiny_builder_a_tiny_decoder_and_schedulers_that_exist(name):
    import diffusers

    from geco_guide.families import TINY_DECODERS
    from geco_guide.sampler.pipelines.adapters import ADAPTERS, adapter_for_class
    from geco_guide.tiny import pipelines

    model = model_named(name)
    assert isinstance(adapter_for_class(getattr(diffusers, model.pipeline)), ADAPTERS[model.adapter])
    assert callable(getattr(pipelines, model.tiny))
    assert model.tiny_decoder is None or model.tiny_decoder in TINY_DECODERS
    assert model.scheduler is None or model.scheduler in model.schedulers
    assert all(isinstance(getattr(diffusers, cls), type) for cls in model.schedulers.values())


@pytest.mark.parametrize("name", GENERATING)
def test_every_model_has_a_preset_its_facts_and_a_tiny_stand_in(name):
    model = model_named(name)
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # the preset's schedule is written for the model's step count
        cfg = load_config(model_preset=model_preset(name), changes={"model.name": name})
    call = model.call
    assert cfg.model.name == name and cfg.model.source == model.hub_id
    assert (cfg.sampling.num_frames, cfg.sampling.height, cfg.sampling.width, cfg.sampling.num_inference_steps,
            cfg.sampling.guidance_scale, cfg.sampling.fps) == (
        call["num_frames"], call["height"], call["width"], call["num_inference_steps"], call["guidance_scale"],
        model.fps)
    assert cfg.sampling.guidance_scale_2 == call.get("guidance_scale_2")
    assert frames_problem(call["num_frames"], model.frame_multiple) is None
    assert call["height"] % model.size_multiple == 0 and call["width"] % model.size_multiple == 0
    # the paper's four anchors, spread over the model's video as over CogVideoX's 49 frames
    assert cfg.guidance.anchors == model.anchors == default_anchors(call["num_frames"], model.temporal_compression)
    assert len(model.anchors) == 4 and model.anchors[-1] == call["num_frames"] - 1
    stand_in = getattr(tiny, model.tiny)(0)
    assert type(stand_in).__name__ == model.pipeline
    temporal = getattr(stand_in, "vae_scale_factor_temporal", None) or stand_in.vae_temporal_compression_ratio
    assert temporal == model.temporal_compression


def test_the_paper_anchors_are_the_quarter_points():
    assert default_anchors(49, 4) == [12, 24, 36, 48]
    assert default_anchors(81, 4) == [20, 40, 60, 80] and default_anchors(161, 8) == [40, 80, 120, 160]
    with pytest.raises(ValueError, match="4k\\+1 frames"):
        default_anchors(50, 4)


def test_an_unknown_or_scored_only_model_is_one_line(capsys):
    for name, expected in (("wan-9", "unknown model 'wan-9'; one of cogvideox-2b"), ("sora-2", "has no open weights")):
        assert generate.main(["--model", name, "--prompt", PROMPT]) == 2
        err = capsys.readouterr().err.strip()
        assert expected in err and "\n" not in err


def test_the_conditioning_image_and_the_model_must_agree_before_anything_loads(tmp_path, capsys):
    """An image-to-video model without --image, a text-to-video one with it, a search with it: one
    line each, before any model loads or any file is written; so for the commands with no image."""
    tiny.tiny_image(0, 64, 64).save(tmp_path / "image.png")
    prompts = tmp_path / "prompts.txt"
    prompts.write_text(PROMPT + "\n")
    i2v = next(name for name in GENERATING if model_named(name).image_to_video)
    image = ["--image", str(tmp_path / "image.png")]
    cases = [
        (generate.main, ["--model", i2v, "model.id=tiny-random"], "is an image-to-video model: it needs a conditioning image"),
        (generate.main, ["--preset", "tiny", *image], "is a text-to-video model: it takes no conditioning image"),
        (generate.main, ["--model", i2v, "model.id=tiny-random", *image, "--search", "2"],
         "a search of an image-to-video model is not supported"),
        (generate.main, ["--model", i2v, "model.id=tiny-random", "--best-of", "2"], "is an image-to-video model"),
    ]
    for main, argv, expected in cases:
        assert main([*argv, "--prompt", PROMPT, "--out", str(tmp_path / "video.mp4")]) == 2
        err = capsys.readouterr().err.strip()
        assert expected in err and "\n" not in err and "loading" not in err, err
    assert ab.main(["--prompts", str(prompts), "--seeds", "0", "--out", str(tmp_path / "ab"), "--model", i2v,
                    "model.id=tiny-random"]) == 2
    err = capsys.readouterr().err.strip()
    assert f"model.name={i2v} is an image-to-video model" in err and "\n" not in err, err
    assert geco_eval.main(["--models", i2v, "--out", str(tmp_path / "eval"), "--preset", "tiny"]) == 2
    err = capsys.readouterr().err.strip()
    assert "image-to-video model and GeCo-Eval's prompts are text only" in err and "\n" not in err, err
    assert sorted(path.name for path in tmp_path.iterdir()) == ["image.png", "prompts.txt"]


@pytest.fixture(scope="module")
def folders(tmp_path_factory) -> dict[str, Path]:
    """Every registry model's tiny stand-in, written with ``save_pretrained`` as a user's download."""
    root = tmp_path_factory.mktemp("weights")
    written = {}
    for name in GENERATING:
        model = model_named(name)
        written[name] = root / name
        getattr(tiny, model.tiny)(0).save_pretrained(written[name])
    tiny.tiny_image(0, 64, 64).save(root / "image.png")
    written["image"] = root / "image.png"
    return written


def small_video(name: str) -> list[str]:
    """The tiny video of a model's stand-in (the paper presets' 49 frames: their anchors are fixed)."""
    model = model_named(name)
    sizes = tiny.tiny_sampling(model)
    if name == "cogvideox-5b":
        sizes["num_frames"] = 49
    return [*(f"sampling.{key}={value}" for key, value in sizes.items()), "sampling.num_inference_steps=2",
            "estimators.geometry=tiny-random", "estimators.flow=tiny-random"]


@pytest.mark.slow
@pytest.mark.parametrize("guided", [True, False], ids=["guided", "unguided"])
@pytest.mark.parametrize("name", GENERATING)
def test_geco_generate_model_runs_every_model_from_a_folder_as_shipped(name, guided, folders, tmp_path, capsys):
    model = model_named(name)
    out = tmp_path / "video.mp4"
    argv = ["--model", name, "--prompt", PROMPT, "--out", str(out), f"model.id={folders[name]}", *small_video(name)]
    if model.image_to_video:
        argv += ["--image", str(folders["image"])]
    if not guided:
        argv.append("--no-guidance")
    rc = generate.main(argv)
    captured = capsys.readouterr()
    assert rc == 0, captured.err
    sidecar = json.loads(out.with_suffix(".json").read_text())
    config = sidecar["config"]
    assert sidecar["model"] == name and config["model"]["dtype"] == "bfloat16"
    assert config["model"]["device"] == sidecar["device"] and config["run"]["memory_plan"] == "auto"
    assert sidecar["num_frames"] == config["sampling"]["num_frames"] and "loading models" in captured.err
    if guided:
        shipped = load_config(model_preset=model_preset(name), changes={"model.name": name})
        assert config["guidance"]["repeats"] == shipped.guidance.repeats  # the preset's, scaled to 2 steps
        assert sidecar["guidance_log"] and sidecar["memory_plan"]["reason"].startswith("auto")
        assert sidecar["geco_scores"]["anchors"] == config["guidance"]["anchors"]
    else:
        assert sidecar["guidance_log"] == [] and sidecar["memory_plan"] is None


@pytest.mark.slow
def test_geco_ab_model_runs_a_registry_model_from_a_folder(folders, tmp_path, capsys):
    name = "wan2.1-t2v-1.3b"
    prompts = tmp_path / "prompts.txt"
    prompts.write_text(PROMPT + "\n")
    out = tmp_path / "ab"
    rc = ab.main(["--prompts", str(prompts), "--seeds", "0", "--out", str(out), "--model", name,
                  f"model.id={folders[name]}", *small_video(name)])
    captured = capsys.readouterr()
    assert rc == 0, captured.err
    config = json.loads((out / "run.json").read_text())["config"]
    shipped = load_config(model_preset=model_preset(name), changes={"model.name": name})
    assert config["model"]["name"] == name and config["sampling"]["fps"] == shipped.sampling.fps
    pair = next((out / "pairs").iterdir())
    for arm in ("unguided", "guided"):
        assert json.loads((pair / f"{arm}.json").read_text())["model"] == name
    assert (out / "report.md").is_file()


@pytest.mark.parametrize("name", GENERATING)
def test_offline_without_weights_each_model_is_the_missing_weights_line(name, tmp_path, monkeypatch, capsys):
    """A fresh machine without network: ``geco generate --model NAME`` (its preset as shipped) ends in
    one line naming the hub id, the config key and how to pass a local folder, before anything loads."""
    import diffusers.utils.constants
    import huggingface_hub.constants

    monkeypatch.setenv("HF_HUB_OFFLINE", "1")
    monkeypatch.setenv("HF_HOME", str(tmp_path / "hf-home"))
    # both libraries read the variables once, at import
    monkeypatch.setattr(huggingface_hub.constants, "HF_HUB_OFFLINE", True)
    monkeypatch.setattr(huggingface_hub.constants, "HF_HUB_CACHE", str(tmp_path / "hf-home" / "hub"))
    monkeypatch.setattr(diffusers.utils.constants, "HF_HUB_OFFLINE", True, raising=False)
    model = model_named(name)
    argv = ["--model", name, "--prompt", PROMPT, "--out", str(tmp_path / "video.mp4")]
    if model.image_to_video:
        tiny.tiny_image(0, 64, 64).save(tmp_path / "image.png")
        argv += ["--image", str(tmp_path / "image.png")]
    assert generate.main(argv) == 2
    err = capsys.readouterr().err.strip()
    assert "\n" not in err and "loading" not in err and err.startswith("error: "), err
    assert model.hub_id in err and "(offline and not in the cache)" in err, err
    assert f"(config: model.id=/path/to/{model.hub_id.split('/')[-1]})" in err, err
    assert not (tmp_path / "video.mp4").exists()
