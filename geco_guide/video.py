"""Video I/O, the metric's frame sampling, and interpretable rendering of heat maps.

* Files: :func:`write_video` / :func:`read_video` (mp4 through imageio-ffmpeg) and
  :func:`read_frames` (mp4 and other ffmpeg formats, gif, folders of png/jpg frames, subsampled
  while decoding). Unreadable inputs raise a one-line :class:`VideoReadError`.
* Sampling (pure functions, the GeCo-Eval protocol): :func:`evaluation_windows` (overlapping
  windows of ``window_seconds`` covering the clip, at most ``max_windows``), each sampled on a
  time grid at ``min(max_fps, fps)`` by :func:`time_grid_indices`; :func:`motion_grid` (the
  frames of Total / Mean Motion).
* Rendering: :func:`colorize` (viridis lookup table over the FIXED range :data:`MAP_RANGE`, so maps
  of different videos are comparable), :func:`colorbar` (its legend with tick labels),
  :func:`draw_text` / :func:`text_strip` (Pillow's default font, sized by :func:`text_scale`) and
  :func:`side_by_side` (labelled panels).

Frames are float ``[S, 3, H, W]`` (or ``[S, H, W, 3]`` on input) in ``[0, 1]``, RGB. Writes are
atomic: the file is written under a temporary name in the same folder, checked (readable, every
frame there) and moved into place with ``os.replace``, so a reader never sees a half-written video.
"""

from __future__ import annotations

import functools
import math
import os
import re
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable, Sequence

import numpy as np
import torch
import torch.nn.functional as F
from torch import Tensor

from .files import WriteError, atomic_path

VIDEO_SUFFIXES = (".mp4", ".mov", ".avi", ".mkv", ".webm", ".m4v", ".gif")
IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg")
DEFAULT_FPS = 8.0


class VideoReadError(ValueError):
    """An input cannot be read as a video (missing, corrupt, empty, too short); one line."""


def _error_reason(err: Exception) -> str:
    """First line of an imageio/ffmpeg error (plus its last, which names the cause), one line."""
    lines = [line.strip() for line in str(err).splitlines() if line.strip()]
    reason = lines[0] if lines else type(err).__name__
    if len(lines) > 1:
        reason += f" ({lines[-1]})"
    return reason


def _to_uint8_hwc(frames) -> np.ndarray:
    if isinstance(frames, torch.Tensor):
        frames = frames.detach().float().cpu().numpy()
    frames = np.asarray(frames)
    if frames.ndim != 4:
        raise ValueError(f"frames must be [S, 3, H, W] or [S, H, W, 3], got shape {list(frames.shape)}")
    if frames.shape[1] == 3 and frames.shape[-1] != 3:
        frames = frames.transpose(0, 2, 3, 1)
    elif frames.shape[-1] != 3:
        raise ValueError(f"frames must be [S, 3, H, W] or [S, H, W, 3], got shape {list(frames.shape)}")
    if frames.shape[0] < 1:
        raise ValueError("frames must hold at least one frame")
    if frames.dtype == np.uint8:
        out = frames
    else:
        out = (np.clip(frames.astype(np.float32), 0.0, 1.0) * 255.0 + 0.5).astype(np.uint8)
    # yuv420p needs even sizes: pad odd sizes by repeating the last row/column.
    pad_h, pad_w = out.shape[1] % 2, out.shape[2] % 2
    if pad_h or pad_w:
        out = np.pad(out, ((0, 0), (0, pad_h), (0, pad_w), (0, 0)), mode="edge")
    return np.ascontiguousarray(out)


def write_video(path: str | os.PathLike, frames, fps: float = 8) -> Path:
    """Write ``frames`` (``[S, 3, H, W]`` or ``[S, H, W, 3]``, float in [0, 1] or uint8) as an
    H.264 mp4 (yuv420p; an odd height/width is padded by one repeated row/column), atomically.
    Returns the path.

    The written file is checked before it takes its name: ffmpeg can fail while writing the
    trailer (a full disk) without the writer raising, which leaves an unreadable file.

    Raises:
        WriteError: one line naming ``path`` (disk full, ffmpeg failed, the file does not hold
            ``S`` readable frames); nothing is left under its name or as a temporary file.
    """
    import imageio.v2 as imageio

    if not fps > 0:
        raise ValueError(f"fps must be > 0, got {fps}")
    path = Path(path)
    data = _to_uint8_hwc(frames)
    with atomic_path(path) as tmp:
        writer = imageio.get_writer(
            tmp, format="FFMPEG", mode="I", fps=fps, codec="libx264", pixelformat="yuv420p",
            macro_block_size=1, quality=8, ffmpeg_log_level="error",
        )
        try:
            for frame in data:
                writer.append_data(frame)
        finally:
            writer.close()
        problem = _written_video_problem(tmp, len(data))
        if problem:
            raise WriteError(f"cannot write {str(path)!r}: {problem}")
    return path


def _written_video_problem(path: Path, expected_frames: int) -> str | None:
    """Why the mp4 at ``path`` is not a readable video of ``expected_frames`` frames, or None.

    ffmpeg counts its packets without decoding (``-c copy``): about 0.1 s for any size, and it
    fails on a file without its index (``moov atom not found``), as a truncated one is.
    """
    import subprocess

    import imageio_ffmpeg

    command = [imageio_ffmpeg.get_ffmpeg_exe(), "-nostdin", "-v", "error", "-i", str(path), "-map", "0:v:0",
               "-c", "copy", "-f", "null", "-", "-progress", "pipe:1", "-nostats"]
    proc = subprocess.run(command, capture_output=True, text=True, errors="replace")
    if proc.returncode != 0:
        lines = [line.strip() for line in proc.stderr.splitlines() if line.strip()]
        return f"the written file is not a readable video ({lines[0] if lines else f'ffmpeg exit {proc.returncode}'})"
    counts = re.findall(r"^frame=(\d+)$", proc.stdout, flags=re.MULTILINE)
    written = int(counts[-1]) if counts else 0
    if written != expected_frames:
        return f"the written file holds {written} frame(s), not {expected_frames}"
    return None


def read_video(path: str | os.PathLike) -> tuple[torch.Tensor, float]:
    """Read a video file -> ``(frames float [S, 3, H, W] in [0, 1], fps)``.

    Raises:
        FileNotFoundError: no such file.
        VideoReadError: the file is not a readable video (corrupt, truncated, empty).
    """
    import imageio.v2 as imageio

    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"video file {str(path)!r} does not exist")
    try:
        reader = imageio.get_reader(path, format="FFMPEG")
        try:
            fps = float(reader.get_meta_data().get("fps", 0.0))
            frames = [np.asarray(frame) for frame in reader]
        finally:
            reader.close()
    except Exception as err:  # imageio/ffmpeg raise OSError, RuntimeError, IndexError, ...
        raise VideoReadError(f"cannot read video {str(path)!r}: {_error_reason(err)}") from err
    if not frames:
        raise VideoReadError(f"cannot read video {str(path)!r}: it holds no frames")
    video = torch.from_numpy(np.stack(frames)[..., :3]).permute(0, 3, 1, 2).float() / 255.0
    return video.contiguous(), fps


# --------------------------------------------------------------------------------------------
# the metric's frame sampling (pure functions)


def sampled_rate(fps: float, max_fps: float) -> float:
    """The evaluation rate of a clip of ``fps``: ``min(max_fps, fps)`` (never upsampled)."""
    if not fps > 0 or not max_fps > 0:
        raise ValueError(f"fps and max_fps must be > 0, got {fps}, {max_fps}")
    return min(float(max_fps), float(fps))


def time_grid_indices(num_frames: int, fps: float, start_s: float, length_s: float, rate: float) -> list[int]:
    """Source frames nearest to the times ``start_s + k / rate``, ``k < max(2, floor(length_s * rate))``.

    The GeCo-Eval script's sampling: times are clamped to the clip (the last frame starts at
    ``num_frames / fps - 1 / fps``), rounded to the nearest frame (half to even) and de-duplicated;
    fewer than 2 distinct frames fall back to the frames nearest the interval's two ends.

    Returns:
        Increasing 0-based source indices (at least 2 when ``num_frames >= 2``).
    """
    if num_frames < 2:
        raise ValueError(f"a clip needs at least 2 frames, got {num_frames}")
    if not fps > 0 or not rate > 0 or not length_s > 0:
        raise ValueError(f"fps, rate and length_s must be > 0, got {fps}, {rate}, {length_s}")
    count = max(2, math.floor(length_s * rate + 1e-9))  # 3 s x 8 fps is 24 samples, not 23.999...
    last_time = num_frames / fps - 1.0 / fps
    indices = sorted({
        min(num_frames - 1, max(0, round(min(max(start_s + k / rate, 0.0), last_time) * fps))) for k in range(count)
    })
    if len(indices) < 2:
        ends = (round(start_s * fps), round((start_s + length_s) * fps))
        indices = sorted({min(num_frames - 1, max(0, i)) for i in ends})
    return indices


@dataclass(frozen=True)
class Window:
    """One evaluation window: its start and length in seconds and its sampled source frames."""

    start_s: float
    length_s: float
    indices: list[int]


def evaluation_windows(num_frames: int, fps: float, window_seconds: float, max_windows: int,
                       max_fps: float) -> list[Window]:
    """The GeCo-Eval windows of a clip of ``num_frames`` frames at ``fps``.

    The clip (duration ``T = num_frames / fps``) is covered by ``n = ceil(T / window_seconds)``
    windows of ``window_seconds``, their starts evenly spaced from 0 to ``T - window_seconds``
    (so they overlap unless ``T`` is a multiple of the length); a clip shorter than one window is
    one window of ``T``; when ``n > max_windows``, exactly ``max_windows`` windows of
    ``T / max_windows`` tile the clip. Each window samples its frames with
    :func:`time_grid_indices` at ``min(max_fps, fps)``.

    Examples: 49 frames at 16 fps (3.06 s) -> 2 windows starting at 0 and 0.0625 s, 24 frames
    each; 10 s at 30 fps -> 4 windows of 3 s; 20 s -> 4 windows of 5 s.
    """
    if max_windows < 1:
        raise ValueError(f"max_windows must be >= 1, got {max_windows}")
    if not window_seconds > 0:
        raise ValueError(f"window_seconds must be > 0, got {window_seconds}")
    rate = sampled_rate(fps, max_fps)
    duration = num_frames / fps
    needed = math.ceil(duration / window_seconds - 1e-9)
    if needed <= 1:
        starts, length = [0.0], min(window_seconds, duration)
    else:
        count, length = (needed, window_seconds) if needed <= max_windows else (max_windows, duration / max_windows)
        starts = [(duration - length) * k / (count - 1) for k in range(count)] if count > 1 else [0.0]
    return [Window(start, length, time_grid_indices(num_frames, fps, start, length, rate)) for start in starts]


def motion_grid(num_frames: int, fps: float, max_fps: float) -> list[int]:
    """The frames Total / Mean Motion are measured on: the whole clip on the windows' time grid
    (:func:`time_grid_indices` from 0 over the clip's duration at ``min(max_fps, fps)``)."""
    return time_grid_indices(num_frames, fps, 0.0, num_frames / fps, sampled_rate(fps, max_fps))


# --------------------------------------------------------------------------------------------
# reading any video: files through imageio, folders of frames


@dataclass
class VideoFrames:
    """Frames read from a video: the selected ones.

    Attributes:
        frames: ``[N, 3, H, W]`` float in ``[0, 1]``, the selected frames in source order.
        indices: the 0-based source index of each selected frame.
        fps: the source frame rate; fps_source: where it came from (``caller``, ``file`` or
            ``default``).
        num_frames: frames in the source.
    """

    frames: Tensor
    indices: list[int]
    fps: float
    num_frames: int
    fps_source: str = "caller"


#: ``select(num_frames, fps) -> increasing source indices``: which frames :func:`read_frames` keeps.
FrameSelector = Callable[[int, float], Sequence[int]]


def _natural_key(path: Path) -> list:
    """``frame2.png`` before ``frame10.png``."""
    return [int(part) if part.isdigit() else part for part in re.split(r"(\d+)", path.name.lower())]


def frame_files(folder: str | os.PathLike) -> list[Path]:
    """The png/jpg frames of a folder in natural order (hidden files skipped)."""
    files = [
        p for p in Path(folder).iterdir()
        if p.is_file() and p.suffix.lower() in IMAGE_SUFFIXES and not p.name.startswith(".")
    ]
    return sorted(files, key=_natural_key)


def _to_float_chw(array: np.ndarray) -> Tensor:
    """An image array (gray, RGB, RGBA; uint8/uint16/float) -> ``[3, H, W]`` float in [0, 1]."""
    array = np.asarray(array)
    if array.ndim == 2:
        array = np.repeat(array[..., None], 3, axis=-1)
    if array.ndim != 3 or array.shape[-1] not in (1, 3, 4):
        raise ValueError(f"not an image array: shape {list(array.shape)}")
    if array.shape[-1] == 1:
        array = np.repeat(array, 3, axis=-1)
    array = array[..., :3]  # alpha is dropped: frames are opaque RGB
    if np.issubdtype(array.dtype, np.integer):
        scaled = array.astype(np.float32) / float(np.iinfo(array.dtype).max)
    else:
        scaled = np.clip(array.astype(np.float32), 0.0, 1.0)
    return torch.from_numpy(np.ascontiguousarray(scaled)).permute(2, 0, 1)


def _stack(path: Path, images: list[Tensor]) -> Tensor:
    sizes = sorted({tuple(img.shape[-2:]) for img in images})
    if len(sizes) > 1:
        raise VideoReadError(f"cannot read video {str(path)!r}: frames have different sizes {sizes[:3]}")
    return torch.stack(images)


def _selection(select: FrameSelector | None, count: int, fps: float, where: Path) -> list[int]:
    indices = list(range(count)) if select is None else sorted(set(select(count, fps)))
    if indices and not (0 <= indices[0] and indices[-1] < count):
        raise ValueError(f"frame selection of {str(where)!r} is out of range [0, {count}): {indices[:3]}...")
    return indices


def _read_folder(path: Path, fps: float, select: FrameSelector | None) -> tuple[list[Tensor], list[int], int]:
    import imageio.v3 as iio

    files = frame_files(path)
    if not files:
        raise VideoReadError(f"cannot read video {str(path)!r}: the folder holds no {'/'.join(IMAGE_SUFFIXES)} frames")
    indices = _selection(select, len(files), fps, path) if len(files) >= 2 else [0]
    images = []
    for i in indices:
        try:
            images.append(_to_float_chw(iio.imread(files[i], plugin="pillow")))  # png/jpg only
        except Exception as err:  # imageio/pillow raise many types for a bad image
            raise VideoReadError(f"cannot read frame {str(files[i])!r}: {_error_reason(err)}") from err
    return images, indices, len(files)


#: Frame rates a GIF's centisecond delay is read back to when it is not exact (see :func:`gif_rate`).
COMMON_RATES = (5.0, 6.0, 8.0, 10.0, 12.0, 15.0, 16.0, 24.0, 25.0, 30.0, 50.0, 60.0)


def gif_rate(delay_ms: float) -> float:
    """The frame rate a GIF frame delay of ``delay_ms`` most plausibly encodes.

    GIF stores delays in whole centiseconds, so a writer rounds ``100 / fps`` down or to nearest:
    8 fps (12.5 cs) is stored as 12 or 13 cs, which read literally is 8.33 or 7.69 fps. Rule: a
    delay of ``d`` cs whose rate ``100 / d`` is a whole number is exact (10 cs -> 10 fps, 4 cs ->
    25 fps); otherwise the rate is the one of :data:`COMMON_RATES` whose exact delay rounds to
    ``d`` (down or to nearest) and lies closest to ``100 / d`` (12 and 13 cs -> 8 fps, 3 cs -> 30,
    6 cs -> 16, 7 cs -> 15); with no such rate, ``100 / d`` as is (9 cs -> 11.1 fps). A delay
    that is not whole centiseconds (not from a GIF) is taken literally. Centiseconds cannot tell
    24 from 25 fps (4 cs) nor, from writers that round down (Pillow), 15 from 16 fps (6 cs): give
    the rate (``--fps``) for those.
    """
    literal = 1000.0 / delay_ms
    centiseconds = delay_ms / 10.0
    if centiseconds != round(centiseconds) or literal == round(literal):
        return literal
    encodes = [rate for rate in COMMON_RATES if centiseconds in (math.floor(100 / rate), math.floor(100 / rate + 0.5))]
    return min(encodes, key=lambda rate: abs(rate - literal), default=literal)


def _file_fps(meta: dict, gif: bool) -> float | None:
    """Frame rate from imageio metadata: ffmpeg's ``fps``, or a gif's ``duration`` (ms per frame,
    read by :func:`gif_rate`)."""
    fps = meta.get("fps")
    if fps and math.isfinite(fps) and fps > 0:
        return float(fps)
    duration = meta.get("duration")
    if gif and duration and duration > 0:
        return gif_rate(float(duration))
    return None


def _open_reader(path: Path):
    import imageio.v2 as imageio

    return imageio.get_reader(path) if path.suffix.lower() == ".gif" else imageio.get_reader(path, format="FFMPEG")


def _frame_count(reader) -> int | None:
    """The container's frame count without decoding (ffmpeg counts packets), or None."""
    try:
        count = reader.count_frames() if hasattr(reader, "count_frames") else reader.get_length()
    except Exception:  # no count in the container: decode to find out
        return None
    return int(count) if isinstance(count, (int, float)) and math.isfinite(count) and count > 0 else None


def _read_file(path: Path, fps: float | None, default_fps: float, select: FrameSelector | None,
               count: int | None = None) -> tuple[list[Tensor], list[int], int, float, str]:
    """Decode a file, keeping only the selected frames: long videos never sit in memory whole.

    The selection needs the frame count, taken from the container; if decoding finds another
    count (a damaged index), the file is read a second time with the true count.
    """
    kept: dict[int, np.ndarray] = {}
    decoded = 0
    try:
        reader = _open_reader(path)
        try:
            file_fps = _file_fps(reader.get_meta_data(), path.suffix.lower() == ".gif")
            source_fps = float(fps or file_fps or default_fps)
            fps_source = "caller" if fps else "file" if file_fps else "default"
            count = count or _frame_count(reader)
            wanted = None if count is None else set(_selection(select, count, source_fps, path))
            for index, frame in enumerate(reader):
                if wanted is None or index in wanted:
                    kept[index] = np.asarray(frame)
                decoded = index + 1
        finally:
            reader.close()
    except Exception as err:  # imageio/ffmpeg/pillow raise OSError, RuntimeError, IndexError, ...
        raise VideoReadError(f"cannot read video {str(path)!r}: {_error_reason(err)}") from err
    if decoded == 0:
        raise VideoReadError(f"cannot read video {str(path)!r}: it holds no frames")
    if decoded == count and wanted is not None:
        indices = sorted(wanted)
    else:
        indices = _selection(select, decoded, source_fps, path) if decoded >= 2 else [0]
    if any(i not in kept for i in indices):  # the container's count was wrong
        return _read_file(path, fps, default_fps, select, count=decoded)
    return [_to_float_chw(kept[i]) for i in indices], indices, decoded, source_fps, fps_source


def read_frames(
    path: str | os.PathLike,
    *,
    fps: float | None = None,
    default_fps: float = DEFAULT_FPS,
    select: FrameSelector | None = None,
    min_frames: int = 1,
) -> VideoFrames:
    """Read the selected frames of a video file (mp4, mov, webm, gif, ...) or a folder of png/jpg
    frames.

    Args:
        path: a video file, or a folder whose images (natural order: ``2.png`` < ``10.png``) are
            the frames.
        fps: the source frame rate, overriding the file's.
        default_fps: the rate of inputs that carry none (folders, gifs without timing).
        select: ``select(num_frames, fps)`` -> the source indices to keep (e.g. the evaluation
            windows' frames); ``None`` keeps every frame.
        min_frames: fewer source frames than this is an error.

    Raises:
        VideoReadError: one line naming the input: missing, corrupt/unreadable, no frames, frames
            of different sizes, fewer than ``min_frames`` frames.
    """
    path = Path(path)
    if fps is not None and not (fps > 0 and math.isfinite(fps)):
        raise ValueError(f"fps must be a finite number > 0, got {fps}")
    if path.is_dir():
        source_fps, fps_source = (float(fps), "caller") if fps else (float(default_fps), "default")
        images, indices, count = _read_folder(path, source_fps, select)
    elif path.is_file():
        images, indices, count, source_fps, fps_source = _read_file(path, fps, default_fps, select)
    else:
        raise VideoReadError(f"cannot read video {str(path)!r}: no such file or folder")
    if count < min_frames:
        raise VideoReadError(f"cannot use video {str(path)!r}: it has {count} frame(s), at least {min_frames} needed")
    return VideoFrames(_stack(path, images), indices, source_fps, count, fps_source)


# --------------------------------------------------------------------------------------------
# heat maps with a fixed colour scale

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


# --------------------------------------------------------------------------------------------
# text: Pillow's default font (Aileron Regular, anti-aliased), scaled with the video

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
    """Integer scale of text next to an image of ``size`` pixels (its height)."""
    return max(1, size // 120)


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


def text_strip(text: str, width: int, scale: int) -> Tensor:
    """``[3, label_height(scale), width]``: one line of white ``text`` on black, left-aligned.

    A line too long for the width is drawn smaller (down to :data:`MIN_FONT_SIZE` pixels) on the
    same baseline; what still does not fit is cut at the right border.
    """
    margin, size = 2 * scale, FONT_SIZE * scale
    mask = text_mask(text, scale)
    while mask.shape[1] > width - 2 * margin and size > MIN_FONT_SIZE:
        size -= 1
        mask = _coverage(text, size)
    strip = torch.zeros(3, label_height(scale), width)
    baseline = scale + _ascent(FONT_SIZE * scale)
    return _blend(strip, mask, margin, baseline - _ascent(size), (1.0, 1.0, 1.0))


def colorbar(width: int, scale: int = 1, value_range: tuple[float, float] = MAP_RANGE, ticks: int = 5) -> Tensor:
    """Legend of :func:`colorize`: ``[3, h, width]`` (``h`` even), a grey ``N/A`` swatch (invalid
    pixels), then the colour bar over ``value_range`` with ``ticks`` labelled ticks; the last
    reads ``0.2+`` because larger values are clipped to its colour. Labels are as in a
    :func:`text_strip` under the bar."""
    margin, bar_h, tick_h = 2 * scale, 4 * scale, 2 * scale
    text_y = margin + bar_h + tick_h + scale  # the line's place in a text strip under the bar
    legend = torch.zeros(3, margin + bar_h + tick_h + label_height(scale), width)
    swatch_w = text_mask("N/A", scale).shape[1]
    legend[:, margin : margin + bar_h, margin : margin + swatch_w] = torch.tensor(INVALID_COLOR)[:, None, None]
    legend = draw_text(legend, "N/A", margin, text_y, scale)
    left = 2 * margin + swatch_w + 4 * scale
    right = width - margin - text_mask("0.2+", scale).shape[1] // 2  # room for the last label
    if right - left < 2:
        return legend
    low, high = value_range
    ramp = torch.linspace(low, high, right - left)
    legend[:, margin : margin + bar_h, left:right] = colorize(ramp[None])
    for k in range(ticks):
        value = low + (high - low) * k / (ticks - 1)
        x = left + round(k * (right - left - 1) / (ticks - 1))
        legend[:, margin + bar_h : margin + bar_h + tick_h, x : x + scale] = 1.0
        label = f"{value:g}" + ("+" if k == ticks - 1 else "")
        label_w = text_mask(label, scale).shape[1]
        legend = draw_text(legend, label, min(max(0, x - label_w // 2), width - label_w), text_y, scale)
    return legend


# --------------------------------------------------------------------------------------------
# labelled panels


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
    (:func:`text_strip`). Layout: :func:`panel_layout`.
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
    out = torch.zeros(num_frames, 3, total_h, total_w)
    for panel, label, (top, left, h, w) in zip(panels, labels, boxes):
        out[:, :, :top, left : left + w] = text_strip(label, w, scale)
        out[:, :, top : top + h, left : left + w] = panel
    return out
