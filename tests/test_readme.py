"""The README's runnable examples stay runnable (those that need no downloaded weights)."""

import re
from pathlib import Path

import pytest

README = Path(__file__).resolve().parents[1] / "README.md"
BLOCKS = re.findall(r"```python\n(.*?)```", README.read_text(), flags=re.S)
OFFLINE_BLOCKS = [b for b in BLOCKS if "from_pretrained" not in b]


def test_readme_has_offline_examples():
    assert OFFLINE_BLOCKS


@pytest.mark.parametrize("code", OFFLINE_BLOCKS, ids=lambda c: c.splitlines()[0][:40])
def test_readme_example_runs(code):
    exec(compile(code, str(README), "exec"), {"__name__": "__readme__"})
