"""A video's sound track (LTX-2's): muxed into the mp4 as an AAC stream beside the copied video
stream, atomically; a GIF, which holds no sound, says so; a bad track is refused before anything
is written."""

from __future__ import annotations

import logging
import math
import subprocess

import imageio_ffmpeg
import numpy as np
import pytest
import torch

from geco_guide.io import video as video_io
from geco_guide.io.files import WriteError
from geco_guide.io.video import SoundTrack, audio_stream, read_video, write_video

RATE = 16000


def tone(seconds: float = 1.0, hz: tuple[float, float] = (440.0, 220.0)) -> SoundTrack:
    """A stereo sine of ``hz`` per channel at half scale: ``[2, RATE * seconds]``."""
    t = torch.arange(int(RATE * seconds)) / RATE
    return SoundTrack(torch.stack([0.5 * torch.sin(2 * math.pi * f * t) for f in hz]), RATE)


def frames() -> torch.Tensor:
    return torch.rand(8, 3, 32, 48, generator=torch.Generator().manual_seed(0))


def decoded_sound(path) -> np.ndarray:
    """The mp4's sound stream decoded by ffmpeg: float ``[N, C]`` at the stream's rate."""
    command = [imageio_ffmpeg.get_ffmpeg_exe(), "-nostdin", "-v", "error", "-i", str(path), "-map", "0:a:0",
               "-f", "f32le", "-"]
    raw = subprocess.run(command, check=True, capture_output=True).stdout
    return np.frombuffer(raw, dtype=np.float32).reshape(-1, 2)


@pytest.mark.slow
def test_the_sound_is_an_aac_stream_of_the_mp4_and_the_video_stream_is_unchanged(tmp_path):
    sound = tone()
    with_sound = write_video(tmp_path / "with.mp4", frames(), fps=8, audio=sound)
    without = write_video(tmp_path / "without.mp4", frames(), fps=8)
    assert audio_stream(with_sound) == {"codec": "aac", "sample_rate": RATE, "channels": "stereo"}
    assert audio_stream(without) is None
    assert torch.equal(read_video(with_sound)[0], read_video(without)[0])
    # the decoded sound is the tone (AAC is lossy: compared by correlation over the whole second)
    decoded = decoded_sound(with_sound)
    assert abs(len(decoded) - RATE) < 2048  # AAC frames are 1024 samples
    n = min(len(decoded), RATE)
    for channel in range(2):
        sent = sound.samples[channel, :n].numpy()
        assert np.corrcoef(sent, decoded[:n, channel])[0, 1] > 0.95
    assert sorted(p.name for p in tmp_path.iterdir()) == ["with.mp4", "without.mp4"]


def test_the_record_says_where_the_sound_went(tmp_path):
    sound = tone(0.5)
    assert sound.record(tmp_path / "a.mp4") == {"file": "a.mp4", "sample_rate": RATE, "channels": 2, "seconds": 0.5}
    gif = sound.record(tmp_path / "a.gif")
    assert gif["file"] is None and "GIF holds no sound" in gif["not_written"]


def test_a_gif_holds_no_sound_and_says_so(tmp_path, caplog):
    with caplog.at_level(logging.WARNING, logger="geco_guide.io.video"):
        path = write_video(tmp_path / "v.gif", frames(), fps=8, audio=tone(0.25))
    assert read_video(path)[0].shape[0] == 8
    assert [r.getMessage() for r in caplog.records] == [
        f"warning: {path}: a GIF holds no sound; the 0.25 s sound track is not written (write an .mp4 to keep it)"]


@pytest.mark.parametrize("samples, match", [
    (torch.zeros(2), r"\[channels, samples\].*\[2\]"),
    (torch.zeros(2, 0), r"\[channels, samples\].*\[2, 0\]"),
    (torch.tensor([[0.0, float("nan")]]), "NaN or inf"),
])
def test_a_bad_sound_track_is_refused_in_one_line(samples, match):
    with pytest.raises(ValueError, match=match) as err:
        SoundTrack(samples, RATE)
    assert "\n" not in str(err.value)


@pytest.mark.parametrize("rate", [0, 16000.0, True])
def test_a_sound_track_rate_is_whole_samples_per_second(rate):
    with pytest.raises(ValueError, match="whole samples per second"):
        SoundTrack(torch.zeros(1, 4), rate)


def test_a_failed_mux_leaves_nothing(tmp_path, monkeypatch):
    # a sound file ffmpeg cannot read: the mux fails, one line names the path, nothing is left
    monkeypatch.setattr(video_io, "_write_wav", lambda path, audio: path.write_bytes(b"not a wav file"))
    target = tmp_path / "v.mp4"
    with pytest.raises(WriteError, match=rf"^cannot write '{target}': muxing the sound failed \(.+\)$"):
        write_video(target, frames(), fps=8, audio=tone(0.25))
    assert list(tmp_path.iterdir()) == []
