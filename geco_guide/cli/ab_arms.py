"""The work of ``geco ab`` (:mod:`geco_guide.cli.ab`), imported once its arguments parsed: the
inputs checked before any model loads, the arms of a pair generated and scored, a process's share
of the pairs, the search arm's K matched on this machine, the report.

A run goes in two phases, so that ``--search matched`` can measure the arms it matches before it
searches, in one process or in several (``accelerate launch``): first every process makes its
pairs' unguided and guided arms (and best-of arms); then, once every process is done, the main
process matches K (:func:`match_search`) and every process adds the search arm to its pairs.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, replace
from datetime import datetime, timezone
from functools import partial
from pathlib import Path
from typing import Any

from .. import generation
from ..bench.ab import (
    AGREEMENT_FILE,
    ARMS,
    BEST_OF,
    MATCHED_SEARCH_FILE,
    MAX_SEED,
    METRICS,
    SEARCH,
    TINY_GUIDANCE_NOTE,
    UNIT_STEMS,
    WARM_UP,
    BestOf,
    InputError,
    Pair,
    SearchArm,
    arm_config,
    arm_title,
    best_of_problem,
    candidate_paths,
    expected_search_s,
    has_maps,
    matched_best_of,
    matched_particles,
    pair_dir,
    parse_seeds,
    plan_pairs,
    read_agreement,
    read_candidate,
    read_matched_search,
    read_result,
    run_arms,
    search_problem,
    shared_candidates,
)
from ..bench.ab_report import write_report
from ..bench.report import fmt, interval_text
from ..bench.runs import PeakMemory, pin_config, process_config, process_state, read_finished, shard
from ..config import GeCoConfig, config_to_dict
from ..estimators import Estimators, load_estimators, load_segmenter
from ..io.devices import resolve_device
from ..io.files import WriteError, remove_temp_files, write_bytes_atomic, write_json_atomic
from ..io.video import read_video, write_video
from ..loss.geco import CUES
from ..metric.evaluate import evaluate_video, finite_or_none, write_maps_video
from ..metric.render import enlarge, side_by_side
from ..perf.decoder_agreement import agreement_rows, agreement_summary
from ..types import plural
from .prompt_files import read_prompts

__all__ = ["PROBE_STEPS", "Inputs", "ProcessModels", "SearchRequest", "add_best_of", "add_maps", "add_search",
           "add_search_arms", "check_output_folder", "choose_best_of", "choose_search", "execute", "foreign_video",
           "local_card", "make_pairs", "match_search", "measure_decoder_agreement", "measure_particle_scoring",
           "predicted_ratio", "run_arm", "run_pair", "validate_inputs", "versions", "write_side_by_side"]

#: The probe that measures one particle's scoring at a resampling step (:func:`measure_particle_scoring`):
#: a search of one particle over this many denoising steps, resampled at each.
PROBE_STEPS = 2


# ----------------------------------------------------------------------------------------------
# inputs, checked before any model loads


@dataclass(frozen=True)
class SearchRequest:
    """What ``--search`` asks for: ``particles`` (``None``: ``matched``, chosen once the first
    pairs are made) and whether they are guided (``--search-guided``)."""

    particles: int | None
    guided: bool = False


@dataclass
class Inputs:
    """What a run works on, once every input passed its checks."""

    cfg: GeCoConfig
    pairs: list[Pair]
    out: Path
    best_of: BestOf | None = None
    search: SearchRequest | None = None


def validate_inputs(args: argparse.Namespace) -> Inputs:
    """Every check that needs no model: prompts, seeds, config (what generate checks before loading,
    for the search arm too), the best-of and search arms, output folder."""
    from .kit import config_from_args

    prompts = read_prompts(args.prompts)
    seeds = parse_seeds(args.seeds)
    cfg = config_from_args(args, args.overrides)
    if not cfg.guidance.enabled:
        raise InputError("guidance.enabled=false leaves nothing to compare: the guided arm needs guidance")
    if cfg.search.particles is not None:
        raise InputError(f"search.particles={cfg.search.particles} would make every arm a search: leave it unset and "
                         f"pass --search {cfg.search.particles} for a search arm (search.* sets its other options)")
    search = choose_search(args.search, args.search_guided, seeds)
    # what generate checks before loading, here before run.json is pinned or any video written: the
    # guided arm (run.particle_batch is the search arm's, checked below); each arm then runs what it
    # can act on (arm_config), and the run keeps its config as given, the device resolved
    guided = cfg if search is None else replace(cfg, run=replace(cfg.run, particle_batch=None))
    cfg = replace(cfg, model=generation.check_generation(guided, prompts[0].text).model)
    best_of = choose_best_of(args.best_of, args.gpu, cfg, seeds)
    if search is not None:  # K particles of the first pair, checked as generate checks them (K >= 2 if matched)
        cfg.search.steps(cfg.sampling.num_inference_steps)  # else found when the search starts, after the pairs
        first = SearchArm(search.particles or 2, search.guided)
        generation.check_generation(arm_config(cfg, Pair(prompts[0], seeds[0]), SEARCH, first), prompts[0].text,
                                    loaded=True)
    pairs = plan_pairs(prompts, seeds)
    out = Path(args.out)
    check_output_folder(out, cfg, pairs, args.overwrite, best_of, search)
    return Inputs(cfg, pairs, out, best_of, search)


def check_output_folder(out: Path, cfg: GeCoConfig, pairs: Sequence[Pair], overwrite: bool = False,
                        best_of: BestOf | None = None, search: SearchRequest | None = None) -> None:
    """Refuse an output folder that holds results of another config or other prompt texts, or
    videos another run left (their sidecars name another prompt or config), unless ``overwrite``."""
    from ..bench.runs import check_output_folder as check_run_folder

    check_run_folder(out, cfg, overwrite)
    if overwrite:
        return
    for pair in pairs:
        result = read_finished(pair_dir(out, pair) / "result.json", [], f"pair {pair.name}", warn=False)
        if result is not None and result.get("prompt") != pair.prompt.text:
            raise InputError(
                f"{pair_dir(out, pair)} was made for the prompt {result.get('prompt')!r}, not {pair.prompt.text!r}; "
                "give this prompt another id, use a new --out folder or pass --overwrite"
            )
        made = [(pair_dir(out, pair) / f"{arm}.json", pair, arm) for arm in (*ARMS, *((SEARCH,) if search else ()))]
        made += [(candidate_paths(out, pair, seed)[1], Pair(pair.prompt, seed), "unguided")
                 for seed in (best_of.seeds(pair)[1:] if best_of is not None else ())]
        for sidecar, unit, arm in made:
            if foreign_video(sidecar, cfg, unit, arm):
                raise InputError(
                    f"{sidecar} was made by another run (its prompt or config differ); "
                    "pass --overwrite to replace it, or use a new --out folder"
                )


def foreign_video(sidecar_path: Path, cfg: GeCoConfig, pair: Pair, arm: str) -> bool:
    """Whether the sidecar (if readable) records a video of another prompt or config than ``arm``
    of ``pair`` (a search arm: of its own particles, guided or not, which a run of another K redoes):
    its :func:`~geco_guide.generation.video_key`, the hash generate's default names carry, differs."""
    try:
        sidecar = json.loads(sidecar_path.read_text(encoding="utf-8"))
        made = generation.video_key(sidecar["config"], sidecar["prompt"])
        config = sidecar["config"]
        search = SearchArm(int(config["search"]["particles"]), bool(config["guidance"]["enabled"])) if arm == SEARCH \
            else None
    except (OSError, ValueError, KeyError, TypeError, AttributeError):  # none, or not a sidecar: redone anyway
        return False
    return made != generation.video_key(config_to_dict(arm_config(cfg, pair, arm, search)), pair.prompt.text)


def local_card(cfg: GeCoConfig) -> str | None:
    """The card of :data:`~geco_guide.perf.cards.GPU_SPECS` that ``model.device`` is, or None (a CPU,
    or a GPU the cost model does not know)."""
    import torch

    from ..perf.cards import GPU_SPECS

    device = resolve_device(cfg.model.device)
    if device.type != "cuda":
        return None
    name = torch.cuda.get_device_name(device).replace(" ", "").upper()
    # the longest first: an "L40S" is no "L4"
    return next((card for card in sorted(GPU_SPECS, key=len, reverse=True) if card.upper() in name), None)


def predicted_ratio(cfg: GeCoConfig, gpu: str) -> float:
    """The guided / unguided sampling time ratio the cost model predicts for ``cfg``'s model, video
    size, steps, schedule, mode and anchor decoder on ``gpu``, under the memory plan
    ``memory_plan=auto`` picks for the card (as ``geco bench cost --gpu``). The model is the
    registry's ``model.name`` (whatever folder holds its weights), or the tiny models."""
    from ..estimators import TINY_RANDOM
    from ..perf.cost import cost_report, cost_settings
    from ..perf.plans import KNOWN_MODELS, card_plan

    key = "tiny" if cfg.model.id == TINY_RANDOM and cfg.model.name == KNOWN_MODELS["tiny"]["family"] else cfg.model.name
    if key not in KNOWN_MODELS:
        traced = ", ".join(name for name in KNOWN_MODELS if name != "tiny")
        raise InputError(f"--best-of matched: the cost model does not trace {cfg.model.name!r} (it traces {traced} "
                         "and the tiny models); pass an integer --best-of N")
    known, s, guidance = KNOWN_MODELS[key], cfg.sampling, cfg.guidance
    mode = "faithful" if guidance.denoiser_grad else "fast"
    card = card_plan(gpu, mode, guidance.decoder, s.num_frames, s.height, s.width, model=key)
    if card["plan"] is None:
        raise InputError(f"--best-of matched: no guided run of this config fits the {gpu}: {card['reason']}")
    settings = cost_settings(preset=known["preset"], model=known["model"] or known["family"],
                             steps=s.num_inference_steps, frames=s.num_frames, height=s.height, width=s.width,
                             dtype=None, decoder=guidance.decoder, plan=card["plan"])
    settings.update(repeats=guidance.repeats, time_travel=list(guidance.time_travel or []) or None)
    return float(cost_report(settings, mode)["roofline"]["ratio_guided_over_unguided"][gpu])


def choose_best_of(value: str | None, gpu: str | None, cfg: GeCoConfig, seeds: Sequence[int]) -> BestOf | None:
    """The best-of arm ``--best-of`` and ``--gpu`` ask for (None: no best-of arm); one
    :class:`InputError` line for a bad value, before anything is generated."""
    from ..perf.cards import GPU_SPECS

    if gpu is not None and gpu not in GPU_SPECS:
        raise InputError(f"--gpu must be one of {', '.join(GPU_SPECS)}, got {gpu!r}")
    if value is None:
        if gpu is not None:
            raise InputError("--gpu names the card --best-of matched predicts for; pass --best-of matched too")
        return None
    if value == "matched":
        card = gpu or local_card(cfg)
        if card is None:
            raise InputError(f"--best-of matched needs a card the cost model knows ({', '.join(GPU_SPECS)}) and "
                             f"the device here ({resolve_device(cfg.model.device)}) is none: pass --gpu NAME or an "
                             "integer --best-of N")
        best_of = matched_best_of(predicted_ratio(cfg, card), card, seeds)
        if best_of.matched_n is not None:
            print(f"note: --best-of matched: N = {best_of.matched_n} predicted on the {card}, capped at {best_of.n}, the "
                  f"least spacing of --seeds: give seeds at least {best_of.matched_n} apart for N = "
                  f"{best_of.matched_n}", file=sys.stderr)
    else:
        if gpu is not None:
            raise InputError("--gpu is for --best-of matched; an integer --best-of N needs no card")
        n = _count(value, "--best-of", "best-of-1 is the unguided arm")
        best_of = BestOf(n)
    if max(seeds) + best_of.n - 1 > MAX_SEED:
        raise InputError(f"--best-of {best_of.n} from seed {max(seeds)} runs past the last seed, 2**63 - 1")
    shared = shared_candidates(seeds, best_of.n)
    if shared is not None:  # said before the run, not only in its report
        print(f"warning: --best-of {best_of.n}: {shared}", file=sys.stderr)
    return best_of


def _count(value: str, flag: str, one: str) -> int:
    """``value`` of ``flag`` as an integer >= 2 (1 is ``one``), or one :class:`InputError` line."""
    try:
        n = int(value)
    except ValueError:
        raise InputError(f"{flag} takes an integer >= 2 or 'matched', got {value!r}") from None
    if n < 2:
        raise InputError(f"{flag} takes an integer >= 2 or 'matched', got {n} ({one})")
    return n


def choose_search(value: str | None, guided: bool, seeds: Sequence[int]) -> SearchRequest | None:
    """The search arm ``--search`` and ``--search-guided`` ask for (None: no search arm); one
    :class:`InputError` line for a bad value, before anything is generated."""
    if value is None:
        if guided:
            raise InputError("--search-guided guides the search arm's particles; pass --search K too")
        return None
    if value == "matched":
        if guided:
            raise InputError("--search matched matches unguided particles to the guided arm's time; K guided particles "
                             "cost K guided videos, which no K >= 2 matches: pass an integer --search K")
        particles = None
    else:
        particles = _count(value, "--search", "a search of one particle is the unguided arm")
    if max(seeds) + (particles or 2) - 1 > MAX_SEED:
        raise InputError(f"--search {particles or 2} from seed {max(seeds)} runs past the last seed, 2**63 - 1")
    return SearchRequest(particles, guided)


# ----------------------------------------------------------------------------------------------
# the arms of one pair


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
            print(f"{where}: {arm} arm ...", file=sys.stderr, flush=True)
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
                print(f"{where}: {best_of.label} arm, candidate {k}/{best_of.n} (seed {seed}) ...", file=sys.stderr,
                      flush=True)
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
        print(f"{where}: {search.label} arm ...", file=sys.stderr, flush=True)
    result["arms"][SEARCH] = run_arm(models, cfg, pair, SEARCH, folder, False, estimators, warm_up=warm_up,
                                     search=search)
    write_side_by_side(folder, cfg.sampling.fps, result, run_arms(None, search) if shown is None else shown)
    if maps:
        add_maps(cfg, pair, out, result, estimators, (SEARCH,))
    else:
        write_json_atomic(folder / "result.json", result)
    return result


def measure_decoder_agreement(models: Any, cfg: GeCoConfig, pair: Pair, out: Path) -> None:
    """``out/decoder_agreement.json``: one more guided call of ``pair`` in which the VAE and the
    tiny decoder both decode the anchor frames at every update (gradient cosine, both losses,
    anchor PSNR: :func:`geco_guide.perf.decoder_agreement.agreement_rows`)."""
    print(f"measuring the tiny decoder against the VAE on {pair.name} (one more guided call) ...", file=sys.stderr,
          flush=True)
    unmasked = replace(pair, prompt=replace(pair.prompt, subjects=None))  # the decoders compared, without a segmenter
    rows = agreement_rows(models, arm_config(cfg, unmasked, "guided"), pair.prompt.text)
    write_json_atomic(out / AGREEMENT_FILE, {"pair": pair.name, "summary": agreement_summary(rows), "updates": rows})


def _pair_line(result: dict[str, Any], best_of: BestOf | None) -> str:
    unguided, guided = (result["arms"][arm] for arm in ARMS)
    warm = " with the models' warm-up, left out of the means" if guided.get(WARM_UP) else ""
    line = (f"fused {unguided['fused']:.4f} -> {guided['fused']:.4f} "
            f"(sampling {unguided['generation_s']:.1f} s -> {guided['generation_s']:.1f} s{warm})")
    if best_of is not None:
        selected = result["arms"][BEST_OF]
        line += (f"; {best_of.label} {selected['fused']:.4f} (kept seed {selected[BEST_OF]['kept_seed']}, "
                 f"sampling {selected['generation_s']:.1f} s)")
    return line


# ----------------------------------------------------------------------------------------------
# a process's share of the pairs


class ProcessModels:
    """The models of one process, each loaded once, when first needed: the estimators (with the
    text segmenter once a prompt with subjects needs it) and the video pipeline once an arm is
    generated; a line on stderr before each load."""

    def __init__(self, cfg: GeCoConfig):
        self.cfg = cfg
        self.models: Any = None
        self.estimators: Estimators | None = None

    def get(self, *, generate: bool, segmenter: bool) -> Estimators:
        """The estimators, with the video pipeline (:attr:`models`) loaded where ``generate``."""
        cfg, device = self.cfg, resolve_device(self.cfg.model.device)
        if segmenter and (self.estimators is None or self.estimators.segmenter is None):
            print(f"loading segmenter: {cfg.estimators.segmenter} ...", file=sys.stderr, flush=True)
        if self.estimators is None:
            print(generation.loading_line(cfg) if generate else
                  f"loading models: geometry {cfg.estimators.geometry}, flow {cfg.estimators.flow} ...",
                  file=sys.stderr, flush=True)
            self.estimators = load_estimators(cfg.estimators, device, segmenter=segmenter)
        elif generate and self.models is None:
            print(generation.loading_line(cfg, estimators=False), file=sys.stderr, flush=True)
        if segmenter and self.estimators.segmenter is None:
            self.estimators = self.estimators.with_segmenter(load_segmenter(cfg.estimators, device))
            if self.models is not None:
                self.models.estimators = self.models.estimators.with_segmenter(self.estimators.segmenter)
        if generate and self.models is None:
            self.models = generation.load_models(cfg, estimators=self.estimators)
            self.estimators = self.models.estimators
        return self.estimators


def _subjects(pairs: Sequence[Pair]) -> bool:
    return any(pair.prompt.subjects is not None for pair in pairs)


def make_pairs(loaded: ProcessModels, pairs: Sequence[Pair], out: Path, maps: bool, tag: str, redo: bool = False,
               on_loaded: Callable[[], None] = lambda: None, agreement: bool = False, best_of: BestOf | None = None,
               search: bool = False) -> None:
    """The first phase of this process: its pairs that are not complete yet (all of them with
    ``redo``), the best-of arm added to complete pairs that lack it, and with ``maps`` the maps of
    complete pairs that have none (models load only if needed: for maps alone, the estimators;
    ``on_loaded`` runs once they did). ``search``: the run has a search arm, which the side by
    sides show where a pair holds one. With ``agreement`` and ``guidance.decoder=tiny``, the tiny
    decoder is measured against the VAE on the first pair (:func:`measure_decoder_agreement`)
    unless the folder holds that measurement already (a run stopped before it measures it when
    resumed). Outside a terminal, where no progress bar shows, one stderr line says which pair and
    arm runs."""
    cfg = loaded.cfg
    finished = {pair.name: None if redo else read_result(out, pair, warn=True, verify=True) for pair in pairs}
    todo = [pair for pair in pairs if finished[pair.name] is None]
    extend = [pair for pair in pairs if best_of is not None and finished[pair.name] is not None
              and best_of_problem(out, pair, finished[pair.name], best_of, verify=True) is not None]
    unmapped = [pair for pair in pairs if maps and finished[pair.name] is not None
                and not has_maps(out, pair, ARMS if pair in extend else run_arms(best_of))]
    measure = (agreement and bool(pairs) and cfg.guidance.decoder == "tiny"
               and (redo or read_agreement(out, warn=True) is None))
    print(f"{tag}{len(pairs) - len(todo) - len(extend)} of {plural(len(pairs), 'pair')} already complete", flush=True)
    if not todo and not extend and not unmapped and not measure:
        on_loaded()
        return
    estimators = loaded.get(generate=bool(todo or extend or measure), segmenter=_subjects([*todo, *extend, *unmapped]))
    on_loaded()
    if unmapped:
        print(f"{tag}making the maps of {len(unmapped)} complete pair(s) that have none", flush=True)
    for pair in unmapped:
        add_maps(cfg, pair, out, finished[pair.name], estimators, ARMS if pair in extend else run_arms(best_of))
    if extend:
        print(f"{tag}adding the {best_of.label} arm to {len(extend)} complete pair(s) that lack it", flush=True)
    lines = not sys.stderr.isatty()
    shown = (*run_arms(best_of), *((SEARCH,) if search else ()))
    work = [(pair, finished[pair.name]) for pair in extend] + [(pair, None) for pair in todo]
    for index, (pair, result) in enumerate(work, start=1):
        where = f"{tag}[{index}/{len(work)}] {pair.name}"
        warm_up = index == 1  # the first calls of the models compile kernels and allocate memory
        if result is None:
            result = run_pair(loaded.models, cfg, pair, out, maps, estimators, where if lines else None, warm_up)
        if best_of is not None:
            result = add_best_of(loaded.models, cfg, pair, out, result, best_of, maps, estimators,
                                 where if lines else None, redo, warm_up, shown)
        print(f"{where}: {_pair_line(result, best_of)}", flush=True)
    if measure:
        measure_decoder_agreement(loaded.models, cfg, pairs[0], out)


def add_search_arms(loaded: ProcessModels, pairs: Sequence[Pair], out: Path, maps: bool, tag: str, search: SearchArm,
                    redo: bool = False, best_of: BestOf | None = None) -> None:
    """The second phase of this process: the search arm added to its complete pairs that lack a
    whole one of ``search``'s particles (all of them with ``redo``), and with ``maps`` the search
    arm's maps where a complete one has none. Its first search is timed as a warm-up: its first
    calls at the particles' batch allocate memory and pick kernels anew."""
    cfg = loaded.cfg
    finished = [(pair, read_result(out, pair)) for pair in pairs]
    complete = [(pair, result) for pair, result in finished if result is not None]
    todo = [(pair, result) for pair, result in complete
            if redo or search_problem(out, pair, result, search, verify=True) is not None]
    redone = {pair.name for pair, _ in todo}
    unmapped = [(pair, result) for pair, result in complete if maps and pair.name not in redone
                and not has_maps(out, pair, (SEARCH,))]
    print(f"{tag}{len(complete) - len(todo)} of {plural(len(pairs), 'pair')} already have the {search.label} arm",
          flush=True)
    if not todo and not unmapped:
        return
    estimators = loaded.get(generate=bool(todo), segmenter=_subjects([pair for pair, _ in [*todo, *unmapped]]))
    for pair, result in unmapped:
        add_maps(cfg, pair, out, result, estimators, (SEARCH,))
    lines = not sys.stderr.isatty()
    shown = run_arms(best_of, search)
    for index, (pair, result) in enumerate(todo, start=1):
        where = f"{tag}[{index}/{len(todo)}] {pair.name}"
        result = add_search(loaded.models, cfg, pair, out, result, search, maps, estimators,
                            where if lines else None, index == 1, shown)
        arm, times = result["arms"][SEARCH], {a: result["arms"][a]["generation_s"] for a in ARMS}
        print(f"{where}: {search.label} fused {arm['fused']:.4f} (kept particle {arm[SEARCH]['kept']}, seed "
              f"{arm[SEARCH]['kept_seed']}; sampling {arm['generation_s']:.1f} s, the guided arm {times['guided']:.1f} s)",
              flush=True)


# ----------------------------------------------------------------------------------------------
# the search arm's K at matched compute, measured here


def measure_particle_scoring(loaded: ProcessModels, cfg: GeCoConfig, pair: Pair) -> tuple[float, dict[str, Any]]:
    """What scoring one particle at a resampling step takes on this machine (s), and how it was
    measured: a search of one unguided particle of ``pair`` over :data:`PROBE_STEPS` denoising
    steps, resampled at each (the scoring decodes the particle's anchor chunks and runs the GeCo
    loss without gradients, as at the search arm's resampling steps); the last resampling's time,
    the first having warmed the scoring's calls."""
    loaded.get(generate=True, segmenter=pair.prompt.subjects is not None)
    probe = arm_config(cfg, pair, SEARCH, SearchArm(1))
    probe = replace(probe, sampling=replace(probe.sampling, num_inference_steps=PROBE_STEPS),
                    search=replace(probe.search, resample_steps=list(range(PROBE_STEPS))))
    print(f"measuring one particle's scoring at a resampling step on {pair.name} (a {PROBE_STEPS}-step search of one "
          "particle) ...", file=sys.stderr, flush=True)
    made = generation.sample(loaded.models, probe, pair.prompt.text, progress=False)
    seconds = [record["seconds"] for record in made.search["resamplings"]]
    return seconds[-1], {"pair": pair.name, "steps": PROBE_STEPS, "particles": 1, "resamplings_s": seconds,
                         "call_s": made.seconds}


def match_search(loaded: ProcessModels, pairs: Sequence[Pair], out: Path, redo: bool = False) -> SearchArm:
    """The search arm of ``--search matched`` (unguided particles): the K recorded in
    ``out/``:data:`~geco_guide.bench.ab.MATCHED_SEARCH_FILE` (unless ``redo``), else K matched
    (:func:`~geco_guide.bench.ab.matched_particles`) on the measured times of the run's first
    complete pair whose arms were not made with the models' warm-up (else its first complete pair)
    and one particle's scoring measured here (:func:`measure_particle_scoring`), and recorded there.

    Raises:
        ValueError: (one line) no complete pair to measure on.
    """
    cfg = loaded.cfg
    recorded = None if redo else read_matched_search(out, warn=True)
    if recorded is not None:
        return SearchArm(recorded["particles"], False, recorded)
    complete = [(pair, result) for pair in pairs if (result := read_result(out, pair)) is not None]
    if not complete:
        raise ValueError("--search matched measures the unguided and guided arms of a complete pair, and no pair is "
                         "complete: rerun to make them")
    pair, result = next(((p, r) for p, r in complete if not any(r["arms"][a].get(WARM_UP) for a in ARMS)), complete[0])
    unguided_s, guided_s = (result["arms"][arm]["generation_s"] for arm in ARMS)
    scoring_s, probe = measure_particle_scoring(loaded, cfg, pair)
    steps = cfg.search.steps(cfg.sampling.num_inference_steps)
    particles, fits = matched_particles(unguided_s, guided_s, scoring_s, len(steps))
    matched = {
        "particles": particles, "fits": fits,
        "rule": "the largest K >= 2 with K x (unguided_s + resamplings x scoring_s) <= guided_s",
        "pair": pair.name, "warm_up": any(result["arms"][a].get(WARM_UP, False) for a in ARMS),
        "unguided_s": unguided_s, "guided_s": guided_s, "scoring_s": scoring_s, "resamplings": len(steps),
        "resample_steps": steps, "expected_s": expected_search_s(particles, unguided_s, scoring_s, len(steps)),
        "probe": probe, "device": result["device"],
        "created": datetime.now(timezone.utc).isoformat(timespec="seconds"),
    }
    write_json_atomic(out / MATCHED_SEARCH_FILE, matched)
    return SearchArm(particles, False, matched)


# ----------------------------------------------------------------------------------------------
# one run per output folder


def versions() -> dict[str, str]:
    import accelerate

    return {**generation.versions(), "accelerate": accelerate.__version__}


def execute(inputs: Inputs, maps: bool, overwrite: bool, command: str) -> int:
    """Every process's share of the pairs (:func:`make_pairs`), then with a search arm K where it is
    matched and every process's search arms (:func:`add_search_arms`), then on the main process
    the report; the exit code (0, 1 with missing pairs, 2 after one error line)."""
    cfg, pairs, out, best_of, request = inputs.cfg, inputs.pairs, inputs.out, inputs.best_of, inputs.search
    state = process_state(cfg)
    main = state.is_main_process
    tag = f"[rank {state.process_index} of {state.num_processes}] " if state.num_processes > 1 else ""
    loaded = ProcessModels(process_config(cfg, state))
    mine = shard(pairs, state.process_index, state.num_processes)
    if best_of is not None and main:
        print(f"{best_of.label}: N = {best_of.n}, {best_of.how}", flush=True)
    search = None
    try:
        make_pairs(loaded, mine, out, maps, tag, redo=overwrite, agreement=main, best_of=best_of,
                   search=request is not None,
                   # once the models loaded: missing weights leave no run.json behind
                   on_loaded=partial(pin_config, out, cfg) if main else lambda: None)
        if request is not None:
            if request.particles is None:  # matched on the pairs every process made
                state.wait_for_everyone()
                if main:
                    search = match_search(loaded, pairs, out, overwrite)
                state.wait_for_everyone()
                if not main:
                    recorded = read_matched_search(out)
                    search = SearchArm(recorded["particles"], False, recorded)
            else:
                search = SearchArm(request.particles, request.guided)
            if main:
                print(f"{search.label}: K = {search.particles}, {search.how}", flush=True)
            add_search_arms(loaded, mine, out, maps, tag, search, overwrite, best_of)
        state.wait_for_everyone()
        if not main:
            return 0
        summary = write_report(out, pairs, cfg, command, versions(), best_of, search)
    except (ValueError, FileNotFoundError, WriteError) as err:  # diverged sampling, weights not there, disk full
        print(f"error: {err}", file=sys.stderr)
        return 2
    print(_last_line(summary, out, best_of, search))
    return 0 if not summary["missing_pairs"] else 1


def _last_line(summary: dict[str, Any], out: Path, best_of: BestOf | None, search: SearchArm | None) -> str:
    """The tiny models' note, if any, then one sentence: each arm against the unguided one."""
    def versus(label: str, diff: dict[str, Any]) -> str:
        return (f"{label} - unguided = {fmt(diff['mean_diff'])}, 95% CI "
                f"{interval_text(diff['ci95'], diff['n'], 'pair')}")

    parts = [versus("fused guided", summary["paired_differences"]["fused"])]
    for arm, chosen in ((BEST_OF, best_of), (SEARCH, search)):
        if chosen is not None:
            parts.append(versus(chosen.label, summary[arm]["vs_unguided"]["paired_differences"]["fused"]))
    note = f"{TINY_GUIDANCE_NOTE}\n" if summary["tiny_models"] else ""
    return f"{note}{plural(summary['pairs'], 'pair')}: {'; '.join(parts)}; report: {out / 'report.md'}"
