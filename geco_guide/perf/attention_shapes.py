"""The denoiser's attention calls of every traced model, traced once and shipped as package data.

A sequence split over GPUs (context parallelism, :mod:`.parallel_cost`) moves what its attention
calls read: the query, key and value of every self-attention. :func:`denoiser_attention` traces one
unguided step of a registry model on fake tensors (:func:`~.tracing.trace_cost`) and keeps the
shapes of the fused attentions its prediction made, with the weights of its models;
:func:`attention_file` gathers every traced model's, the package data
``geco_guide/perf/data/denoiser_attention.json`` that the cost of several GPUs reads (no tracing
at a call). Predicted facts of the published configs, no weights, nothing measured.
"""

from __future__ import annotations

import functools
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

from ..families.published import read_package_json, traced_models
from .cost import cost_settings
from .measure import GIB
from .tracing import trace_cost

__all__ = ["ATTENTION_PATH", "REGENERATE_ATTENTION", "attention_file", "denoiser_attention", "load_attention"]

ATTENTION_PATH = Path(__file__).resolve().parent / "data" / "denoiser_attention.json"
REGENERATE_ATTENTION = "geco bench attention-shapes --threads 1 --json geco_guide/perf/data/denoiser_attention.json"


def denoiser_attention(name: str) -> dict[str, Any]:
    """Registry model ``name``'s prediction of one step (both CFG halves) at its default call, traced:
    ``attention`` (each distinct fused attention: ``query`` and ``key`` shapes ``[B, heads, tokens,
    head_dim]``, ``element_bytes``, ``calls`` per prediction; a key shorter than its query is a
    cross-attention to the text) and ``weights_gb`` per model (GiB)."""
    settings = cost_settings(preset="full", model=name, steps=1, frames=None, height=None, width=None, dtype=None)
    trace = trace_cost(settings, "unguided")
    predictions = trace["stages"]["denoiser_cfg"]["calls"]
    calls = trace["attention"].get("denoiser_cfg/forward", [])
    if not calls:
        raise RuntimeError(f"{name}: the trace saw no fused attention in the denoiser (another attention path?)")
    attention = [{**call, "calls": call["calls"] // predictions} for call in calls]
    return {"attention": attention, "weights_gb": {k: v / GIB for k, v in trace["weights_bytes"].items() if v},
            "video": {k: settings[k] for k in ("frames", "height", "width")}}


def attention_file(models: Sequence[str] = (), argv: Sequence[str] = (),
                   on_model: Callable[[str], None] | None = None) -> dict[str, Any]:
    """The shipped attention file: :func:`denoiser_attention` of ``models`` (default: every traced
    model); ``on_model`` is told each one traced (a progress line)."""
    out: dict[str, Any] = {"note": "traced on fake tensors from the published configs (no weights): the fused "
                                   "attentions of one step's prediction, per model",
                           "command": REGENERATE_ATTENTION, "argv": list(argv), "models": {}}
    for name in models or traced_models():
        out["models"][name] = denoiser_attention(name)
        if on_model is not None:
            on_model(f"{name}: {sum(c['calls'] for c in out['models'][name]['attention'])} attention calls")
    return out


@functools.cache
def load_attention() -> dict[str, Any]:
    """The shipped attention file (:data:`ATTENTION_PATH`).

    Raises:
        PackageDataError: (one line naming the file) missing, unreadable or damaged.
    """
    return read_package_json(ATTENTION_PATH, f"regenerate it with {REGENERATE_ATTENTION}, or reinstall geco_guide")
