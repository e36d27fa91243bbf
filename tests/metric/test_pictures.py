"""What the pictures show a person: maps and detection frames at a readable size, colour-bar
labels that never run together, one heading size per row, canvases as large as what they draw,
and plot labels in a reader's words."""

from __future__ import annotations

import io

import pytest
import torch
from PIL import Image, ImageDraw

from geco_guide.bench import geco_eval, robustness
from geco_guide.io.plots import legend_width, text_width
from geco_guide.metric.evaluate import map_caption
from geco_guide.metric.render import (
    FONT_SIZE,
    READABLE_HEIGHT,
    colorbar,
    colorbar_ticks,
    colorize,
    enlarge,
    fitting_size,
    label_height,
    map_frames,
    side_by_side,
    text_mask,
    text_scale,
)


def ink_rows(strip: torch.Tensor) -> tuple[int, int]:
    """First and last row of a ``[3, h, w]`` strip holding any drawn text."""
    rows = torch.nonzero(strip.amax(dim=(0, 2)) > 0.5).flatten()
    return int(rows[0]), int(rows[-1])


def ink_runs(row: torch.Tensor, min_gap: int) -> int:
    """Runs of inked columns in ``row [3, h, w]`` separated by at least ``min_gap`` blank columns."""
    inked = (row.amax(dim=(0, 1)) > 0.5).tolist()
    runs, blank = 0, min_gap
    for on in inked:
        if on and blank >= min_gap:
            runs += 1
        blank = 0 if on else blank + 1
    return runs


def test_enlarge_by_whole_factors_to_a_readable_height():
    frames = torch.rand(2, 3, 32, 48)
    big = enlarge(frames)
    assert big.shape == (2, 3, 192, 288) and big.shape[-2] >= READABLE_HEIGHT
    assert torch.equal(big[..., ::6, ::6], frames)  # each pixel a 6x6 block
    assert enlarge(torch.rand(1, 3, 240, 320)).shape == (1, 3, 240, 320)  # tall enough: unchanged
    assert enlarge(torch.rand(1, 3, 100, 10)).shape == (1, 3, 200, 20)


def test_map_frames_of_a_small_clip_are_enlarged_with_full_size_captions():
    frames = torch.rand(3, 3, 32, 48)
    heat = [colorize(torch.rand(3, 32, 48) * 0.2) for _ in range(3)]
    captions = [map_caption({"time_s": t / 8, "fused": 0.0561, "motion": 0.0423, "structure": 0.0562}) for t in range(3)]
    assert captions[1] == "t = 0.12 s   fused 0.056   motion 0.042   structure 0.056"  # lower case, not T=0.12S
    out = map_frames(frames, heat, ["SOURCE", "MOTION", "STRUCTURE", "FUSED"], captions)
    scale = text_scale(192)
    assert out.shape[0] == 3 and out.shape[-1] >= 4 * 288  # was 204 pixels wide before enlarging
    assert out.shape[-2] >= label_height(scale) + 192 + label_height(scale)
    # the caption and every heading fit at the full font size: none is shrunk to be unreadable
    assert fitting_size(captions[0], out.shape[-1], scale) == FONT_SIZE * scale
    assert fitting_size("STRUCTURE", 288, scale) == FONT_SIZE * scale
    with pytest.raises(ValueError, match="one caption per frame"):
        map_frames(frames, heat, ["SOURCE", "MOTION", "STRUCTURE", "FUSED"], captions[:2])


def test_headings_of_one_row_share_one_size():
    """"unguided" no longer draws smaller than "guided": both at the size the longer fits."""
    video = torch.rand(2, 3, 32, 48)
    out = side_by_side([video, video], ["unguided", "guided"])
    top = label_height(text_scale(32))
    gap = 2 * text_scale(32)
    left, right = out[0, :, :top, :48], out[0, :, :top, 48 + gap :]
    # both words reach from an ascender ("d") to a descender ("g"): equal ink heights, equal sizes
    assert ink_rows(left) == ink_rows(right)


@pytest.mark.parametrize("scale", [1, 2, 4])
def test_colorbar_labels_never_touch(scale):
    for width in range(60, 1300, 37):
        (bar_left, bar_right), placed = colorbar_ticks(width, scale)
        boxes = [(label_left, label_left + text_mask(label, scale).shape[1]) for _, label, label_left in placed]
        digit = text_mask("0", scale).shape[1]
        assert all(a[1] + digit <= b[0] for a, b in zip(boxes, boxes[1:])), (width, placed)
        assert all(0 <= lo and hi <= width for lo, hi in boxes)
        if placed:  # the scale's ends are always labelled
            assert placed[0][1] == "0" and placed[-1][1] == "0.2+"
        legend = colorbar(width, scale)
        text_rows = legend[:, legend.shape[1] - label_height(scale) :]
        # the drawn row: "N/A" and each label, apart (a label's own letters are closer than a digit)
        assert ink_runs(text_rows, digit) == 1 + len(placed), (width, placed)
    # the width of the tiny preset's maps before they were enlarged: fewer labels, not "0.150.2+"
    (_, _), placed = colorbar_ticks(204, 2)
    assert 2 <= len(placed) < 5


def test_pareto_canvas_is_sized_to_the_panels_drawn():
    stats = {"mean": 0.5, "std": None, "n": 1}
    arms = {"unguided": {"groups": {"all": {"mean_motion": stats, "fused": stats},
                                    "indoor": {"mean_motion": stats, "fused": stats}}}}
    two = Image.open(io.BytesIO(geco_eval.plot_png({"arms": arms}))).convert("L")
    every = {"m": {"groups": {g: {"mean_motion": stats, "fused": stats} for g in ("all", *geco_eval.SCENARIOS)}}}
    five = Image.open(io.BytesIO(geco_eval.plot_png({"arms": every}))).convert("L")
    assert two.width < 0.5 * five.width
    for image in (two, five):
        inked = [x for x in range(image.width) if image.crop((x, 0, x + 1, image.height)).getextrema()[0] < 255]
        assert inked[0] < 80 and image.width - inked[-1] <= 60  # not 60 % blank on the right
    # many arms: the canvas grows to hold the legend row
    many = {f"a-long-model-name-{k}": arms["unguided"] for k in range(8)}
    image = Image.open(io.BytesIO(geco_eval.plot_png({"arms": many}))).convert("L")
    draw = ImageDraw.Draw(Image.new("RGB", (1, 1)))
    assert image.width >= geco_eval.PARETO_LEFT + legend_width(draw, list(many))


def test_robustness_x_labels_say_what_sigma_is_and_fit_their_panel():
    labels = robustness.ROBUSTNESS_X_LABELS
    assert "relative depth error" in labels["depth"] and "pixels" in labels["flow"]
    assert all("exp" not in label for label in labels.values())
    draw = ImageDraw.Draw(Image.new("RGB", (1, 1)))
    # panels are 260 pixels wide, 360 apart: a label stays clear of the next column
    assert all(text_width(draw, label) <= 340 for label in (*labels.values(), robustness.ROBUSTNESS_AXIS_NOTE))
