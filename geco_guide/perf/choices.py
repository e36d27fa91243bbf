"""The vocabularies of the perf harness's options, without torch: what ``geco bench``'s parser
offers, so that ``geco bench --help`` and a mistyped option answer at once."""

from __future__ import annotations

__all__ = ["NOMINAL_STEPS", "RSS_EXACT_MMAP_THRESHOLD", "SAMPLING_MODES"]

#: The paper's step count: what ``sampling`` extrapolates to and the tiny preset's paper schedule.
NOMINAL_STEPS = 50
#: faithful: backpropagate through the denoiser (the paper); fast: its output held constant;
#: unguided: no guidance.
SAMPLING_MODES = ("faithful", "fast", "unguided")
#: ``--rss-exact``: allocations from 64 KiB up are mapped on their own and unmapped when freed.
RSS_EXACT_MMAP_THRESHOLD = 64 * 1024
