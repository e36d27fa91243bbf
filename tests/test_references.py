"""Every dotted ``geco_guide.*`` name the docstrings, the docs and the README mention resolves: a
module, or a name inside one (a renamed or moved function must take its mentions along)."""

from __future__ import annotations

import importlib
import re
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
SOURCES = [*sorted((ROOT / "geco_guide").rglob("*.py")), *sorted((ROOT / "scripts").glob("*.py")),
           *sorted((ROOT / "docs").glob("*.md")), ROOT / "README.md"]
DOTTED = re.compile(r"\bgeco_guide(?:\.[A-Za-z_][A-Za-z0-9_]*)+")


def resolves(name: str) -> bool:
    """Whether ``name`` is a module of the package or an attribute path inside one."""
    parts = name.split(".")
    for split in range(len(parts), 0, -1):
        try:
            target = importlib.import_module(".".join(parts[:split]))
        except ImportError:
            continue
        for attribute in parts[split:]:
            if not hasattr(target, attribute):
                return False
            target = getattr(target, attribute)
        return True
    return False


def test_every_dotted_reference_resolves():
    unresolved = sorted({f"{name} ({path.relative_to(ROOT)})" for path in SOURCES
                         for name in DOTTED.findall(path.read_text(encoding="utf-8")) if not resolves(name)})
    assert not unresolved, unresolved


def test_the_check_notices_a_name_that_does_not_resolve():
    assert resolves("geco_guide.metric.render.MAP_RANGE") and resolves("geco_guide.bench")
    assert not resolves("geco_guide.video.MAP_RANGE") and not resolves("geco_guide.metric.render.NO_SUCH_NAME")


def test_the_performance_page_stays_a_page_and_its_records_live_apart():
    page, records = ROOT / "docs" / "performance.md", ROOT / "docs" / "performance_records.md"
    assert page.stat().st_size <= 20_000 and records.is_file()
    assert "## Which GPU runs what" in page.read_text() and "## Which GPU runs what" not in records.read_text()
