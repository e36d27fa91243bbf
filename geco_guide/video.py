"""Read and write video files (mp4 through imageio-ffmpeg).

Frames are float ``[S, 3, H, W]`` (or ``[S, H, W, 3]`` on input) in ``[0, 1]``, RGB. Writes are
atomic: the file is written under a temporary name in the same folder and moved into place with
``os.replace``, so a reader never sees a half-written video.
"""

from __future__ import annotations

import os
import tempfile
from pathlib import Path

import numpy as np
import torch


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


def _umask() -> int:
    mask = os.umask(0)
    os.umask(mask)
    return mask


def write_video(path: str | os.PathLike, frames, fps: float = 8) -> Path:
    """Write ``frames`` (``[S, 3, H, W]`` or ``[S, H, W, 3]``, float in [0, 1] or uint8) as an
    H.264 mp4 (yuv420p; an odd height/width is padded by one repeated row/column), atomically.
    Returns the path."""
    import imageio.v2 as imageio

    if not fps > 0:
        raise ValueError(f"fps must be > 0, got {fps}")
    path = Path(path)
    data = _to_uint8_hwc(frames)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.stem}.", suffix=path.suffix or ".mp4", dir=path.parent)
    os.close(fd)
    try:
        writer = imageio.get_writer(
            tmp, format="FFMPEG", mode="I", fps=fps, codec="libx264", pixelformat="yuv420p",
            macro_block_size=1, quality=8, ffmpeg_log_level="error",
        )
        try:
            for frame in data:
                writer.append_data(frame)
        finally:
            writer.close()
        os.chmod(tmp, 0o666 & ~_umask())  # mkstemp makes 0600 files
        os.replace(tmp, path)
    except BaseException:
        if os.path.exists(tmp):
            os.unlink(tmp)
        raise
    return path


def read_video(path: str | os.PathLike) -> tuple[torch.Tensor, float]:
    """Read a video file -> ``(frames float [S, 3, H, W] in [0, 1], fps)``.

    Raises:
        FileNotFoundError: no such file.
        ValueError: the file is not a readable video (corrupt, truncated, empty).
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
        lines = [line.strip() for line in str(err).splitlines() if line.strip()]
        reason = lines[0] if lines else type(err).__name__
        if len(lines) > 1:
            reason += f" ({lines[-1]})"
        raise ValueError(f"cannot read video {str(path)!r}: {reason}") from err
    if not frames:
        raise ValueError(f"cannot read video {str(path)!r}: it holds no frames")
    video = torch.from_numpy(np.stack(frames)[..., :3]).permute(0, 3, 1, 2).float() / 255.0
    return video.contiguous(), fps
