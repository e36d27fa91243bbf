"""Guidance and particle search per card and per number of GPUs, from the shipped estimates.

Everything here is arithmetic on the cost model's traces kept in the memory plans' estimates
(``geco_guide/sampler/data/memory_plans.json``, written by ``geco bench plans``): nothing is
traced, so a caller can ask for any card, mode, number of particles and number of GPUs at once.

* :func:`guidance_cost`: the guided run under the plan ``run.memory_plan=auto`` picks for the
  card (with model CPU offload where nothing fits without), on one GPU or with ``run.devices``
  dealing the anchor chunks over N (:func:`~.cost.decode_over_gpus`).
* :func:`search_cost`: a search of ``K`` particles (``search.particles``, unguided particles):
  ``K x`` the denoiser's prediction at every step (the particles dealt over the GPUs in
  sub-batches), at most ``K - 1`` more per resampling (the re-noised copies), a scoring of every
  particle at each resampling (its anchor decode, whose chunks ``run.devices`` deals over the
  GPUs, and the estimators' forward on the pipeline's GPU), then each final particle's decode and
  its protocol scoring (the selection), each GPU decoding and scoring its share of the particles
  at once (only the scores meet), as ``run.devices`` runs them.
* :func:`matched_particles`: the most particles whose search is predicted to take no longer than
  guidance on the card.

Times are the cost model's (roofline with one efficiency calibrated on the measured unguided H200
step of CogVideoX-5B): predicted, never measured.
"""

from __future__ import annotations

from typing import Any

from ..families import default_anchors, model_named
from ..metric.protocol import EvaluationConfig, scoring_plan
from ..sampler.config import GuidanceConfig
from ..sampler.memory_plan import choose_plan, load_estimates
from ..sampler.run_options import RunOptions
from ..sampler.search import MAX_PARTICLES, choose_particle_batch, default_resample_steps
from .cards import card_memory_gib
from .cost import anchor_chunk_bytes, decode_over_gpus

__all__ = ["estimates_entry", "guidance_cost", "matched_particles", "protocol_seconds", "search_cost"]


def estimates_entry(name: str, estimates: dict[str, Any] | None = None) -> dict[str, Any]:
    """Registry model ``name``'s entry of the estimates (default: the shipped ones); ValueError
    (one line) for a model they do not hold."""
    estimates = load_estimates() if estimates is None else estimates
    if name not in estimates["models"]:
        raise ValueError(f"the memory plans' estimates do not hold {name!r}; they hold "
                         f"{', '.join(estimates['models'])} (geco bench plans writes them)")
    return estimates["models"][name]


def _chunks(name: str, entry: dict[str, Any]) -> tuple[int, int]:
    """``(anchor chunks of an update, bytes each moves to another GPU)`` of ``name``'s traced video."""
    model, video = model_named(name), entry["video"]
    return (len(default_anchors(video["frames"], model.temporal_compression)),
            anchor_chunk_bytes(model, video["height"], video["width"], entry["chunk_latents"]))


def guidance_cost(name: str, gpu: str, mode: str = "faithful", decoder: str = "vae", num_gpus: int = 1,
                  estimates: dict[str, Any] | None = None) -> dict[str, Any]:
    """The guided run of registry model ``name``'s traced video on ``num_gpus`` cards ``gpu``
    (``run.devices``): the plan ``auto`` picks for the card's memory (``offload``: with model CPU
    offload, where nothing fits without), its ``time_s`` and the ``peak_gb`` each card is held to
    (the one-GPU peak: the planner's rule for several devices). ``plan`` ``None`` and the
    planner's line in ``reason`` where no plan fits, or where the estimates have no such mode and
    decoder."""
    estimates = load_estimates() if estimates is None else estimates
    entry = estimates_entry(name, estimates)
    table = entry["estimates"].get(f"{mode}/{decoder}")
    if table is None:
        return {"plan": None, "reason": f"no estimates with decoder {decoder} ({name} has no tiny decoder)"}
    video, memory = entry["video"], card_memory_gib(gpu)
    config = GuidanceConfig(denoiser_grad=mode == "faithful", decoder=decoder)
    reason = ""
    for offload in (False, True):
        try:
            choice = choose_plan(config, RunOptions(), model_id=entry["model_ids"][0], frames=video["frames"],
                                 height=video["height"], width=video["width"], device_gb=memory, offload=offload,
                                 estimates=estimates)
        except ValueError as err:
            reason = str(err)
            continue
        estimate = table[choice.plan.name]
        seconds = estimate["ratio_guided_over_unguided"][gpu] * entry["unguided"]["time_s"][gpu]
        if num_gpus > 1 and estimate["anchor_decode_s"] is not None:
            chunks, chunk_bytes = _chunks(name, entry)
            decode = estimate["anchor_decode_s"][gpu]
            spread, moved = decode_over_gpus(decode, chunks, num_gpus, entry["schedule"]["updates"], chunk_bytes, gpu)
            seconds += spread + moved - decode
        return {"plan": choice.plan.name, "offload": offload, "time_s": seconds,
                "peak_gb": estimate["offload_peak_gb" if offload else "peak_gb"], "reason": choice.reason}
    return {"plan": None, "reason": reason}


def protocol_seconds(name: str, gpu: str, estimates: dict[str, Any] | None = None) -> float:
    """The GeCo-protocol scoring of one of registry model ``name``'s videos on ``gpu`` (what a
    search's selection scores each final particle with): the flow estimator on the protocol's
    frame pairs and the geometry estimator on its windows' frames (:func:`scoring_plan` at the
    model's frame rate), at the per-pair and per-frame times of a guided update (the geometry
    estimator's per frame: a lower bound for windows of more frames)."""
    entry = estimates_entry(name, estimates)
    units, frames = entry["search_units"], entry["video"]["frames"]
    plan = scoring_plan(frames, float(model_named(name).fps), EvaluationConfig())
    return (plan["flow_pairs"] * units["ufm_pair_s"][gpu]
            + plan["windows"] * plan["window_frames"] * units["vggt_frame_s"][gpu])


def _particle_batch(name: str, entry: dict[str, Any], particles: int, gpu: str, num_gpus: int,
                    estimates: dict[str, Any]) -> tuple[Any, bool, str]:
    """The particle batch the search gets on the card (without offload if one fits, else with):
    ``(batch or None, offload, reason)``."""
    video, reason = entry["video"], ""
    for offload in (False, True):
        try:
            batch = choose_particle_batch(GuidanceConfig(enabled=False), RunOptions(), particles, None,
                                          model_id=entry["model_ids"][0], frames=video["frames"],
                                          height=video["height"], width=video["width"],
                                          device_gb=card_memory_gib(gpu), offload=offload, devices=num_gpus,
                                          estimates=estimates)
        except ValueError as err:
            reason = str(err)
            continue
        return batch, offload, batch.reason
    return None, False, reason


def search_cost(name: str, particles: int, gpu: str, num_gpus: int = 1,
                estimates: dict[str, Any] | None = None) -> dict[str, Any]:
    """A search of ``particles`` unguided particles of registry model ``name``'s traced video on
    ``num_gpus`` cards ``gpu`` with the default ``search`` options (resampling every tenth of the
    schedule through its middle, re-noised copies), as the module docstring says: ``time_s`` and
    its parts (``denoiser_s``, ``scoring_s``, ``final_decode_s``, ``protocol_s``), the particle
    ``batch`` per call and the ``peak_gb`` of the pipeline's GPU (``None`` and the planner's line in
    ``reason`` where even one particle's work does not fit)."""
    estimates = load_estimates() if estimates is None else estimates
    entry = estimates_entry(name, estimates)
    units, steps = entry["search_units"], entry["schedule"]["steps"]
    resamplings = len(default_resample_steps(steps))
    per_gpu = -(-particles // num_gpus)
    renoised = -(-(particles - 1) * resamplings // num_gpus)  # at most: every copy after the first
    denoiser = (steps * per_gpu + renoised) * units["prediction_s"][gpu]
    chunks, chunk_bytes = _chunks(name, entry)
    decode = units["scoring_decode_s"][gpu] * particles * resamplings
    spread, moved = decode_over_gpus(decode, chunks, num_gpus, particles * resamplings, chunk_bytes, gpu)
    scorings = (units["scoring_s"][gpu] - units["scoring_decode_s"][gpu]) * particles * resamplings + spread + moved
    final = per_gpu * units["final_decode_s"][gpu]
    protocol = per_gpu * protocol_seconds(name, gpu, estimates)
    batch, offload, reason = _particle_batch(name, entry, particles, gpu, num_gpus, estimates)
    return {"particles": particles, "num_gpus": num_gpus, "time_s": denoiser + scorings + final + protocol,
            "denoiser_s": denoiser, "scoring_s": scorings, "final_decode_s": final, "protocol_s": protocol,
            "resamplings": resamplings, "batch": batch.size if batch else None, "offload": offload,
            "peak_gb": batch.predicted_peak_gb if batch else None, "reason": reason}


def matched_particles(name: str, gpu: str, mode: str = "faithful", decoder: str = "vae",
                      estimates: dict[str, Any] | None = None) -> int | None:
    """The most particles whose search (:func:`search_cost`, one card ``gpu``) is predicted to take
    no longer than guidance in ``mode`` with ``decoder`` on that card (:func:`guidance_cost`):
    search and guidance at matched compute. ``None`` where guidance fits no plan on the card; at
    least 1."""
    guided = guidance_cost(name, gpu, mode, decoder, estimates=estimates)
    if guided["plan"] is None:
        return None
    low, high = 1, MAX_PARTICLES
    while low < high:  # the search's time grows with its particles
        middle = (low + high + 1) // 2
        if search_cost(name, middle, gpu, estimates=estimates)["time_s"] <= guided["time_s"]:
            low = middle
        else:
            high = middle - 1
    return low
