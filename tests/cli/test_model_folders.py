"""A local model folder (``model.id=/path``) is checked from its small files before anything loads:
another model's folder is one line naming both models, a damaged folder one line naming the file
(never the hub's "cannot be reached ... hf download"). The folders here are written by hand: a
``model_index.json``, the configs and weights of a few bytes, as ``save_pretrained`` lays them out.
"""

from __future__ import annotations

import json
from pathlib import Path

import pytest
import torch
from safetensors.torch import save_file

from geco_guide.__main__ import main
from geco_guide.sampler.pipelines.loading import ModelConfig, load_video_pipeline, pipeline_from_pretrained
from geco_guide.sampler.pipelines.model_folder import ModelFolderError, check_model_folder
from geco_guide.families import model_named

TINY = ["--prompt", "a marble bust", "estimators.geometry=tiny-random", "estimators.flow=tiny-random"]


def pipeline_folder(root: Path, pipeline: str, transformer: str, vae: str, latents: int, *, patch=2, patch_t=None,
                    experts: int = 1, **settings) -> Path:
    """A pipeline folder of ``pipeline`` with a denoiser (two with ``experts=2``) of class
    ``transformer`` and patches ``patch`` / ``patch_t``, a VAE of ``latents`` channels (``z_dim``
    for Wan's), a scheduler, and the pipeline's ``settings`` (``expand_timesteps``)."""
    root.mkdir(parents=True)
    index = {"_class_name": pipeline, "_diffusers_version": "0.36.0", **settings,
             "scheduler": ["diffusers", "FlowMatchEulerDiscreteScheduler"], "vae": ["diffusers", vae]}
    denoisers = ["transformer", "transformer_2"][:experts]
    for name in denoisers:
        index[name] = ["diffusers", transformer]
        _component(root / name, {"_class_name": transformer, "in_channels": latents, "patch_size": patch,
                                 "patch_size_t": patch_t})
    if "WanPipeline" == pipeline:
        index.setdefault("transformer_2", [None, None])
    _component(root / "vae", {"_class_name": vae, ("z_dim" if "Wan" in vae else "latent_channels"): latents})
    (root / "scheduler").mkdir()
    (root / "scheduler" / "scheduler_config.json").write_text(json.dumps({"_class_name": index["scheduler"][1]}))
    (root / "model_index.json").write_text(json.dumps(index))
    return root


def _component(folder: Path, config: dict) -> None:
    folder.mkdir()
    (folder / "config.json").write_text(json.dumps(config))
    save_file({"weight": torch.zeros(4, 4)}, str(folder / "diffusion_pytorch_model.safetensors"))


WAN = ("WanPipeline", "WanTransformer3DModel", "AutoencoderKLWan")
FOLDERS = {
    "wan2.1": lambda root: pipeline_folder(root, *WAN, 16, patch=[1, 2, 2], expand_timesteps=False),
    "wan2.2-a14b": lambda root: pipeline_folder(root, *WAN, 16, patch=[1, 2, 2], experts=2, boundary_ratio=0.875,
                                                expand_timesteps=False),
    "wan2.2-ti2v": lambda root: pipeline_folder(root, *WAN, 48, patch=[1, 2, 2], expand_timesteps=True),
    # a folder of an older diffusers, whose model_index.json has no expand_timesteps
    "wan2.2-ti2v-older": lambda root: pipeline_folder(root, *WAN, 48, patch=[1, 2, 2]),
    "cogvideox1.5": lambda root: pipeline_folder(root, "CogVideoXPipeline", "CogVideoXTransformer3DModel",
                                                 "AutoencoderKLCogVideoX", 16, patch=2, patch_t=2),
    "ltx-with-ltx2-denoiser": lambda root: pipeline_folder(root, "LTXPipeline", "LTX2VideoTransformer3DModel",
                                                           "AutoencoderKLLTXVideo", 128, patch=1, patch_t=1),
}


def _one_error(capsys) -> str:
    err = capsys.readouterr().err.strip()
    assert "\n" not in err and "Traceback" not in err and err.startswith("error: "), err
    assert "from the Hugging Face hub" not in err, err  # the line of weights the hub would have
    return err


@pytest.mark.parametrize("model, folder, expected", [
    ("ltx-video", "wan2.1", "is not a folder of ltx-video: its model_index.json names the pipeline WanPipeline, "
                            "ltx-video's is LTXPipeline (the pipeline of wan2.1-t2v-1.3b, wan2.1-t2v-14b, "
                            "wan2.2-t2v-a14b or wan2.2-ti2v-5b)"),
    ("wan2.1-t2v-1.3b", "wan2.2-a14b", "is not a folder of wan2.1-t2v-1.3b: it holds 2 denoisers (model_index.json "
                                       "lists transformer_2), wan2.1-t2v-1.3b has 1 (the layout of wan2.2-t2v-a14b)"),
    ("wan2.2-t2v-a14b", "wan2.1", "it holds 1 denoiser (model_index.json lists no transformer_2), wan2.2-t2v-a14b "
                                  "has 2"),
    ("wan2.1-t2v-1.3b", "wan2.2-ti2v", "its model_index.json has expand_timesteps=True, wan2.1-t2v-1.3b's pipeline "
                                       "does not expand them (the layout of wan2.2-ti2v-5b)"),
    ("wan2.1-t2v-14b", "wan2.2-ti2v-older", "its VAE makes 48-channel latents (vae/config.json), wan2.1-t2v-14b's "
                                            "16 (the layout of wan2.2-ti2v-5b)"),
    ("cogvideox-5b", "cogvideox1.5", "its transformer patches 2 latent frames together (transformer/config.json), "
                                     "cogvideox-5b's 1 (the layout of cogvideox1.5-5b)"),
    ("ltx-video", "ltx-with-ltx2-denoiser", "its transformer/config.json names LTX2VideoTransformer3DModel, "
                                            "ltx-video's is LTXVideoTransformer3DModel"),
])
def test_another_models_folder_is_one_line_naming_both_before_loading(model, folder, expected, tmp_path, capsys,
                                                                     no_loading):
    path = FOLDERS[folder](tmp_path / folder)
    out = tmp_path / "out"
    assert main(["generate", "--model", model, *TINY, "--out", str(out), f"model.id={path}"]) == 2
    err = _one_error(capsys)
    assert f"error: model.id={path} " in err and expected in err, err
    assert not out.exists()


def test_geco_ab_refuses_a_wan22_folder_as_wan21_before_loading(tmp_path, capsys, no_loading):
    path = FOLDERS["wan2.2-a14b"](tmp_path / "Wan2.2-T2V-A14B")
    prompts = tmp_path / "prompts.txt"
    prompts.write_text("a marble bust\n")
    argv = ["ab", "--prompts", str(prompts), "--seeds", "0", "--out", str(tmp_path / "ab"), "--model",
            "wan2.1-t2v-1.3b", f"model.id={path}", "estimators.geometry=tiny-random", "estimators.flow=tiny-random"]
    assert main(argv) == 2
    assert "is not a folder of wan2.1-t2v-1.3b: it holds 2 denoisers" in _one_error(capsys)
    assert not (tmp_path / "ab").exists()


@pytest.mark.parametrize("model, folder", [("wan2.1-t2v-1.3b", "wan2.1"), ("wan2.2-t2v-a14b", "wan2.2-a14b"),
                                           ("wan2.2-ti2v-5b", "wan2.2-ti2v"), ("cogvideox1.5-5b", "cogvideox1.5")])
def test_a_folder_of_the_models_own_layout_passes(model, folder, tmp_path):
    check_model_folder(model_named(model), FOLDERS[folder](tmp_path / folder))


def _truncate(path: Path) -> None:
    path.write_bytes(path.read_bytes()[:-10])


def _randomise(path: Path) -> None:
    path.write_bytes(torch.randint(0, 256, (4096,), dtype=torch.uint8, generator=torch.Generator().manual_seed(0))
                     .numpy().tobytes())


WEIGHTS = "transformer/diffusion_pytorch_model.safetensors"
DAMAGE = {
    "no model_index.json": ("model_index.json", Path.unlink, "model_index.json is missing: {folder} is no diffusers "
                                                             "pipeline folder"),
    "an empty model_index.json": ("model_index.json", lambda p: p.write_text(""), "model_index.json is damaged "
                                                                                  "(empty)"),
    "no vae folder": ("vae/config.json", lambda p: [p.unlink(), (p.parent / "diffusion_pytorch_model.safetensors")
                                                    .unlink(), p.parent.rmdir()],
                      "vae is missing (model_index.json lists the component 'vae')"),
    "truncated weights": (WEIGHTS, _truncate, f"{WEIGHTS} is truncated: "),
    "random weights": (WEIGHTS, _randomise, f"{WEIGHTS} is damaged (no safetensors header"),
    "no weights": (WEIGHTS, Path.unlink, "transformer holds no weights"),
    "an empty config": ("transformer/config.json", lambda p: p.write_text(""), "transformer/config.json is damaged "
                                                                               "(empty)"),
    "a config of bad JSON": ("scheduler/scheduler_config.json", lambda p: p.write_text("{\"_class_name\""),
                             "scheduler/scheduler_config.json is damaged (Expecting"),
}


@pytest.mark.parametrize("damage", DAMAGE)
def test_a_damaged_folder_is_one_line_naming_the_file_before_loading(damage, tmp_path, capsys, no_loading):
    file, spoil, expected = DAMAGE[damage]
    folder = FOLDERS["wan2.1"](tmp_path / "Wan2.1-T2V-1.3B")
    spoil(folder / file)
    out = tmp_path / "out"
    assert main(["generate", "--model", "wan2.1-t2v-1.3b", *TINY, "--out", str(out), f"model.id={folder}"]) == 2
    err = _one_error(capsys)
    assert err.startswith("error: wan2.1-t2v-1.3b (model.id): ") and expected.format(folder=folder) in err, err
    assert not out.exists()


@pytest.mark.slow  # imports diffusers' pipelines
def test_the_python_loader_checks_the_folder_before_loading(tmp_path):
    folder = FOLDERS["wan2.2-a14b"](tmp_path / "Wan2.2-T2V-A14B")
    with pytest.raises(ModelFolderError, match="is not a folder of wan2.1-t2v-1.3b: it holds 2 denoisers"):
        load_video_pipeline(ModelConfig(name="wan2.1-t2v-1.3b", id=str(folder), dtype="float32", device="cpu"))


def test_a_folder_that_does_not_load_is_the_folders_line_not_the_hubs(tmp_path):
    class Pipeline:
        @classmethod
        def from_pretrained(cls, source, **kwargs):
            raise OSError(f"Error no file named diffusion_pytorch_model.bin found in directory {source}.")

    with pytest.raises(ModelFolderError) as err:
        pipeline_from_pretrained(Pipeline, str(tmp_path), "wan2.1-t2v-1.3b", "model.id=/path/to/x",
                                 dtype=torch.float32)
    message = str(err.value)
    assert message.startswith(f"wan2.1-t2v-1.3b: the folder {tmp_path} does not load: OSError: Error no file named")
    assert "hf download" not in message and "\n" not in message


def test_a_hub_id_of_another_model_is_refused_by_its_cached_configs(tmp_path, monkeypatch, capsys, no_loading):
    """``model.id`` naming another model's hub repo whose configs are in the hub cache (no weights
    needed): one line naming the repo and the model, before anything loads or downloads."""
    import huggingface_hub.constants

    commit = "0" * 40
    repo = tmp_path / "hub" / "models--Wan-AI--Wan2.2-T2V-A14B-Diffusers"
    FOLDERS["wan2.2-a14b"](repo / "snapshots" / commit)
    (repo / "refs").mkdir()
    (repo / "refs" / "main").write_text(commit)
    monkeypatch.setattr(huggingface_hub.constants, "HF_HUB_CACHE", str(tmp_path / "hub"))
    monkeypatch.setattr(huggingface_hub.constants, "HF_HUB_OFFLINE", True)
    out = tmp_path / "out"
    assert main(["generate", "--model", "wan2.1-t2v-1.3b", *TINY, "--out", str(out),
                 "model.id=Wan-AI/Wan2.2-T2V-A14B-Diffusers"]) == 2
    err = _one_error(capsys)
    assert ("error: model.id=Wan-AI/Wan2.2-T2V-A14B-Diffusers is not a folder of wan2.1-t2v-1.3b: it holds 2 "
            "denoisers") in err, err
    assert not out.exists()
