"""What every command shares: one-line argparse errors, the config flags (``--preset``,
``--config``, the estimators), telling ``key=value`` overrides from inputs, and the config they
make together."""

from __future__ import annotations

import argparse
import functools
import re
import sys
from collections.abc import Callable, Iterable, Sequence
from pathlib import Path
from typing import Any

from omegaconf import DictConfig, OmegaConf

from ..config import GeCoConfig, load_config

#: The config keys the estimator flags set (the config's section is ``estimators``).
ESTIMATOR_KEYS = {"geometry_estimator": "estimators.geometry", "flow_estimator": "estimators.flow"}
_OVERRIDE = re.compile(r"^[A-Za-z_][\w.]*=")


class Parser(argparse.ArgumentParser):
    """argparse whose errors are one line (scripts and logs read the first line only)."""

    def error(self, message: str) -> None:  # type: ignore[override]
        self.exit(2, f"error: {message} (see --help)\n")


def add_config_flags(parser: argparse.ArgumentParser, *, estimators: bool = True,
                     preset_help: str = "a preset of configs/ (tiny: tiny random models, CPU, offline)") -> None:
    """``--preset``, ``--config`` and, with ``estimators``, ``--geometry-estimator`` /
    ``--flow-estimator`` (``--vggt`` / ``--ufm`` stay accepted: users pass them today)."""
    parser.add_argument("--preset", default=None, help=preset_help)
    parser.add_argument("--config", default=None, help="YAML config file (applied after --preset)")
    if estimators:
        parser.add_argument("--geometry-estimator", "--vggt", dest="geometry_estimator", default=None,
                            metavar="ID_OR_DIR", help="geometry estimator: hub id or local folder (estimators.geometry)")
        parser.add_argument("--flow-estimator", "--ufm", dest="flow_estimator", default=None,
                            metavar="ID_OR_DIR", help="flow estimator: hub id or local folder (estimators.flow)")


def split_overrides(arguments: Iterable[str]) -> tuple[list[str], list[str]]:
    """``(overrides, others)``: a ``key=value`` argument is an override unless it names an
    existing file (``a=b.mp4`` is a video when it exists)."""
    arguments = list(arguments)
    overrides = [a for a in arguments if _OVERRIDE.match(a) and not Path(a).exists()]
    return overrides, [a for a in arguments if a not in overrides]


def is_config_key(key: str) -> bool:
    """Whether ``key`` (dotted) names a config option, or an entry of a free mapping such as
    ``evaluation.model_fps.<model>``."""
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
    """The validated config of ``--preset`` / ``--config``, the ``key=value`` ``overrides``,
    the estimator flags and ``options`` (``{config key: value}``, ``None`` values skipped), the
    flags last so that they win over a stray override of the same key."""
    items = list(overrides)
    flags = {key: getattr(args, dest, None) for dest, key in ESTIMATOR_KEYS.items()}
    for key, value in {**flags, **(options or {})}.items():
        if value is not None:
            items.append(f"{key}={value}")
    return load_config(getattr(args, "config", None), getattr(args, "preset", None), items)


def interruptible(kept: str) -> Callable[[Callable[..., int]], Callable[..., int]]:
    """Ctrl-C ends the decorated ``main`` with one line saying what was kept (``kept``) and exit
    code 130, the shell's code for SIGINT, instead of a traceback from wherever it stopped."""

    def decorate(main: Callable[..., int]) -> Callable[..., int]:
        @functools.wraps(main)
        def run(argv: list[str] | None = None) -> int:
            try:
                return main(argv)
            except KeyboardInterrupt:
                print(f"interrupted: {kept}", file=sys.stderr)
                return 130

        return run

    return decorate
