"""The import graph points down: geometry/types at the bottom, estimators and the loss beside each
other on them, the sampler and the tools above (see README, "Layout")."""

from __future__ import annotations

import ast
from pathlib import Path

PACKAGE = Path(__file__).resolve().parents[1] / "geco_guide"


def imported_modules(path: Path) -> set[str]:
    """Absolute names of the geco_guide modules that ``path`` imports (relative imports resolved)."""
    module = ".".join(path.relative_to(PACKAGE.parent).with_suffix("").parts)
    package = module if path.name == "__init__.py" else module.rsplit(".", 1)[0]
    names = set()
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.ImportFrom):
            if node.level:
                base = package.rsplit(".", node.level - 1)[0] if node.level > 1 else package
                target = f"{base}.{node.module}" if node.module else base
            else:
                target = node.module or ""
            names.add(target)
            names.update(f"{target}.{alias.name}" for alias in node.names)
        elif isinstance(node, ast.Import):
            names.update(alias.name for alias in node.names)
    return {n for n in names if n.startswith("geco_guide")}


def imports_of(subpackage: str) -> dict[str, set[str]]:
    return {str(p.relative_to(PACKAGE)): imported_modules(p) for p in (PACKAGE / subpackage).glob("*.py")}


def test_geometry_and_types_import_nothing_of_the_package():
    for name in ("geometry.py", "types.py"):
        assert imported_modules(PACKAGE / name) == set(), name


def test_estimators_and_loss_only_import_downwards():
    allowed = ("geco_guide.geometry", "geco_guide.types")
    for subpackage, own in (("estimators", "geco_guide.estimators"), ("loss", "geco_guide.loss")):
        for path, names in imports_of(subpackage).items():
            foreign = {n for n in names if not n.startswith((own, *allowed))}
            # the one exception, for type annotations only: the loader's argument is the config's section
            if path == "estimators/__init__.py":
                foreign -= {"geco_guide.config", "geco_guide.config.EstimatorsConfig"}
            assert not foreign, f"{path} imports {sorted(foreign)}"
