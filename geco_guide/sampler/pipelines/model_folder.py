"""A local pipeline folder (``model.id=/path``, the layout ``save_pretrained`` writes) checked
before anything loads, from its small files alone:

* that it is whole (:func:`check_folder_files`): its ``model_index.json``, a subfolder for each
  component it lists, each component's config, and weights (the denoiser(s) and the VAE must
  have some) whose safetensors header and size agree (a download cut short, a file of other
  bytes);
* that it is the registry model's (:func:`check_folder_model`): the pipeline class, one denoiser
  or two experts (Wan 2.2 A14B), the denoiser class and temporal patch and the pipeline's
  ``expand_timesteps`` of the published configs (:mod:`geco_guide.families.published`), and the
  VAE's latent channels. A smaller stand-in of the model's own layout (the tiny random models,
  saved) passes: a latent width no registry model of that pipeline has tells no other model.

A hub id is checked the same way by its configs in the hub cache, where they are there
(:func:`check_cached_model`). Each problem is one line naming the file (:class:`ModelFolderError`),
instead of a traceback or a shape error after minutes of loading, or a run of one model recorded
as another.
"""

from __future__ import annotations

import json
import zipfile
from collections.abc import Callable
from pathlib import Path
from typing import Any

from ...families import MODELS, VideoModel
from ...families.published import published_configs, traced_models

__all__ = ["PIPELINE_INDEX", "ModelFolderError", "cached_pipeline_configs", "check_cached_model", "check_folder_files",
           "check_folder_model", "check_model_folder"]

#: The file whose presence says a folder is a diffusers pipeline.
PIPELINE_INDEX = "model_index.json"
#: The components whose weights the video is made with: their config and weights must be there.
WEIGHTED = ("transformer", "transformer_2", "vae")
#: The config files a component's subfolder may hold (models, schedulers, guiders, processors,
#: tokenizers).
CONFIG_FILES = ("config.json", "scheduler_config.json", "guider_config.json", "preprocessor_config.json",
                "tokenizer_config.json")
WEIGHT_SUFFIXES = (".safetensors", ".bin")


class ModelFolderError(ValueError):
    """A local model folder that is damaged or another model's: one line naming the file."""


def check_model_folder(model: VideoModel, folder: Path) -> None:
    """:func:`check_folder_files`, then :func:`check_folder_model`.

    Raises:
        ModelFolderError: one line naming the folder's file and what is wrong with it.
    """
    try:
        index = check_folder_files(folder)
    except ModelFolderError as err:
        raise ModelFolderError(f"{model.name} (model.id): {err}") from None
    check_folder_model(model, folder, index)


def _read_json(path: Path) -> dict[str, Any]:
    if not path.is_file():
        raise ModelFolderError(f"{path} is missing")
    try:
        data = json.loads(path.read_text(encoding="utf-8"))
    except (OSError, ValueError) as err:
        raise ModelFolderError(f"{path} is damaged ({'empty' if not path.stat().st_size else err})") from None
    if not isinstance(data, dict):
        raise ModelFolderError(f"{path} is damaged (not a JSON object)")
    return data


def _listed(index: dict[str, Any], name: str) -> bool:
    """Whether ``model_index.json`` lists component ``name`` (``[library, class]``, not ``[null, null]``)."""
    spec = index.get(name)
    return isinstance(spec, list) and len(spec) == 2 and spec[1] is not None


def check_folder_files(folder: Path) -> dict[str, Any]:
    """The folder's ``model_index.json``, once every component it lists is there: a subfolder,
    configs that are JSON, weights that are whole (and some for the :data:`WEIGHTED` ones).

    Raises:
        ModelFolderError: one line naming the missing or damaged file.
    """
    index_path = folder / PIPELINE_INDEX
    if not index_path.is_file():
        raise ModelFolderError(f"{index_path} is missing: {folder} is no diffusers pipeline folder (the folder "
                               "save_pretrained writes, or `hf download <repo> --local-dir <folder>` fetches)")
    index = _read_json(index_path)
    for name in (key for key in index if not key.startswith("_") and _listed(index, key)):
        sub = folder / name
        if not sub.is_dir():
            raise ModelFolderError(f"{sub} is missing ({PIPELINE_INDEX} lists the component {name!r})")
        for config in CONFIG_FILES:
            if (sub / config).exists():
                _read_json(sub / config)
        if name in WEIGHTED:
            _read_json(sub / "config.json")
        _check_weights(sub, required=name in WEIGHTED)
    return index


def _check_weights(sub: Path, required: bool) -> None:
    """Every weights file of a component's subfolder whole, and with ``required`` one at least."""
    files = sorted(p for p in sub.iterdir() if p.suffix in WEIGHT_SUFFIXES)
    if required and not files:
        raise ModelFolderError(f"{sub} holds no weights (diffusion_pytorch_model.safetensors)")
    for shards in sub.glob("*.index.json"):
        for shard in sorted(set(_read_json(shards).get("weight_map", {}).values())):
            if not (sub / shard).is_file():
                raise ModelFolderError(f"{sub / shard} is missing ({shards.name} lists it)")
    for path in files:
        (_check_safetensors if path.suffix == ".safetensors" else _check_torch_file)(path)


def _check_safetensors(path: Path) -> None:
    """The header of a safetensors file read and its tensors' extent checked against the size."""
    size = path.stat().st_size
    with path.open("rb") as f:
        head = f.read(8)
        length = int.from_bytes(head, "little") if len(head) == 8 else None
        if length is None or length > size - 8:
            raise ModelFolderError(f"{path} is damaged (no safetensors header: a file cut short or of other bytes)")
        try:
            header = json.loads(f.read(length))
            end = max((entry["data_offsets"][1] for key, entry in header.items() if key != "__metadata__"), default=0)
        except (ValueError, TypeError, KeyError, IndexError) as err:
            raise ModelFolderError(f"{path} is damaged (its safetensors header does not read: {err})") from None
    if 8 + length + end > size:
        raise ModelFolderError(f"{path} is truncated: {size} bytes where its header lists {8 + length + end}")


def _check_torch_file(path: Path) -> None:
    """A ``.bin`` torch file: a zip archive whole to its directory, or a legacy pickle."""
    with path.open("rb") as f:
        legacy = f.read(1) == b"\x80"
    if not (zipfile.is_zipfile(path) or legacy):
        raise ModelFolderError(f"{path} is damaged (neither a torch zip archive nor a pickle)")


def _temporal_patch(config: dict[str, Any]) -> int:
    """Latent frames per denoiser token: ``patch_size_t``, or the first of a 3-D ``patch_size``."""
    patch = config.get("patch_size")
    return int(config.get("patch_size_t") or (patch[0] if isinstance(patch, list) else 1))


def _latent_channels(vae: dict[str, Any]) -> int | None:
    value = vae.get("latent_channels", vae.get("z_dim"))
    return value if isinstance(value, int) else None


def _names(names: list[str]) -> str:
    """``a``, ``a or b``, ``a, b or c``."""
    return f"{', '.join(names[:-1])} or {names[-1]}" if len(names) > 1 else names[0]


def _looks_like(model: VideoModel, fits: Callable[[VideoModel], bool]) -> str:
    """`` (the layout of a or b)``: the other generating models of the same pipeline class that a
    folder's fact fits; ``''`` where none does."""
    others = [m.name for m in MODELS.values()
              if m.generates and m.name != model.name and m.pipeline == model.pipeline and fits(m)]
    return f" (the layout of {_names(others)})" if others else ""


#: The small files :func:`check_folder_model` reads.
MODEL_CONFIGS = (PIPELINE_INDEX, "transformer/config.json", "vae/config.json")


def check_cached_model(model: VideoModel, repo_id: str, revision: str | None = None) -> None:
    """:func:`check_folder_model` of hub repo ``repo_id``'s configs in the hub cache, where they are
    there (:func:`cached_pipeline_configs`); nothing otherwise.

    Raises:
        ModelFolderError: one line naming ``repo_id``, ``model`` and what the repo holds instead.
    """
    snapshot = cached_pipeline_configs(repo_id, revision)
    if snapshot is not None:
        check_folder_model(model, snapshot, _read_json(snapshot / PIPELINE_INDEX), source=repo_id)


def cached_pipeline_configs(repo_id: str, revision: str | None = None) -> Path | None:
    """The hub cache's snapshot folder of ``repo_id`` where it holds :data:`MODEL_CONFIGS` (what
    :func:`check_folder_model` compares, no weights), ``None`` otherwise (not cached: nothing to
    compare before the download)."""
    from huggingface_hub import try_to_load_from_cache

    paths = []
    for name in MODEL_CONFIGS:
        try:
            cached = try_to_load_from_cache(repo_id, name, revision=revision)
        except (ValueError, OSError):  # not a repo id
            return None
        if not isinstance(cached, str):
            return None
        paths.append(Path(cached))
    return paths[0].parent


def check_folder_model(model: VideoModel, folder: Path, index: dict[str, Any], source: str | None = None) -> None:
    """That the pipeline folder ``folder`` (its ``model_index.json``: ``index``; a hub cache's
    snapshot of ``source``) is ``model``'s.

    Raises:
        ModelFolderError: one line naming the folder (``source``), ``model`` and what the folder
            holds instead.
    """
    def refuse(what: str, likely: str = "") -> ModelFolderError:
        return ModelFolderError(f"model.id={source or folder} is not a folder of {model.name}: {what}{likely}")

    found = index.get("_class_name")
    if found not in (model.pipeline, f"GeCo{model.pipeline}"):
        users = [m.name for m in MODELS.values() if m.generates and m.pipeline == found]
        likely = f" (the pipeline of {_names(users)})" if users else ""
        raise refuse(f"its {PIPELINE_INDEX} names the pipeline {found}, {model.name}'s is {model.pipeline}", likely)
    experts = 2 if _listed(index, "transformer_2") else 1
    wanted = 2 if "guidance_scale_2" in model.call else 1
    if experts != wanted:
        raise refuse(f"it holds {experts} denoiser{'s' if experts > 1 else ''} ({PIPELINE_INDEX} "
                     f"{'lists' if experts > 1 else 'lists no'} transformer_2), {model.name} has {wanted}",
                     _looks_like(model, lambda m: ("guidance_scale_2" in m.call) == (experts == 2)))
    transformer = _read_json(folder / "transformer" / "config.json")
    _check_published(model, folder, index, transformer, refuse)
    latents = _latent_channels(_read_json(folder / "vae" / "config.json"))
    known = {m.latent_channels for m in MODELS.values() if m.generates and m.pipeline == model.pipeline}
    if latents != model.latent_channels and latents in known:
        raise refuse(f"its VAE makes {latents}-channel latents (vae/config.json), {model.name}'s "
                     f"{model.latent_channels}", _looks_like(model, lambda m: m.latent_channels == latents))


def _check_published(model: VideoModel, folder: Path, index: dict[str, Any], transformer: dict[str, Any],
                     refuse: Callable[..., ModelFolderError]) -> None:
    """The folder's denoiser class, temporal patch and ``expand_timesteps`` against the published
    configs of ``model`` (nothing to compare for a model without them)."""
    if model.name not in traced_models():
        return
    published = published_configs(model.name)
    expected = published.transformer["_class_name"]
    if transformer.get("_class_name") != expected:
        raise refuse(f"its transformer/config.json names {transformer.get('_class_name')}, {model.name}'s is "
                     f"{expected}")
    patch, wanted = _temporal_patch(transformer), _temporal_patch(published.transformer)
    if patch != wanted:
        raise refuse(f"its transformer patches {patch} latent frames together (transformer/config.json), "
                     f"{model.name}'s {wanted}",
                     _looks_like(model, lambda m: _published(m, "transformer", _temporal_patch) == patch))
    if "expand_timesteps" in index:
        expands = _expands(published.pipeline)
        if bool(index["expand_timesteps"]) != expands:
            raise refuse(f"its {PIPELINE_INDEX} has expand_timesteps={index['expand_timesteps']}, {model.name}'s "
                         f"pipeline {'expands' if expands else 'does not expand'} them",
                         _looks_like(model, lambda m: _published(m, "pipeline", _expands) == (not expands)))


def _expands(config: dict[str, Any]) -> bool:
    return bool(config.get("expand_timesteps", False))


def _published(model: VideoModel, part: str, fact: Callable[[dict[str, Any]], Any]) -> Any:
    """``fact`` of a part of ``model``'s published configs (``transformer``: its config;
    ``pipeline``: its settings); ``None`` for a model without published configs."""
    return fact(getattr(published_configs(model.name), part)) if model.name in traced_models() else None
