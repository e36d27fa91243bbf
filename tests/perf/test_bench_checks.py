"""The checks of ``geco bench``'s options that argparse cannot make alone: one BadOption line each."""

from __future__ import annotations

import pytest

from geco_guide.families import DEFAULT_MODEL
from geco_guide.perf.bench_checks import BadOption, check_frames, check_sides, check_torch_device


def test_frames_the_default_models_vae_cannot_make_are_one_line():
    check_frames(49, guided=True, model=DEFAULT_MODEL)
    with pytest.raises(BadOption, match="^--frames"):
        check_frames(10, guided=False, model=DEFAULT_MODEL)


def test_sides_must_be_multiples():
    check_sides(480, None, 16)
    with pytest.raises(BadOption, match="--width must be a multiple of 16, got 50"):
        check_sides(None, 50, 16)


def test_a_device_that_is_not_one_is_named():
    with pytest.raises(BadOption, match="--device 'nonsense' is not a torch device"):
        check_torch_device("nonsense")
