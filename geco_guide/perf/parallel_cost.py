"""Guided and unguided runs over several GPUs of one card: context parallelism, split CFG and the
anchor decode dealt over the GPUs; arithmetic on the shipped estimates, nothing traced.

Context parallelism (``run.context_parallel``, diffusers' ``ContextParallelConfig``) splits the
denoiser's token sequence over ``N`` ranks: each rank computes ``1 / N`` of every call, forward and
backward (linear layers, norms and attention all scale with the tokens; each rank still holds and
reads all the weights, milliseconds a call at these sizes, left out), and the self-attentions
exchange what they read (:func:`attention_traffic`, from the traced attention shapes of
:mod:`.attention_shapes`) over the card's interconnect (:data:`~.cards.INTERCONNECT_BYTES_PER_S`),
not overlapped with compute. As ``run.context_parallel`` runs it, the attention is Ulysses (heads
that do not divide over the ranks are refused) and the anchor chunks are dealt over the ranks as
``run.devices`` deals them over GPUs (:func:`~.cost.decode_over_gpus`: each rank decodes its
chunks, forward and backward, and only the anchor frames travel); every rank runs the estimators,
the loss and the final decode whole. ``compose`` predicts what the runtime does not run: ring
attention where the heads do not divide, and split CFG (``run.split_cfg``, the GeCo pipeline's:
the two CFG halves on two groups of ranks) where that is faster.

The estimates keep no denoiser time per plan: :func:`denoiser_seconds` gets it from one plan's
fast and faithful estimates, which differ by the differentiated calls alone (the same decode,
estimators and loss; fast mode predicts once more after each time-travel update). Memory per rank
(the first GPU, which also holds the estimators): the planner's rule
(:func:`~geco_guide.sampler.running.memory_plan.process_peak`): the weights replicated, the differentiated
denoiser's activations (the plan's faithful peak minus its fast peak) divided over the ranks that
share a call, everything else whole (an upper bound: the fast peak's own denoiser activations are
not divided). Without context parallelism the first GPU's peak is the one-GPU peak (the planner's
rule for ``run.devices``). Where nothing fits, model CPU offload, its transfers in the time
(:func:`~.search_cost.offload_transfer_s`).
"""

from __future__ import annotations

from typing import Any

from ..families import model_named
from ..sampler.running.memory_plan import DEVICE_HEADROOM, PLANS, load_estimates, process_peak
from .attention_shapes import load_attention
from .cards import GPU_SPECS, INTERCONNECT_BYTES_PER_S, card_memory_gib
from .cost import decode_over_gpus
from .full_size import text_embed_shape
from .search_cost import anchor_chunks, estimates_entry, guidance_cost, offload_transfer_s
from .tracing import count_schedule_calls

__all__ = ["attention_traffic", "cfg_half_bytes", "denoiser_seconds", "parallel_guidance", "parallel_report",
           "parallel_table", "parallel_unguided", "schedule_counts"]


def _numel(shape: list[int]) -> int:
    out = 1
    for side in shape:
        out *= side
    return out


def attention_traffic(attention: list[dict[str, Any]], ranks: int, backend: str) -> dict[str, float]:
    """Bytes one rank sends in one prediction's self-attentions with the tokens split over
    ``ranks`` (``attention``: the traced calls of :func:`~.attention_shapes.denoiser_attention`,
    query ``[B, heads, tokens, head_dim]``), ``forward`` and ``backward``. A query of ``q`` bytes
    leaves ``q / ranks`` on each rank. ``ulysses`` (all-to-all of the heads): the query, key, value
    and output each all-to-all once, a rank keeping ``1 / ranks`` of its share,
    ``4 q (ranks - 1) / ranks^2`` forward and as much backward (their gradients). ``ring``: each
    rank's key and value pass ``ranks - 1`` hops, ``2 q (ranks - 1) / ranks`` forward, twice that
    backward (key and value again, and their gradients). Only the self-attentions of the split
    sequence move anything (:func:`_split_attention`)."""
    forward = 0.0
    for call in _split_attention(attention):
        if ranks == 1:
            continue
        q = _numel(call["query"]) * call["element_bytes"] * call["calls"]
        forward += 4 * q * (ranks - 1) / ranks**2 if backend == "ulysses" else 2 * q * (ranks - 1) / ranks
    return {"forward": forward, "backward": forward if backend == "ulysses" else 2 * forward}


def _split_attention(attention: list[dict[str, Any]]) -> list[dict[str, Any]]:
    """The self-attentions over the sequence a context-parallel plan splits (the longest query's
    tokens); a cross-attention reads a key every rank holds (the text), and a shorter sequence (a
    text refiner's) runs whole on every rank: neither moves anything."""
    tokens = max(call["query"][2] for call in attention)
    return [call for call in attention if call["query"][2] == call["key"][2] == tokens]


def _heads_divide(attention: list[dict[str, Any]], ranks: int) -> bool:
    """Whether every split self-attention's heads divide over the ranks (what Ulysses needs)."""
    return all(call["query"][1] % ranks == 0 for call in _split_attention(attention))


def schedule_counts(name: str, entry: dict[str, Any]) -> dict[str, int]:
    """``steps``, ``updates`` and ``time_travel`` (the time-travel updates, after each of which fast
    mode predicts once more) of registry model ``name``'s traced schedule (its estimates' entry)."""
    schedule = entry["schedule"]
    settings = {"preset": "full", "model": name, **entry["video"], "steps": schedule["steps"],
                "repeats": schedule["repeats"], "time_travel": schedule["time_travel"]}
    counts = count_schedule_calls("fast", settings)
    return {"steps": schedule["steps"], "updates": counts["updates"], "time_travel": counts["time_travel_updates"]}


def denoiser_seconds(entry: dict[str, Any], counts: dict[str, int], plan: str, decoder: str, gpu: str,
                     mode: str) -> dict[str, float]:
    """The denoiser's part of a guided run under ``plan`` on one ``gpu``: ``cfg_calls`` predictions
    without gradients of ``cfg_s`` each (the search units' prediction), ``grad_calls``
    differentiated ones of ``grad_s`` each (faithful mode: the plan's faithful run minus its fast
    run, plus fast mode's extra predictions, over the updates)."""
    unguided, cfg_s = entry["unguided"]["time_s"][gpu], entry["search_units"]["prediction_s"][gpu]
    if mode == "fast":
        return {"cfg_calls": counts["steps"] + counts["time_travel"], "cfg_s": cfg_s, "grad_calls": 0, "grad_s": 0.0}
    fast, faithful = (entry["estimates"][f"{m}/{decoder}"][plan]["ratio_guided_over_unguided"][gpu] * unguided
                      for m in ("fast", "faithful"))
    grad_s = (faithful - fast + counts["time_travel"] * cfg_s) / counts["updates"]
    return {"cfg_calls": counts["steps"], "cfg_s": cfg_s, "grad_calls": counts["updates"], "grad_s": grad_s}


def cfg_half_bytes(name: str, entry: dict[str, Any]) -> int:
    """What split CFG moves per call to the second half's GPUs and back: its latents in and its
    prediction out (bf16), its text embeddings in."""
    model, video = model_named(name), entry["video"]
    s = model.spatial_compression
    latents = (((video["frames"] - 1) // model.temporal_compression + 1) * model.latent_channels
               * (video["height"] // s) * (video["width"] // s))
    tokens, dim = text_embed_shape(name)[1:]
    return 2 * (2 * latents) + 2 * tokens * dim


def _layouts(name: str, num_gpus: int, context_parallel: bool, compose: bool) -> list[tuple[int, bool]]:
    """``(ranks splitting each call's tokens, split CFG)`` to weigh on ``num_gpus`` GPUs: split CFG
    where the GeCo pipeline runs the model, on two GPUs (``run.devices``) or, composed with context
    parallelism (``compose``, not run), two groups of ranks."""
    split = model_named(name).guided_by == "pipeline" and num_gpus >= 2
    if not context_parallel:
        return [(1, False)] + [(1, True)] * split
    composed = compose and split and num_gpus % 2 == 0 and num_gpus >= 4
    return [(num_gpus, False)] + [(num_gpus // 2, True)] * composed


def _traffic_s(facts: dict[str, Any], gpu: str, cp: int, split: bool, calls: dict[str, float],
               recompute: bool) -> tuple[float, str | None]:
    """Seconds of the collectives of ``calls`` (``cfg_calls``, ``grad_calls``) on one rank, and the
    backend: Ulysses (the less traffic) where the heads divide over the ranks, else ring."""
    if cp == 1:
        return 0.0, None
    backend = "ulysses" if _heads_divide(facts["attention"], cp) else "ring"
    traffic = attention_traffic(facts["attention"], cp, backend)
    share = 0.5 if split else 1.0  # a group of ranks runs one CFG half
    grad = traffic["forward"] * (1 + recompute) + traffic["backward"]
    moved = share * (calls["cfg_calls"] * traffic["forward"] + calls["grad_calls"] * grad)
    return moved / INTERCONNECT_BYTES_PER_S[gpu], backend


def _layout_cost(name: str, entry: dict[str, Any], counts: dict[str, int], gpu: str, num_gpus: int,
                 layout: tuple[int, bool], plan: Any, offload: bool, mode: str, decoder: str) -> dict[str, Any]:
    """One ``layout`` (:func:`_layouts`) under one plan, with or without offload, the anchor chunks
    dealt over ``num_gpus``: :func:`parallel_guidance`'s keys."""
    cp, split = layout
    ranks = cp * (2 if split else 1)
    estimate = entry["estimates"][f"{mode}/{decoder}"][plan.name]
    guided = estimate["ratio_guided_over_unguided"][gpu] * entry["unguided"]["time_s"][gpu]
    calls = denoiser_seconds(entry, counts, plan.name, decoder, gpu, mode)
    denoiser = calls["cfg_calls"] * calls["cfg_s"] + calls["grad_calls"] * calls["grad_s"]
    traffic_s, backend = _traffic_s(load_attention()["models"][name], gpu, cp, split, calls,
                                    plan.denoiser_checkpointing)
    if split:
        halves = calls["cfg_calls"] + 2 * calls["grad_calls"]
        traffic_s += halves * cfg_half_bytes(name, entry) / INTERCONNECT_BYTES_PER_S[gpu]
    seconds = guided - denoiser + denoiser / ranks + traffic_s
    if estimate["anchor_decode_s"] is not None and num_gpus > 1:
        chunks, chunk_bytes = anchor_chunks(name, entry)
        decode = estimate["anchor_decode_s"][gpu]
        spread, moved = decode_over_gpus(decode, chunks, num_gpus, counts["updates"], chunk_bytes, gpu)
        seconds += spread + moved - decode
    if offload:
        seconds += offload_transfer_s(name, gpu, counts["updates"], decoder)
    key = "offload_peak_gb" if offload else "peak_gb"
    fast_peak = entry["estimates"][f"fast/{decoder}"][plan.name][key]
    sharing = ranks if cp > 1 else 1  # run.devices plans for the one-GPU peak
    peak = process_peak(estimate[key], fast_peak, sharing) if mode == "faithful" else estimate[key]
    return {"plan": plan.name, "offload": offload, "time_s": seconds, "peak_gb": peak, "context_parallel": cp,
            "split_cfg": split, "backend": backend, "traffic_s": traffic_s, "denoiser_s": denoiser / ranks + traffic_s}


def parallel_guidance(name: str, gpu: str, num_gpus: int, mode: str = "faithful", decoder: str = "vae",
                      context_parallel: bool = True, compose: bool = False,
                      estimates: dict[str, Any] | None = None) -> dict[str, Any]:
    """The guided run of registry model ``name``'s traced video on ``num_gpus`` cards ``gpu``, the
    anchor chunks dealt over the GPUs: with ``context_parallel`` every call's tokens split over the
    GPUs as ``run.context_parallel`` splits them (Ulysses), or with ``compose`` composed with what
    it does not run (ring attention where the heads do not divide, split CFG where faster; see the
    module docstring); else ``run.devices``, split CFG where the pipeline has it and it is faster. The plan of least time whose peak on the first GPU fits the card (94 % of its memory), without
    model CPU offload if one does. Returns ``plan``, ``offload``, ``time_s``, ``peak_gb``,
    ``context_parallel`` (ranks per call), ``split_cfg``, ``backend``, ``traffic_s`` (the
    collectives and split CFG's transfers) and ``denoiser_s`` (per rank, with them); ``plan``
    ``None`` and ``reason`` where nothing fits."""
    if num_gpus < 1:
        raise ValueError(f"the number of GPUs must be >= 1, got {num_gpus}")
    estimates = load_estimates() if estimates is None else estimates
    entry = estimates_entry(name, estimates)
    if f"{mode}/{decoder}" not in entry["estimates"]:
        return {"plan": None, "reason": f"no estimates with decoder {decoder} ({name} has no tiny decoder)"}
    attention = load_attention()["models"][name]["attention"]
    if context_parallel and not compose and not _heads_divide(attention, num_gpus):
        heads = sorted({call["query"][1] for call in _split_attention(attention)})
        return {"plan": None, "reason": f"Ulysses needs the heads ({', '.join(map(str, heads))}) divisible by {num_gpus}"}
    counts, budget = schedule_counts(name, entry), DEVICE_HEADROOM * card_memory_gib(gpu)
    least = None
    for offload in (False, True):
        # the more saving plan first: a tie in time goes to it, as the planner's
        costs = [_layout_cost(name, entry, counts, gpu, num_gpus, layout, plan, offload, mode, decoder)
                 for layout in _layouts(name, num_gpus, context_parallel, compose) for plan in reversed(PLANS)]
        least = min(costs, key=lambda cost: cost["peak_gb"])
        fitting = [cost for cost in costs if cost["peak_gb"] <= budget]
        if fitting:
            return min(fitting, key=lambda cost: cost["time_s"])
    return {"plan": None, "reason": f"does not fit ({least['peak_gb']:.1f} GiB at least, with offload)",
            "least_peak_gb": least["peak_gb"]}


def parallel_unguided(name: str, gpu: str, num_gpus: int, estimates: dict[str, Any] | None = None) -> dict[str, Any]:
    """The unguided run (the stock pipeline's) of registry model ``name``'s traced video with its
    denoiser's tokens split over ``num_gpus`` cards ``gpu`` as ``run.context_parallel`` splits
    them: ``time_s`` (its predictions at ``1 / N`` plus the collectives), ``traffic_s``,
    ``backend``; ``peak_gb`` per GPU is the one-GPU peak (its final decode, not split, is the larger
    part). ``time_s`` ``None`` and ``reason`` where Ulysses cannot split the heads."""
    entry = estimates_entry(name, estimates)
    attention = load_attention()["models"][name]["attention"]
    if not _heads_divide(attention, num_gpus):
        return {"time_s": None, "reason": f"Ulysses needs the heads divisible by {num_gpus}"}
    steps = entry["schedule"]["steps"]
    cfg_s = entry["search_units"]["prediction_s"][gpu]
    traffic_s, backend = _traffic_s(load_attention()["models"][name], gpu, num_gpus, False,
                                    {"cfg_calls": steps, "grad_calls": 0}, False)
    seconds = entry["unguided"]["time_s"][gpu] - steps * cfg_s * (1 - 1 / num_gpus) + traffic_s
    return {"time_s": seconds, "traffic_s": traffic_s, "backend": backend, "peak_gb": entry["unguided"]["peak_gb"]}


def parallel_report(name: str, mode: str, num_gpus: int, estimates: dict[str, Any] | None = None) -> dict[str, Any]:
    """``geco bench cost --context-parallel N``: registry model ``name``'s run in ``mode`` on every
    card of :data:`~.cards.GPU_SPECS`, on one GPU and on ``num_gpus`` (``run.devices`` with split
    CFG where it helps; context parallelism as ``run.context_parallel`` runs it, the anchor decode
    dealt over the GPUs; and composed with ring attention or split CFG, which it does not run),
    beside the unguided run on one GPU and split over ``num_gpus``, and the bytes one rank sends
    per prediction with each attention backend."""
    estimates = load_estimates() if estimates is None else estimates
    entry = estimates_entry(name, estimates)
    attention = load_attention()["models"][name]["attention"]
    cards = {}
    for gpu in GPU_SPECS:
        row: dict[str, Any] = {"unguided_s": entry["unguided"]["time_s"][gpu],
                               "unguided_parallel": parallel_unguided(name, gpu, num_gpus, estimates)}
        if mode != "unguided":
            one = guidance_cost(name, gpu, mode, estimates=estimates)
            if one["plan"] is None:
                least = min(e["offload_peak_gb"] for e in entry["estimates"][f"{mode}/vae"].values())
                one["reason"] = f"does not fit ({least:.1f} GiB at least, with offload)"
            row.update(one_gpu=one,
                       devices=parallel_guidance(name, gpu, num_gpus, mode, context_parallel=False, estimates=estimates),
                       context_parallel=parallel_guidance(name, gpu, num_gpus, mode, estimates=estimates),
                       composed=parallel_guidance(name, gpu, num_gpus, mode, compose=True, estimates=estimates))
        cards[gpu] = row
    traffic = {backend: attention_traffic(attention, num_gpus, backend) for backend in ("ulysses", "ring")}
    return {"subcommand": "cost --context-parallel", "model": name, "mode": mode, "num_gpus": num_gpus,
            "note": "predicted from the shipped estimates and traced attention shapes; nothing measured",
            "attention_bytes_per_prediction_per_rank": traffic, "cards": cards}


def _cell(cost: dict[str, Any], unguided_s: float) -> str:
    if cost["plan"] is None:
        return cost["reason"]
    layout = [cost["plan"]] + ["offload"] * cost["offload"] + ["split CFG"] * bool(cost.get("split_cfg"))
    if cost.get("context_parallel", 1) > 1:
        layout.append(f"{cost['backend']} over {cost['context_parallel']}")
    return f"{cost['time_s']:.0f} s ({cost['time_s'] / unguided_s:.2f}x), {cost['peak_gb']:.1f} GiB ({', '.join(layout)})"


def parallel_table(report: dict[str, Any]) -> str:
    """Markdown: :func:`parallel_report` per card, times over the one-GPU unguided run."""
    n, mode = report["num_gpus"], report["mode"]
    traffic = report["attention_bytes_per_prediction_per_rank"]
    lines = [f"{report['model']}, {mode}, predicted on 1 and {n} GPUs of each card (x unguided on 1 GPU; "
             f"GiB: the first GPU's peak); over {n} ranks one prediction's self-attentions send "
             + ", ".join(f"{t['forward'] / 1e9:.2f} GB per rank forward with {b}" for b, t in traffic.items()) + ":"]
    header = ["card", "unguided, 1 GPU", f"unguided, context parallel over {n}"]
    if mode != "unguided":
        header += [f"{mode}, 1 GPU", f"{mode}, run.devices over {n}", f"{mode}, context parallel over {n}",
                   f"{mode}, context parallel over {n} with ring or split CFG (not run)"]
    lines += ["| " + " | ".join(header) + " |", "|" + "---|" * len(header)]
    for gpu, row in report["cards"].items():
        unguided, split = row["unguided_s"], row["unguided_parallel"]
        cells = [gpu, f"{unguided:.0f} s", split["reason"] if split["time_s"] is None else
                 f"{split['time_s']:.0f} s ({split['time_s'] / unguided:.2f}x)"]
        if mode != "unguided":
            cells += [_cell(row[key], unguided) for key in ("one_gpu", "devices", "context_parallel", "composed")]
        lines.append("| " + " | ".join(cells) + " |")
    return "\n".join(lines)
