"""Video files: :func:`write_video` / :func:`read_video` (mp4 through imageio-ffmpeg, with a
:class:`SoundTrack` muxed in where the model made one; GIFs, which hold no sound, through
Pillow) and :func:`read_frames` (mp4 and other ffmpeg formats, gif, folders of png/jpg frames,
subsampled while decoding by a frame selector, e.g. the protocol's of
:mod:`geco_guide.metric.protocol`). A GIF is written frame for frame and read by its frame delays
(a frame held ``k`` times as long is ``k`` frames: :func:`gif_frame_repeats`), so a video that
holds a frame keeps its frame count. Unreadable inputs raise a one-line :class:`VideoReadError`.

Frames are float ``[S, 3, H, W]`` (or ``[S, H, W, 3]`` on input) in ``[0, 1]``, RGB. Writes are
atomic: the file is written under a temporary name in the same folder, checked (readable, every
frame there) and moved into place with ``os.replace``, so a reader never sees a half-written video.
"""

from __future__ import annotations

import logging
import math
import os
import re
import subprocess
import tempfile
import wave
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Any
from pathlib import Path

import numpy as np
import torch
from torch import Tensor

from .files import WriteError, atomic_path

__all__ = ["FPS_RANGE", "IMAGE_SUFFIXES", "VIDEO_SUFFIXES", "SoundTrack", "VideoFrames", "VideoReadError",
           "audio_stream", "check_fps", "frame_files", "gif_frame_repeats", "gif_rate", "input_stem", "read_frames",
           "read_image", "read_video", "write_video"]

logger = logging.getLogger(__name__)

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


#: Frame rates :func:`write_video` writes: an mp4 from one frame per 100 s to 1000 fps; a GIF
#: stores whole centiseconds per frame (at least 1, at most 65535), so at most 100 fps.
FPS_RANGE = {"mp4": (0.01, 1000.0), "gif": (0.01, 100.0)}


def check_fps(fps: float, suffix: str = ".mp4") -> None:
    """One-line ValueError unless ``fps`` lies in the :data:`FPS_RANGE` of the format of
    ``suffix`` (``.gif``, or anything else: mp4): ``inf`` or ``1e-300`` overflow the writers."""
    kind = "gif" if suffix.lower() == ".gif" else "mp4"
    low, high = FPS_RANGE[kind]
    if not low <= fps <= high:  # NaN fails too
        raise ValueError(f"fps must be in [{low:g}, {high:g}] for a {kind} video, got {fps}")


def _to_uint8_hwc(frames, even: bool = True) -> np.ndarray:
    """Frames -> ``[S, H, W, 3]`` uint8; with ``even``, odd sizes padded (yuv420p needs even)."""
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
        # A NaN frame would be written black (and scored as a real one): refuse it by its number.
        # (The metric's check_frame_values sits beside io on the ground floor: io cannot import it.)
        bad = np.flatnonzero(~np.isfinite(frames.reshape(frames.shape[0], -1)).all(axis=1))
        if bad.size:
            raise ValueError(f"frames must be finite: frame(s) {bad[:10].tolist()} hold NaN or inf values")
        out = (np.clip(frames.astype(np.float32), 0.0, 1.0) * 255.0 + 0.5).astype(np.uint8)
    # yuv420p needs even sizes: pad odd sizes by repeating the last row/column.
    pad_h, pad_w = out.shape[1] % 2, out.shape[2] % 2
    if even and (pad_h or pad_w):
        out = np.pad(out, ((0, 0), (0, pad_h), (0, pad_w), (0, 0)), mode="edge")
    return np.ascontiguousarray(out)


@dataclass(frozen=True)
class SoundTrack:
    """The sound a model made with its video (LTX-2's vocoder): ``samples`` float ``[C, N]`` in
    ``[-1, 1]`` (``C`` channels of ``N`` samples; louder is clipped when written), ``rate``
    samples per second."""

    samples: Tensor
    rate: int

    def __post_init__(self) -> None:
        shape = list(self.samples.shape)
        if self.samples.ndim != 2 or 0 in shape:
            raise ValueError(f"a sound track must be [channels, samples] with both >= 1, got shape {shape}")
        if isinstance(self.rate, bool) or not isinstance(self.rate, int) or self.rate < 1:
            raise ValueError(f"a sound track's rate must be whole samples per second >= 1, got {self.rate!r}")
        if not torch.isfinite(self.samples).all():
            raise ValueError("a sound track must be finite: its samples hold NaN or inf values")

    @property
    def seconds(self) -> float:
        return self.samples.shape[1] / self.rate

    def record(self, video: Path) -> dict[str, Any]:
        """What a sidecar says of it once written with ``video``: the file that holds it (the mp4;
        ``None`` for a GIF, which holds no sound), its rate, channels and length."""
        held = video.suffix.lower() != ".gif"
        return {"file": video.name if held else None, "sample_rate": self.rate,
                "channels": int(self.samples.shape[0]), "seconds": round(self.seconds, 6),
                **({} if held else {"not_written": "a GIF holds no sound: write an .mp4 to keep it"})}


def write_video(path: str | os.PathLike, frames, fps: float = 8, audio: SoundTrack | None = None) -> Path:
    """Write ``frames`` (``[S, 3, H, W]`` or ``[S, H, W, 3]``, float in [0, 1] or uint8) as an
    H.264 mp4 (yuv420p; an odd height/width is padded by one repeated row/column) with ``audio``
    as its AAC sound stream, or as a looping GIF when ``path`` ends in ``.gif`` (a GIF holds no
    sound: ``audio`` is left out, with a warning), atomically. Returns the path.

    The written file is checked before it takes its name: ffmpeg can fail while writing the
    trailer (a full disk) without the writer raising, which leaves an unreadable file.

    Raises:
        ValueError: ``fps`` outside :data:`FPS_RANGE`, frames of a wrong shape or holding NaN or
            inf; before anything is written.
        WriteError: one line naming ``path`` (disk full, ffmpeg failed, the file does not hold
            ``S`` readable frames, or lacks the sound stream); nothing is left under its name or
            as a temporary file.
    """
    path = Path(path)
    check_fps(fps, path.suffix)
    if path.suffix.lower() == ".gif":
        if audio is not None:
            logger.warning("warning: %s: a GIF holds no sound; the %.2f s sound track is not written (write an .mp4 "
                           "to keep it)", path, audio.seconds)
        return _write_gif(path, _to_uint8_hwc(frames, even=False), fps)
    data = _to_uint8_hwc(frames)
    with atomic_path(path) as tmp:
        if audio is None:
            _write_frames(tmp, data, fps)
        else:
            with tempfile.TemporaryDirectory(prefix="geco-sound-") as work:
                silent, sound = Path(work) / "video.mp4", Path(work) / "sound.wav"
                _write_frames(silent, data, fps)
                _write_wav(sound, audio)
                _mux(silent, sound, tmp, path)
        problem = _written_video_problem(tmp, len(data))
        if problem is None and audio is not None and audio_stream(tmp) is None:
            problem = "the written file holds no sound stream"
        if problem:
            raise WriteError(f"cannot write {str(path)!r}: {problem}")
    return path


def _write_frames(path: Path, data: np.ndarray, fps: float) -> None:
    """``data [S, H, W, 3]`` uint8 as an H.264 mp4 at ``path`` (no sound)."""
    import imageio.v2 as imageio

    writer = imageio.get_writer(
        path, format="FFMPEG", mode="I", fps=fps, codec="libx264", pixelformat="yuv420p",
        macro_block_size=1, quality=8, ffmpeg_log_level="error",
    )
    try:
        for frame in data:
            writer.append_data(frame)
    finally:
        writer.close()


def _write_wav(path: Path, audio: SoundTrack) -> None:
    """``audio`` as 16-bit PCM WAV (clipped to [-1, 1]): what ffmpeg reads to encode the sound."""
    pcm = (audio.samples.detach().float().cpu().clamp(-1.0, 1.0) * 32767.0).round().to(torch.int16)
    with wave.open(str(path), "wb") as file:
        file.setnchannels(pcm.shape[0])
        file.setsampwidth(2)
        file.setframerate(audio.rate)
        file.writeframes(pcm.T.contiguous().numpy().tobytes())  # interleaved: one sample of each channel in turn


def _mux(video: Path, sound: Path, out: Path, named: Path) -> None:
    """``video``'s stream copied and ``sound`` encoded as AAC into the mp4 ``out``; WriteError
    naming ``named`` (the path the caller asked for) when ffmpeg fails."""
    import imageio_ffmpeg

    command = [imageio_ffmpeg.get_ffmpeg_exe(), "-nostdin", "-v", "error", "-y", "-i", str(video), "-i", str(sound),
               "-map", "0:v:0", "-map", "1:a:0", "-c:v", "copy", "-c:a", "aac", "-b:a", "192k", str(out)]
    proc = subprocess.run(command, check=False, capture_output=True, text=True, errors="replace")
    if proc.returncode != 0:
        lines = [line.strip() for line in proc.stderr.splitlines() if line.strip()]
        raise WriteError(f"cannot write {str(named)!r}: muxing the sound failed "
                         f"({lines[-1] if lines else f'ffmpeg exit {proc.returncode}'})")


def audio_stream(path: str | os.PathLike) -> dict[str, Any] | None:
    """The first sound stream of the video at ``path``, as ffmpeg describes it: ``{"codec",
    "sample_rate", "channels"}`` (channels as ffmpeg names the layout: ``mono``, ``stereo``, ...),
    or ``None`` where it has none."""
    import imageio_ffmpeg

    command = [imageio_ffmpeg.get_ffmpeg_exe(), "-nostdin", "-hide_banner", "-i", str(path)]
    proc = subprocess.run(command, check=False, capture_output=True, text=True, errors="replace")
    found = re.search(r"Stream #\d+:\d+.*?: Audio: (\w+).*?, (\d+) Hz, ([^,]+),", proc.stderr)
    if found is None:
        return None
    return {"codec": found.group(1), "sample_rate": int(found.group(2)), "channels": found.group(3).strip()}


def _write_gif(path: Path, data: np.ndarray, fps: float) -> Path:
    """``data [S, H, W, 3]`` uint8 as a looping GIF at ``fps`` (whole centiseconds per frame, see
    :func:`gif_rate`), every frame written, atomically, checked to hold ``S`` readable frames.

    Every frame is its own GIF frame with its own palette, written with Pillow's frame encoder:
    Pillow's animated-GIF writer merges identical consecutive frames into one longer frame, so a
    still mask (or a video that holds a frame) would read back with fewer frames. The GIF is
    encoded in memory and then written as bytes, so a failed write (a full disk) is one error."""
    from PIL import GifImagePlugin, Image

    delay_ms = 1000.0 / fps
    frames = [Image.fromarray(frame).convert("P", palette=Image.Palette.ADAPTIVE) for frame in data]
    header, _ = GifImagePlugin.getheader(frames[0], info={"loop": 0, "duration": delay_ms})
    parts = [*header]
    for frame in frames:
        parts += GifImagePlugin.getdata(frame, duration=delay_ms, include_color_table=True)
    encoded = b"".join(bytes(part) for part in parts) + b";"
    with atomic_path(path) as tmp:
        tmp.write_bytes(encoded)
        problem = _written_gif_problem(tmp, len(data))
        if problem:
            raise WriteError(f"cannot write {str(path)!r}: {problem}")
    return path


def _written_gif_problem(path: Path, expected_frames: int) -> str | None:
    """Why the GIF at ``path`` is not a readable image sequence of ``expected_frames`` frames, or None."""
    from PIL import Image

    try:
        with Image.open(path) as image:
            written = image.n_frames
    except OSError as err:
        return f"the written file is not a readable GIF ({err})"
    if written != expected_frames:
        return f"the written file holds {written} frame(s), not {expected_frames}"
    return None


def _written_video_problem(path: Path, expected_frames: int) -> str | None:
    """Why the mp4 at ``path`` is not a readable video of ``expected_frames`` frames, or None.

    ffmpeg counts its packets without decoding (``-c copy``), cheap whatever the video's size,
    and fails on a file without its index (``moov atom not found``), as a truncated one is.
    """
    import imageio_ffmpeg

    command = [imageio_ffmpeg.get_ffmpeg_exe(), "-nostdin", "-v", "error", "-i", str(path), "-map", "0:v:0",
               "-c", "copy", "-f", "null", "-", "-progress", "pipe:1", "-nostats"]
    proc = subprocess.run(command, check=False, capture_output=True, text=True, errors="replace")
    if proc.returncode != 0:
        lines = [line.strip() for line in proc.stderr.splitlines() if line.strip()]
        return f"the written file is not a readable video ({lines[0] if lines else f'ffmpeg exit {proc.returncode}'})"
    counts = re.findall(r"^frame=(\d+)$", proc.stdout, flags=re.MULTILINE)
    written = int(counts[-1]) if counts else 0
    if written != expected_frames:
        return f"the written file holds {written} frame(s), not {expected_frames}"
    return None


def read_video(path: str | os.PathLike) -> tuple[torch.Tensor, float]:
    """Read a video file (mp4 and the like through ffmpeg, or a GIF, by its frame delays: see
    :func:`gif_frame_repeats`) -> ``(frames float [S, 3, H, W] in [0, 1], fps)``; fps 0.0 where
    the file states none.

    Raises:
        FileNotFoundError: no such file.
        VideoReadError: the file is not a readable video (corrupt, truncated, empty).
    """
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"video file {str(path)!r} does not exist")
    if path.suffix.lower() == ".gif":
        images, _, _, fps, fps_source = _read_gif(path, None, 0.0, None)
        return torch.stack(images), fps if fps_source == "file" else 0.0
    try:
        reader = _open_reader(path)
        try:
            fps = _file_fps(reader.get_meta_data()) or 0.0
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


def input_stem(path: str | os.PathLike) -> str:
    """The name outputs of a video input are given: a file's stem, a folder's own name (``.``
    and ``..`` named after the folder they stand for, not the hidden ``.<suffix>``)."""
    path = Path(path)
    if path.suffix and not path.is_dir():
        return path.stem
    return path.name if path.name not in ("", "..") else path.resolve().name or "root"


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


def read_image(path: str | os.PathLike) -> Any:
    """The conditioning image of an image-to-video call (``--image``): a PNG or JPEG as an RGB
    ``PIL.Image``; VideoReadError (one line) for a missing, unreadable or other kind of file."""
    from PIL import Image, UnidentifiedImageError

    path = Path(path)
    if path.suffix.lower() not in IMAGE_SUFFIXES:
        raise VideoReadError(f"--image {str(path)!r} must be a {'/'.join(IMAGE_SUFFIXES)} file")
    if not path.is_file():
        raise VideoReadError(f"--image {str(path)!r}: no such file")
    try:
        with Image.open(path) as image:
            return image.convert("RGB")
    except (OSError, UnidentifiedImageError) as err:
        raise VideoReadError(f"cannot read --image {str(path)!r}: {_error_reason(err)}") from None


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


def _file_fps(meta: dict) -> float | None:
    """Frame rate from imageio's ffmpeg metadata, or None where the file states none."""
    fps = meta.get("fps")
    return float(fps) if fps and math.isfinite(fps) and fps > 0 else None


def gif_frame_repeats(delays_ms: Sequence[float]) -> tuple[list[int], float | None]:
    """How many video frames each GIF frame stands for, and the video's rate, from the frames'
    delays in milliseconds.

    GIF writers merge identical consecutive frames into one frame shown for their summed delay
    (Pillow's animated writer does), so a frame held ``k`` times as long as the usual one is ``k``
    frames of the video: the usual delay is the most common one (the shortest of equally common
    ones), and each frame counts ``round(delay / usual)`` frames, at least one. The rate is
    :func:`gif_rate` of the usual delay. Delays of 0 (no timing) count one frame each; a GIF
    without any timing has no rate (``None``).
    """
    timed = [d for d in delays_ms if d > 0]
    if not timed:
        return [1] * len(delays_ms), None
    counts: dict[float, int] = {}
    for delay in timed:
        counts[delay] = counts.get(delay, 0) + 1
    usual = min(counts, key=lambda d: (-counts[d], d))
    return [max(1, round(d / usual)) if d > 0 else 1 for d in delays_ms], gif_rate(usual)


def _read_gif(path: Path, fps: float | None, default_fps: float,
              select: FrameSelector | None) -> tuple[list[Tensor], list[int], int, float, str]:
    """Decode the selected frames of a GIF, its frames counted by their delays
    (:func:`gif_frame_repeats`): one pass reads the delays, a second decodes the frames kept."""
    from PIL import Image, ImageSequence

    try:
        with Image.open(path) as image:
            delays = [float(frame.info.get("duration") or 0) for frame in ImageSequence.Iterator(image)]
            repeats, file_fps = gif_frame_repeats(delays)
            count = sum(repeats)
            source_fps = float(fps or file_fps or default_fps)
            fps_source = "caller" if fps else "file" if file_fps else "default"
            indices = _selection(select, count, source_fps, path) if count >= 2 else [0]
            owner = np.repeat(np.arange(len(repeats)), repeats)  # video frame -> GIF frame
            arrays = {}
            for k in sorted({int(owner[i]) for i in indices}):
                image.seek(k)
                arrays[k] = np.asarray(image.convert("RGB"))
    except (OSError, ValueError, EOFError) as err:  # Pillow's errors for a damaged GIF
        raise VideoReadError(f"cannot read video {str(path)!r}: {_error_reason(err)}") from err
    return [_to_float_chw(arrays[int(owner[i])]) for i in indices], indices, count, source_fps, fps_source


def _open_reader(path: Path):
    import imageio.v2 as imageio

    return imageio.get_reader(path, format="FFMPEG")


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
            file_fps = _file_fps(reader.get_meta_data())
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
    elif path.is_file() and path.suffix.lower() == ".gif":
        images, indices, count, source_fps, fps_source = _read_gif(path, fps, default_fps, select)
    elif path.is_file():
        images, indices, count, source_fps, fps_source = _read_file(path, fps, default_fps, select)
    else:
        raise VideoReadError(f"cannot read video {str(path)!r}: no such file or folder")
    if count < min_frames:
        raise VideoReadError(f"cannot use video {str(path)!r}: it has {count} frame(s), at least {min_frames} needed")
    return VideoFrames(_stack(path, images), indices, source_fps, count, fps_source)
# --------------------------------------------------------------------------------------------
# text: Pillow's default font (Aileron Regular, anti-aliased), scaled with the video
