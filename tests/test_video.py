"""Video files: mp4 round trip through imageio-ffmpeg, atomic writes, clear errors."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import torch

from geco_guide.video import read_video, write_video


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
