"""The memory plans' estimates (``plans``) and the plan of a card (``cost --gpu``), from the cost model.

:func:`plan_estimates` traces every named plan (:data:`~geco_guide.sampler.memory_plan.PLANS`) of
every known model, mode and anchor decoder with :func:`~.cost.cost_report` and keeps what the
planner needs: the peak as weights + activations, the peak with model CPU offload, and the
predicted H200 time. The result is the package data ``geco_guide/sampler/data/memory_plans.json``
that ``run.memory_plan=auto`` reads at a call (no tracing at start-up).

With model CPU offload (``enable_model_cpu_offload()``) the pipeline keeps the estimators and the
tiny decoder on the device (they are excluded from offload) and moves the transformer and the VAE
in when they run: the offload peak of a stage is its live activations plus those resident
weights plus the weights of the model at work there.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from typing import Any

from ..estimators import TINY_RANDOM
from ..sampler.config import GuidanceConfig
from ..sampler.memory_plan import PLANS, choose_plan
from ..sampler.run_options import RunOptions
from .cost import GPU_SPECS, cost_report, cost_settings
from .measure import GIB

__all__ = ["KNOWN_MODELS", "card_plan", "offload_peak", "plan_estimate", "plan_estimates", "with_card"]

#: The models the estimates know: the cost preset that builds each, and the hub ids that name it
#: (so that a command line can check a budget before any model loads).
KNOWN_MODELS: dict[str, dict[str, Any]] = {
    "cogvideox-5b": {"preset": "full", "model_ids": ["THUDM/CogVideoX-5b", "zai-org/CogVideoX-5b"]},
    "tiny": {"preset": "tiny", "model_ids": [TINY_RANDOM]},
}
MODES = ("fast", "faithful")
ANCHOR_DECODERS = ("vae", "tiny")
#: Weights on the device through a whole call under model CPU offload (the estimators are no
#: components: offloading leaves them where they are).
RESIDENT_UNDER_OFFLOAD = ("geometry_estimator", "flow_estimator", "guidance_decoder")
#: The offloaded model at work in each cost stage (the anchor decode's is the VAE unless the tiny
#: decoder decodes the anchors, and that one is resident).
STAGE_MODEL = {"denoiser_cfg": "transformer", "denoiser": "transformer", "anchor_decode": "vae",
               "final_decode": "vae"}
REGENERATE = "python scripts/benchmark.py plans --threads 1 --json geco_guide/sampler/data/memory_plans.json"


def offload_peak(report: dict[str, Any]) -> dict[str, Any]:
    """The largest stage peak of a cost ``report`` under model CPU offload: ``weights_gb`` (resident
    + the model at work), ``activations_gb`` (live at that stage's peak) and ``at`` (stage/kind)."""
    weights = report["weights_gb"]
    resident = sum(weights.get(name, 0.0) for name in RESIDENT_UNDER_OFFLOAD)
    tiny_anchors = report["settings"].get("decoder") == "tiny"
    best = {"weights_gb": 0.0, "activations_gb": 0.0, "at": None}
    for stages in report["unit_traces"].values():
        for stage, kinds in stages.items():
            model = None if stage == "anchor_decode" and tiny_anchors else STAGE_MODEL.get(stage)
            at_work = resident + (weights.get(model, 0.0) if model else 0.0)
            for kind, value in kinds.items():
                if kind == "calls":
                    continue
                live = value["peak_live_bytes"] / GIB
                if at_work + live > best["weights_gb"] + best["activations_gb"]:
                    best = {"weights_gb": at_work, "activations_gb": live, "at": f"{stage}/{kind}"}
    return best


def plan_estimate(report: dict[str, Any]) -> dict[str, Any]:
    """What the planner keeps of one plan's cost report."""
    offload = offload_peak(report)
    return {"weights_gb": sum(report["weights_gb"].values()), "activations_gb": report["activations_peak_gb"],
            "peak_gb": report["peak_memory_gb"], "peak_at": report["peak_at"],
            "offload_weights_gb": offload["weights_gb"], "offload_activations_gb": offload["activations_gb"],
            "offload_peak_gb": offload["weights_gb"] + offload["activations_gb"], "offload_peak_at": offload["at"],
            "time_s": report["roofline"]["wall_time_s"]["H200"]["guided"],
            "ratio_guided_over_unguided": report["roofline"]["ratio_guided_over_unguided"]}


def seconds_text(seconds: float) -> str:
    """Whole seconds, or three significant digits below 10 s (a tiny model's call is milliseconds)."""
    return f"{seconds:.0f} s" if seconds >= 10 else f"{seconds:.3g} s"


def plan_estimates(models: Sequence[str] = tuple(KNOWN_MODELS), argv: Sequence[str] = (),
                   on_report: Callable[[str], None] | None = None) -> dict[str, Any]:
    """The estimates file: for each model of :data:`KNOWN_MODELS`, its denoiser signature, hub ids,
    traced video size and, per ``mode/decoder``, each plan's :func:`plan_estimate`.
    ``on_report`` is told each finished trace (a progress line)."""
    out: dict[str, Any] = {"note": "predicted by the cost model (fake tensors, roofline calibrated on the H200), "
                                   "not measured; memory in GiB, time in H200 seconds for the traced video (the "
                                   "tiny models' times only order their plans)",
                           "command": REGENERATE, "argv": list(argv), "models": {}}
    for key in models:
        known = KNOWN_MODELS[key]
        entry: dict[str, Any] = {"model_ids": known["model_ids"], "estimates": {}}
        for mode in MODES:
            for decoder in ANCHOR_DECODERS:
                table = {}
                for plan in PLANS:
                    settings = cost_settings(preset=known["preset"], steps=None, frames=None, height=None, width=None,
                                             dtype=None, decoder=decoder, plan=plan.name)
                    report = cost_report(settings, mode)
                    table[plan.name] = plan_estimate(report)
                    entry.setdefault("signature", report["signature"])
                    entry.setdefault("video", {k: settings[k] for k in ("frames", "height", "width")})
                    if on_report is not None:
                        on_report(f"{key} {mode}/{decoder} {plan.name}: peak {table[plan.name]['peak_gb']:.1f} GiB, "
                                  f"offload {table[plan.name]['offload_peak_gb']:.1f} GiB, "
                                  f"H200 {seconds_text(table[plan.name]['time_s'])}")
                entry["estimates"][f"{mode}/{decoder}"] = table
        out["models"][key] = entry
    return out


def card_plan(gpu: str, mode: str, decoder: str, frames: int, height: int, width: int,
              estimates: dict[str, Any] | None = None) -> dict[str, Any]:
    """The plan ``memory_plan=auto`` picks for CogVideoX-5B on ``gpu`` (its memory from
    :data:`~.cost.GPU_SPECS`): without offload if one fits, else with model CPU offload; ``plan``
    ``None`` and the planner's line in ``reason`` where none fits either."""
    device_gb = GPU_SPECS[gpu]["memory_gb"] * 1e9 / GIB
    config = GuidanceConfig(denoiser_grad=mode == "faithful", decoder=decoder)
    errors = []
    for offload in (False, True):
        try:
            choice = choose_plan(config, RunOptions(), model_id=KNOWN_MODELS["cogvideox-5b"]["model_ids"][0], frames=frames,
                                 height=height, width=width, device_gb=device_gb, offload=offload, estimates=estimates)
        except ValueError as err:
            errors.append(str(err))
            continue
        return {"gpu": gpu, "memory_gib": device_gb, "plan": choice.plan.name, "offload": offload,
                "reason": choice.reason, "budget_gb": choice.budget_gb, "predicted_peak_gb": choice.predicted_peak_gb}
    return {"gpu": gpu, "memory_gib": device_gb, "plan": None, "offload": None, "reason": errors[-1],
            "budget_gb": None, "predicted_peak_gb": None}


def with_card(report: dict[str, Any], card: dict[str, Any]) -> dict[str, Any]:
    """``report`` (of the plan ``card`` chose: :func:`card_plan`) with ``plan``, ``card``, and
    ``peak_memory_gb`` the peak the card sees: under model CPU offload where the card needs it
    (``peak_memory_gb_without_offload`` keeps the other)."""
    out = {**report, "plan": card["plan"], "card": card}
    if card["offload"]:
        peak = offload_peak(report)
        out.update(peak_memory_gb=peak["weights_gb"] + peak["activations_gb"], peak_at=peak["at"],
                   peak_memory_gb_without_offload=report["peak_memory_gb"])
    return out
