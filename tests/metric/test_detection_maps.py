"""Per-frame detection maps and their writers refuse bad frames and frame rates up front."""

from __future__ import annotations

import pytest
import torch

from geco_guide.metric.detection import detection_maps, write_detection
from geco_guide.types import NonFiniteFramesError


def test_a_nan_frame_is_an_error_as_in_evaluate_video():
    frames = torch.rand(4, 3, 16, 16)
    frames[2, 1, 3, 3] = float("nan")
    # The check runs before any estimator is used: these stand-ins would fail if called.
    with pytest.raises(NonFiniteFramesError, match=r"frame\(s\) \[2\]"):
        detection_maps(frames, object(), object())


@pytest.mark.parametrize("fps", [1e-300, float("inf"), 500.0])
def test_gif_frame_rates_outside_the_range_are_refused_before_writing(tmp_path, fps):
    with pytest.raises(ValueError, match=r"fps must be in \[0.01, 100\] for a gif"):
        write_detection(torch.rand(3, 3, 8, 8), tmp_path / "clip", ["png", "gif"], fps)
    assert list(tmp_path.iterdir()) == []  # not even the png frames


def test_detection_gifs_are_written_by_the_video_writer(tmp_path):
    (path,) = write_detection(torch.rand(3, 3, 9, 11), tmp_path / "clip", ["gif"], 10.0)
    assert path.name == "clip.detection.gif" and path.read_bytes()[:6] in (b"GIF89a", b"GIF87a")
