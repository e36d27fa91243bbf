"""Rendering GeCo maps so a person reads them right: :func:`colorize` (viridis over the FIXED
range :data:`MAP_RANGE`, so maps of different videos are comparable), :func:`colorbar` (its legend
with tick labels), :func:`draw_text` / :func:`text_strip` (Pillow's default font, sized by
:func:`text_scale`), :func:`side_by_side` (labelled panels) and :func:`map_frames` (the maps
enlarged to a readable size, labelled, with the legend and a caption per frame). Frames are
``[S, 3, H, W]`` in ``[0, 1]``."""

from __future__ import annotations

import functools
import math
from typing import Any

import numpy as np
import torch
import torch.nn.functional as F
from torch import Tensor

__all__ = ["FONT_SIZE", "INVALID_COLOR", "MAP_RANGE", "MIN_FONT_SIZE", "OUTLINE_COLOR", "READABLE_HEIGHT", "VIRIDIS",
           "colorbar", "colorbar_ticks", "colorize", "draw_text", "enlarge", "fitting_size", "hatch",
           "label_height", "map_frames", "outline", "panel_layout", "side_by_side", "text_mask", "text_scale",
           "text_strip"]

# Viridis (matplotlib's perceptually uniform, colour-blind-safe map): 9 evenly spaced samples,
# linearly interpolated in between (sRGB, 0-255).
VIRIDIS = torch.tensor(
    [
        [0x44, 0x01, 0x54], [0x47, 0x2D, 0x7B], [0x3B, 0x52, 0x8B], [0x2C, 0x72, 0x8E], [0x21, 0x90, 0x8C],
        [0x27, 0xAD, 0x81], [0x5D, 0xC8, 0x63], [0xAA, 0xDC, 0x32], [0xFD, 0xE7, 0x25],
    ],
    dtype=torch.float32,
) / 255.0


#: The fixed value range of GeCo heat maps: residuals in normalised image units / relative depth.
#: 0.2 sits above generated videos' typical fused scores (0.1-0.3 in the paper); larger values
#: are clipped to the top colour, so one colour means one value in every video.
MAP_RANGE = (0.0, 0.2)


#: Pixels without a valid value (occluded, not co-visible, low confidence): neutral grey, a
#: colour viridis never takes.
INVALID_COLOR = (0.5, 0.5, 0.5)


def colorize(values: Tensor, valid: Tensor | None = None, value_range: tuple[float, float] = MAP_RANGE) -> Tensor:
    """Map values ``[..., H, W]`` to viridis RGB ``[..., 3, H, W]`` over a fixed range.

    Values outside ``value_range`` are clipped to its ends; pixels where ``valid [..., H, W]`` is
    False (and NaNs) are :data:`INVALID_COLOR`.
    """
    low, high = value_range
    if not high > low:
        raise ValueError(f"value_range must be increasing, got {value_range}")
    values = values.detach().float()
    finite = torch.isfinite(values)
    t = ((torch.where(finite, values, torch.zeros_like(values)) - low) / (high - low)).clamp(0, 1)
    t = t * (VIRIDIS.shape[0] - 1)
    lo = t.floor().long().clamp(max=VIRIDIS.shape[0] - 2)
    frac = (t - lo)[..., None]
    lut = VIRIDIS.to(values.device)
    rgb = lut[lo] * (1 - frac) + lut[lo + 1] * frac  # [..., H, W, 3]
    keep = finite if valid is None else finite & valid.to(values.device).bool()
    rgb = torch.where(keep[..., None], rgb, rgb.new_tensor(INVALID_COLOR))
    return rgb.movedim(-1, -3).contiguous()


#: Font size in pixels per unit of :func:`text_scale` (text next to a 480-pixel-high video is
#: drawn at 4 x 9 = 36 pixels).
FONT_SIZE = 9


#: The smallest size :func:`text_strip` shrinks a line to so that it fits its width.
MIN_FONT_SIZE = 7


@functools.cache
def _font(size: int) -> tuple[Any, int]:
    """``(font, upscale)`` for text of ``size`` pixels: Pillow's default font at that size, or,
    in a Pillow without sizes for it (before 10.1, or built without FreeType), its fixed bitmap
    font and the integer factor the drawn text is enlarged by."""
    from PIL import ImageFont

    try:
        font = ImageFont.load_default(size=size)
    except TypeError:  # Pillow < 10.1: load_default takes no size
        font = ImageFont.load_default()
    if isinstance(font, ImageFont.FreeTypeFont):
        return font, 1
    return font, max(1, round(size / FONT_SIZE))  # its 11-pixel lines stand in for FONT_SIZE ones


def _line_height(font: Any) -> int:
    if hasattr(font, "getmetrics"):
        ascent, descent = font.getmetrics()
        return ascent + descent
    return font.getbbox("Ag|")[3]


def _ascent(size: int) -> int:
    """Rows from the top of a line of text at ``size`` pixels to its baseline."""
    font, upscale = _font(size)
    return (font.getmetrics()[0] if hasattr(font, "getmetrics") else font.getbbox("A")[3]) * upscale


def _coverage(text: str, size: int) -> Tensor:
    """``[line height, width]`` float coverage in [0, 1] of ``text`` drawn at ``size`` pixels
    (anti-aliased; the same text and size always give the same pixels)."""
    from PIL import Image, ImageDraw

    font, upscale = _font(size)
    height = _line_height(font)
    width = 0
    if text:
        width = max(math.ceil(font.getlength(text)), font.getbbox(text)[2])
    if width == 0:
        return torch.zeros(height * upscale, 0)
    image = Image.new("L", (width, height), 0)
    ImageDraw.Draw(image).text((0, 0), text, fill=255, font=font)
    mask = torch.from_numpy(np.asarray(image, dtype=np.float32) / 255.0)
    return mask.repeat_interleave(upscale, 0).repeat_interleave(upscale, 1)


def text_scale(size: int) -> int:
    """Integer scale of text next to an image of ``size`` pixels (its height): at least 2
    (18-pixel text), as the 9 pixels of scale 1 are hard to read at a video's native size."""
    return max(2, size // 120)


def text_mask(text: str, scale: int = 1) -> Tensor:
    """``[line height, width]`` float coverage in [0, 1] of one line of ``text`` in Pillow's
    default font at ``FONT_SIZE * scale`` pixels. The height is the font's line height (ascent +
    descent) whatever the text, so lines of one scale share a baseline; the width grows with the
    text. Characters the font lacks are drawn as its placeholder box."""
    return _coverage(text, FONT_SIZE * scale)


def _blend(image: Tensor, mask: Tensor, x: int, y: int, color: tuple[float, float, float]) -> Tensor:
    out = image.clone()
    height, width = out.shape[-2:]
    top, left = max(0, y), max(0, x)
    bottom, right = min(height, y + mask.shape[0]), min(width, x + mask.shape[1])
    if bottom <= top or right <= left:
        return out
    alpha = mask[top - y : bottom - y, left - x : right - x].to(out.device, out.dtype)
    region = out[:, top:bottom, left:right]
    colour = out.new_tensor(color)[:, None, None]
    out[:, top:bottom, left:right] = region * (1 - alpha) + colour * alpha
    return out


def draw_text(image: Tensor, text: str, x: int, y: int, scale: int = 1, color: tuple[float, float, float] = (1.0, 1.0, 1.0)) -> Tensor:
    """``image [3, H, W]`` with ``text`` (:func:`text_mask`) blended in ``color``, the top-left
    corner of its line at column ``x``, row ``y`` (clipped at the image border). Returns a new
    tensor."""
    return _blend(image, text_mask(text, scale), x, y, color)


def label_height(scale: int) -> int:
    """Height of a :func:`text_strip`: a line of text with ``scale`` pixels above and below,
    rounded up to an even height (which yuv420p video needs)."""
    font, upscale = _font(FONT_SIZE * scale)
    height = _line_height(font) * upscale + 2 * scale
    return height + height % 2


def fitting_size(text: str, width: int, scale: int) -> int:
    """The font size in pixels a :func:`text_strip` of ``width`` draws ``text`` at: ``FONT_SIZE *
    scale``, or smaller (down to :data:`MIN_FONT_SIZE`) where the line would not fit."""
    size = FONT_SIZE * scale
    while _coverage(text, size).shape[1] > width - 4 * scale and size > MIN_FONT_SIZE:
        size -= 1
    return size


def text_strip(text: str, width: int, scale: int, size: int | None = None) -> Tensor:
    """``[3, label_height(scale), width]``: one line of white ``text`` on black, left-aligned.

    A line too long for the width is drawn smaller (:func:`fitting_size`) on the same baseline;
    what still does not fit is cut at the right border. ``size`` (pixels, at most ``FONT_SIZE *
    scale``) draws it at that size instead: headings of one row share one.
    """
    margin, size = 2 * scale, fitting_size(text, width, scale) if size is None else size
    mask = _coverage(text, size)
    strip = torch.zeros(3, label_height(scale), width)
    baseline = scale + _ascent(FONT_SIZE * scale)
    return _blend(strip, mask, margin, baseline - _ascent(size), (1.0, 1.0, 1.0))


def colorbar_ticks(width: int, scale: int = 1, value_range: tuple[float, float] = MAP_RANGE,
                   ticks: int = 5) -> tuple[tuple[int, int], list[tuple[int, str, int]]]:
    """Where :func:`colorbar` draws its bar and ticks: ``((left, right), [(x, label, label_left), ...])``
    (the bar spans columns ``[left, right)``; a tick at column ``x`` has its label's box from
    ``label_left``, ``text_mask(label, scale).shape[1]`` wide). ``ticks`` evenly spaced ticks, or
    fewer (3, then both ends) where their labels would come closer than the width of a digit; none
    where even the two ends would, or the bar does not fit."""
    margin, gap = 2 * scale, text_mask("0", scale).shape[1]
    low, high = value_range
    swatch_end = margin + text_mask("N/A", scale).shape[1]
    left = swatch_end + gap + text_mask(f"{low:g}", scale).shape[1] // 2 + 1  # "0" a digit clear of "N/A"
    top_label = f"{high:g}+"
    right = width - margin - text_mask(top_label, scale).shape[1] // 2  # room for the last label
    if right - left < 2:
        return (left, left), []
    for count in dict.fromkeys(n for n in (ticks, 3, 2) if 2 <= n <= ticks):
        placed: list[tuple[int, str, int]] = []
        end = swatch_end
        for k in range(count):
            x = left + round(k * (right - left - 1) / (count - 1))
            label = f"{low + (high - low) * k / (count - 1):g}" + ("+" if k == count - 1 else "")
            label_w = text_mask(label, scale).shape[1]
            label_left = min(max(0, x - label_w // 2), width - label_w)
            if label_left < end + gap:
                break
            placed.append((x, label, label_left))
            end = label_left + label_w
        else:
            return (left, right), placed
    return (left, right), []


def colorbar(width: int, scale: int = 1, value_range: tuple[float, float] = MAP_RANGE, ticks: int = 5) -> Tensor:
    """Legend of :func:`colorize`: ``[3, h, width]`` (``h`` even), a grey ``N/A`` swatch (invalid
    pixels), then the colour bar over ``value_range`` with up to ``ticks`` labelled ticks
    (:func:`colorbar_ticks`: labels never touch); the last reads ``0.2+`` because larger values are
    clipped to its colour. Labels are as in a :func:`text_strip` under the bar."""
    margin, bar_h, tick_h = 2 * scale, 4 * scale, 2 * scale
    text_y = margin + bar_h + tick_h + scale  # the line's place in a text strip under the bar
    legend = torch.zeros(3, margin + bar_h + tick_h + label_height(scale), width)
    swatch_w = text_mask("N/A", scale).shape[1]
    legend[:, margin : margin + bar_h, margin : margin + swatch_w] = torch.tensor(INVALID_COLOR)[:, None, None]
    legend = draw_text(legend, "N/A", margin, text_y, scale)
    (left, right), placed = colorbar_ticks(width, scale, value_range, ticks)
    if right - left < 2:
        return legend
    ramp = torch.linspace(*value_range, right - left)
    legend[:, margin : margin + bar_h, left:right] = colorize(ramp[None], value_range=value_range)
    for x, label, label_left in placed:
        legend[:, margin + bar_h : margin + bar_h + tick_h, x : x + scale] = 1.0
        legend = draw_text(legend, label, label_left, text_y, scale)
    return legend


#: Panels lower than this are enlarged for a person to read (:func:`enlarge`): a 32x48 clip's maps
#: would be 204 pixels wide with its labels shrunk to the smallest font.
READABLE_HEIGHT = 192


def enlarge(frames: Tensor, min_height: int = READABLE_HEIGHT) -> Tensor:
    """``frames [..., H, W]`` enlarged by the smallest whole factor that makes them at least
    ``min_height`` high (nearest: every pixel becomes a square block, no value is blended; factor 1
    for frames already as high)."""
    factor = max(1, math.ceil(min_height / frames.shape[-2]))
    if factor == 1:
        return frames
    return frames.repeat_interleave(factor, -2).repeat_interleave(factor, -1)


def map_frames(frames: Tensor, heat: list[Tensor], labels: list[str], captions: list[str]) -> Tensor:
    """The frames of a maps video or detection picture: ``[S, 3, H', W']``.

    ``frames [S, 3, H, W]`` and the colourised maps ``heat`` (each ``[S, 3, H, W]``), enlarged to a
    readable height (:func:`enlarge`) and labelled side by side (``labels``, one per panel), the
    colour scale (:func:`colorbar`) under them, then one caption line per frame (``captions``).
    """
    if len(captions) != frames.shape[0]:
        raise ValueError(f"need one caption per frame, got {len(captions)} for {frames.shape[0]} frames")
    panels = [enlarge(panel.detach().float().cpu()) for panel in (frames, *heat)]
    grid = side_by_side(panels, labels)
    num, _, _, width = grid.shape
    scale = text_scale(panels[0].shape[-2])
    legend = colorbar(width, scale)[None].expand(num, -1, -1, -1)
    lines = torch.stack([text_strip(caption, width, scale) for caption in captions])
    return torch.cat((grid, legend, lines), dim=-2)


def panel_layout(sizes: list[tuple[int, int]]) -> tuple[tuple[int, int], list[tuple[int, int, int, int]]]:
    """Where :func:`side_by_side` puts panels of ``sizes`` ``(H, W)`` (already at a common H).

    Returns:
        ``((total_height, total_width), [(top, left, height, width), ...])``: each panel's video
        area; its label strip (:func:`label_height`) sits above it, panels are separated by
        ``2 * scale`` black columns, ``scale = text_scale(H)``.
    """
    height = sizes[0][0]
    scale = text_scale(height)
    top, gap = label_height(scale), 2 * scale
    boxes, left = [], 0
    for h, w in sizes:
        boxes.append((top, left, h, w))
        left += w + gap
    return (top + height, left - gap), boxes


def side_by_side(videos: list[Tensor], labels: list[str]) -> Tensor:
    """Labelled panels in a row: ``[S_i, 3, H_i, W_i]`` each -> ``[S, 3, H', W']``.

    Panels are resized (bilinear) to the tallest height keeping their aspect ratio; a shorter
    video holds its last frame, so ``S = max S_i``. Each label is drawn above its panel
    (:func:`text_strip`), all at one size. Layout: :func:`panel_layout`.
    """
    if not videos or len(videos) != len(labels):
        raise ValueError(f"need one label per video, got {len(videos)} videos and {len(labels)} labels")
    for k, video in enumerate(videos):
        if not isinstance(video, Tensor) or video.ndim != 4 or video.shape[1] != 3 or video.shape[0] < 1:
            raise ValueError(f"videos[{k}] must be a [S, 3, H, W] tensor, got {getattr(video, 'shape', type(video))}")
    height = max(v.shape[-2] for v in videos)
    num_frames = max(v.shape[0] for v in videos)
    panels = []
    for video in videos:
        video = video.detach().float().cpu()
        if video.shape[-2] != height:
            width = max(1, round(video.shape[-1] * height / video.shape[-2]))
            video = F.interpolate(video, size=(height, width), mode="bilinear", align_corners=False)
        if video.shape[0] < num_frames:
            video = torch.cat((video, video[-1:].expand(num_frames - video.shape[0], -1, -1, -1)))
        panels.append(video.clamp(0, 1))
    (total_h, total_w), boxes = panel_layout([tuple(p.shape[-2:]) for p in panels])
    scale = text_scale(height)
    # one size for every heading: the largest at which each fits over its panel
    size = min(fitting_size(label, w, scale) for label, (_, _, _, w) in zip(labels, boxes))
    out = torch.zeros(num_frames, 3, total_h, total_w)
    for panel, label, (top, left, h, w) in zip(panels, labels, boxes):
        out[:, :, :top, left : left + w] = text_strip(label, w, scale, size)
        out[:, :, top : top + h, left : left + w] = panel
    return out


#: Period in pixels (at text scale 1) of the stripes over pixels a dynamic mask left out.
HATCH_PERIOD = 6


def hatch(images: Tensor, mask: Tensor, scale: int = 1) -> Tensor:
    """``images [..., 3, H, W]`` with diagonal grey-and-white stripes where ``mask [..., H, W]``:
    pixels a dynamic mask left out, drawn so nobody reads them as consistent (plain grey means
    "no valid pixel", a colour a score)."""
    height, width = images.shape[-2:]
    rows = torch.arange(height, device=images.device)[:, None]
    cols = torch.arange(width, device=images.device)[None, :]
    period = HATCH_PERIOD * max(1, scale)
    stripe = ((rows + cols) % period) < period // 2  # [H, W]
    pattern = torch.where(stripe, images.new_tensor(0.85), images.new_tensor(INVALID_COLOR[0]))
    return torch.where(mask.to(images.device).bool()[..., None, :, :], pattern, images)


#: The outline of a mover scored against its own motion: white, a colour viridis never takes.
OUTLINE_COLOR = (1.0, 1.0, 1.0)


def outline(images: Tensor, labels: Tensor, color: tuple[float, float, float] = OUTLINE_COLOR) -> Tensor:
    """``images [..., 3, H, W]`` with the edge of each region of ``labels [..., H, W]`` (int, 0:
    none) drawn in ``color``: its pixels with a 4-neighbour of another label, so two movers that
    touch keep their own outlines."""
    labels = labels.to(images.device)
    edge = torch.zeros_like(labels, dtype=torch.bool)
    across = labels[..., :, 1:] != labels[..., :, :-1]
    down = labels[..., 1:, :] != labels[..., :-1, :]
    edge[..., :, 1:] |= across
    edge[..., :, :-1] |= across
    edge[..., 1:, :] |= down
    edge[..., :-1, :] |= down
    edge &= labels > 0
    return torch.where(edge[..., None, :, :], images.new_tensor(color)[:, None, None], images)
