"""Scatter plots drawn with Pillow's ImageDraw and its default font (Pillow is a declared
dependency): no matplotlib.

A :class:`Panel` maps data to a pixel box with axes, ticks and labels; :func:`legend` adds a
row of coloured markers with labels. Markers come in several shapes (:data:`SHAPES`) so that
series drawn on top of each other stay told apart. Used by the A/B report, the GeCo-Eval report
and the robustness sweep.
"""

from __future__ import annotations

import functools
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

__all__ = ["FONT_SIZE", "Panel", "legend", "legend_width", "limits", "plot_font", "text", "text_width"]

#: Marker shapes of :func:`marker`.
SHAPES = ("circle", "square", "triangle", "diamond")


def limits(values: Sequence[float]) -> tuple[float, float]:
    """Axis limits around ``values`` with a 6 % margin (a small range around a constant, so a
    single value still gets an axis of non-zero width)."""
    low, high = min(values), max(values)
    pad = 0.06 * (high - low) if high > low else max(abs(low) * 0.1, 1e-3)
    return low - pad, high + pad


#: Pixels of the plots' text. Pillow's default font at its default 10 pixels draws a space one
#: or two pixels wide, so that words run together ("not toscale"); from 12 a space reads as one.
FONT_SIZE = 12


@functools.cache
def plot_font() -> Any:
    """Pillow's default font at :data:`FONT_SIZE` pixels, or its fixed bitmap font in a Pillow
    without sizes for it (before 10.1, or built without FreeType)."""
    from PIL import ImageFont

    try:
        return ImageFont.load_default(size=FONT_SIZE)
    except TypeError:  # Pillow < 10.1: load_default takes no size
        return ImageFont.load_default()


def text(draw: Any, xy: tuple[float, float], text: str, align: str) -> float:
    """Draw black ``text`` (:func:`plot_font`) with its box aligned at ``xy``: ``align`` is
    horizontal (``l``, ``m``, ``r``) + vertical (``t``, ``m``, ``b``); works with bitmap fonts too.
    Returns the text width."""
    left, top, right, bottom = draw.textbbox((0, 0), text, font=plot_font())
    width, height = right - left, bottom - top
    x = xy[0] - {"l": 0, "m": width / 2, "r": width}[align[0]] - left
    y = xy[1] - {"t": 0, "m": height / 2, "b": height}[align[1]] - top
    draw.text((x, y), text, fill=(0, 0, 0), font=plot_font())
    return width


@dataclass
class Panel:
    """One scatter panel: a pixel box on the canvas and data limits."""

    box: tuple[int, int, int, int]  # left, top, right, bottom (the plot area)
    xlim: tuple[float, float]
    ylim: tuple[float, float]

    def to_pixel(self, x: float, y: float) -> tuple[float, float]:
        left, top, right, bottom = self.box
        u = left + (x - self.xlim[0]) / (self.xlim[1] - self.xlim[0]) * (right - left)
        v = bottom - (y - self.ylim[0]) / (self.ylim[1] - self.ylim[0]) * (bottom - top)
        return u, v

    def __post_init__(self) -> None:
        for name, (low, high) in (("xlim", self.xlim), ("ylim", self.ylim)):
            if not high > low:  # a zero-width range would divide by zero in to_pixel
                raise ValueError(f"{name} must be an increasing range, got {(low, high)} (see limits())")

    def draw_axes(self, draw: Any, title: str, xlabel: str, ylabel: str,
                  xticks: Sequence[tuple[float, str]] | None = None) -> None:
        """Frame, title, labels and ticks; ``xticks``: ``(x, label)`` pairs replacing the
        default three x ticks (at both ends and the middle of ``xlim``)."""
        left, top, right, bottom = self.box
        draw.rectangle(self.box, outline=(0, 0, 0))
        text(draw, (left - 50, top - 44), title, "lt")
        text(draw, ((left + right) / 2, bottom + 24), xlabel, "mt")
        text(draw, (left - 50, top - 8), ylabel, "lb")
        if xticks is None:
            xticks = [(x, f"{x:.3g}") for x in (self.xlim[0] + t * (self.xlim[1] - self.xlim[0]) for t in (0.0, 0.5, 1.0))]
        for x, label in xticks:
            u, _ = self.to_pixel(x, self.ylim[0])
            draw.line([(u, bottom), (u, bottom + 4)], fill=(0, 0, 0))
            text(draw, (u, bottom + 6), label, "mt")
        for t in (0.0, 0.5, 1.0):
            y = self.ylim[0] + t * (self.ylim[1] - self.ylim[0])
            _, v = self.to_pixel(self.xlim[0], y)
            draw.line([(left - 4, v), (left, v)], fill=(0, 0, 0))
            text(draw, (left - 6, v), f"{y:.3g}", "rm")

    def dot(self, draw: Any, x: float, y: float, color: tuple[int, int, int], radius: int = 4,
            shape: str = "circle") -> None:
        marker(draw, self.to_pixel(x, y), color, radius, shape)


def marker(draw: Any, centre: tuple[float, float], color: tuple[int, int, int], radius: int = 4,
           shape: str = "circle") -> None:
    """A filled marker of ``shape`` (one of :data:`SHAPES`) with a black outline at ``centre``."""
    u, v = centre
    r = radius
    if shape == "circle":
        draw.ellipse([u - r, v - r, u + r, v + r], fill=color, outline=(0, 0, 0))
    elif shape == "square":
        draw.rectangle([u - r, v - r, u + r, v + r], fill=color, outline=(0, 0, 0))
    elif shape == "triangle":
        draw.polygon([(u, v - r - 1), (u + r + 1, v + r), (u - r - 1, v + r)], fill=color, outline=(0, 0, 0))
    elif shape == "diamond":
        draw.polygon([(u, v - r - 1), (u + r + 1, v), (u, v + r + 1), (u - r - 1, v)], fill=color, outline=(0, 0, 0))
    else:
        raise ValueError(f"shape must be one of {SHAPES}, got {shape!r}")


#: Columns of a legend entry besides its label: the marker with the space after it, and the gap
#: to the next entry.
LEGEND_MARKER_W, LEGEND_GAP = 9, 24


def text_width(draw: Any, text: str) -> int:
    """Pixel width of ``text`` as :func:`text` draws it."""
    left, _, right, _ = draw.textbbox((0, 0), text, font=plot_font())
    return right - left


def legend_width(draw: Any, labels: Sequence[str]) -> int:
    """Pixel width of the row :func:`legend` draws for ``labels`` (to size a canvas)."""
    return sum(LEGEND_MARKER_W + text_width(draw, label) + LEGEND_GAP for label in labels) - LEGEND_GAP


def legend(draw: Any, panel: Panel, entries: Sequence[tuple[str, tuple[int, int, int]]],
           shapes: Sequence[str] | None = None) -> None:
    """Coloured markers (``shapes``, one per entry; default circles) with labels in a row below
    the panel's x label (:func:`legend_width` wide)."""
    u, v = panel.box[0], panel.box[3] + 48
    for k, (label, color) in enumerate(entries):
        marker(draw, (u, v), color, 4, "circle" if shapes is None else shapes[k])
        u += LEGEND_MARKER_W + text(draw, (u + LEGEND_MARKER_W, v), label, "lm") + LEGEND_GAP
