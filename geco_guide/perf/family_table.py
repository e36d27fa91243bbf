"""The per-family cost table (``geco bench cost --all-models``): every traced registry model on an
H200 and on a 24 GB card, unguided, guided (fast, faithful, the tiny decoder), searched at the
particles that match guidance's time, and on 4 GPUs (faithful with ``run.devices`` and split CFG,
faithful with context parallelism, a search), from the shipped estimates (predicted;
the cost model's traces, ``geco bench plans`` and ``geco bench attention-shapes``)."""

from __future__ import annotations

from typing import Any

from ..families.published import LEFT_OUT, traced_models
from ..sampler.running.memory_plan import DEVICE_HEADROOM, load_estimates
from .cards import MEASURED_RUNS, card_memory_gib
from .parallel_cost import parallel_guidance
from .search_cost import guidance_cost, matched_particles, search_cost

__all__ = ["SEARCH_GPUS", "SEARCH_PARTICLES", "TABLE_CARDS", "family_rows", "family_table"]

#: The cards of the table: the H200 the cost model is calibrated on, and a 24 GB card.
TABLE_CARDS = ("H200", "RTX4090")
#: The several-GPU columns: this many cards, and a search of this many particles on them.
SEARCH_GPUS, SEARCH_PARTICLES = 4, 4


def _seconds(seconds: float) -> str:
    return f"{seconds:.0f} s" if seconds >= 10 else f"{seconds:.2g} s"


def _guided(cost: dict[str, Any], table: dict[str, Any] | None) -> str:
    if cost["plan"] is None:
        if table is None:
            return "no tiny decoder"
        least = min(estimate["offload_peak_gb"] for estimate in table.values())
        return f"does not fit ({least:.1f} GiB at least, with offload)"
    plan = cost["plan"] + (" + offload" if cost["offload"] else "")
    return f"{_seconds(cost['time_s'])}, {cost['peak_gb']:.1f} GiB ({plan})"


def _unguided(entry: dict[str, Any], gpu: str) -> str:
    unguided, budget = entry["unguided"], DEVICE_HEADROOM * card_memory_gib(gpu)
    seconds = _seconds(unguided["time_s"][gpu])
    if unguided["peak_gb"] <= budget:
        return f"{seconds}, {unguided['peak_gb']:.1f} GiB"
    if unguided["offload_peak_gb"] <= budget:
        return f"{seconds}, {unguided['offload_peak_gb']:.1f} GiB (offload)"
    return f"does not fit ({unguided['offload_peak_gb']:.1f} GiB with offload)"


def _search(costs: list[dict[str, Any]], unguided_s: float) -> str:
    """A search's cell: its time and ratio, a range over ``costs`` (the H200's measured estimator rates of each run)."""
    cost = costs[-1]
    if cost["peak_gb"] is None:
        return f"K={cost['particles']}: does not fit"
    offload = " + offload" if cost["offload"] else ""
    low, high = min(c["time_s"] for c in costs), max(c["time_s"] for c in costs)
    seconds = _seconds(high) if f"{low:.0f}" == f"{high:.0f}" else f"{low:.0f}-{_seconds(high)}"
    ratios = f"{low / unguided_s:.2f}" if f"{low / unguided_s:.2f}" == f"{high / unguided_s:.2f}" else (
        f"{low / unguided_s:.2f}-{high / unguided_s:.2f}")
    return f"K={cost['particles']}: {seconds} ({ratios}x), {cost['peak_gb']:.1f} GiB{offload}"


def _parallel(cost: dict[str, Any], unguided_s: float, composed: dict[str, Any] | None = None) -> str:
    """A cell of :func:`~.parallel_cost.parallel_guidance`: time, ratio to one-GPU unguided, peak per
    GPU, layout; then, if given and other, the time of the ``composed`` run (ring or split CFG, not run)."""
    if cost["plan"] is None:
        text = cost["reason"]
    else:
        layout = [cost["plan"]] + ["offload"] * cost["offload"] + ["split CFG"] * cost["split_cfg"]
        if cost["context_parallel"] > 1:
            layout.append(f"{cost['backend']} over {cost['context_parallel']}")
        text = (f"{_seconds(cost['time_s'])} ({cost['time_s'] / unguided_s:.2f}x), {cost['peak_gb']:.1f} GiB "
                f"({', '.join(layout)})")
    if composed is None or composed["plan"] is None or composed["time_s"] == cost.get("time_s"):
        return text
    layout = f", {'split CFG, ' * composed['split_cfg']}{composed['backend']} over {composed['context_parallel']}"
    return f"{text}; composed: {_seconds(composed['time_s'])} ({composed['time_s'] / unguided_s:.2f}x{layout})"


def family_rows(estimates: dict[str, Any] | None = None) -> list[dict[str, str]]:
    """One row per traced model and card of :data:`TABLE_CARDS`: each column's cell as the table
    prints it (predicted time, peak memory per card, the plan; or why it does not fit). The search
    on 4 H200s is a range: the estimators at the rates of each measured H200 run."""
    estimates = load_estimates() if estimates is None else estimates
    rows = []
    for name in (name for name in traced_models() if name in estimates["models"]):
        entry = estimates["models"][name]
        for gpu in TABLE_CARDS:
            unguided_s = entry["unguided"]["time_s"][gpu]
            faithful = guidance_cost(name, gpu, "faithful", estimates=estimates)
            matched = matched_particles(name, gpu, estimates=estimates)
            runs = MEASURED_RUNS if gpu == "H200" else ("fast",)  # the measured estimator rates: the H200's
            several = [search_cost(name, SEARCH_PARTICLES, gpu, SEARCH_GPUS, estimates=estimates, measured=run)
                       for run in runs]
            rows.append({
                "model": name, "card": f"{gpu} ({card_memory_gib(gpu):.0f} GiB)",
                "unguided": _unguided(entry, gpu),
                "fast": _guided(guidance_cost(name, gpu, "fast", estimates=estimates), entry["estimates"]["fast/vae"]),
                "faithful": _guided(faithful, entry["estimates"]["faithful/vae"]),
                "tiny": _guided(guidance_cost(name, gpu, "faithful", "tiny", estimates=estimates),
                                entry["estimates"].get("faithful/tiny")),
                "search": "-" if matched is None else _search([search_cost(name, matched, gpu, estimates=estimates)],
                                                               unguided_s),
                "gpus": _parallel(parallel_guidance(name, gpu, SEARCH_GPUS, context_parallel=False,
                                                    estimates=estimates), unguided_s),
                "cp": _parallel(parallel_guidance(name, gpu, SEARCH_GPUS, estimates=estimates), unguided_s,
                                parallel_guidance(name, gpu, SEARCH_GPUS, compose=True, estimates=estimates)),
                "search_gpus": _search(several, unguided_s),
            })
    return rows


#: The table's columns: (key of :func:`family_rows`, header).
COLUMNS = (("model", "model"), ("card", "card"), ("unguided", "unguided"), ("fast", "fast"),
           ("faithful", "faithful"), ("tiny", "faithful, tiny decoder"),
           ("search", "search, K matched to faithful"),
           ("gpus", f"faithful on {SEARCH_GPUS} GPUs: run.devices (x unguided on 1)"),
           ("cp", f"faithful on {SEARCH_GPUS} GPUs: context parallel, the anchor decode dealt; composed: with ring "
                  "or split CFG (not run)"),
           ("search_gpus", f"search K={SEARCH_PARTICLES} on {SEARCH_GPUS} GPUs (x unguided on 1)"))


def family_table(estimates: dict[str, Any] | None = None) -> str:
    """Markdown: :func:`family_rows`, then the models left out and why."""
    lines = ["| " + " | ".join(header for _, header in COLUMNS) + " |", "|" + "---|" * len(COLUMNS)]
    lines += ["| " + " | ".join(row[key] for key, _ in COLUMNS) + " |" for row in family_rows(estimates)]
    lines += ["", "Not traced: " + "; ".join(f"{name} ({why})" for name, why in LEFT_OUT.items()) + "."]
    return "\n".join(lines)
