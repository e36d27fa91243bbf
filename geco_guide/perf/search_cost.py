"""Guidance and particle search per card and per number of GPUs, from the shipped estimates.

Everything here is arithmetic on the cost model's traces kept in the memory plans' estimates
(``geco_guide/sampler/running/data/memory_plans.json``, written by ``geco bench plans``): nothing is
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
step of CogVideoX-5B), predicted; on the H200 a search's estimators run at the rates the H200
runs measured (:data:`~.cards.H200_MEASURED_ESTIMATORS_S`: the roofline under-predicts these
many small kernels several-fold), per family scaled by its predicted over CogVideoX-5B's. Model CPU
offload's transfers are in the times (:func:`offload_transfer_s`).
"""

from __future__ import annotations

from typing import Any

from ..families import default_anchors, model_named
from ..metric.protocol import EvaluationConfig, scoring_plan
from ..sampler.algorithm.config import GuidanceConfig
from ..sampler.running.memory_plan import DEVICE_HEADROOM, choose_plan, load_estimates
from ..sampler.running.run_options import RunOptions
from ..sampler.search.particle_search import MAX_PARTICLES, default_resample_steps, particle_gb
from .attention_shapes import load_attention
from .cards import (H200_MEASURED_ESTIMATORS_S, H200_MEASURED_UPDATES, HOST_BYTES_PER_S, MEASURED_RUNS,
                    card_memory_gib)
from .cost import anchor_chunk_bytes, decode_over_gpus
from .full_size import CALIBRATION_MODEL
from .measure import GIB

__all__ = ["anchor_chunks", "estimates_entry", "estimator_rates", "guidance_cost", "matched_particles",
           "offload_transfer_s", "protocol_seconds", "search_cost"]


def estimates_entry(name: str, estimates: dict[str, Any] | None = None) -> dict[str, Any]:
    """Registry model ``name``'s entry of the estimates (default: the shipped ones); ValueError
    (one line) for a model they do not hold."""
    estimates = load_estimates() if estimates is None else estimates
    if name not in estimates["models"]:
        raise ValueError(f"the memory plans' estimates do not hold {name!r}; they hold "
                         f"{', '.join(estimates['models'])} (geco bench plans writes them)")
    return estimates["models"][name]


def anchor_chunks(name: str, entry: dict[str, Any]) -> tuple[int, int]:
    """``(anchor chunks of an update, bytes each moves to another GPU)`` of ``name``'s traced video."""
    model, video = model_named(name), entry["video"]
    return (len(default_anchors(video["frames"], model.temporal_compression)),
            anchor_chunk_bytes(model, video["height"], video["width"], entry["chunk_latents"]))


def guidance_cost(name: str, gpu: str, mode: str = "faithful", decoder: str = "vae", num_gpus: int = 1,
                  estimates: dict[str, Any] | None = None) -> dict[str, Any]:
    """The guided run of registry model ``name``'s traced video on ``num_gpus`` cards ``gpu``
    (``run.devices``): the plan ``auto`` picks for the card's memory (``offload``: with model CPU
    offload, where nothing fits without), its ``time_s`` and the ``peak_gb`` each card is held to
    (the one-GPU peak: the planner's rule for several devices), offload's transfers in the time.
    Split CFG and context parallelism: :mod:`.parallel_cost`. ``plan`` ``None`` and the
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
            chunks, chunk_bytes = anchor_chunks(name, entry)
            decode = estimate["anchor_decode_s"][gpu]
            spread, moved = decode_over_gpus(decode, chunks, num_gpus, entry["schedule"]["updates"], chunk_bytes, gpu)
            seconds += spread + moved - decode
        if offload:
            seconds += offload_transfer_s(name, gpu, entry["schedule"]["updates"], decoder)
        return {"plan": choice.plan.name, "offload": offload, "time_s": seconds,
                "peak_gb": estimate["offload_peak_gb" if offload else "peak_gb"], "reason": choice.reason}
    return {"plan": None, "reason": reason}


def offload_transfer_s(name: str, gpu: str, updates: int, decoder: str = "vae", decodes: int = 1) -> float:
    """Model CPU offload's transfers over a run of registry model ``name``: each switch between the
    denoiser and the VAE moves one in and the other out over the card's host link
    (:data:`~.cards.HOST_BYTES_PER_S`). ``updates`` guided updates (or a search's scorings) with the
    VAE decoding their anchors switch twice each (to the VAE and back), the final decodes once each
    (``decodes``), a two-expert model once more at its expert switch; the tiny decoder and the
    estimators stay on the device."""
    weights = load_attention()["models"][name]["weights_gb"]
    switches = (2 * updates if decoder == "vae" else 0) + decodes + ("transformer_2" in weights)
    return switches * (weights["transformer"] + weights.get("vae", 0.0)) * GIB / HOST_BYTES_PER_S[gpu]


def _update_forwards(units: dict[str, Any], gpu: str) -> dict[str, float]:
    """One guided update's forward seconds of the estimators and the loss, predicted, from ``units``."""
    vggt, ufm = units["vggt_frame_s"][gpu] * units["anchors"], units["ufm_pair_s"][gpu] * units["pairs"]
    return {"vggt": vggt, "ufm": ufm, "loss": units["scoring_s"][gpu] - units["scoring_decode_s"][gpu] - vggt - ufm}


def estimator_rates(name: str, gpu: str, measured: str | None = "fast",
                    estimates: dict[str, Any] | None = None) -> dict[str, float]:
    """Seconds of one guided update's forward of VGGT, UFM and the loss for registry model ``name``
    on ``gpu``: on the H200 with ``measured`` (``fast`` or ``faithful``, the run whose breakdown
    gives them), VGGT's and UFM's at the measured rates of CogVideoX-5B
    (:data:`~.cards.H200_MEASURED_ESTIMATORS_S`) times the model's predicted over CogVideoX-5B's
    predicted (another video's frames reach the estimators at other sizes); the loss's, and
    everything elsewhere or with ``measured`` ``None``, predicted."""
    predicted = _update_forwards(estimates_entry(name, estimates)["search_units"], gpu)
    if gpu != "H200" or measured is None:
        return predicted
    if measured not in MEASURED_RUNS:
        raise ValueError(f"measured must be one of {', '.join(MEASURED_RUNS)} or None, got {measured!r}")
    reference = _update_forwards(estimates_entry(CALIBRATION_MODEL, estimates)["search_units"], gpu)
    rates = H200_MEASURED_ESTIMATORS_S[measured]
    return {part: seconds * rates[part] / H200_MEASURED_UPDATES / reference[part] if part in rates else seconds
            for part, seconds in predicted.items()}


def protocol_seconds(name: str, gpu: str, estimates: dict[str, Any] | None = None, measured: str | None = "fast") -> float:
    """The GeCo-protocol scoring of one of registry model ``name``'s videos on ``gpu`` (what a
    search's selection scores each final particle with): the flow estimator on the protocol's
    frame pairs and the geometry estimator on its windows' frames (:func:`scoring_plan` at the
    model's frame rate), at the per-pair and per-frame rates of a guided update's forward
    (:func:`estimator_rates`; the geometry estimator's per frame: a lower bound for windows of more
    frames)."""
    entry = estimates_entry(name, estimates)
    units, frames = entry["search_units"], entry["video"]["frames"]
    rates = estimator_rates(name, gpu, measured, estimates)
    plan = scoring_plan(frames, float(model_named(name).fps), EvaluationConfig())
    return (plan["flow_pairs"] * rates["ufm"] / units["pairs"]
            + plan["windows"] * plan["window_frames"] * rates["vggt"] / units["anchors"])


def _particle_batch(name: str, entry: dict[str, Any], particles: int, gpu: str,
                    num_gpus: int) -> tuple[int | None, bool, float | None]:
    """``(batch, offload, peak_gb)`` of a search on the card: the most particles a call takes (at
    most a ``num_gpus``-th of them) beside every model's weights and every particle's latents and
    video, without model CPU offload if they fit, else with (the estimators resident, the larger
    of the denoiser and the VAE at work). One particle's work runs no backward: the unguided call's
    activations (its prediction and its whole video's decode, more than a scoring's chunk decode;
    the estimators' forward without gradients is not counted). ``(None, False, None)`` where one
    particle's work does not fit."""
    video = entry["video"]
    weights, models = entry["estimates"]["fast/vae"]["leanest"]["weights_gb"], load_attention()["models"][name]
    video_weights = sum(models["weights_gb"].get(k, 0.0) for k in ("transformer", "transformer_2", "vae"))
    work = entry["unguided"]["peak_gb"] - video_weights
    held = particles * particle_gb(video["frames"], video["height"], video["width"])
    budget = DEVICE_HEADROOM * card_memory_gib(gpu)
    at_work = max(models["weights_gb"]["transformer"], models["weights_gb"].get("vae", 0.0))
    for offload, resident in ((False, weights), (True, weights - video_weights + at_work)):
        free = budget - resident - held
        if free >= work:
            size = min(-(-particles // num_gpus), int(free // work))
            return size, offload, resident + held + size * work
    return None, False, None


def search_cost(name: str, particles: int, gpu: str, num_gpus: int = 1, estimates: dict[str, Any] | None = None,
                measured: str | None = "fast") -> dict[str, Any]:
    """A search of ``particles`` unguided particles of registry model ``name``'s traced video on
    ``num_gpus`` cards ``gpu`` with the default ``search`` options (resampling every tenth of the
    schedule through its middle, re-noised copies), as the module docstring says, the estimators
    and the loss at :func:`estimator_rates` (``measured``: which H200 run's): ``time_s`` and its
    parts (``denoiser_s``, ``scoring_s``, ``final_decode_s``, ``protocol_s``, ``offload_s``), the
    particle ``batch`` per call, ``offload`` and the ``peak_gb`` of the pipeline's GPU
    (:func:`_particle_batch`; ``None`` where even one particle's work does not fit)."""
    estimates = load_estimates() if estimates is None else estimates
    entry = estimates_entry(name, estimates)
    units, steps = entry["search_units"], entry["schedule"]["steps"]
    resamplings = len(default_resample_steps(steps))
    per_gpu = -(-particles // num_gpus)
    renoised = -(-(particles - 1) * resamplings // num_gpus)  # at most: every copy after the first
    denoiser = (steps * per_gpu + renoised) * units["prediction_s"][gpu]
    chunks, chunk_bytes = anchor_chunks(name, entry)
    decode = units["scoring_decode_s"][gpu] * particles * resamplings
    spread, moved = decode_over_gpus(decode, chunks, num_gpus, particles * resamplings, chunk_bytes, gpu)
    scorings = sum(estimator_rates(name, gpu, measured, estimates).values()) * particles * resamplings + spread + moved
    final = per_gpu * units["final_decode_s"][gpu]
    protocol = per_gpu * protocol_seconds(name, gpu, estimates, measured)
    batch, offload, peak = _particle_batch(name, entry, particles, gpu, num_gpus)
    moves = offload_transfer_s(name, gpu, resamplings, decodes=per_gpu) if offload else 0.0
    return {"particles": particles, "num_gpus": num_gpus, "time_s": denoiser + scorings + final + protocol + moves,
            "denoiser_s": denoiser, "scoring_s": scorings, "final_decode_s": final, "protocol_s": protocol,
            "offload_s": moves, "resamplings": resamplings, "batch": batch, "offload": offload, "peak_gb": peak}


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
