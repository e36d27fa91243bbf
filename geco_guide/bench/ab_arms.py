"""The arms of one A/B pair (the engine of ``geco ab``, whose run is :mod:`geco_guide.bench.ab_run`):
an arm generated and scored, the pair's two arms, the best-of and search arms added to a complete
pair, their maps and side-by-side videos, and the tiny decoder's agreement with the VAE measured on
a pair. Progress goes to the log, one record before each arm where the caller asks for it."""

from __future__ import annotations

import json
import logging
import sys
import time
from collections.abc import Callable, Sequence
from dataclasses import replace
from datetime import datetime, timezone
from pathlib import Path
from typing import Any

from .. import generation
from ..config import GeCoConfig
from ..estimators import Estimators
from ..io.files import remove_temp_files, write_bytes_atomic, write_json_atomic
from ..io.video import read_video, write_video
from ..loss.geco import CUES
from ..metric.evaluate import evaluate_video, finite_or_none, write_maps_video
from ..metric.render import enlarge, side_by_side
from .ab import (
    AGREEMENT_FILE,
    ARMS,
    BEST_OF,
    METRICS,
    SEARCH,
    UNIT_STEMS,
    WARM_UP,
    BestOf,
    Pair,
    SearchArm,
    arm_config,
    arm_title,
    candidate_paths,
    pair_dir,
    read_candidate,
    run_arms,
)
from .runs import PeakMemory

__all__ = ["AgreementProbe", "add_best_of", "add_maps", "add_search", "measure_decoder_agreement", "run_arm",
           "run_pair", "write_side_by_side"]

logger = logging.getLogger(__name__)

#: What measures the tiny decoder against the VAE in one guided call of ``(models, config, prompt)``:
#: ``{"summary": ..., "updates": [one row per update]}``.
AgreementProbe = Callable[[Any, GeCoConfig, str], dict[str, Any]]


def run_arm(models: Any, cfg: GeCoConfig, pair: Pair, arm: str, folder: Path, maps: bool, estimators: Estimators,
            stem: str | None = None, warm_up: bool = False, search: SearchArm | None = None) -> dict[str, Any]:
    """Generate one arm of a pair into ``folder/<stem>.mp4`` (``stem``: the arm's name) + sidecar
    and score it with ``estimators``; what an unfinished run left there is replaced (other runs'
    outputs were refused before). A prompt's subjects are masked, by the estimators' segmenter, in
    every arm's scores, in the guided arm's guidance and in the search's scoring of its particles.
    ``warm_up``: the process's first work, whose times include the models' warm-up (recorded, and
    left out of the report's means). ``search``: the search arm's particles.

    The search arm's ``generation_s`` is its sampling without the selection (the protocol scoring
    of its final particles, which ``generate`` times with it): that is in its ``evaluation_s``, as a
    best-of arm's candidates' scoring is in its own."""
    stem = stem or arm
    masks = estimators.masks_for(pair.prompt.subjects)
    with PeakMemory(models.pipe.device) as memory:
        generated = generation.generate(arm_config(cfg, pair, arm, search), pair.prompt.text,
                                        out=folder / f"{stem}.mp4", models=models, overwrite=True,
                                        progress=sys.stderr.isatty())  # a log gets a line per arm instead
    start = time.perf_counter()
    evaluation = evaluate_video(generated.video_path, estimators, cfg.evaluation, maps=maps, dynamic_masks=masks)
    evaluation_s = time.perf_counter() - start
    made = generated.sidecar.get("search")
    selection_s = made["selection_s"] if made is not None else 0.0
    record = {
        "video": generated.video_path.name,
        "sidecar": generated.sidecar_path.name,
        **{metric: float(getattr(evaluation, metric)) for metric in METRICS},
        "generation_s": generated.sidecar["timings"]["sampling_s"] - selection_s,
        "evaluation_s": evaluation_s + selection_s,
        "peak_memory_mib": memory.peak_mib,
        "memory_kind": memory.kind,
        "guidance_updates": len(generated.sidecar["guidance_log"]),
        WARM_UP: warm_up,
        "evaluation": evaluation.to_dict(),
    }
    if made is not None:
        record[SEARCH] = {
            "particles": search.particles, "guided": search.guided,
            "chosen": "given" if search.matched is None else "matched", "kept": made["kept"], "kept_seed": made["final_particles"][made["kept"]]["seed"],
            "kept_lineage": made["kept_lineage"], "resample_steps": made["resample_steps"],
            "resampled": sum(r["resampled"] for r in made["resamplings"]),
            "resampling_s": sum(r["seconds"] for r in made["resamplings"]), "selection_s": selection_s,
        }
    if maps:
        record["maps_video"] = write_maps_video(evaluation, folder / f"{stem}_maps.mp4").name
    return record


def add_maps(cfg: GeCoConfig, pair: Pair, out: Path, result: dict[str, Any], estimators: Estimators,
             arms: Sequence[str] | None = None) -> None:
    """The maps videos of the ``arms`` (default: :data:`~geco_guide.bench.ab.ARMS`) of a complete
    pair that have none: their videos are scored again with maps (deterministic: the scores in
    ``result.json`` stay), then ``result.json`` names them."""
    folder = pair_dir(out, pair)
    for arm in ARMS if arms is None else arms:
        if (folder / f"{arm}_maps.mp4").is_file():
            result["arms"][arm]["maps_video"] = f"{arm}_maps.mp4"
            continue
        evaluation = evaluate_video(folder / f"{arm}.mp4", estimators, cfg.evaluation, maps=True,
                                    dynamic_masks=estimators.masks_for(pair.prompt.subjects))
        result["arms"][arm]["maps_video"] = write_maps_video(evaluation, folder / f"{arm}_maps.mp4").name
    write_json_atomic(folder / "result.json", result)


def write_side_by_side(folder: Path, fps: float, result: dict[str, Any] | None = None,
                       arms: Sequence[str] = ARMS) -> None:
    """``side_by_side.mp4``: the videos of the ``arms`` the pair holds next to each other (all of
    :data:`~geco_guide.bench.ab.ARMS` before its ``result`` is written), labelled by their own
    records (``best-of-3``, ``search-4``), enlarged to a readable height as the maps are
    (:func:`~geco_guide.metric.render.enlarge`: a tiny model's 60-pixel video had 6-pixel labels)."""
    shown = [arm for arm in arms if result is None or arm in result["arms"]]
    labels = [arm if result is None else arm_title(arm, result["arms"][arm]) for arm in shown]
    videos = [enlarge(read_video(folder / f"{arm}.mp4")[0]) for arm in shown]
    write_video(folder / "side_by_side.mp4", side_by_side(videos, labels), fps=fps)


def run_pair(models: Any, cfg: GeCoConfig, pair: Pair, out: Path, maps: bool, estimators: Estimators,
             where: str | None = None, warm_up: bool = False) -> dict[str, Any]:
    """Both arms (with ``where``, a stderr line ``<where>: <arm> arm ...`` before each; ``warm_up``:
    see :func:`run_arm`), the side-by-side video, then ``result.json`` (last: it marks the pair
    complete)."""
    folder = pair_dir(out, pair)
    remove_temp_files(folder, UNIT_STEMS)
    arms = {}
    for arm in ARMS:
        if where is not None:
            logger.info("%s: %s arm ...", where, arm)
        arms[arm] = run_arm(models, cfg, pair, arm, folder, maps, estimators, warm_up=warm_up)
    write_side_by_side(folder, cfg.sampling.fps)
    result = {
        "pair": pair.name,
        "prompt_id": pair.prompt.id,
        "prompt": pair.prompt.text,
        **({} if pair.prompt.subjects is None else {"subjects": pair.prompt.subjects}),
        "seed": pair.seed,
        "device": str(models.pipe.device),
        "side_by_side": "side_by_side.mp4",
        "created": datetime.now(timezone.utc).isoformat(timespec="seconds"),
        "arms": arms,
    }
    write_json_atomic(folder / "result.json", result)
    return result


def add_best_of(models: Any, cfg: GeCoConfig, pair: Pair, out: Path, result: dict[str, Any], best_of: BestOf,
                maps: bool, estimators: Estimators, where: str | None = None, redo: bool = False,
                warm_up: bool = False, shown: Sequence[str] | None = None) -> dict[str, Any]:
    """The best-of arm of a complete pair: the candidates not made whole yet (all of them with
    ``redo``; with ``where``, a stderr line before each; ``warm_up``: see :func:`run_arm`), the one
    :func:`~geco_guide.generation.best_candidate` picks copied to ``best_of.mp4`` with a sidecar
    listing every candidate, the side by side of the ``shown`` arms the pair holds (default: its
    two arms and this one), then ``result.json`` with the arm."""
    folder = pair_dir(out, pair)
    candidates = folder / "candidates"
    seeds = best_of.seeds(pair)
    remove_temp_files(candidates, [stem for seed in seeds[1:] for stem in (f"seed{seed}", f"seed{seed}.scores")])
    records = [result["arms"]["unguided"]]
    for k, seed in enumerate(seeds[1:], start=2):
        record = None if redo else read_candidate(out, pair, seed, warn=True, verify=True)
        if record is None:
            if where is not None:
                logger.info("%s: %s arm, candidate %d/%d (seed %d) ...", where, best_of.label, k, best_of.n, seed)
            record = run_arm(models, cfg, Pair(pair.prompt, seed), "unguided", candidates, False, estimators,
                             stem=f"seed{seed}", warm_up=warm_up)
            write_json_atomic(candidate_paths(out, pair, seed)[2], record)
        records.append(record)
    kept = generation.best_candidate([record[generation.SELECTION_SCORE] for record in records])
    video, sidecar, _ = candidate_paths(out, pair, seeds[kept])
    chosen = {"n": best_of.n, "kept_seed": seeds[kept],
              "score": f"{generation.SELECTION_SCORE} (the GeCo protocol, evaluation.*)",
              "candidates": [{"seed": seed, "video": str(candidate_paths(out, pair, seed)[0].relative_to(folder)),
                              **{key: finite_or_none(record[key]) for key in CUES}}
                             for seed, record in zip(seeds, records)]}
    if result["arms"].pop(BEST_OF, None) is not None:  # an earlier arm, of another N: no longer complete
        write_json_atomic(folder / "result.json", result)
    (folder / f"{BEST_OF}_maps.mp4").unlink(missing_ok=True)
    write_bytes_atomic(folder / f"{BEST_OF}.mp4", video.read_bytes())
    write_json_atomic(folder / f"{BEST_OF}.json", {**json.loads(sidecar.read_text(encoding="utf-8")),
                                                    "video": f"{BEST_OF}.mp4", BEST_OF: chosen})
    result["arms"][BEST_OF] = {
        **{key: records[kept][key] for key in (*METRICS, "memory_kind", "evaluation")},
        "video": f"{BEST_OF}.mp4",
        "sidecar": f"{BEST_OF}.json",
        # the arm's compute: every candidate's sampling and scoring
        "generation_s": sum(record["generation_s"] for record in records),
        "evaluation_s": sum(record["evaluation_s"] for record in records),
        "peak_memory_mib": max(record["peak_memory_mib"] for record in records),
        "guidance_updates": 0,
        WARM_UP: any(record.get(WARM_UP, False) for record in records),
        BEST_OF: chosen,
    }
    write_side_by_side(folder, cfg.sampling.fps, result, run_arms(best_of) if shown is None else shown)
    if maps:
        add_maps(cfg, pair, out, result, estimators, (BEST_OF,))
    else:
        write_json_atomic(folder / "result.json", result)
    return result


def add_search(models: Any, cfg: GeCoConfig, pair: Pair, out: Path, result: dict[str, Any], search: SearchArm,
               maps: bool, estimators: Estimators, where: str | None = None, warm_up: bool = False,
               shown: Sequence[str] | None = None) -> dict[str, Any]:
    """The search arm of a complete pair (:func:`run_arm` with ``search``: ``search.particles``
    particles from the pair's seed), the side by side of the ``shown`` arms the pair holds
    (default: its two arms and this one), then ``result.json`` with the arm (an arm of other
    particles it held is dropped first)."""
    folder = pair_dir(out, pair)
    remove_temp_files(folder, (SEARCH, f"{SEARCH}_maps"))
    if result["arms"].pop(SEARCH, None) is not None:  # an earlier arm, of other particles: no longer complete
        write_json_atomic(folder / "result.json", result)
    (folder / f"{SEARCH}_maps.mp4").unlink(missing_ok=True)
    if where is not None:
        logger.info("%s: %s arm ...", where, search.label)
    result["arms"][SEARCH] = run_arm(models, cfg, pair, SEARCH, folder, False, estimators, warm_up=warm_up,
                                     search=search)
    write_side_by_side(folder, cfg.sampling.fps, result, run_arms(None, search) if shown is None else shown)
    if maps:
        add_maps(cfg, pair, out, result, estimators, (SEARCH,))
    else:
        write_json_atomic(folder / "result.json", result)
    return result


def measure_decoder_agreement(models: Any, cfg: GeCoConfig, pair: Pair, out: Path, measure: AgreementProbe) -> None:
    """``out/decoder_agreement.json``: one more guided call of ``pair`` in which the VAE and the
    tiny decoder both decode the anchor frames at every update, measured by ``measure`` (gradient
    cosine, both losses, anchor PSNR: the perf layer's, which the command hands down)."""
    logger.info("measuring the tiny decoder against the VAE on %s (one more guided call) ...", pair.name)
    unmasked = replace(pair, prompt=replace(pair.prompt, subjects=None))  # the decoders compared, without a segmenter
    write_json_atomic(out / AGREEMENT_FILE, {"pair": pair.name, **measure(models, arm_config(cfg, unmasked, "guided"),
                                                                          pair.prompt.text)})
