"""The lifecycle VGGT and UFM share: construction, random init, checkpoint loading, trunk dtype,
gradient checkpointing and freezing.

A :class:`FrozenEstimator` subclass builds its modules in ``__init__`` and ends it with
:meth:`FrozenEstimator._finish_init`; it declares

* ``config_class`` (a dataclass with ``from_dict``) and ``model_name`` (used in error messages),
* ``default_repo_id`` and ``checkpoint_files`` (weights file names, first found wins),
* ``trunk_modules`` (dotted submodule names stored in :meth:`trunk_to`'s dtype; the heads stay
  float32) and ``checkpointed_modules`` (dotted names of the modules whose
  ``gradient_checkpointing`` flag :attr:`gradient_checkpointing` sets; the first one is read),
* :meth:`reset_parameters` (a random initialisation that fills every parameter and buffer).

It may override :meth:`load_checkpoint` (checks and key aliases beyond a strict load),
:meth:`config_from_json` (a ``config.json`` in another schema too) and ``config_required``.
:meth:`save_pretrained` writes a folder that :meth:`from_pretrained` loads as the same model.
"""

from __future__ import annotations

import json
import os
from collections.abc import Mapping
from pathlib import Path
from typing import Any, ClassVar, TypeVar

import torch
from torch import Tensor, nn

from ..io.files import write_bytes_atomic, write_json_atomic
from .loading import (
    CheckpointMismatchError,
    fetch_checkpoint_file,
    fetch_config_file,
    load_state_dict_checked,
    load_weights,
)

__all__ = ["FrozenEstimator", "check_frame_pairs"]

E = TypeVar("E", bound="FrozenEstimator")


def check_frame_pairs(source: Tensor, target: Tensor) -> None:
    """ValueError (one line) unless ``source`` and ``target`` are floating ``[N, 3, H, W]`` frames
    of one shape: what every flow estimator takes."""
    for name, x in (("source", source), ("target", target)):
        if not isinstance(x, Tensor) or x.ndim != 4 or x.shape[1] != 3 or not x.is_floating_point():
            raise ValueError(f"{name} must be a floating [N, 3, H, W] tensor in [0, 1], got "
                             f"{getattr(x, 'dtype', type(x).__name__)} {list(getattr(x, 'shape', []))}")
    if source.shape != target.shape:
        raise ValueError(f"source and target shapes differ: {list(source.shape)} vs {list(target.shape)}")


class FrozenEstimator(nn.Module):
    """A pretrained backbone used frozen (no parameter gradients, eval mode); gradients still flow
    to its inputs. ``autocast_dtype`` (e.g. ``torch.bfloat16``) runs the trunk under autocast."""

    config_class: ClassVar[type]
    model_name: ClassVar[str]
    default_repo_id: ClassVar[str]
    checkpoint_files: ClassVar[tuple[str, ...]]
    ignored_checkpoint_prefixes: ClassVar[tuple[str, ...]] = ()
    trunk_modules: ClassVar[tuple[str, ...]]
    checkpointed_modules: ClassVar[tuple[str, ...]]
    #: Whether a pretrained model must come with a ``config.json``; without one, the default
    #: architecture is assumed.
    config_required: ClassVar[bool] = False

    @classmethod
    def resolve_config(cls, config: Any) -> Any:
        """``None`` -> the default architecture, a mapping -> ``config_class.from_dict``, else as is."""
        if config is None:
            return cls.config_class()
        if not isinstance(config, cls.config_class):
            return cls.config_class.from_dict(config)
        return config

    def _finish_init(self, *, gradient_checkpointing: bool, autocast_dtype: torch.dtype | None) -> None:
        """End of a subclass's ``__init__``: precision knobs, random weights, frozen, eval mode."""
        self.autocast_dtype = autocast_dtype
        self.gradient_checkpointing = gradient_checkpointing
        self.reset_parameters()
        self.requires_grad_(False)
        self.eval()

    def reset_parameters(self, generator: torch.Generator | None = None) -> None:
        raise NotImplementedError

    @property
    def gradient_checkpointing(self) -> bool:
        """Recompute the trunk's block activations in backward (``checkpointed_modules``)."""
        return self.get_submodule(self.checkpointed_modules[0]).gradient_checkpointing

    @gradient_checkpointing.setter
    def gradient_checkpointing(self, value: bool) -> None:
        for name in self.checkpointed_modules:
            self.get_submodule(name).gradient_checkpointing = bool(value)

    def trunk_to(self: E, dtype: torch.dtype) -> E:
        """Store the trunk (``trunk_modules``: nearly all parameters and compute) in ``dtype``, e.g.
        bfloat16 on a GPU; the heads stay float32 and so do the outputs. Returns ``self``."""
        for name in self.trunk_modules:
            self.get_submodule(name).to(dtype)
        return self

    # ---- construction and loading -------------------------------------------------------------

    @classmethod
    def _materialised(cls: type[E], config: Any, device: torch.device | str = "cpu", **kwargs: Any) -> E:
        """Built on the meta device (no init cost) and given uninitialised storage on ``device``."""
        with torch.device("meta"):
            model = cls(config, **kwargs)
        return model.to_empty(device=device)

    @classmethod
    def random(cls: type[E], config: Any = None, seed: int = 0, **kwargs: Any) -> E:
        """A randomly initialised model whose weights depend only on ``seed`` (global RNG untouched)."""
        model = cls._materialised(config, **kwargs)
        model.reset_parameters(torch.Generator().manual_seed(seed))
        return model

    def load_checkpoint(self, state_dict: Mapping[str, Tensor]) -> None:
        """Strict load; ``ignored_checkpoint_prefixes`` are dropped.

        Raises:
            CheckpointMismatchError: every missing, unexpected and mis-shaped key listed.
        """
        load_state_dict_checked(self, state_dict, model_name=self.model_name,
                                ignore_prefixes=self.ignored_checkpoint_prefixes)

    @classmethod
    def from_state_dict(cls: type[E], config: Any, state_dict: Mapping[str, Tensor], **kwargs: Any) -> E:
        """Build from ``config`` (a ``config_class`` instance or its dict; None = the default
        architecture) and load ``state_dict`` with :meth:`load_checkpoint`; ``kwargs`` go to the
        constructor (``gradient_checkpointing``, ``autocast_dtype``)."""
        model = cls._materialised(config, **kwargs)  # every parameter and buffer is overwritten
        model.load_checkpoint(state_dict)
        return model

    @classmethod
    def config_from_json(cls, raw: Mapping[str, Any]) -> Any:
        """The architecture a parsed ``config.json`` describes (our ``to_dict`` schema)."""
        return cls.config_class.from_dict(raw)

    @classmethod
    def _pretrained_config(cls, repo_id_or_local_dir: str | os.PathLike, config: Any, **fetch: Any) -> Any:
        """The architecture of a pretrained model: ``config`` as given, else the ``config.json``
        beside the weights (so a folder of any size loads as what it is), else the default
        (``config_required`` makes the file mandatory).

        Raises:
            CheckpointMismatchError: the ``config.json`` is not JSON or not a config of this model.
        """
        if config is not None:
            return config
        path = fetch_config_file(repo_id_or_local_dir, required=cls.config_required, **fetch)
        if path is None:
            return None
        try:
            return cls.config_from_json(json.loads(path.read_text(encoding="utf-8")))
        except (UnicodeDecodeError, json.JSONDecodeError, ValueError, TypeError) as err:
            reason = str(err).splitlines()[0] if str(err) else type(err).__name__
            raise CheckpointMismatchError(f"{cls.model_name}: {str(path)!r} is not a readable {cls.model_name} "
                                          f"config.json ({reason})") from None

    def save_pretrained(self, save_directory: str | os.PathLike) -> Path:
        """Write ``config.json`` (this architecture, :meth:`config_from_json`'s schema) and
        ``model.safetensors`` (the weights in their stored dtypes) into ``save_directory``, each
        file atomically; :meth:`from_pretrained` of the folder loads the same model. Returns the
        folder."""
        from safetensors.torch import save

        folder = Path(save_directory)
        state = {key: value.detach().contiguous().cpu() for key, value in self.state_dict().items()}
        write_json_atomic(folder / "config.json", self.config.to_dict())
        write_bytes_atomic(folder / "model.safetensors", save(state, metadata={"format": "pt"}))
        return folder

    @classmethod
    def from_pretrained(cls: type[E], repo_id_or_local_dir: str | os.PathLike | None = None, *,
                        config: Any = None, dtype: torch.dtype = torch.float32,
                        device: torch.device | str = "cpu", revision: str | None = None,
                        cache_dir: str | os.PathLike | None = None, **kwargs: Any) -> E:
        """Load the weights (``checkpoint_files``) from a hub repo id (default
        ``default_repo_id``) or a local folder, on ``device``; ``dtype`` applies to the trunk
        (:meth:`trunk_to`); ``kwargs`` go to the constructor.

        Raises:
            WeightsNotFoundError: one line naming the repo id, when the files are neither in the
                folder nor reachable / cached.
            CheckpointMismatchError: the weights do not fit the architecture.
        """
        source = cls.default_repo_id if repo_id_or_local_dir is None else repo_id_or_local_dir
        fetch = dict(model_name=cls.model_name, revision=revision, cache_dir=cache_dir)
        config = cls._pretrained_config(source, config, **fetch)
        weights: Path = fetch_checkpoint_file(source, cls.checkpoint_files, **fetch)
        state_dict = load_weights(weights)  # a file that is no checkpoint fails before the model is allocated
        model = cls._materialised(config, device, **kwargs)
        model.load_checkpoint(state_dict)
        return model.trunk_to(dtype)
