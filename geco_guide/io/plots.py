"""Scatter plots drawn with Pillow's ImageDraw and its default font (Pillow is a declared
dependency): no matplotlib.

A :class:`Panel` maps data to a pixel box with axes, ticks and labels; :func:`legend` adds a
row of coloured dots with labels. Used by the A/B report and the GeCo-Eval report.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any


def limits(values: Sequence[float]) -> tuple[float, float]:
    """Axis limits around ``values`` with a 6 % margin (a unit-width range around a constant)."""
    low, high = min(values), max(values)
    pad = 0.06 * (high - low) if high > low else max(abs(low) * 0.1, 1e-3)
    return low - pad, high + pad


def text(draw: Any, xy: tuple[float, float], text: str, align: str) -> float:
    """Draw black ``text`` with its box aligned at ``xy``: ``align`` is horizontal (``l``, ``m``,
    ``r``) + vertical (``t``, ``m``, ``b``); works with bitmap fonts too. Returns the text width."""
    left, top, right, bottom = draw.textbbox((0, 0), text)
    width, height = right - left, bottom - top
    x = xy[0] - {"l": 0, "m": width / 2, "r": width}[align[0]] - left
    y = xy[1] - {"t": 0, "m": height / 2, "b": height}[align[1]] - top
    draw.text((x, y), text, fill=(0, 0, 0))
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

    def draw_axes(self, draw: Any, title: str, xlabel: str, ylabel: str) -> None:
        left, top, right, bottom = self.box
        draw.rectangle(self.box, outline=(0, 0, 0))
        text(draw, (left - 50, top - 44), title, "lt")
        text(draw, ((left + right) / 2, bottom + 24), xlabel, "mt")
        text(draw, (left - 50, top - 8), ylabel, "lb")
        for t in (0.0, 0.5, 1.0):
            x = self.xlim[0] + t * (self.xlim[1] - self.xlim[0])
            y = self.ylim[0] + t * (self.ylim[1] - self.ylim[0])
            u, _ = self.to_pixel(x, self.ylim[0])
            _, v = self.to_pixel(self.xlim[0], y)
            draw.line([(u, bottom), (u, bottom + 4)], fill=(0, 0, 0))
            text(draw, (u, bottom + 6), f"{x:.3g}", "mt")
            draw.line([(left - 4, v), (left, v)], fill=(0, 0, 0))
            text(draw, (left - 6, v), f"{y:.3g}", "rm")

    def dot(self, draw: Any, x: float, y: float, color: tuple[int, int, int], radius: int = 4) -> None:
        u, v = self.to_pixel(x, y)
        draw.ellipse([u - radius, v - radius, u + radius, v + radius], fill=color, outline=(0, 0, 0))


def legend(draw: Any, panel: Panel, entries: Sequence[tuple[str, tuple[int, int, int]]]) -> None:
    """Coloured dots with labels in a row below the panel's x label."""
    u, v = panel.box[0], panel.box[3] + 48
    for label, color in entries:
        draw.ellipse([u - 4, v - 4, u + 4, v + 4], fill=color, outline=(0, 0, 0))
        u += 9 + text(draw, (u + 9, v), label, "lm") + 24
