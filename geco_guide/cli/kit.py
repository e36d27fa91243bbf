"""What every command shares: one-line argparse errors, the config flags (``--preset``,
``--config``, ``--model``, the estimators), telling ``key=value`` overrides from inputs, the config
they make together, the one-line error every command ends with, Ctrl-C.

Imports no torch (nor the config, which does), so that ``--help`` and argument errors answer at
once: each command module registers its options with ``register_subcommand(parser)`` and imports
what does the work inside ``run(args)``."""

from __future__ import annotations

import argparse
import functools
import json
import re
import sys
import warnings
from collections.abc import Callable, Iterable, Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    from ..config import GeCoConfig

__all__ = ["ESTIMATOR_KEYS", "Parser", "add_config_flags", "add_model_flag", "check_choice", "check_flags_agree",
           "config_from_args",
           "interruptible", "is_config_key", "one_line_warnings", "parse_count", "print_error",
           "split_overrides"]

#: The config keys the estimator flags set (the config's section is ``estimators``).
ESTIMATOR_KEYS = {"geometry_estimator": "estimators.geometry", "flow_estimator": "estimators.flow"}
_OVERRIDE = re.compile(r"^[A-Za-z_][\w.]*=")


class Parser(argparse.ArgumentParser):
    """argparse whose errors are one line (scripts and logs read the first line only)."""

    def error(self, message: str) -> None:  # type: ignore[override]
        self.exit(2, f"error: {message} (see --help)\n")


class RenamedFlag(argparse.Action):
    """A flag's earlier spelling: refused in one line naming the new one."""

    def __init__(self, option_strings: Sequence[str], dest: str, new: str, **kwargs: Any) -> None:
        self.new = new
        super().__init__(option_strings, dest, nargs="?", help=argparse.SUPPRESS, **kwargs)

    def __call__(self, parser: argparse.ArgumentParser, namespace: argparse.Namespace, values: Any,
                 option_string: str | None = None) -> None:
        parser.error(f"{option_string} is the earlier name of {self.new}: use {self.new} instead")


def add_config_flags(parser: argparse.ArgumentParser, *, estimators: bool = True,
                     preset_help: str = "a preset of configs/ (tiny: tiny random models, CPU, offline)") -> None:
    """``--preset``, ``--config`` and, with ``estimators``, ``--geometry-estimator`` /
    ``--flow-estimator`` (their earlier names ``--vggt`` / ``--ufm`` are refused, naming them)."""
    parser.add_argument("--preset", default=None, help=preset_help)
    parser.add_argument("--config", default=None, help="YAML config file (applied after --preset)")
    if estimators:
        parser.add_argument("--geometry-estimator", dest="geometry_estimator", default=None,
                            metavar="NAME_ID_OR_DIR", help="geometry estimator: vggt-1b (default), da3-small, da3-base, "
                            "a hub id or a local folder (estimators.geometry)")
        parser.add_argument("--flow-estimator", dest="flow_estimator", default=None,
                            metavar="NAME_ID_OR_DIR", help="flow estimator: ufm-base (default), waft, waft:ID_OR_PATH "
                            "(WAFT weights without a config.json), a hub id or a local folder (estimators.flow)")
        parser.add_argument("--vggt", action=RenamedFlag, new="--geometry-estimator")
        parser.add_argument("--ufm", action=RenamedFlag, new="--flow-estimator")


def add_model_flag(parser: argparse.ArgumentParser) -> None:
    """``--model NAME``: a model of the registry (``model.name``), with its preset of configs/
    where there is one (after ``--preset``)."""
    from ..families import video_models

    parser.add_argument("--model", default=None, metavar="NAME",
                        help=f"the video model: {', '.join(video_models())} (model.name; its call defaults, and its "
                             "preset of configs/ where there is one)")


def output_folder(text: str) -> str:
    """argparse type of ``--out``: a folder's name; an empty one would write into the working folder."""
    if not text.strip():
        raise argparse.ArgumentTypeError("must name an output folder, got an empty string")
    return text


def parse_count(text: str) -> int:
    """A whole number >= 1 written in digits (``--best-of``, ``--search``): ``1e20`` or ``2.5`` are
    refused by argparse in one line."""
    if not re.fullmatch(r"\s*\d+\s*", text) or int(text) < 1:
        raise argparse.ArgumentTypeError(f"must be a whole number >= 1 written in digits, got {text!r}")
    return int(text)


def check_choice(option: str, values: str | Sequence[str], choices: Sequence[str]) -> None:
    """ValueError (one line) unless every one of ``values`` is one of ``choices``: the check of an
    option whose choices live with the code that reads them (a torch module), made in ``run``."""
    for value in [values] if isinstance(values, str) else values:
        if value not in choices:
            raise ValueError(f"{option} takes one of {', '.join(choices)}; got {value!r}")


def print_error(err: BaseException) -> int:
    """The one line a command ends with on an error it expected: ``error: ...`` on stderr; 2."""
    print(f"error: {err}", file=sys.stderr)
    return 2


def split_overrides(arguments: Iterable[str]) -> tuple[list[str], list[str]]:
    """``(overrides, others)``: a ``key=value`` argument is an override unless it names an
    existing file (``a=b.mp4`` is a video when it exists)."""
    arguments = list(arguments)
    overrides = [a for a in arguments if _OVERRIDE.match(a) and not Path(a).exists()]
    return overrides, [a for a in arguments if a not in overrides]


def is_config_key(key: str) -> bool:
    """Whether ``key`` (dotted) names a config option, or an entry of a free mapping such as
    ``evaluation.model_fps.<model>``."""
    from omegaconf import DictConfig, OmegaConf

    from ..config import GeCoConfig

    node: Any = OmegaConf.structured(GeCoConfig)
    for part in key.split("."):
        if not isinstance(node, DictConfig):
            return False
        if part not in node:
            return OmegaConf.get_type(node) is dict
        node = node[part]
    return True


def config_from_args(args: argparse.Namespace, overrides: Sequence[str] = (),
                     options: dict[str, Any] | None = None) -> GeCoConfig:
    """The validated config of ``--preset`` / ``--model`` / ``--config``, the ``key=value``
    ``overrides``, the estimator flags and ``options`` (``{config key: value}`` as Python values,
    ``None`` values skipped), the flags last so that they win over a stray override of the same
    key; an override and a flag that set one key to two values are refused (:func:`check_flags_agree`).
    ``--model NAME`` sets ``model.name`` and applies the preset of that name where configs/ has one."""
    from ..config import load_config, model_preset

    flags = {key: getattr(args, dest, None) for dest, key in ESTIMATOR_KEYS.items()}
    model = getattr(args, "model", None)
    changes = {key: value for key, value in {**flags, **(options or {})}.items() if value is not None}
    if model is not None:
        changes["model.name"] = model
    check_flags_agree(overrides, changes)
    return load_config(getattr(args, "config", None), getattr(args, "preset", None), list(overrides),
                       changes=changes, model_preset=model_preset(model) if model is not None else None)


def check_flags_agree(overrides: Sequence[str], changes: dict[str, Any], flags: dict[str, str] | None = None) -> None:
    """ValueError (one line) for a ``key=value`` override of a key that a flag of the same command
    line sets to another value (``--model wan2.1-t2v-1.3b`` with ``model.name=cogvideox-5b``):
    which one was meant cannot be told, so neither wins in silence. ``changes``: ``{config key:
    value}`` of the flags given; ``flags``: the flag of a key, where it is not the kit's own
    (``--model``, the estimator flags). An override that agrees with its flag passes."""
    import yaml

    flags = {"model.name": "--model", **{k: f"--{d.replace('_', '-')}" for d, k in ESTIMATOR_KEYS.items()},
             **(flags or {})}
    for item in overrides:
        key, _, text = item.partition("=")
        key = key.strip()
        if key not in changes:
            continue
        value = changes[key]
        try:
            same = text.strip() == value if isinstance(value, str) else yaml.safe_load(text) == value
        except yaml.YAMLError:
            same = False
        if not same:
            shown = f"{value!r}" if isinstance(value, str) else json.dumps(value)
            if key in flags:
                shown += f" ({flags[key]} {' '.join(value) if isinstance(value, list) else value})"
            raise ValueError(f"{key}={text.strip()} disagrees with the flag that sets {key} to {shown}: give {key} once")


def one_line_warnings() -> Callable[..., None]:
    """A ``warnings.showwarning`` for commands: ``warning: <message>`` on stderr, once per
    message, without the file, line and source line Python adds (they point into the library, not
    at what to change; a check run at several stages of a command would repeat it)."""
    shown: set[tuple[type[Warning], str]] = set()

    def show(message: Warning | str, category: type[Warning], filename: str, lineno: int, file: Any = None,
             line: str | None = None) -> None:
        if (category, str(message)) not in shown:
            shown.add((category, str(message)))
            print(f"warning: {message}", file=sys.stderr if file is None else file)

    return show


def interruptible(kept: str) -> Callable[[Callable[..., int]], Callable[..., int]]:
    """Ctrl-C ends the decorated command ``run`` with one line saying what was kept (``kept``) and
    exit code 130, the shell's code for SIGINT, instead of a traceback from wherever it stopped;
    while it runs, each warning is one line (:func:`one_line_warnings`) and the library's log lines
    show on stderr (:func:`~geco_guide.io.logs.log_to_stderr`)."""

    def decorate(run: Callable[..., int]) -> Callable[..., int]:
        @functools.wraps(run)
        def guarded(*args: Any, **kwargs: Any) -> int:
            from ..io.logs import log_to_stderr

            log_to_stderr()
            try:
                with warnings.catch_warnings():
                    warnings.showwarning = one_line_warnings()
                    return run(*args, **kwargs)
            except KeyboardInterrupt:
                print(f"interrupted: {kept}", file=sys.stderr)
                return 130

        return guarded

    return decorate
