"""Quoted tables held to what their commands print on this machine: the same rows and columns,
every text cell equal, every number within what CPUs' float32 kernels move."""

from __future__ import annotations

import re

#: How far a quoted number may lie from the one printed here. float32 kernels differ between CPUs
#: (AVX2 / AVX-512, their reductions' order), and a detection ranks pixels by their residuals: where
#: a cue sees the defect, last bits move a printed digit or two (measured, an AMD EPYC against the
#: page's machine: M_struct's Task 2 AP 12.80 / 12.77, F1 33.08 / 33.11, SRCC -0.455 / -0.459;
#: a drawn mover's deformation 3.221 / 3.220); a
#: number may differ by this fraction of itself, or by :data:`LAST_DIGITS` units of its last
#: printed digit, whichever is more.
RELATIVE_TOLERANCE = 2.5e-3
LAST_DIGITS = 5
#: Where a cue cannot see the defect (M_motion on occlusions, every cue of the 3D scene on adjacent
#: pairs) its residuals there are float32 noise, and their ranks differ between CPUs (measured:
#: AP 3.65 / 2.61, F1 11.24 / 8.60). A detection percentage (Tasks 2 and 3) under this on both
#: sides reads "sees nothing", whatever its digits.
NEAR_CHANCE = 15.0
NUMBER = re.compile(r"-?\d+(\.\d+)?")


def _close(a: str, b: str, header: str) -> bool:
    """Whether cells ``a`` and ``b`` of the column ``header`` read the same (see above)."""
    if a == b:
        return True
    if not (NUMBER.fullmatch(a) and NUMBER.fullmatch(b)):
        return False
    x, y = float(a), float(b)
    if "(%)" in header and not header.startswith("Task 1") and max(x, y) < NEAR_CHANCE:
        return True
    allowed = max(RELATIVE_TOLERANCE * max(abs(x), abs(y)), LAST_DIGITS * 10.0 ** -len(b.partition(".")[2]))
    return abs(x - y) <= allowed * (1 + 1e-9)


def same_table(printed: str, documented: str) -> bool:
    """Whether two markdown tables read the same: the same rows and columns, every text cell
    equal, every number as close to the other as :data:`RELATIVE_TOLERANCE`, :data:`LAST_DIGITS`
    and :data:`NEAR_CHANCE` allow."""
    rows_a, rows_b = [r.split("|") for r in printed.splitlines()], [r.split("|") for r in documented.splitlines()]
    if len(rows_a) != len(rows_b) or any(len(a) != len(b) for a, b in zip(rows_a, rows_b)):
        return False
    headers = [cell.strip() for cell in rows_b[0]]
    return all(_close(a.strip(), b.strip(), header)
               for row_a, row_b in zip(rows_a, rows_b) for a, b, header in zip(row_a, row_b, headers))
