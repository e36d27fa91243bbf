"""The names ``run.memory_plan`` takes, apart from the plans themselves (:mod:`.memory_plan`), so
that the run options check a name without importing the planner that reads them.

Ground floor of the sampler: imports nothing.
"""

from __future__ import annotations

__all__ = ["AUTO", "EXPLICIT", "NAMED_PLANS", "PLAN_NAMES"]

#: ``run.memory_plan`` that asks the planner for the plan that fits the memory budget.
AUTO = "auto"
#: ``run.memory_plan`` that takes the run options' own checkpointing flags.
EXPLICIT = "explicit"
#: The named plans, from the least recomputation (and the most memory) to the least memory.
NAMED_PLANS = ("fastest", "partial", "chunked", "checkpointed", "leanest")
#: Every name ``run.memory_plan`` takes.
PLAN_NAMES = (AUTO, EXPLICIT, *NAMED_PLANS)
