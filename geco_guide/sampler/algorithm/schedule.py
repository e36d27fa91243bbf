"""The guidance schedule: recursive repeats R_t, the step size and the time-travel window.

Steps are 0-based indices into the sampler's timestep table (step 0 is the noisiest). The
repeat schedule is written compactly as comma-separated ``RxN`` runs ("R repeats for N steps"),
so the paper's schedule (R = 0 for steps 0-2, 3 for 3-19, 2 for 20-49) is ``"0x3,3x17,2x30"``;
a plain ``R`` counts as one step, and an explicit list of per-step ints is accepted too.

Other step counts (:func:`scale_schedule`): a schedule written as runs (``"0x3,3x17,2x30"``) is a
list of phases, and for a sampler with another number of steps each phase boundary ``b`` of the
``N`` steps it was written for moves to ``round(b * M / N)`` (half up) of the ``M`` steps, phases
that shrink to nothing disappear, and the time-travel window ``[first, last]`` (the steps
``[first, last + 1)``) scales the same way, keeping at least one step; a warning names the result.
The paper's 50-step schedule at 25 steps is ``"0x2,3x8,2x15"`` with time travel ``[8, 10]``. A
schedule given per step (a list of ints, or a string without runs such as ``"0,2,2,1"``) is kept
exactly and must match the step count.
"""

from __future__ import annotations

import math
import warnings
from collections.abc import Sequence
from dataclasses import dataclass

__all__ = ["PAPER_STEP_SIZE", "PAPER_REPEATS", "PAPER_TIME_TRAVEL", "GuidanceSchedule", "ScheduleScaledWarning",
           "paper_schedule", "parse_repeats", "scale_schedule"]


class ScheduleScaledWarning(UserWarning):
    """A schedule written for another step count was scaled (the message names the result)."""


# One config is often checked more than once before a run (config, then pipeline): say it once.
warnings.filterwarnings("once", category=ScheduleScaledWarning)

#: The paper's denoising steps, the count its schedule is written for.
PAPER_STEPS = 50
PAPER_REPEATS = "0x3,3x17,2x30"
PAPER_STEP_SIZE = 3.0
PAPER_TIME_TRAVEL = (15, 20)


def parse_repeats(spec: str | Sequence[int]) -> list[int]:
    """Expand a repeat schedule into one ``R_t`` per step.

    Args:
        spec: ``"0x3,3x17,2x30"`` (runs of ``R x count``), ``"1,2,2"`` or a sequence of ints.

    Raises:
        ValueError: malformed spec or negative values.
    """
    if isinstance(spec, str):
        repeats: list[int] = []
        for part in spec.replace(" ", "").split(","):
            if not part:
                raise ValueError(f"repeats {spec!r}: empty entry (write runs like '0x3,3x17,2x30')")
            value, _, count = part.partition("x")
            try:
                r, n = int(value), int(count) if count else 1
            except ValueError:
                raise ValueError(f"repeats {spec!r}: cannot read {part!r} (write runs like '0x3,3x17,2x30')") from None
            if r < 0 or n < 1:
                raise ValueError(f"repeats {spec!r}: {part!r} needs R >= 0 and a count >= 1")
            repeats.extend([r] * n)
        return repeats
    repeats = [int(r) for r in spec]
    if any(r < 0 for r in repeats):
        raise ValueError(f"repeats must be >= 0, got {repeats}")
    return repeats


def _runs(spec: str) -> list[tuple[int, int]]:
    runs = []
    for part in spec.replace(" ", "").split(","):
        value, _, count = part.partition("x")
        runs.append((int(value), int(count) if count else 1))
    return runs


def scale_schedule(
    repeats: str | Sequence[int], time_travel: Sequence[int] | None, num_steps: int
) -> tuple[str | Sequence[int], Sequence[int] | None]:
    """``(repeats, time_travel)`` for ``num_steps`` steps: runs scaled in proportion (module docstring).

    Per-step schedules, schedules that already cover ``num_steps`` and malformed ones come back
    unchanged (:meth:`GuidanceSchedule.build` then accepts or rejects them). Warns when it scales.
    """
    if not isinstance(repeats, str) or "x" not in repeats or num_steps < 1:
        return repeats, time_travel
    parse_repeats(repeats)  # malformed specs raise here, with their message
    runs = _runs(repeats)
    total = sum(n for _, n in runs)
    if total == num_steps:
        return repeats, time_travel

    def at(boundary: int) -> int:
        return int(math.floor(boundary * num_steps / total + 0.5))

    scaled, start, end = [], 0, 0
    for r, n in runs:
        end += n
        count = at(end) - at(start)
        if count > 0:
            if scaled and scaled[-1][0] == r:
                scaled[-1] = (r, scaled[-1][1] + count)
            else:
                scaled.append((r, count))
        start = end
    new_repeats = ",".join(f"{r}x{n}" for r, n in scaled)
    new_window = time_travel
    if time_travel is not None and len(time_travel) == 2:
        first, last = (int(x) for x in time_travel)
        if 0 <= first <= last < total:  # (an invalid window is left for build() to reject)
            new_first = min(at(first), num_steps - 1)
            new_window = [new_first, max(new_first, min(at(last + 1) - 1, num_steps - 1))]
    warnings.warn(
        f"guidance schedule written for {total} steps, the sampler runs {num_steps}: repeats {repeats!r} -> "
        f"{new_repeats!r}, time_travel {list(time_travel) if time_travel else None} -> "
        f"{list(new_window) if new_window else None} (phases scaled in proportion; give one R_t per step to set "
        "them exactly)",
        ScheduleScaledWarning,
        stacklevel=3,
    )
    return new_repeats, new_window


@dataclass(frozen=True)
class GuidanceSchedule:
    """What guidance does at each denoising step.

    Attributes:
        repeats: ``R_t`` per step (number of guided updates at that step).
        step_size: normalised step size of every update (the paper's eta).
        time_travel: inclusive ``(first, last)`` step window of time travel, or ``None``.
    """

    repeats: tuple[int, ...]
    step_size: float = PAPER_STEP_SIZE
    time_travel: tuple[int, int] | None = PAPER_TIME_TRAVEL

    @classmethod
    def build(
        cls,
        repeats: str | Sequence[int],
        num_steps: int,
        step_size: float = PAPER_STEP_SIZE,
        time_travel: Sequence[int] | None = PAPER_TIME_TRAVEL,
    ) -> "GuidanceSchedule":
        """Parse and validate a schedule for ``num_steps`` denoising steps.

        Raises:
            ValueError: a length that does not match ``num_steps``, negative ``step_size``, or a
                time-travel window that is not ``[first, last]`` inside the steps.
        """
        if num_steps < 1:
            raise ValueError(f"num_inference_steps must be >= 1, got {num_steps}")
        per_step = parse_repeats(repeats)
        if len(per_step) != num_steps:
            raise ValueError(
                f"guidance repeats schedule {repeats!r} covers {len(per_step)} steps but the sampler runs "
                f"{num_steps} steps (num_inference_steps); give one R_t per step"
            )
        step_size = float(step_size)
        if not step_size >= 0.0:  # also rejects NaN
            raise ValueError(f"guidance step_size must be >= 0, got {step_size}")
        window = None
        if time_travel is not None and len(time_travel) > 0:
            if len(time_travel) != 2:
                raise ValueError(f"time_travel must be [first_step, last_step] or empty, got {list(time_travel)}")
            first, last = (int(s) for s in time_travel)
            if not 0 <= first <= last < num_steps:
                raise ValueError(
                    f"time_travel window [{first}, {last}] must satisfy 0 <= first <= last < {num_steps} (the step count)"
                )
            window = (first, last)
        return cls(repeats=tuple(per_step), step_size=step_size, time_travel=window)

    @property
    def num_steps(self) -> int:
        return len(self.repeats)

    def repeats_at(self, step: int) -> int:
        return self.repeats[step]

    def time_travel_at(self, step: int) -> bool:
        return self.time_travel is not None and self.time_travel[0] <= step <= self.time_travel[1]

    @property
    def total_updates(self) -> int:
        return sum(self.repeats)


def paper_schedule(num_steps: int = 50) -> GuidanceSchedule:
    """The GeCo paper's schedule for 50 DDIM steps."""
    return GuidanceSchedule.build(PAPER_REPEATS, num_steps, PAPER_STEP_SIZE, PAPER_TIME_TRAVEL)
