"""Video files: mp4 round trip through imageio-ffmpeg, atomic writes, clear errors."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import torch

from geco_guide.io.files import WriteError
from geco_guide.io.video import (
    VideoReadError,
    gif_frame_repeats,
    gif_rate,
    read_frames,
    read_video,
    write_video,
)
from geco_guide.metric import render
from geco_guide.metric.protocol import (
    evaluation_windows,
    motion_grid,
    sampled_rate,
    time_grid_indices,
)
from geco_guide.metric.render import (
    FONT_SIZE,
    INVALID_COLOR,
    MAP_RANGE,
    MIN_FONT_SIZE,
    VIRIDIS,
    colorbar,
    colorize,
    draw_text,
    fitting_size,
    label_height,
    panel_layout,
    side_by_side,
    text_mask,
    text_scale,
    text_strip,
)


def smooth_video(frames=5, h=32, w=48):
    yy, xx = torch.meshgrid(torch.linspace(0, 1, h), torch.linspace(0, 1, w), indexing="ij")
    return torch.stack([torch.stack([xx, yy, torch.full_like(xx, 0.1 * t + 0.3)]) for t in range(frames)])


def test_round_trip_chw_and_hwc(tmp_path: Path):
    video = smooth_video()
    path = write_video(tmp_path / "a.mp4", video, fps=8)
    frames, fps = read_video(path)
    assert frames.shape == video.shape and frames.dtype == torch.float32
    assert fps == pytest.approx(8.0)
    assert (frames - video).abs().mean() < 0.02
    path2 = write_video(tmp_path / "b.mp4", video.permute(0, 2, 3, 1).numpy(), fps=4)
    frames2, fps2 = read_video(path2)
    assert fps2 == pytest.approx(4.0) and (frames2 - video).abs().mean() < 0.02


def test_write_is_atomic_and_leaves_no_temporary_files(tmp_path: Path):
    target = tmp_path / "out" / "v.mp4"
    write_video(target, smooth_video(), fps=8)
    old = target.read_bytes()
    with pytest.raises(ValueError):
        write_video(target, torch.rand(2, 4, 8, 8), fps=8)  # bad shape: the old file stays intact
    assert target.read_bytes() == old
    assert sorted(p.name for p in target.parent.iterdir()) == ["v.mp4"]


def test_failed_encode_cleans_up(tmp_path: Path, monkeypatch):
    import imageio.v2 as imageio

    def broken_writer(*args, **kwargs):
        raise RuntimeError("encoder exploded")

    monkeypatch.setattr(imageio, "get_writer", broken_writer)
    with pytest.raises(RuntimeError, match="exploded"):
        write_video(tmp_path / "x.mp4", smooth_video(), fps=8)
    assert list(tmp_path.iterdir()) == []


@pytest.fixture
def failing_writer(monkeypatch):
    """imageio's writer, made to fail at the end as ffmpeg does on a full disk: ``mode="trailer"``
    truncates the file at close without raising (ffmpeg's exit status is not checked by imageio),
    ``mode="write"`` raises ENOSPC from ``append_data``."""
    import errno

    import imageio.v2 as imageio

    real_get_writer = imageio.get_writer
    mode = {"mode": None}  # the first write succeeds until a test sets the mode

    class Writer:
        def __init__(self, path, **kwargs):
            self.path, self.inner = Path(path), real_get_writer(path, **kwargs)

        def append_data(self, frame):
            if mode["mode"] == "write":
                raise OSError(errno.ENOSPC, "No space left on device\n\nFFMPEG COMMAND: ...")
            self.inner.append_data(frame)

        def close(self):
            self.inner.close()
            if mode["mode"] == "trailer":
                self.path.write_bytes(self.path.read_bytes()[: self.path.stat().st_size // 2])

    monkeypatch.setattr(imageio, "get_writer", Writer)
    return mode


@pytest.mark.parametrize("mode, reason", [("trailer", "not a readable video"), ("write", "No space left on device")])
def test_a_failing_writer_is_one_line_naming_the_file_and_leaves_nothing(tmp_path: Path, failing_writer, mode, reason):
    target = write_video(tmp_path / "v.mp4", smooth_video(), fps=8)
    old = target.read_bytes()
    failing_writer["mode"] = mode
    with pytest.raises(WriteError, match=rf"^cannot write '{target}': .*{reason}") as info:
        write_video(target, smooth_video(frames=6), fps=8)
    assert "\n" not in str(info.value)
    assert target.read_bytes() == old and [p.name for p in tmp_path.iterdir()] == ["v.mp4"]


def test_a_written_video_with_missing_frames_is_refused(tmp_path: Path, monkeypatch):
    import imageio.v2 as imageio

    real_get_writer = imageio.get_writer

    class DroppingWriter:  # an encoder that silently loses the last frame
        def __init__(self, path, **kwargs):
            self.inner, self.frames = real_get_writer(path, **kwargs), []

        def append_data(self, frame):
            self.frames.append(frame)

        def close(self):
            for frame in self.frames[:-1]:
                self.inner.append_data(frame)
            self.inner.close()

    monkeypatch.setattr(imageio, "get_writer", DroppingWriter)
    with pytest.raises(WriteError, match="holds 4 frame\\(s\\), not 5"):
        write_video(tmp_path / "v.mp4", smooth_video(frames=5), fps=8)
    assert list(tmp_path.iterdir()) == []


def test_corrupt_and_missing_files_give_clear_errors(tmp_path: Path):
    good = write_video(tmp_path / "good.mp4", smooth_video(), fps=8)
    truncated = tmp_path / "truncated.mp4"
    truncated.write_bytes(good.read_bytes()[:300])
    with pytest.raises(ValueError, match="cannot read video .*truncated.mp4"):
        read_video(truncated)
    junk = tmp_path / "junk.mp4"
    junk.write_bytes(b"not a video" * 50)
    with pytest.raises(ValueError, match="cannot read video"):
        read_video(junk)
    with pytest.raises(FileNotFoundError):
        read_video(tmp_path / "missing.mp4")


def test_uint8_and_value_clipping(tmp_path: Path):
    data = np.full((2, 16, 16, 3), 200, dtype=np.uint8)
    frames, _ = read_video(write_video(tmp_path / "u.mp4", data, fps=8))
    assert (frames * 255 - 200).abs().max() < 4
    frames, _ = read_video(write_video(tmp_path / "c.mp4", torch.full((2, 3, 16, 16), 3.0), fps=8))
    assert frames.min() > 0.95


# --- the metric's sampling -----------------------------------------------------------------


def test_time_grid_takes_the_nearest_frames_at_most_max_fps():
    assert sampled_rate(24.0, 8.0) == 8.0 and sampled_rate(6.0, 8.0) == 6.0  # never upsampled
    # 3 s at 8 fps from 24 fps: 24 samples, every third frame
    assert time_grid_indices(240, 24.0, 0.0, 3.0, 8.0) == list(range(0, 72, 3))
    # 30 fps: k * 3.75 rounded half to even (7.5 -> 8, 22.5 -> 22), as numpy's rint in the script
    assert time_grid_indices(300, 30.0, 0.0, 1.0, 8.0) == [0, 4, 8, 11, 15, 19, 22, 26]
    # times past the clip are clamped to its last frame and de-duplicated
    assert time_grid_indices(10, 8.0, 0.5, 3.0, 8.0) == list(range(4, 10))
    assert time_grid_indices(2, 30.0, 0.0, 0.01, 8.0) == [0, 1]  # at least 2 frames
    with pytest.raises(ValueError):
        time_grid_indices(1, 8.0, 0.0, 3.0, 8.0)
    with pytest.raises(ValueError):
        time_grid_indices(5, 0.0, 0.0, 3.0, 8.0)


def test_windows_follow_the_geco_eval_script():
    # CogVideoX at its native 16 fps: 49 frames = 3.06 s -> 2 overlapping 3 s windows
    windows = evaluation_windows(49, 16.0, 3.0, 4, 8.0)
    assert [w.start_s for w in windows] == [0.0, 0.0625] and [w.length_s for w in windows] == [3.0, 3.0]
    assert windows[0].indices == list(range(0, 48, 2)) and windows[1].indices == list(range(1, 49, 2))
    # 10 s at 30 fps -> ceil(10 / 3) = 4 windows of 3 s, starts evenly spaced, the last ends the clip
    windows = evaluation_windows(300, 30.0, 3.0, 4, 8.0)
    assert [round(w.start_s, 4) for w in windows] == [0.0, 2.3333, 4.6667, 7.0]
    assert all(len(w.indices) == 24 for w in windows) and windows[-1].indices[-1] == 296
    # more than 4 windows needed -> exactly 4 equal windows tiling the clip (20 s: 5 s each)
    windows = evaluation_windows(600, 30.0, 3.0, 4, 8.0)
    assert [w.start_s for w in windows] == [0.0, 5.0, 10.0, 15.0] and {w.length_s for w in windows} == {5.0}
    assert [len(w.indices) for w in windows] == [40] * 4
    # shorter than a window: one window over the whole clip
    windows = evaluation_windows(17, 8.0, 3.0, 4, 8.0)
    assert len(windows) == 1 and windows[0].indices == list(range(17)) and windows[0].length_s == 17 / 8
    with pytest.raises(ValueError):
        evaluation_windows(49, 16.0, 3.0, 0, 8.0)


def test_motion_grid_spans_the_clip_at_the_evaluation_rate():
    assert motion_grid(49, 16.0, 8.0) == list(range(0, 48, 2))  # 3.06 s -> 24 samples
    assert motion_grid(9, 8.0, 8.0) == list(range(9))


# --- reading any video -----------------------------------------------------------------------


def test_read_frames_keeps_the_selected_frames_while_decoding(tmp_path: Path):
    video = smooth_video(frames=13).clamp(0, 1)
    path = write_video(tmp_path / "a.mp4", video, fps=24)
    asked = []

    def every_third(count: int, fps: float) -> list[int]:
        asked.append((count, fps))
        return list(range(0, count, 3))

    clip = read_frames(path, select=every_third)
    assert asked == [(13, 24.0)]  # the count comes from the container, before decoding
    assert clip.indices == [0, 3, 6, 9, 12] and clip.fps == 24.0 and clip.num_frames == 13
    assert clip.fps_source == "file" and clip.frames.shape[0] == 5
    assert (clip.frames - video[clip.indices]).abs().mean() < 0.02
    clip = read_frames(path, fps=4.0)  # the caller's rate wins over the file's
    assert clip.indices == list(range(13)) and clip.fps == 4.0 and clip.fps_source == "caller"


def test_read_gif_and_frame_folder(tmp_path: Path):
    import imageio.v2 as imageio

    video = smooth_video(frames=4)
    data = (video.permute(0, 2, 3, 1).numpy() * 255).round().astype(np.uint8)
    imageio.mimsave(tmp_path / "a.gif", list(data), duration=100, loop=0)  # 100 ms a frame
    clip = read_frames(tmp_path / "a.gif")
    assert clip.fps == pytest.approx(10.0) and clip.frames.shape == (4, 3, 32, 48)
    folder = tmp_path / "frames"
    folder.mkdir()
    order = [0, 1, 2, 3]
    for k, name in zip(order, ["f1.png", "f2.jpg", "f10.png", "f11.PNG"]):  # natural order, any case
        imageio.imwrite(folder / name, data[k])
    (folder / "readme.txt").write_text("not a frame")
    clip = read_frames(folder)
    assert clip.fps == 8.0 and clip.fps_source == "default" and clip.num_frames == 4 and clip.indices == order
    assert (clip.frames - video).abs().mean() < 0.03
    assert read_frames(folder, fps=2.0).fps == 2.0


@pytest.mark.parametrize(
    "delay_ms, fps",
    [(100, 10.0), (40, 25.0), (50, 20.0), (120, 8.0), (130, 8.0), (30, 30.0), (60, 16.0), (70, 15.0),
     (170, 6.0), (90, 100 / 9), (125, 8.0), (33.3, 1000 / 33.3)],
)
def test_gif_delays_are_read_as_the_rate_they_encode(delay_ms, fps):
    assert gif_rate(delay_ms) == pytest.approx(fps)


@pytest.mark.parametrize("fps", [8, 10, 12, 16, 30])  # 24 and 15 fps store the delays of 25 and 16
def test_a_gif_written_at_a_common_rate_is_read_at_that_rate(tmp_path: Path, fps):
    import imageio.v2 as imageio

    data = (smooth_video(frames=3).permute(0, 2, 3, 1).numpy() * 255).astype(np.uint8)
    imageio.mimsave(tmp_path / "a.gif", list(data), duration=1000 / fps, loop=0)  # stored in whole centiseconds
    assert read_frames(tmp_path / "a.gif").fps == fps


def test_read_frames_errors_are_one_line_video_read_errors(tmp_path: Path):
    import imageio.v2 as imageio

    (tmp_path / "junk.mp4").write_bytes(b"not a video" * 50)
    (tmp_path / "empty").mkdir()
    mixed = tmp_path / "mixed"
    mixed.mkdir()
    imageio.imwrite(mixed / "0.png", np.zeros((8, 8, 3), np.uint8))
    imageio.imwrite(mixed / "1.png", np.zeros((8, 10, 3), np.uint8))
    broken = tmp_path / "broken"
    broken.mkdir()
    (broken / "0.png").write_bytes(b"garbage")
    one = write_video(tmp_path / "one.mp4", smooth_video(frames=1), fps=8)
    cases = [
        (tmp_path / "junk.mp4", "cannot read video"),
        (tmp_path / "missing.mp4", "no such file"),
        (tmp_path / "empty", "holds no"),
        (mixed, "different sizes"),
        (broken, "cannot read frame"),
        (one, "1 frame"),
    ]
    for path, message in cases:
        with pytest.raises(VideoReadError, match=message) as info:
            read_frames(path, min_frames=2)
        assert isinstance(info.value, ValueError) and "\n" not in str(info.value) and str(path) in str(info.value)


# --- heat maps, text, panels -------------------------------------------------------------------


def test_colorize_uses_a_fixed_clipped_range():
    low, high = MAP_RANGE
    values = torch.tensor([[low, high, 10 * high, -1.0, (low + high) / 2, float("nan")]])
    valid = torch.tensor([[True, True, True, True, False, True]])
    rgb = colorize(values, valid)
    assert rgb.shape == (3, 1, 6)
    assert torch.allclose(rgb[:, 0, 0], VIRIDIS[0]) and torch.allclose(rgb[:, 0, 1], VIRIDIS[-1])
    assert torch.allclose(rgb[:, 0, 2], VIRIDIS[-1]) and torch.allclose(rgb[:, 0, 3], VIRIDIS[0])  # clipped
    for k in (4, 5):  # invalid and NaN
        assert torch.allclose(rgb[:, 0, k], torch.tensor(INVALID_COLOR))
    ramp = colorize(torch.linspace(low, high, 50)[None])[:, 0]  # viridis gets brighter along the range
    luminance = 0.2126 * ramp[0] + 0.7152 * ramp[1] + 0.0722 * ramp[2]
    assert (luminance.diff() > 0).all()
    assert colorize(torch.zeros(2, 4, 5, 6)).shape == (2, 4, 3, 5, 6)


def test_text_and_legend():
    from PIL import ImageFont

    def line_height(size):
        ascent, descent = ImageFont.load_default(size=size).getmetrics()
        return ascent + descent

    # masks: one line of Pillow's default font at FONT_SIZE * scale, as high as the font's line
    ab = text_mask("AB", 1)
    assert ab.dtype == torch.float32 and ab.shape == (line_height(FONT_SIZE), ab.shape[1]) and ab.shape[1] > 0
    assert text_mask("AB", 3).shape[0] == line_height(3 * FONT_SIZE) and text_mask("AB", 3).shape[1] > 2 * ab.shape[1]
    assert 0.0 <= ab.min() and ab.max() <= 1.0 and ab.max() > 0.8 and torch.equal(ab, text_mask("AB", 1))  # deterministic
    assert text_mask("ABC").shape[1] > ab.shape[1] and text_mask("ABC").shape[0] == ab.shape[0]  # one line height
    assert text_mask("").shape == (ab.shape[0], 0) and text_mask(" ").max() == 0.0
    assert not torch.equal(text_mask("a"), text_mask("A"))  # lower case is its own
    for unknown in ("~", "\u4e2d"):  # a character the font lacks is drawn (its placeholder), no error
        mask = text_mask(unknown)
        assert mask.shape[0] == ab.shape[0] and mask.shape[1] > 0 and mask.max() > 0.5
    # drawing: blended in the colour at (x, y), clipped at every border
    image = draw_text(torch.zeros(3, 10, 8), "HELLO", 2, 3)
    assert image.shape == (3, 10, 8) and image[:, :3].max() == 0.0 and image[:, :, :2].max() == 0.0
    assert torch.allclose(image[:, 3:, 2:], text_mask("HELLO")[:7, :6].expand(3, -1, -1))
    red = draw_text(torch.zeros(3, 10, 8), "HELLO", -3, -4, color=(1.0, 0.0, 0.0))
    rows = text_mask("HELLO").shape[0] - 4  # the line's rows left inside the image
    assert torch.allclose(red[0, :rows], text_mask("HELLO")[4:, 3:11]) and red[0, rows:].max() == 0.0
    assert red[1:].max() == 0.0 and red[0].max() > 0.5
    assert torch.equal(draw_text(torch.ones(3, 4, 4), "HELLO", 5, 0), torch.ones(3, 4, 4))  # all outside
    # strips: even heights (yuv420p), text shrunk to fit the width down to MIN_FONT_SIZE
    for scale in range(1, 9):
        assert label_height(scale) % 2 == 0 and label_height(scale) >= line_height(FONT_SIZE * scale)
        assert text_strip("GUIDED", 300, scale).shape == (3, label_height(scale), 300)
    assert text_scale(32) == 2 and text_scale(240) == 2 and text_scale(480) == 4  # 18-pixel text at least
    strip = text_strip("STRUCTURE", 48, 1)  # a 32x48 panel's label
    assert text_mask("STRUCTURE").shape[1] > 48 - 4 and strip[:, :, -2:].max() == 0.0 and strip.max() > 0.8
    line = "t = 0.12 s   fused 0.002   motion 0.002   structure 0.002"  # the score line under four 32x48 panels
    assert text_strip(line, 198, 1)[:, :, -2:].max() == 0.0
    guided, strip = text_mask("GUIDED", 2), text_strip("GUIDED", 300, 2)  # it fits: full size, 2 * scale from
    rows, columns = 2 + guided.shape[0], 4 + guided.shape[1]  # the left, scale from the top
    assert torch.allclose(strip[:, 2:rows, 4:columns], guided.expand(3, -1, -1))
    assert strip[:, :2].max() == 0.0 and strip[:, rows:].max() == 0.0 and strip[:, :, columns:].max() == 0.0
    assert MIN_FONT_SIZE <= FONT_SIZE
    # the legend
    legend = colorbar(200, scale=1)
    assert legend.shape[0] == 3 and legend.shape[2] == 200 and legend.shape[1] % 2 == 0
    assert all(colorbar(300, scale).shape[1] % 2 == 0 for scale in range(1, 5))
    bar = legend[:, 3]
    assert (bar - torch.tensor(INVALID_COLOR)[:, None]).abs().amax(0).lt(1e-6).any()  # the N/A swatch
    assert any(torch.allclose(bar[:, x], VIRIDIS[0]) for x in range(200))
    assert any(torch.allclose(bar[:, x], VIRIDIS[-1]) for x in range(200))
    assert legend[:, 2 + 4 + 2 :].max() > 0.8  # the tick labels under the bar


def test_without_font_sizes_the_bitmap_font_is_enlarged(monkeypatch):
    """A Pillow whose default font takes no size (before 10.1, or no FreeType) still draws text."""
    from PIL import ImageFont

    def load_default(*args, **kwargs):
        if args or kwargs:
            raise TypeError("load_default() takes 0 positional arguments")
        return ImageFont.load_default_imagefont()

    monkeypatch.setattr(ImageFont, "load_default", load_default)
    render._font.cache_clear()
    try:
        one, three = text_mask("AB", 1), text_mask("AB", 3)
        assert one.shape[1] > 0 and one.max() == 1.0 and three.shape == (one.shape[0] * 3, one.shape[1] * 3)
        assert label_height(3) % 2 == 0 and text_strip("AB", 60, 3).shape == (3, label_height(3), 60)
    finally:
        render._font.cache_clear()


def test_side_by_side_layout():
    a = torch.rand(4, 3, 32, 48)
    b = torch.rand(2, 3, 16, 16)  # shorter and smaller: resized to height 32, last frame held
    out = side_by_side([a, b], ["unguided", "guided"])
    (height, width), boxes = panel_layout([(32, 48), (32, 32)])
    scale = text_scale(32)
    right = 48 + 2 * scale  # after a black gap of 2 * scale columns
    assert out.shape == (4, 3, height, width) and boxes == [(label_height(scale), 0, 32, 48), (label_height(scale), right, 32, 32)]
    top = boxes[0][0]
    assert torch.equal(out[:, :, top:, :48], a)
    assert torch.equal(out[2, :, top:, right:], out[1, :, top:, right:])  # held
    # the labels, both at the largest size at which each fits its panel (one heading size per row)
    size = min(fitting_size("unguided", 48, scale), fitting_size("guided", 32, scale))
    assert torch.equal(out[:, :, :top, :48], text_strip("unguided", 48, scale, size).expand(4, -1, -1, -1))
    assert torch.equal(out[:, :, :top, right:], text_strip("guided", 32, scale, size).expand(4, -1, -1, -1))
    assert out[0, :, :top, :48].max() > 0.8 and out[:, :, :, 48:right].max() == 0.0  # drawn; a black gap
    with pytest.raises(ValueError, match="one label per video"):
        side_by_side([a], ["x", "y"])
    with pytest.raises(ValueError, match=r"videos\[0\]"):
        side_by_side([a[0]], ["x"])


# --- frame rates and frames the writer refuses, GIFs ---------------------------------------------


@pytest.mark.parametrize("fps", [float("inf"), 1e-300, float("nan"), 0.0, -8.0, 5000.0])
def test_write_video_refuses_frame_rates_outside_its_range(tmp_path: Path, fps):
    with pytest.raises(ValueError, match=r"fps must be in \[0.01, 1000\] for a mp4 video"):
        write_video(tmp_path / "v.mp4", torch.rand(2, 3, 8, 8), fps=fps)
    assert list(tmp_path.iterdir()) == []


def test_write_video_refuses_a_nan_frame_instead_of_writing_it_black(tmp_path: Path):
    frames = torch.rand(3, 3, 8, 8)
    frames[1, 0, 2, 2] = float("nan")
    with pytest.raises(ValueError, match=r"frame\(s\) \[1\] hold NaN or inf"):
        write_video(tmp_path / "v.mp4", frames)
    assert list(tmp_path.iterdir()) == []


def test_write_video_writes_gifs_by_their_suffix(tmp_path: Path):
    frames = torch.rand(4, 3, 9, 11)  # odd sizes: a GIF needs no padding
    path = write_video(tmp_path / "v.gif", frames, fps=10)
    clip = read_frames(path)
    assert clip.frames.shape == (4, 3, 9, 11) and clip.fps == pytest.approx(10.0)
    assert (clip.frames - frames).abs().mean() < 0.1  # a GIF's palette is lossy
    with pytest.raises(ValueError, match=r"\[0.01, 100\] for a gif"):
        write_video(tmp_path / "w.gif", frames, fps=200)


def test_a_gif_keeps_every_frame_of_a_video_that_holds_one(tmp_path: Path):
    from PIL import Image

    still = torch.zeros(17, 3, 12, 16)
    still[:, :, 3:7, 4:9] = 1.0  # a static mask: 17 identical frames
    path = write_video(tmp_path / "still.gif", still, fps=8)
    with Image.open(path) as image:
        assert image.n_frames == 17  # Pillow's animated writer would merge them into one frame
    clip = read_frames(path)
    assert clip.num_frames == 17 and clip.fps == 8.0 and torch.equal(clip.frames, still)
    video = torch.rand(6, 3, 12, 16)
    video[3] = video[2]  # a held frame
    frames, fps = read_video(write_video(tmp_path / "held.gif", video, fps=10))
    assert frames.shape[0] == 6 and fps == 10.0


def test_a_gif_whose_writer_merged_held_frames_is_read_by_its_frame_delays(tmp_path: Path):
    import imageio.v2 as imageio
    from PIL import Image

    video = torch.rand(9, 3, 12, 16)
    video[4] = video[5] = video[3]  # held for three frames: imageio / Pillow write one frame of 3 x 125 ms
    data = (video.permute(0, 2, 3, 1).numpy() * 255).round().astype(np.uint8)
    imageio.mimsave(tmp_path / "held.gif", list(data), duration=125, loop=0)
    with Image.open(tmp_path / "held.gif") as image:
        assert image.n_frames == 7
    clip = read_frames(tmp_path / "held.gif")
    assert clip.num_frames == 9 and clip.fps == 8.0
    assert (clip.frames - video).abs().mean() < 0.1
    picked = read_frames(tmp_path / "held.gif", select=lambda count, fps: [0, 4, 8])
    assert picked.indices == [0, 4, 8] and (picked.frames - video[[0, 4, 8]]).abs().mean() < 0.1


@pytest.mark.parametrize("delays, repeats, fps", [
    ([120, 120, 370, 120], [1, 1, 3, 1], 8.0),   # Pillow's centiseconds: 3 x 125 ms stored as 37 cs
    ([100, 100, 200, 100, 300], [1, 1, 2, 1, 3], 10.0),
    ([500, 100, 100, 100], [5, 1, 1, 1], 10.0),   # a title frame held half a second
    ([0, 0, 0], [1, 1, 1], None),                  # no timing: one frame each, no rate
    ([40, 40, 0, 40], [1, 1, 1, 1], 25.0),
])
def test_gif_frame_repeats_count_each_frame_by_its_delay(delays, repeats, fps):
    assert gif_frame_repeats(delays) == (repeats, fps)


@pytest.mark.parametrize("suffix", [".gif", ".mp4"])
def test_a_video_written_to_a_full_disk_is_one_error_and_nothing_else(tmp_path: Path, monkeypatch, suffix: str):
    """The temporary file is /dev/full (every write fails with ENOSPC): one WriteError, no file left, and
    no writer retrying its write when collected (an ignored traceback after the error line)."""
    import gc
    import os
    import sys
    import tempfile

    made = tempfile.mkstemp

    def on_a_full_disk(*args, **kwargs):
        fd, name = made(*args, **kwargs)
        os.close(fd)
        os.unlink(name)
        os.symlink("/dev/full", name)
        return os.open(name, os.O_WRONLY), name

    monkeypatch.setattr(tempfile, "mkstemp", on_a_full_disk)
    unraisable: list = []
    monkeypatch.setattr(sys, "unraisablehook", unraisable.append)
    with pytest.raises(WriteError, match=rf"^cannot write '.*v\{suffix}': ") as err:
        write_video(tmp_path / f"v{suffix}", torch.rand(4, 3, 16, 16), fps=10)
    gc.collect()
    assert "\n" not in str(err.value) and unraisable == [] and list(tmp_path.iterdir()) == []


def test_every_window_of_a_very_slow_clip_holds_two_frames():
    # 4 frames at 0.01 fps: the last window starts past the last frame's time; it keeps that
    # frame and the one before (GeCo needs a pair), as every other window does.
    windows = evaluation_windows(4, 0.01, 3.0, 4, 8.0)
    assert len(windows) == 4 and all(len(w.indices) == 2 for w in windows)
    assert windows[-1].indices == [2, 3] and windows[0].indices == [0, 1]
