"""The published full-size configs of the registry's models, for the cost model and the memory planner.

For each model of :data:`~geco_guide.families.MODELS` whose configs were found in public sources,
``data/published_configs.json`` holds, keyed by registry name: the denoiser's config (Wan 2.2
A14B's two experts: ``transformer`` and ``transformer_2``) and the VAE's, as their hub
repositories' ``config.json`` files hold them (``_class_name`` names the diffusers class; keys the
files leave out are the classes' defaults), the scheduler's, the pipeline's own settings
(``boundary_ratio``, ``expand_timesteps``) and the prompt length its pipeline pads its text
embeddings to; ``source`` says where each came from. The cost model builds the real diffusers
classes from them on the meta device: no weights, nothing downloaded.

:data:`LEFT_OUT` names the registry models the cost model does not trace, and why.

The file is read when a model's configs are asked for, never to build a command line (the traced
models are the registry's, less :data:`LEFT_OUT`); a file that is missing, not JSON or without a
model's entry is one line naming it (:class:`PackageDataError`, :func:`read_package_json`).

Ground floor: reads JSON, imports nothing heavy.
"""

from __future__ import annotations

import json
from dataclasses import dataclass, field
from functools import lru_cache
from pathlib import Path
from typing import Any

__all__ = ["LEFT_OUT", "PUBLISHED_PATH", "PackageDataError", "PublishedConfigs", "published_configs",
           "read_package_json", "traced_models"]

PUBLISHED_PATH = Path(__file__).resolve().parent / "data" / "published_configs.json"

#: Registry models that generate but that the cost model does not trace, and why (the planner gives
#: them the most memory-saving plan, as any model its estimates do not know).
LEFT_OUT: dict[str, str] = {
    "hunyuanvideo-1.5": "its transformer orders the text tokens by the values of their masks (boolean indexing) and "
                        "tests whether the image embeddings are all zero: shapes that depend on values, which a trace "
                        "without values (fake tensors) cannot follow",
    "ltx-2": "its denoiser's call carries an audio stream (audio latents from the audio VAE, the text connectors' "
             "outputs, the spatio-temporal and modality guidance calls): the configs of the audio VAE, the connectors "
             "and the vocoder were not gathered here, so its calls cannot be built without guessing",
    "cogvideox-5b-i2v": "image-to-video: its denoiser also takes the image latents; not traced yet",
    "hunyuanvideo-1.5-i2v": "image-to-video, and the text-token ordering of hunyuanvideo-1.5",
}


@dataclass(frozen=True)
class PublishedConfigs:
    """One model's published full-size configs (``data/published_configs.json``).

    Attributes:
        name: the registry name.
        transformer: the denoiser's config (``_class_name`` and its keys).
        transformer_2: the second expert's (Wan 2.2 A14B), ``None`` for one denoiser.
        vae: the VAE's config.
        scheduler: the scheduler's config.
        pipeline: the pipeline's own settings (``boundary_ratio``, ``expand_timesteps``).
        prompt_tokens: the length the pipeline pads a prompt's text embeddings to.
        source: where the configs come from.
    """

    name: str
    transformer: dict[str, Any] = field(hash=False)
    vae: dict[str, Any] = field(hash=False)
    scheduler: dict[str, Any] = field(hash=False)
    pipeline: dict[str, Any] = field(hash=False)
    prompt_tokens: int
    source: str
    transformer_2: dict[str, Any] | None = field(default=None, hash=False)

    @staticmethod
    def kwargs(config: dict[str, Any]) -> dict[str, Any]:
        """A config's constructor keywords: its keys without ``_class_name``, lists as tuples
        (the configs of diffusers' classes take tuples where JSON has lists)."""
        return {key: tuple(value) if isinstance(value, list) else value for key, value in config.items()
                if key != "_class_name"}


class PackageDataError(ValueError):
    """A data file the package ships is missing or damaged: one line naming the file and how to
    get a sound one back."""


def read_package_json(path: Path, remedy: str = "reinstall geco_guide") -> dict[str, Any]:
    """The ``{"models": {...}}`` table of the package data file ``path``.

    Raises:
        PackageDataError: (one line naming ``path`` and ``remedy``) the file is missing or
            unreadable, is not JSON, or holds no ``models`` table.
    """
    try:
        text = path.read_text(encoding="utf-8")
    except OSError as err:
        raise PackageDataError(f"the package data file {path} cannot be read ({err.strerror or err}): "
                               f"{remedy}") from None
    try:
        table = json.loads(text)
    except ValueError as err:
        raise PackageDataError(f"the package data file {path} is damaged (not JSON: {err}): {remedy}") from None
    if not isinstance(table, dict) or not isinstance(table.get("models"), dict):
        raise PackageDataError(f"the package data file {path} is damaged (no 'models' table): {remedy}")
    return table


@lru_cache(maxsize=1)
def _table() -> dict[str, Any]:
    return read_package_json(PUBLISHED_PATH)["models"]


def traced_models() -> list[str]:
    """The registry names the cost model traces, in the registry's order: every model that
    generates, less :data:`LEFT_OUT` (a command line lists them without reading the data file)."""
    from . import MODELS

    return [name for name, model in MODELS.items() if model.generates and name not in LEFT_OUT]


def published_configs(name: str) -> PublishedConfigs:
    """The :class:`PublishedConfigs` of registry model ``name``.

    Raises:
        ValueError: (one line) a model without published configs here, with the reason where it
            was left out.
    """
    if name not in traced_models():
        why = LEFT_OUT.get(name, "no published configs were gathered for it")
        raise ValueError(f"the cost model does not trace {name!r}: {why}; traced: {', '.join(traced_models())}")
    entry = _table().get(name)
    try:
        return PublishedConfigs(name=name, transformer=dict(entry["transformer"]), vae=dict(entry["vae"]),
                                scheduler=dict(entry["scheduler"]), pipeline=dict(entry["pipeline"]),
                                prompt_tokens=int(entry["text"]["prompt_tokens"]), source=str(entry["source"]),
                                transformer_2=entry.get("transformer_2"))
    except (KeyError, TypeError, ValueError) as err:
        problem = "no entry" if entry is None else (
            f"an entry without the key {err}" if isinstance(err, KeyError) else f"a damaged entry ({err})")
        raise PackageDataError(f"the package data file {PUBLISHED_PATH} is damaged ({name} has {problem}): "
                               "reinstall geco_guide") from None
