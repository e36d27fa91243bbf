"""Recursive schedule R_t, step size and time-travel window."""

from __future__ import annotations

import pytest

from geco_guide.sampler.algorithm.schedule import GuidanceSchedule, paper_schedule, parse_repeats


def test_paper_schedule():
    s = paper_schedule(50)
    assert s.num_steps == 50
    assert s.repeats[:3] == (0, 0, 0)
    assert set(s.repeats[3:20]) == {3} and set(s.repeats[20:]) == {2}
    assert s.total_updates == 17 * 3 + 30 * 2
    assert s.step_size == 3.0
    assert [i for i in range(50) if s.time_travel_at(i)] == [15, 16, 17, 18, 19, 20]


def test_parse_repeats_forms():
    assert parse_repeats("0x2, 3x1,1") == [0, 0, 3, 1]
    assert parse_repeats([1, 0, 2]) == [1, 0, 2]
    for bad in ("", "ax2", "1x0", "-1x2", "1,,2"):
        with pytest.raises(ValueError, match="repeats"):
            parse_repeats(bad)


def test_schedule_length_must_match_step_count():
    with pytest.raises(ValueError, match="covers 50 steps but the sampler runs 30"):
        GuidanceSchedule.build("0x3,3x17,2x30", 30)


def test_negative_eta_and_bad_windows_are_rejected():
    with pytest.raises(ValueError, match="step_size must be >= 0"):
        GuidanceSchedule.build("1x4", 4, step_size=-0.5)
    with pytest.raises(ValueError, match="time_travel"):
        GuidanceSchedule.build("1x4", 4, time_travel=[3, 4])
    with pytest.raises(ValueError, match="time_travel"):
        GuidanceSchedule.build("1x4", 4, time_travel=[2, 1])
    with pytest.raises(ValueError, match="time_travel"):
        GuidanceSchedule.build("1x4", 4, time_travel=[1])
    s = GuidanceSchedule.build("1x4", 4, time_travel=[])
    assert s.time_travel is None and not any(s.time_travel_at(i) for i in range(4))
