"""The house: the import graph of the package (module- and function-level imports) points down
the floors of docs/architecture.md, with no circles, and scoring a video loads no diffusion code."""

from __future__ import annotations

import ast
import subprocess
import sys
from pathlib import Path

import pytest

PACKAGE = Path(__file__).resolve().parents[1] / "geco_guide"
ENTRY_POINTS = ("__main__", "generate")

# Floors from the bottom up; a module imports its own subpackage or lower floors. Rooms on one
# floor do not import each other (the metric never imports the sampler, nor bench perf).
FLOORS = [
    ["geco_guide", "geco_guide.geometry", "geco_guide.types", "geco_guide.io", "geco_guide.families"],
    ["geco_guide.loss", "geco_guide.estimators"],
    ["geco_guide.metric", "geco_guide.sampler.diffusers_private"],
    ["geco_guide.sampler.algorithm"],
    ["geco_guide.sampler.running"],
    ["geco_guide.sampler.search"],
    ["geco_guide.sampler.pipelines", "geco_guide.sampler"],
    ["geco_guide.config", "geco_guide.tiny"],
    ["geco_guide.generation"],
    ["geco_guide.bench", "geco_guide.perf"],
    ["geco_guide.cli"],
    [f"geco_guide.{name}" for name in ENTRY_POINTS],
]
DIFFUSION_PACKAGES = ("diffusers", "transformers", "accelerate")
#: The text segmenters are transformers' models (SAM 3 video, Grounding DINO, SAM 2 video): their
#: module imports transformers inside its functions only, so nothing loads it unless text masks
#: are asked for.
LAZY_TRANSFORMERS = ("geco_guide.estimators.segmenters",)


def module_name(path: Path) -> str:
    parts = path.relative_to(PACKAGE.parent).with_suffix("").parts
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def _type_checking_only(tree: ast.AST) -> set[int]:
    """Line numbers of imports under ``if TYPE_CHECKING:`` (never executed)."""
    lines: set[int] = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.If) and getattr(node.test, "id", None) == "TYPE_CHECKING":
            lines.update(n.lineno for stmt in node.body for n in ast.walk(stmt) if hasattr(n, "lineno"))
    return lines


def imported_modules(path: Path, *, external: bool = False, type_checking: bool = False) -> set[str]:
    """Absolute names of the modules ``path`` imports anywhere in it (relative imports resolved,
    ``from package import module`` counted as the module); geco_guide's, or the others'. Those
    under ``if TYPE_CHECKING:`` only with ``type_checking``."""
    module = module_name(path)
    package = module if path.name == "__init__.py" else module.rsplit(".", 1)[0]
    tree = ast.parse(path.read_text())
    skip = set() if type_checking else _type_checking_only(tree)
    names: set[str] = set()
    for node in ast.walk(tree):
        if getattr(node, "lineno", None) in skip:
            continue
        if isinstance(node, ast.ImportFrom):
            if node.level:
                base = package.rsplit(".", node.level - 1)[0] if node.level > 1 else package
                target = f"{base}.{node.module}" if node.module else base
            else:
                target = node.module or ""
            names.add(target)
            for alias in node.names:
                candidate = f"{target}.{alias.name}"
                if (PACKAGE.parent / (candidate.replace(".", "/") + ".py")).is_file() or (
                        PACKAGE.parent / candidate.replace(".", "/")).is_dir():
                    names.add(candidate)
        elif isinstance(node, ast.Import):
            names.update(alias.name for alias in node.names)
    if external:
        return {n.split(".")[0] for n in names if not n.startswith("geco_guide")}
    return {n for n in names if n.startswith("geco_guide")}


def floor_of(name: str) -> tuple[int, str]:
    """(floor, room) of a module: the longest room name it lies in."""
    best = max((room for floor in FLOORS for room in floor if name == room or name.startswith(room + ".")), key=len)
    return next(i for i, floor in enumerate(FLOORS) if best in floor), best


def sources() -> list[Path]:
    return sorted(PACKAGE.rglob("*.py"))


def graph(*, type_checking: bool = False) -> dict[str, set[str]]:
    """Module -> the package's modules it imports (with ``type_checking``, those imported for type
    hints only as well)."""
    edges: dict[str, set[str]] = {}
    known = {module_name(p) for p in sources()}
    for path in sources():
        targets = set()
        for name in imported_modules(path, type_checking=type_checking):
            while name not in known and "." in name:  # a name imported from a module: the module
                name = name.rsplit(".", 1)[0]
            targets.add(name)
        edges[module_name(path)] = targets - {module_name(path)}
    return edges


@pytest.mark.slow
def test_every_import_points_down_or_stays_in_its_room():
    wrong = []
    for source, targets in graph().items():
        if source == "geco_guide":
            continue  # the public facade: lazy names only (import_module), checked below
        floor, room = floor_of(source)
        for target in targets:
            target_floor, target_room = floor_of(target)
            if target_room != room and (target_floor > floor or (target_floor == floor and target_room != "geco_guide")):
                wrong.append(f"{source} -> {target}")
    assert not wrong, "imports that run up or sideways:\n" + "\n".join(sorted(wrong))


def test_the_package_facade_imports_nothing_at_import_time():
    assert graph()["geco_guide"] == set()


def import_circles(edges: dict[str, set[str]]) -> list[str]:
    """Each circle of ``edges`` found by a depth-first walk, as ``a -> b -> a``."""
    state: dict[str, int] = {}
    circles = []

    def visit(node: str, path: list[str]) -> None:
        state[node] = 1
        for target in sorted(edges.get(node, ())):
            if target == "geco_guide":
                continue
            if state.get(target) == 1:
                circles.append(" -> ".join(path[path.index(target):] + [target]))
            elif target not in state:
                visit(target, path + [target])
        state[node] = 2

    for node in sorted(edges):
        if node not in state:
            visit(node, [node])
    return circles


def test_no_import_circles_lazy_and_type_checking_imports_included():
    """An import under ``if TYPE_CHECKING:`` is a circle all the same: the two modules cannot be
    understood (or moved) one without the other, and the guard is all that keeps it from failing."""
    circles = import_circles(graph(type_checking=True))
    assert not circles, "\n".join(circles)


def test_the_circle_walk_finds_a_circle_guarded_by_type_checking(tmp_path, monkeypatch):
    package = tmp_path / "geco_guide"
    package.mkdir()
    (package / "__init__.py").write_text("")
    (package / "plans.py").write_text("from typing import TYPE_CHECKING\nif TYPE_CHECKING:\n"
                                      "    from .options import Options\n")
    (package / "options.py").write_text("from .plans import NAMES\n")
    monkeypatch.setattr(sys.modules[__name__], "PACKAGE", package)
    assert import_circles(graph()) == []
    assert import_circles(graph(type_checking=True)) == [
        "geco_guide.options -> geco_guide.plans -> geco_guide.options"]


def test_the_metric_and_the_floors_below_import_no_diffusion_code():
    for path in sources():
        floor, room = floor_of(module_name(path))
        if floor <= 1 or room == "geco_guide.metric":
            found = imported_modules(path, external=True) & set(DIFFUSION_PACKAGES)
            if module_name(path) in LAZY_TRANSFORMERS:
                found -= {"transformers"}
            assert not found, f"{path.relative_to(PACKAGE)} imports {sorted(found)}"


def test_the_text_segmenters_import_transformers_lazily():
    for name in LAZY_TRANSFORMERS:
        tree = ast.parse((PACKAGE.parent / (name.replace(".", "/") + ".py")).read_text())
        top = {alias.name.split(".")[0] for node in tree.body if isinstance(node, ast.Import) for alias in node.names}
        top |= {(node.module or "").split(".")[0] for node in tree.body if isinstance(node, ast.ImportFrom)}
        assert not top & set(DIFFUSION_PACKAGES), name


@pytest.mark.slow
def test_scoring_a_video_with_the_public_api_loads_no_diffusers():
    probe = ("import sys, geco_guide; geco_guide.GeCoLoss; geco_guide.evaluate_video; "
             f"print(sorted(m for m in {DIFFUSION_PACKAGES!r} if m in sys.modules))")
    out = subprocess.run([sys.executable, "-c", probe], capture_output=True, text=True, timeout=120)
    assert out.returncode == 0, out.stderr
    assert out.stdout.strip() == "[]"


def test_the_top_of_the_package_is_small_and_no_source_file_is_long():
    top = sorted(p.name for p in PACKAGE.glob("*.py"))
    assert len(top) <= 12, top
    long = {str(p.relative_to(PACKAGE.parent)): n for p in sources() if (n := len(p.read_text().splitlines())) > 800}
    assert not long, long
    scripts = PACKAGE.parent / "scripts"
    long = {p.name: n for p in scripts.glob("*.py") if (n := len(p.read_text().splitlines())) > 800}
    assert not long, long


#: The floors below the config, whose functions take the config section they use.
SECTION_FLOORS = ("geco_guide.loss", "geco_guide.estimators", "geco_guide.metric", "geco_guide.sampler")


def test_the_floors_below_the_config_take_its_sections_not_the_whole_config():
    """A loader or the metric takes ``model``, ``estimators``, ``evaluation``, ... (typed), never the
    whole config: no parameter annotated ``GeCoConfig``, no ``cfg`` / ``config`` without a type or
    typed ``Any`` (the estimators' model configs excepted: each model class has its own), and no
    import of the config module (the import rule above)."""
    wrong = []
    for path in sources():
        name = module_name(path)
        if not name.startswith(SECTION_FLOORS):
            continue
        for node in ast.walk(ast.parse(path.read_text())):
            if not isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)):
                continue
            for arg in [*node.args.posonlyargs, *node.args.args, *node.args.kwonlyargs]:
                annotation = ast.unparse(arg.annotation) if arg.annotation is not None else ""
                untyped = (arg.arg in ("cfg", "config") and annotation in ("", "Any")
                           and not (arg.arg == "config" and name.startswith("geco_guide.estimators")))
                if "GeCoConfig" in annotation or untyped:
                    wrong.append(f"{name}.{node.name}({arg.arg}: {annotation or '?'})")
    assert not wrong, "functions that take the whole config:\n" + "\n".join(sorted(wrong))
