"""The repository's scripts as modules, for the tests that call their functions."""

from __future__ import annotations

import importlib.util
import sys
from pathlib import Path
from types import ModuleType

SCRIPTS = Path(__file__).resolve().parents[1] / "scripts"


def load_script(file_name: str, module_name: str | None = None) -> ModuleType:
    """``scripts/<file_name>`` imported as ``module_name`` (default: its stem), registered in
    ``sys.modules`` first (dataclasses look their module up there)."""
    path = SCRIPTS / file_name
    spec = importlib.util.spec_from_file_location(module_name or path.stem, path)
    module = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = module
    spec.loader.exec_module(module)
    return module
