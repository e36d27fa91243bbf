"""The memory plans' estimates (``plans``) and the plan of a card (``cost --gpu``), from the cost model.

:func:`plan_estimates` traces every named plan (:data:`~geco_guide.sampler.running.memory_plan.PLANS`) of
every traced registry model (:func:`~geco_guide.families.published.traced_models`) and the tiny
test models, in each mode and with each anchor decoder the model has, with
:func:`~.cost.cost_report`, and keeps what the planner needs (the peak as weights + activations,
the peak with model CPU offload, the predicted H200 time) and what the per-family cost table needs
(the unguided run, the units of a search, the anchor decode per card). The result is the package
data ``geco_guide/sampler/running/data/memory_plans.json`` that ``run.memory_plan=auto`` reads at a call
(no tracing at start-up) and that ``geco bench cost --all-models`` prints.

With model CPU offload (``enable_model_cpu_offload()``) the pipeline keeps the estimators and the
tiny decoder on the device (they are excluded from offload) and moves the transformer and the VAE
in when they run: the offload peak of a stage is its live activations plus those resident
weights plus the weights of the model at work there (one expert of a two-expert model).
"""

from __future__ import annotations

import logging
from collections.abc import Callable, Sequence
from typing import Any

from ..estimators import TINY_RANDOM
from ..families import DEFAULT_MODEL, model_named
from ..families.published import traced_models
from ..loss.geco import frame_pairs
from ..sampler.algorithm.config import GuidanceConfig
from ..sampler.running.memory_plan import PLANS, choose_plan
from ..sampler.running.run_options import RunOptions
from .cards import GPU_SPECS, card_memory_gib
from .cost import cost_report, cost_settings
from .full_size import CALIBRATION_MODEL
from .measure import GIB
from .tracing import cost_guidance, trace_cost

__all__ = ["ANCHOR_DECODERS", "KNOWN_MODELS", "MODES", "REGENERATE", "anchor_decoders", "card_plan",
           "offload_peak", "plan_estimate", "plan_estimates", "search_units", "unguided_estimate", "with_card"]

logger = logging.getLogger(__name__)


def _known_models() -> dict[str, dict[str, Any]]:
    known = {}
    for name in traced_models():
        model = model_named(name)
        known[name] = {"preset": "full", "model": name, "model_ids": [model.hub_id, *model.hub_aliases]}
    return {**known, "tiny": {"preset": "tiny", "model": None, "family": CALIBRATION_MODEL, "model_ids": [TINY_RANDOM]}}


#: The models the estimates know: the cost preset and registry model that build each (the tiny
#: models: CogVideoX's stand-ins, ``family``), and the hub ids that name it (so that a command line can check a budget before any model loads).
KNOWN_MODELS: dict[str, dict[str, Any]] = _known_models()
MODES = ("fast", "faithful")
ANCHOR_DECODERS = ("vae", "tiny")
#: Weights on the device through a whole call under model CPU offload (the estimators are no
#: components: offloading leaves them where they are).
RESIDENT_UNDER_OFFLOAD = ("geometry_estimator", "flow_estimator", "guidance_decoder")
#: The offloaded model at work in each cost stage (the anchor decode's is the VAE unless the tiny
#: decoder decodes the anchors, and that one is resident).
STAGE_MODEL = {"denoiser_cfg": "transformer", "denoiser": "transformer", "anchor_decode": "vae",
               "final_decode": "vae"}
REGENERATE = "geco bench plans --threads 1 --json geco_guide/sampler/running/data/memory_plans.json"


def anchor_decoders(key: str) -> tuple[str, ...]:
    """The anchor decoders a known model's estimates cover: the VAE, and the tiny decoder where its
    family has one (LTX-Video has none)."""
    known = KNOWN_MODELS[key]
    if known["model"] is not None and model_named(known["model"]).tiny_decoder is None:
        return ("vae",)
    return ANCHOR_DECODERS


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
    """What the planner and the cost table keep of one plan's cost report: the peak (weights +
    activations, and under model CPU offload), the predicted H200 time of the guided run, its ratio
    to the unguided run per card, and the run's anchor decode per card (what ``run.devices``
    spreads)."""
    offload = offload_peak(report)
    decode = report["per_stage"].get("anchor_decode")
    return {"weights_gb": sum(report["weights_gb"].values()), "activations_gb": report["activations_peak_gb"],
            "peak_gb": report["peak_memory_gb"], "peak_at": report["peak_at"],
            "offload_weights_gb": offload["weights_gb"], "offload_activations_gb": offload["activations_gb"],
            "offload_peak_gb": offload["weights_gb"] + offload["activations_gb"], "offload_peak_at": offload["at"],
            "time_s": report["roofline"]["wall_time_s"]["H200"]["guided"],
            "ratio_guided_over_unguided": report["roofline"]["ratio_guided_over_unguided"],
            "anchor_decode_s": {gpu: decode["time_s"][gpu] for gpu in GPU_SPECS} if decode else None}


def unguided_estimate(report: dict[str, Any]) -> dict[str, Any]:
    """The unguided run of a cost ``report``, as the video model runs it without GeCo (its
    denoiser(s) and VAE; no estimators, and no text encoder: freed or offloaded once the prompt is
    encoded): ``time_s`` per card, ``peak_gb`` (its weights and the unguided call's activations)
    and ``offload_peak_gb`` (under model CPU offload: the model at work and its stage's
    activations)."""
    weights = report["weights_gb"]
    video = sum(weights.get(name, 0.0) for name in ("transformer", "transformer_2", "vae"))
    stages = report["unit_traces"]["unguided"]
    live = {f"{stage}/{kind}": value["peak_live_bytes"] / GIB for stage, kinds in stages.items()
            for kind, value in kinds.items() if kind != "calls"}
    offload = max(weights.get(STAGE_MODEL.get(key.split("/")[0], ""), 0.0) + gb for key, gb in live.items())
    return {"time_s": {gpu: w["unguided"] for gpu, w in report["roofline"]["wall_time_s"].items()},
            "peak_gb": video + max(live.values()), "offload_peak_gb": offload}


def _seconds(trace_stage: dict[str, Any], kind: str, efficiency: float) -> dict[str, float]:
    """Predicted seconds per card of one traced stage's ``kind`` (forward or backward)."""
    return {gpu: trace_stage.get(kind, {}).get("roofline_s", {}).get(gpu, 0.0) / efficiency for gpu in GPU_SPECS}


def search_units(report: dict[str, Any]) -> dict[str, Any]:
    """One video's units of a search, per card, from a guided cost ``report`` (one update traced):
    ``prediction_s`` (a step's prediction without gradients), ``scoring_s`` (a resampling's scoring
    of one particle: the forward of the update's anchor decode, estimators and loss, no backward;
    ``scoring_decode_s`` its anchor decode alone, which ``run.devices`` deals over the GPUs),
    ``final_decode_s``, and for the selection's protocol scoring ``vggt_frame_s`` and
    ``ufm_pair_s`` (the update's estimator forwards per frame and per pair: the geometry
    estimator's per frame is a lower bound for longer windows, its attention across frames grows
    faster than their count)."""
    efficiency = report["roofline"]["efficiency"]
    stages = report["unit_traces"]["guided"]
    guidance = cost_guidance(report["settings"], report["mode"], "1", None)
    pairs = len(frame_pairs(len(guidance.anchors), guidance.loss.pairs))
    scoring = {gpu: sum(_seconds(stages[name], "forward", efficiency)[gpu] for name in
                        ("anchor_decode", "vggt", "ufm", "loss") if name in stages) for gpu in GPU_SPECS}
    return {"prediction_s": {gpu: report["per_stage"]["denoiser_cfg"]["time_s"][gpu] /
                             max(report["per_stage"]["denoiser_cfg"]["count"], 1) for gpu in GPU_SPECS},
            "scoring_s": scoring, "scoring_decode_s": _seconds(stages["anchor_decode"], "forward", efficiency),
            "final_decode_s": report["per_stage"]["final_decode"]["time_s"],
            "vggt_frame_s": {gpu: s / len(guidance.anchors) for gpu, s in
                             _seconds(stages["vggt"], "forward", efficiency).items()},
            "ufm_pair_s": {gpu: s / pairs for gpu, s in _seconds(stages["ufm"], "forward", efficiency).items()},
            "anchors": len(guidance.anchors), "pairs": pairs}


def seconds_text(seconds: float) -> str:
    """Whole seconds, or three significant digits below 10 s (a tiny model's call is milliseconds)."""
    return f"{seconds:.0f} s" if seconds >= 10 else f"{seconds:.3g} s"


def _settings(known: dict[str, Any], decoder: str, plan: str) -> dict[str, Any]:
    return cost_settings(preset=known["preset"], model=known["model"] or known["family"], steps=None, frames=None,
                         height=None, width=None, dtype=None, decoder=decoder, plan=plan)


def model_estimates(key: str, on_report: Callable[[str], None] | None = None) -> dict[str, Any]:
    """One known model's entry of the estimates file (:func:`plan_estimates`)."""
    known = KNOWN_MODELS[key]
    entry: dict[str, Any] = {"model_ids": known["model_ids"], "estimates": {}}
    for decoder in anchor_decoders(key):
        unguided = trace_cost(_settings(known, decoder, PLANS[0].name), "unguided")  # no plan acts unguided
        for mode in MODES:
            table = {}
            for plan in PLANS:
                settings = _settings(known, decoder, plan.name)
                report = cost_report(settings, mode, unguided=unguided)
                table[plan.name] = plan_estimate(report)
                entry.setdefault("signature", report["signature"])
                entry.setdefault("video", {k: settings[k] for k in ("frames", "height", "width")})
                if (mode, decoder, plan.name) == ("fast", "vae", PLANS[0].name):
                    entry["schedule"] = {**{k: settings[k] for k in ("steps", "repeats", "time_travel")},
                                         "updates": report["counts"]["updates"]}
                    entry["unguided"] = unguided_estimate(report)
                    entry["search_units"] = search_units(report)
                    entry["chunk_latents"] = cost_guidance(settings, mode, "1", None).chunk_latents
                    entry["efficiency"] = report["roofline"]["efficiency"]
                if on_report is not None:
                    on_report(f"{key} {mode}/{decoder} {plan.name}: peak {table[plan.name]['peak_gb']:.1f} GiB, "
                              f"offload {table[plan.name]['offload_peak_gb']:.1f} GiB, "
                              f"H200 {seconds_text(table[plan.name]['time_s'])}")
            entry["estimates"][f"{mode}/{decoder}"] = table
    return entry


def plan_estimates(models: Sequence[str] = tuple(KNOWN_MODELS), argv: Sequence[str] = (),
                   on_report: Callable[[str], None] | None = None) -> dict[str, Any]:
    """The estimates file: for each model of :data:`KNOWN_MODELS`, its denoiser signature, hub ids,
    traced video size, schedule, unguided run, search units and, per ``mode/decoder``, each plan's
    :func:`plan_estimate`. ``on_report`` is told each finished trace (a progress line)."""
    out: dict[str, Any] = {"note": "predicted by the cost model (fake tensors, roofline calibrated on the H200), "
                                   "not measured; memory in GiB, time in H200 seconds for the traced video (the "
                                   "tiny models' times only order their plans)",
                           "command": REGENERATE, "argv": list(argv), "models": {}}
    for key in models:
        out["models"][key] = model_estimates(key, on_report)
    return out


def card_plan(gpu: str, mode: str, decoder: str, frames: int, height: int, width: int,
              estimates: dict[str, Any] | None = None, model: str = DEFAULT_MODEL) -> dict[str, Any]:
    """The plan ``memory_plan=auto`` picks for registry ``model`` on ``gpu`` (its memory from
    :data:`~.cards.GPU_SPECS`): without offload if one fits, else with model CPU offload; ``plan``
    ``None`` and the planner's line in ``reason`` where none fits either."""
    device_gb = card_memory_gib(gpu)
    config = GuidanceConfig(denoiser_grad=mode == "faithful", decoder=decoder)
    errors = []
    for offload in (False, True):
        try:
            choice = choose_plan(config, RunOptions(), model_id=KNOWN_MODELS[model]["model_ids"][0], frames=frames,
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
