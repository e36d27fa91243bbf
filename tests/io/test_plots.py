"""The reports' plots (:mod:`geco_guide.io.plots`): text a person reads as written."""

from __future__ import annotations

import numpy as np
from PIL import Image, ImageDraw

from geco_guide.io.plots import text


def _blank_runs(phrase: str) -> list[int]:
    """Widths of the blank column runs between the inked columns of ``phrase`` drawn by :func:`text`."""
    image = Image.new("RGB", (400, 40), (255, 255, 255))
    text(ImageDraw.Draw(image), (5, 5), phrase, "lt")
    inked = (np.asarray(image).min(axis=-1) < 160).any(axis=0)
    columns = np.flatnonzero(inked)
    runs, width = [], 0
    for ink in inked[columns[0]: columns[-1] + 1]:
        if ink:
            if width:
                runs.append(width)
            width = 0
        else:
            width += 1
    return runs


def test_spaces_read_as_spaces():
    # "not toscale" was what robustness.png showed: Pillow's default 10-pixel font draws a space
    # as narrow as the gap between two letters
    runs = sorted(_blank_runs("not to scale"), reverse=True)
    assert len(runs) >= 2 and runs[1] >= 3 and runs[1] > runs[2], runs
