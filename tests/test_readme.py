"""The README and the docs: their runnable examples stay runnable (those that need no downloaded
weights), the README stays a short front door whose first bash block is what CI runs, and the text
speaks of the project alone."""

import re
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
README = ROOT / "README.md"
DOCS = sorted((ROOT / "docs").glob("*.md"))
PAGES = [README, *DOCS]
README_MAX_BYTES = 12 * 1024
# Names of machines, issue numbers and folders outside the repository have no place in the text.
FORBIDDEN = re.compile(r"issue\s[0-9]+|machine\s[AB]\b|cpu[B]|\.\.[/]shared", re.I)  # written so that it does not match itself


def python_blocks(path: Path) -> list[str]:
    return re.findall(r"```python\n(.*?)```", path.read_text(), flags=re.S)


def offline(blocks: list[str]) -> list[str]:
    return [b for b in blocks if "from_pretrained" not in b]


BLOCKS = python_blocks(README)
OFFLINE_BLOCKS = offline(BLOCKS)
def first_statement(code: str) -> str:
    """The first line that is not an import: what names an example in a test id."""
    lines = [line for line in code.splitlines() if line.strip() and not line.startswith(("import ", "from "))]
    return (lines or code.splitlines())[0][:40]


EXAMPLES = [
    pytest.param(path, code, id=f"{path.relative_to(ROOT)}:{i}:{first_statement(code)}")
    for path in PAGES
    for i, code in enumerate(offline(python_blocks(path)))
]


def test_readme_has_offline_examples():
    assert OFFLINE_BLOCKS


@pytest.mark.parametrize("path, code", EXAMPLES)
@pytest.mark.slow
def test_example_runs(path, code):
    exec(compile(code, str(path), "exec"), {"__name__": "__readme__"})


def test_readme_is_a_short_front_door():
    size = len(README.read_bytes())
    assert size <= README_MAX_BYTES, f"README.md is {size} bytes, over {README_MAX_BYTES}: move the detail to docs/"


def test_first_bash_block_holds_the_two_setup_commands():
    """.ci/run runs the non-comment lines of the README's first bash block in a fresh venv."""
    block = re.search(r"^```bash\n(.*?)^```$", README.read_text(), flags=re.S | re.M)
    assert block, "README.md has no ```bash block"
    commands = [line for line in block.group(1).splitlines() if line.strip() and not line.startswith("#")]
    assert len(commands) == 2, commands
    assert all(c.startswith("pip install torch==") for c in commands), commands
    # the CPU build: plain PyPI torch on Linux pulls GB of CUDA wheels onto a CPU-only machine
    assert all(c.split("&&")[0].strip().endswith("--index-url https://download.pytorch.org/whl/cpu")
               for c in commands), commands
    assert "python -m geco_guide.generate --preset tiny" in commands[0]
    assert "python -m pytest" in commands[1]


@pytest.mark.parametrize("path", PAGES, ids=lambda p: str(p.relative_to(ROOT)))
def test_text_speaks_of_the_project_alone(path):
    hits = [m.group(0) for m in FORBIDDEN.finditer(path.read_text())]
    assert not hits, f"{path.relative_to(ROOT)}: {hits}"


@pytest.mark.parametrize("path", PAGES, ids=lambda p: str(p.relative_to(ROOT)))
def test_the_hook_is_shown_with_the_estimators_names(path):
    """``geometry_estimator=`` / ``flow_estimator=``, as the pipeline's components; the earlier
    ``geometry=`` / ``flow=`` are only mentioned, never shown in a call."""
    calls = re.findall(r"attach_geco_guidance\([^)]*\)", path.read_text())
    old = [c for c in calls if re.search(r"\b(geometry|flow)=", c)]
    assert not old, f"{path.relative_to(ROOT)}: {old}"
