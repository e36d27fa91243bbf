"""Stage profiling of a pipeline call: per-stage forward and backward intervals.

Both profilers of the package (:class:`StageProfiler` here, timing; :class:`~.tracing.CostTracker`,
counting FLOPs) attribute a stage's backward with :func:`call_marking_backward`: the backward of a
wrapped call starts at the first execution of an output's ``grad_fn`` (a node pre-hook) and ends
when the gradient w.r.t. its last tensor input is computed (an identity autograd function on every
input). The autograd engine runs ready nodes in decreasing creation order, so the backward of a
stage runs contiguously between these two events.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Sequence
from typing import Any

import torch
from torch import Tensor

from .measure import synchronize

__all__ = ["StageProfiler", "breakdown_of", "call_marking_backward", "summarize_profile", "union_seconds",
           "update_windows"]


def output_tensors(obj: Any) -> list[Tensor]:
    """Tensors in a (nested) output: tensors, tuples/lists, dicts (diffusers outputs), dataclasses."""
    if isinstance(obj, Tensor):
        return [obj]
    if isinstance(obj, (tuple, list)):
        return [t for item in obj for t in output_tensors(item)]
    if isinstance(obj, dict):
        return [t for item in obj.values() for t in output_tensors(item)]
    if hasattr(obj, "__dataclass_fields__"):
        return [t for name in obj.__dataclass_fields__ for t in output_tensors(getattr(obj, name))]
    return []


class _BackwardMark(torch.autograd.Function):
    """Identity whose backward calls ``callback`` (the gradient w.r.t. a stage input is done)."""

    @staticmethod
    def forward(ctx, callback, x):  # type: ignore[override]
        ctx.callback = callback
        return x.view_as(x)

    @staticmethod
    def backward(ctx, grad):  # type: ignore[override]
        ctx.callback()
        return None, grad


def call_marking_backward(
    fn: Callable[..., Any],
    args: tuple,
    kwargs: dict[str, Any],
    on_backward_start: Callable[[], None],
    on_backward_end: Callable[[], None],
) -> Any:
    """``fn(*args, **kwargs)``; with autograd on, ``on_backward_start()`` runs at each execution
    of an output's ``grad_fn`` and ``on_backward_end()`` each time the gradient w.r.t. a tensor
    input requiring grad is computed (see the module docstring). Without autograd, a plain call."""
    if not torch.is_grad_enabled():
        return fn(*args, **kwargs)

    def mark(x: Any) -> Any:
        if isinstance(x, Tensor) and x.requires_grad:
            return _BackwardMark.apply(on_backward_end, x)
        return x

    out = fn(*(mark(a) for a in args), **{k: mark(v) for k, v in kwargs.items()})
    for node in {id(t.grad_fn): t.grad_fn for t in output_tensors(out) if t.grad_fn is not None}.values():
        node.register_prehook(lambda grad_outputs: on_backward_start())
    return out


class StageProfiler:
    """Per-stage forward/backward times of a pipeline call, installed on the instances only.

    ``wrap(obj, name, stage)`` replaces the bound method ``obj.name`` by a wrapper that times the
    call (forward) and, when autograd is on, its backward (:func:`call_marking_backward`). On
    CUDA every event synchronises the device (added by the harness).
    """

    def __init__(self, device: torch.device) -> None:
        self.device = device
        self.calls: list[dict[str, Any]] = []
        self.loop_start: float | None = None
        self.step_ends: list[float] = []

    def now(self) -> float:
        synchronize(self.device)
        return time.perf_counter()

    def reset(self) -> None:
        self.calls, self.loop_start, self.step_ends = [], None, []

    def wrap(self, obj: Any, name: str, stage: str) -> None:
        original = getattr(obj, name)

        def wrapper(*args: Any, **kwargs: Any) -> Any:
            call: dict[str, Any] = {"stage": stage, "grad": torch.is_grad_enabled(),
                                    "bwd_start": None, "bwd_end": None}

            def timed(*args: Any, **kwargs: Any) -> Any:
                call["start"] = self.now()
                out = original(*args, **kwargs)
                call["end"] = self.now()
                return out

            out = call_marking_backward(timed, args, kwargs, lambda: self._bwd_start(call), lambda: self._bwd_end(call))
            self.calls.append(call)
            return out

        setattr(obj, name, wrapper)

    def _bwd_start(self, call: dict[str, Any]) -> None:
        if call["bwd_start"] is None:
            call["bwd_start"] = self.now()

    def _bwd_end(self, call: dict[str, Any]) -> None:
        call["bwd_end"] = self.now()

    def mark_loop_start(self, obj: Any, name: str) -> None:
        """Mark the loop start at the first call of ``obj.name`` (``model_output`` of the GeCo
        pipeline: every step makes at least one, the unguided steps directly, the guided ones
        through ``predict``), an instance attribute over the method."""
        original = getattr(obj, name)

        def wrapper(*args: Any, **kwargs: Any) -> Any:
            if self.loop_start is None:
                self.loop_start = self.now()
            return original(*args, **kwargs)

        setattr(obj, name, wrapper)

    def mark_step_ends(self, scheduler: Any) -> None:
        """Mark each step's end when ``scheduler.step`` returns (every step of the loop ends with
        it), an instance attribute over the method."""
        original = scheduler.step

        def step(*args: Any, **kwargs: Any) -> Any:
            out = original(*args, **kwargs)
            self.step_ends.append(self.now())
            return out

        scheduler.step = step

    def intervals(self) -> list[dict[str, Any]]:
        """Every timed interval: ``stage, kind (forward|backward), grad, start, end``."""
        out = []
        for call in self.calls:
            out.append({"stage": call["stage"], "kind": "forward", "grad": call["grad"],
                        "start": call["start"], "end": call["end"]})
            if call["bwd_start"] is not None and call["bwd_end"] is not None:
                out.append({"stage": call["stage"], "kind": "backward", "grad": True,
                            "start": call["bwd_start"], "end": call["bwd_end"]})
        return out


def union_seconds(spans: Sequence[tuple[float, float]]) -> float:
    """Total length of the union of ``(start, end)`` spans (overlaps counted once)."""
    total, current = 0.0, None
    for start, end in sorted(spans):
        if current is None or start > current[1]:
            if current is not None:
                total += current[1] - current[0]
            current = [start, end]
        else:
            current[1] = max(current[1], end)
    return total + (current[1] - current[0] if current is not None else 0.0)


def update_windows(loop_start: float, step_ends: Sequence[float], log: Sequence[dict[str, Any]]) -> list[tuple[float, float]]:
    """``(start, end)`` of every guided update from the step boundaries and the records.

    A step's updates run back to back from its start (the previous step's end, or the loop start)
    and each lasts its record's ``seconds``; the few microseconds of Python between them shift
    the windows slightly early, so the step's final prediction still falls after the last one.
    """
    windows, start = [], None
    step_starts = [loop_start, *step_ends]
    current_step = None
    for record in log:
        if record["step"] != current_step:
            current_step, start = record["step"], step_starts[record["step"]]
        windows.append((start, start + record["seconds"]))
        start += record["seconds"]
    return windows


def summarize_profile(profiler: StageProfiler, log: Sequence[dict[str, Any]]) -> dict[str, Any]:
    """Stage seconds split by where they happened: ``update`` (inside a guided update), ``loop``
    (the rest of the denoising loop: the final predictions of each step) and ``post`` (after the
    loop: the final VAE decode); plus counts and the ``loss`` remainder of the updates."""
    update_seconds = [r["seconds"] for r in log]
    windows = update_windows(profiler.loop_start, profiler.step_ends, log) if log else []
    loop_end = profiler.step_ends[-1] if profiler.step_ends else float("inf")

    def where(start: float) -> str:
        if any(a <= start <= b for a, b in windows):
            return "update"
        return "loop" if start <= loop_end else "post"

    spans: dict[tuple[str, str, str], list[tuple[float, float]]] = {}
    counts: dict[tuple[str, str, str], int] = {}
    for iv in profiler.intervals():
        key = (iv["stage"], iv["kind"], where(iv["start"]))
        spans.setdefault(key, []).append((iv["start"], iv["end"]))
        counts[key] = counts.get(key, 0) + 1
    seconds = {key: union_seconds(value) for key, value in spans.items()}
    in_updates = sum(v for (_, _, w), v in seconds.items() if w == "update")
    return {
        "seconds": {"/".join(k): v for k, v in sorted(seconds.items())},
        "counts": {"/".join(k): v for k, v in sorted(counts.items())},
        "denoiser_forwards_with_grad": sum(1 for c in profiler.calls if c["stage"] == "denoiser" and c["grad"]),
        "updates_s": sum(update_seconds),
        "attributed_in_updates_s": in_updates,
        "loss_s": sum(update_seconds) - in_updates,
    }


def breakdown_of(profile: dict[str, Any], scale: dict[str, float] | None = None) -> dict[str, Any]:
    """The report's breakdown: seconds per stage and counts, optionally with the ``update`` and
    ``loop`` parts scaled (extrapolation to the nominal step count)."""
    scale = scale or {"update": 1.0, "loop": 1.0, "post": 1.0}

    def total(stage: str, kind: str, where: Sequence[str] = ("update", "loop", "post"), table: str = "seconds") -> float:
        value = sum(scale[w] * profile[table].get(f"{stage}/{kind}/{w}", 0) for w in where)
        return int(round(value)) if table == "counts" else value

    return {
        "denoiser_forward_s": total("denoiser", "forward"),
        "denoiser_backward_s": total("denoiser", "backward"),
        "vae_slice_decode_forward_s": total("vae_decode", "forward", ("update",)),
        "vae_slice_decode_backward_s": total("vae_decode", "backward", ("update",)),
        "vae_final_decode_s": total("vae_decode", "forward", ("loop", "post")),
        "vggt_forward_s": total("vggt", "forward"),
        "vggt_backward_s": total("vggt", "backward"),
        "ufm_forward_s": total("ufm", "forward"),
        "ufm_backward_s": total("ufm", "backward"),
        "loss_s": scale["update"] * profile["loss_s"],
        "guided_updates_s": scale["update"] * profile["updates_s"],
        "counts": {
            "denoiser_forwards": total("denoiser", "forward", table="counts"),
            "denoiser_forwards_in_updates": total("denoiser", "forward", ("update",), table="counts"),
            "denoiser_backwards": total("denoiser", "backward", table="counts"),
            "vae_slice_decodes": total("vae_decode", "forward", ("update",), table="counts"),
            "vggt_calls": total("vggt", "forward", table="counts"),
            "ufm_calls": total("ufm", "forward", table="counts"),
        },
    }
