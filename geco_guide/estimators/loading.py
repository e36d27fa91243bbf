"""Checkpoint loading shared by the estimators: hub ids or local folders, safetensors or torch files.

Offline without weights ends in one :class:`WeightsNotFoundError` line that names the repository
id and how to pass a local folder instead; a file that cannot be read as a checkpoint (empty,
truncated, random bytes) in one :class:`UnreadableCheckpointError` line naming it; a checkpoint
whose keys do not fit the module in a :class:`CheckpointMismatchError` listing what is missing,
unexpected or mis-shaped. :func:`check_weight_sources` looks for the weights of every model of a run
(:class:`WeightsSource` rows) before any loads, and names all that are missing in one line.
"""

from __future__ import annotations

import contextlib
import os
from collections.abc import Callable, Iterator, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import torch
from torch import Tensor, nn

__all__ = ["CHECKPOINT_SUFFIXES", "CheckpointMismatchError", "UnreadableCheckpointError",
           "WeightsNotFoundError", "WeightsSource", "check_weight_sources", "check_weights_available",
           "fetch_checkpoint_file", "fetch_config_file", "load_state_dict_checked", "load_weights",
           "pretrained_or_one_line", "quiet_hub_retries", "short_reason"]


class WeightsNotFoundError(FileNotFoundError):
    """A checkpoint could be found neither in a local folder nor in the hub cache / on the hub."""


class CheckpointMismatchError(ValueError):
    """A state dict does not fit the module it is loaded into."""


class UnreadableCheckpointError(ValueError):
    """A weights file that cannot be read: empty, truncated, or not a checkpoint at all."""


# A path ending in one of these names a checkpoint file, not a folder or a repo id.
CHECKPOINT_SUFFIXES = (".pth", ".pt", ".safetensors", ".bin")


@contextlib.contextmanager
def quiet_hub_retries() -> Iterator[None]:
    """huggingface_hub logs a line per failed attempt and per retry while the hub cannot be
    reached; the failure ends in one error line instead."""
    from huggingface_hub.utils import logging as hub_logging

    level = hub_logging.get_verbosity()
    hub_logging.set_verbosity_error()
    try:
        yield
    finally:
        hub_logging.set_verbosity(level)


def fetch_checkpoint_file(
    repo_id_or_dir: str | os.PathLike,
    filenames: Sequence[str],
    *,
    model_name: str,
    revision: str | None = None,
    cache_dir: str | os.PathLike | None = None,
) -> Path:
    """Return the checkpoint file itself, or the first of ``filenames`` available in a local
    folder or a Hugging Face repo.

    A file on disk is the checkpoint; a folder on disk is searched for ``filenames``; anything else
    is a hub repo id, resolved through the local cache first (so ``HF_HUB_OFFLINE=1`` works once
    downloaded).

    Raises:
        WeightsNotFoundError: none of the files can be had (missing file or folder, offline,
            unknown repo).
    """
    path = Path(repo_id_or_dir).expanduser()
    if path.is_file():
        return path
    if path.suffix.lower() in CHECKPOINT_SUFFIXES:
        raise WeightsNotFoundError(f"{model_name}: checkpoint file {str(repo_id_or_dir)!r} does not exist")
    if path.is_dir():
        for name in filenames:
            if (path / name).is_file():
                return path / name
        raise WeightsNotFoundError(
            f"{model_name}: none of {list(filenames)} found in local folder {str(path)!r}"
        )
    repo_id = str(repo_id_or_dir)
    if looks_like_local_path(repo_id):
        raise WeightsNotFoundError(
            f"{model_name}: local folder {repo_id!r} does not exist "
            "(pass an existing folder or a Hugging Face repo id such as 'owner/name')"
        )
    from huggingface_hub import hf_hub_download
    from huggingface_hub.utils import EntryNotFoundError, LocalEntryNotFoundError

    reason = ""
    for name in filenames:
        try:
            with quiet_hub_retries():
                return Path(hf_hub_download(repo_id, name, revision=revision, cache_dir=cache_dir))
        except LocalEntryNotFoundError:
            reason = " (offline and not in the cache)"
            break
        except EntryNotFoundError:
            continue  # the repo exists but stores the weights under another name
        except Exception as exc:  # offline, unknown repo, gated, network: all end the same way
            reason = hub_failure_reason(exc)
            break
    raise hub_weights_unavailable(model_name, repo_id, reason)


def hub_weights_unavailable(model_name: str, repo_id: str, reason: str = "") -> WeightsNotFoundError:
    """The one line for weights of hub repo ``repo_id`` that are neither cached nor reachable."""
    return WeightsNotFoundError(
        f"{model_name}: could not load weights for {repo_id!r} from the Hugging Face hub or its "
        f"local cache{reason}; download them where you have network "
        f"(`hf download {repo_id}`; huggingface_hub < 0.34: `huggingface-cli download {repo_id}`) and pass the "
        "local folder instead of the repo id"
    )


def pretrained_or_one_line(load: Callable[[str], Any], source: str, *, model_name: str, folder_hint: str,
                           gated: bool = False) -> Any:
    """``load(source)`` (a ``from_pretrained``) of a hub id or a local folder, with the one-line
    errors of every loader here.

    Args:
        load: a hub id or a folder's path -> the model.
        source: the hub id or local folder the user gave.
        model_name: what the message calls the model.
        folder_hint: how to pass a local folder instead (e.g. ``model.id=/path/to/CogVideoX-5b``).
        gated: the repo is gated on the hub: the message says how to get access.

    Raises:
        WeightsNotFoundError: the folder does not exist, or the weights are neither in the hub
            cache nor reachable (the reason named: offline, gated, unknown repo, network).
    """
    path = Path(source).expanduser()
    if looks_like_local_path(source) and not path.is_dir():
        raise WeightsNotFoundError(f"{model_name}: local folder {source!r} does not exist (pass an existing folder or "
                                   f"a hub id: {folder_hint})")
    try:
        with quiet_hub_retries():
            return load(str(path) if path.is_dir() else source)
    except (OSError, ValueError) as err:
        if isinstance(err, ValueError) and type(err).__name__ != "HFValidationError":
            raise
        reason = (" (a gated repo: accept its licence on the hub, then log in with `hf auth login`)" if gated
                  else hub_failure_reason(err))
        raise WeightsNotFoundError(f"{hub_weights_unavailable(model_name, source, reason)} ({folder_hint})") from None


def looks_like_local_path(source: str) -> bool:
    """Whether ``source`` names a local path rather than a hub id (``owner/name``)."""
    return source.startswith((".", "/", "~")) or source.count("/") > 1 or os.sep in source.replace("/", "")


def check_weights_available(source: str | os.PathLike, filenames: Sequence[str], *, model_name: str,
                            revision: str | None = None) -> None:
    """Whether loading ``source`` can find its weights, found out cheaply before any model loads:
    a local path must exist; a hub id must have one of ``filenames`` in the local cache, or be
    reachable (one metadata request; loading then downloads it).

    Raises:
        WeightsNotFoundError: the line loading would end in, minutes earlier.
    """
    path = Path(source).expanduser()
    if path.exists():
        return
    source = str(source)
    if looks_like_local_path(source) or path.suffix.lower() in CHECKPOINT_SUFFIXES:
        raise WeightsNotFoundError(f"{model_name}: local path {source!r} does not exist "
                                   "(pass an existing folder or file, or a Hugging Face repo id such as 'owner/name')")
    from huggingface_hub import file_exists, try_to_load_from_cache

    if any(isinstance(try_to_load_from_cache(source, name, revision=revision), str) for name in filenames):
        return
    try:
        with quiet_hub_retries():
            if any(file_exists(source, name, revision=revision) for name in filenames):
                return
        reason = f" (the repo has none of {list(filenames)})"
    except Exception as exc:  # offline, unknown repo, gated, network: all end the same way
        reason = hub_failure_reason(exc)
    raise hub_weights_unavailable(model_name, source, reason)


@dataclass(frozen=True)
class WeightsSource:
    """One model whose weights a run needs, as :func:`check_weight_sources` checks it.

    Attributes:
        key: the config key that names the weights (``estimators.geometry``, ``model.id``), or
            the command-line flag that does (``--weights NAME``).
        source: its value: a hub id or a local path.
        model_name: what messages call the model.
        filenames: files whose presence says the weights are there (one is enough).
        revision: the hub revision, or None.
        example: the local-path example of the message (default ``/path/to/<source's name>``).
    """

    key: str
    source: str
    model_name: str
    filenames: tuple[str, ...] = ("config.json",)
    revision: str | None = None
    example: str | None = None


def check_weight_sources(rows: Sequence[WeightsSource]) -> None:
    """Whether every model of ``rows`` can find its weights (:func:`check_weights_available` each:
    a cache look-up or one metadata request), before any loads.

    Raises:
        WeightsNotFoundError: one line naming every model whose weights are missing, each as
            loading it would say it, with the config key that points at a local path instead.
    """
    problems = []
    for row in rows:
        try:
            check_weights_available(row.source, row.filenames, model_name=row.model_name, revision=row.revision)
        except WeightsNotFoundError as err:
            example = row.example or f"/path/to/{Path(str(row.source)).name}"
            where = row.key if row.key.startswith("--") else f"config: {row.key}"  # a flag, or a config key
            problems.append(f"{err} ({where}={example})")
    if len(problems) == 1:
        raise WeightsNotFoundError(problems[0])
    if problems:
        listed = "; ".join(f"({k}) {problem}" for k, problem in enumerate(problems, start=1))
        raise WeightsNotFoundError(f"{len(problems)} models lack their weights: {listed}")


def hub_failure_reason(exc: Exception) -> str:
    """Why a hub request failed, as the parenthesis of :func:`hub_weights_unavailable`'s line."""
    name = type(exc).__name__
    if name == "GatedRepoError":
        return " (a gated repo: accept its licence on the hub, then log in with `hf auth login`)"
    if name == "OfflineModeIsEnabled" or "offline" in str(exc).lower():
        return " (offline and not in the cache)"
    if name == "RepositoryNotFoundError":
        return " (no such repo, or it is private)"
    return f" (not in the cache, and the hub cannot be reached: {name})"


def fetch_config_file(
    repo_id_or_dir: str | os.PathLike,
    *,
    model_name: str,
    required: bool,
    revision: str | None = None,
    cache_dir: str | os.PathLike | None = None,
) -> Path | None:
    """The ``config.json`` that describes a checkpoint: in a local folder, beside a checkpoint
    file, or in a hub repo; ``None`` where there is none and it is not ``required``.

    Raises:
        WeightsNotFoundError: a ``required`` file is missing or cannot be had (as
            :func:`fetch_checkpoint_file`).
    """
    path = Path(repo_id_or_dir).expanduser()
    if path.is_file() or path.is_dir():
        beside = (path.parent if path.is_file() else path) / "config.json"
        if beside.is_file():
            return beside
        if required:
            raise WeightsNotFoundError(f"{model_name}: no config.json in local folder {str(beside.parent)!r}")
        return None
    try:
        return fetch_checkpoint_file(repo_id_or_dir, ["config.json"], model_name=model_name, revision=revision,
                                     cache_dir=cache_dir)
    except WeightsNotFoundError:
        if required:
            raise
        return None  # the weights' own fetch says what is missing, if anything


def short_reason(err: BaseException, limit: int = 100) -> str:
    """``Type: first sentence`` of a reader's error (torch's run to paragraphs)."""
    text = (str(err).strip().splitlines() or [""])[0].split(". ")[0]
    text = text if len(text) <= limit else text[: limit - 3] + "..."
    return f"{type(err).__name__}: {text}" if text else type(err).__name__


def unreadable(path: Path, reason: str) -> UnreadableCheckpointError:
    """The one line of a checkpoint file that cannot be read."""
    return UnreadableCheckpointError(
        f"{str(path)!r} is not a readable checkpoint ({reason}); it may be truncated or another kind of "
        "file: download it again"
    )


def load_weights(path: str | os.PathLike) -> dict[str, Tensor]:
    """Read a state dict from ``.safetensors`` or a torch file (``.pt``, ``.pth``, ``.bin``).

    Raises:
        UnreadableCheckpointError: one line naming the file, when it is empty, truncated or not a
            checkpoint (the readers' own errors are pickle, EOF, zip or header errors).
        CheckpointMismatchError: the file holds something other than a state dict of tensors.
    """
    path = Path(path)
    try:
        if path.stat().st_size == 0:
            raise unreadable(path, "the file is empty")
        if path.suffix == ".safetensors":
            from safetensors.torch import load_file

            state = load_file(str(path))
        else:
            state = torch.load(path, map_location="cpu", weights_only=True)
    except UnreadableCheckpointError:
        raise
    except Exception as err:  # UnpicklingError, EOFError, RuntimeError (zip), SafetensorError, OSError, ...
        raise unreadable(path, short_reason(err)) from None
    if isinstance(state, Mapping) and "model" in state and isinstance(state["model"], Mapping):
        state = state["model"]  # training checkpoints wrap the weights
    if not isinstance(state, Mapping):
        raise CheckpointMismatchError(f"{path} does not hold a state dict")
    not_tensors = [str(key) for key, value in state.items() if not isinstance(value, Tensor)]
    if not_tensors:
        raise CheckpointMismatchError(f"{path} does not hold a state dict of tensors: {_summarise(not_tensors, 3)} "
                                      "are not tensors")
    return dict(state)


def _summarise(keys: Sequence[str], limit: int = 12) -> str:
    keys = sorted(keys)
    shown = ", ".join(keys[:limit])
    return shown + (f", ... ({len(keys) - limit} more)" if len(keys) > limit else "")


def load_state_dict_checked(
    module: nn.Module,
    state_dict: Mapping[str, Tensor],
    *,
    model_name: str,
    ignore_prefixes: Sequence[str] = (),
    aliases: Mapping[str, str] | None = None,
) -> None:
    """Load ``state_dict`` into ``module`` strictly, after renaming and dropping keys.

    Args:
        module: the target module; its parameters and persistent buffers must all be covered.
        state_dict: checkpoint tensors; cast to each target tensor's dtype on copy.
        model_name: used in the error message.
        ignore_prefixes: checkpoint keys starting with one of these are dropped (heads we skip).
        aliases: alternative checkpoint key -> our key (e.g. de-duplicated safetensors names).

    Raises:
        CheckpointMismatchError: with every missing, unexpected and mis-shaped key listed.
    """
    aliases = aliases or {}
    renamed: dict[str, Tensor] = {}
    for key, value in state_dict.items():
        if any(key.startswith(prefix) for prefix in ignore_prefixes):
            continue
        renamed[aliases.get(key, key)] = value
    expected = module.state_dict()
    missing = [k for k in expected if k not in renamed]
    unexpected = [k for k in renamed if k not in expected]
    misshaped = [
        f"{k} {tuple(renamed[k].shape)} vs {tuple(expected[k].shape)}"
        for k in expected
        if k in renamed and renamed[k].shape != expected[k].shape
    ]
    if missing or unexpected or misshaped:
        parts = []
        if missing:
            parts.append(f"missing {len(missing)}: {_summarise(missing)}")
        if unexpected:
            parts.append(f"unexpected {len(unexpected)}: {_summarise(unexpected)}")
        if misshaped:
            parts.append(f"wrong shape {len(misshaped)} (checkpoint vs model): {_summarise(misshaped)}")
        raise CheckpointMismatchError(f"{model_name} checkpoint does not fit: " + "; ".join(parts))
    module.load_state_dict(renamed, strict=True, assign=False)
