"""A/B test of GeCo guidance on your prompts: unguided vs guided video from the same noise.

    geco ab --prompts prompts.txt --seeds 0 1 2 --out ab/ --preset tiny
    geco ab --prompts prompts.jsonl --seeds 0 --out ab/ --config my.yaml guidance.step_size=2.0
    geco ab --prompts prompts.jsonl --seeds 0 10 20 --out ab/ --preset cogvideox-5b --best-of matched --gpu H100
    accelerate launch scripts/ab_compare.py --prompts prompts.txt --seeds 0 1 --out ab/ --preset cogvideox-5b

The prompts file holds one prompt per line, or JSON lines ``{"id": "bust", "prompt": "..."}``
(``id`` optional; blank lines and ``#`` comments are skipped). A prompt's id (its slug when not
given) names its output folders, so ids must be unique and filesystem-safe. A JSON line's optional
``"subjects": "a dog, a ball"`` (what moves on its own; ``--prompts dynamic``: our suite) are masked
in every arm's scores and in the guided arm's guidance, by the segmenter of ``estimators.segmenter``.

For every prompt x seed ("pair"), both arms run :func:`geco_guide.generation.generate` with the same
config and seed, so both start from the same initial noise (``torch.Generator("cpu").manual_seed
(seed)``); the unguided arm is exactly ``python -m geco_guide.generate --no-guidance --seed S``.
Both videos are scored by :func:`geco_guide.metric.evaluate.evaluate_video` with the same estimators and
the config's ``evaluation`` protocol. ``<out>/pairs/<id>-s<seed>/`` then holds ``unguided.mp4``,
``guided.mp4`` (each with its generation sidecar ``.json``), ``side_by_side.mp4``, with
``--maps`` the maps videos, and last ``result.json``, whose presence marks the pair complete.

``--best-of N`` adds a third arm, selection: the unguided seeds ``seed .. seed + N - 1`` (the
first is the unguided arm's video; the others in ``candidates/``), each scored with the same
protocol, the one :func:`geco_guide.generation.best_candidate` picks copied to ``best_of.mp4``
(its sidecar lists every candidate), and ``result.json`` rewritten with the arm. ``--best-of
matched`` takes N = round of the guided / unguided sampling time ratio the cost model predicts
for the run's config on ``--gpu`` (default: the local GPU, when it is a card the model knows).

Every file is written atomically, so killing the run at any moment loses at most the pair (or
best-of candidate) in progress and never leaves a truncated file; a rerun skips complete pairs and
candidates and redoes, with a warning naming the file, one whose result is damaged or lacks
fields, or whose videos or sidecars are gone or unreadable. Outputs another run left in a pair
folder (their sidecar names another prompt or config) are refused unless ``--overwrite``, which
redoes every pair. While a run works in a folder it holds ``<out>/.run.lock`` (its pid): a second
run there is refused, and the lock of a run that was killed is taken over. ``--maps`` on a resumed
folder also makes the maps of complete pairs that have none (their videos are scored again; only
the estimators load), and with ``guidance.decoder=tiny`` a folder without a whole
``decoder_agreement.json`` gets it measured, whatever the pairs' state. Under ``accelerate
launch`` the pairs are dealt round-robin to the processes; at the end the main process rebuilds
``results.csv`` (one row per pair and arm), ``summary.json``, ``report.md`` and ``pareto.png``
from the pairs' ``result.json`` files; scores that are not finite are left out of its statistics
and named. ``run.json`` pins the config: reusing an output folder with a different config is
refused (unless ``--overwrite``).
"""

from __future__ import annotations

import argparse
import json
import shlex
import sys
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, replace
from datetime import datetime, timezone
from functools import partial
from pathlib import Path
from typing import TYPE_CHECKING, Any

from ..io.files import WriteError, remove_temp_files, write_bytes_atomic, write_json_atomic
from ..io.logs import log_to_stderr
from .kit import DeferredImports, Parser, add_config_flags, config_from_args, interruptible

if TYPE_CHECKING:  # the rest bound at run time by _IMPLEMENTATION
    from ..bench.ab import (
        AGREEMENT_FILE,
        ARMS,
        BEST_OF,
        MAX_SEED,
        METRICS,
        TINY_GUIDANCE_NOTE,
        UNIT_STEMS,
        WARM_UP,
        BestOf,
        InputError,
        Pair,
        arm_config,
        best_of_problem,
        candidate_paths,
        has_maps,
        pair_dir,
        parse_seeds,
        plan_pairs,
        read_agreement,
        read_candidate,
        read_result,
        run_arms,
    )
    from ..bench.ab_report import write_report
    from ..bench.report import fmt, interval_text
    from ..bench.runs import PeakMemory, pin_config, process_config, process_state, read_finished, run_lock, shard
    from ..config import GeCoConfig, config_to_dict
    from ..estimators import Estimators, load_estimators
    from ..io.devices import resolve_device
    from ..io.video import read_video, write_video
    from ..metric.evaluate import evaluate_video, finite_or_none, write_maps_video
    from ..metric.render import enlarge, side_by_side
    from ..perf.decoder_agreement import agreement_rows, agreement_summary
    from .. import generation
    from ..types import plural
    from .prompt_files import read_prompts

#: What the command runs on, imported once the arguments parsed: it loads torch.
_IMPLEMENTATION = DeferredImports(__name__, {
    "..bench.ab": ("AGREEMENT_FILE", "ARMS", "BEST_OF", "MAX_SEED", "METRICS", "TINY_GUIDANCE_NOTE", "UNIT_STEMS",
                   "WARM_UP", "BestOf", "InputError", "Pair", "arm_config", "best_of_problem", "candidate_paths",
                   "has_maps", "pair_dir", "parse_seeds", "plan_pairs", "read_agreement", "read_candidate",
                   "read_result", "run_arms"),
    "..bench.ab_report": ("write_report",),
    "..bench.report": ("fmt", "interval_text"),
    "..bench.runs": ("PeakMemory", "pin_config", "process_config", "process_state", "read_finished", "run_lock",
                     "shard"),
    "..config": ("config_to_dict",),
    "..estimators": ("Estimators", "load_estimators"),
    "..io.devices": ("resolve_device",),
    "..io.video": ("read_video", "write_video"),
    "..metric.evaluate": ("evaluate_video", "finite_or_none", "write_maps_video"),
    "..metric.render": ("enlarge", "side_by_side"),
    "..perf.decoder_agreement": ("agreement_rows", "agreement_summary"),
    "..types": ("plural",),
    "..": ("generation",),
    ".prompt_files": ("read_prompts",),
})
__getattr__ = _IMPLEMENTATION.attribute

__all__ = ["PROG", "build_parser", "choose_best_of", "command", "local_card", "main", "run_shard",
           "validate_inputs"]

PROG = "geco ab"


def check_output_folder(out: Path, cfg: GeCoConfig, pairs: Sequence[Pair], overwrite: bool = False,
                        best_of: BestOf | None = None) -> None:
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
        made = [(pair_dir(out, pair) / f"{arm}.json", pair, arm) for arm in ARMS]
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
    of ``pair``: its :func:`~geco_guide.generation.video_key`, the hash generate's default names
    carry, differs."""
    try:
        sidecar = json.loads(sidecar_path.read_text(encoding="utf-8"))
        made = generation.video_key(sidecar["config"], sidecar["prompt"])
    except (OSError, ValueError, KeyError, TypeError, AttributeError):  # none, or not a sidecar: redone anyway
        return False
    return made != generation.video_key(config_to_dict(arm_config(cfg, pair, arm)), pair.prompt.text)


# ----------------------------------------------------------------------------------------------
# one pair


def run_arm(models: Any, cfg: GeCoConfig, pair: Pair, arm: str, folder: Path, maps: bool, estimators: Estimators,
            stem: str | None = None, warm_up: bool = False) -> dict[str, Any]:
    """Generate one arm of a pair into ``folder/<stem>.mp4`` (``stem``: the arm's name) + sidecar
    and score it with ``estimators``; what an unfinished run left there is replaced (other runs'
    outputs were refused before). A prompt's subjects are masked, by the estimators' segmenter, in
    every arm's scores and in the guided arm's guidance. ``warm_up``: the process's first work, whose
    times include the models' warm-up (recorded, and left out of the report's means)."""
    stem = stem or arm
    masks = estimators.masks_for(pair.prompt.subjects)
    with PeakMemory(models.pipe.device) as memory:
        generated = generation.generate(arm_config(cfg, pair, arm), pair.prompt.text, out=folder / f"{stem}.mp4",
                                        models=models, overwrite=True)
    start = time.perf_counter()
    evaluation = evaluate_video(generated.video_path, estimators, cfg.evaluation, maps=maps, dynamic_masks=masks)
    evaluation_s = time.perf_counter() - start
    record = {
        "video": generated.video_path.name,
        "sidecar": generated.sidecar_path.name,
        **{metric: float(getattr(evaluation, metric)) for metric in METRICS},
        "generation_s": generated.sidecar["timings"]["sampling_s"],
        "evaluation_s": evaluation_s,
        "peak_memory_mib": memory.peak_mib,
        "memory_kind": memory.kind,
        "guidance_updates": len(generated.sidecar["guidance_log"]),
        WARM_UP: warm_up,
        "evaluation": evaluation.to_dict(),
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


def write_side_by_side(folder: Path, fps: float, arms: Sequence[str] | None = None,
                       labels: Sequence[str] | None = None) -> None:
    """``side_by_side.mp4``: the arms' videos next to each other, labelled (default: every arm of
    :data:`~geco_guide.bench.ab.ARMS`, by its name), enlarged to a readable height as the maps are
    (:func:`~geco_guide.metric.render.enlarge`: a tiny model's 60-pixel video had 6-pixel labels)."""
    arms = ARMS if arms is None else arms
    videos = [enlarge(read_video(folder / f"{arm}.mp4")[0]) for arm in arms]
    write_video(folder / "side_by_side.mp4", side_by_side(videos, list(arms if labels is None else labels)), fps=fps)


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
                warm_up: bool = False) -> dict[str, Any]:
    """The best-of arm of a complete pair: the candidates not made whole yet (all of them with
    ``redo``; with ``where``, a stderr line before each; ``warm_up``: see :func:`run_arm`), the one
    :func:`~geco_guide.generation.best_candidate` picks copied to ``best_of.mp4`` with a sidecar
    listing every candidate, the three-arm side by side, then ``result.json`` with the arm."""
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
                              **{key: finite_or_none(record[key]) for key in ("fused", "motion", "structure")}}
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
    write_side_by_side(folder, cfg.sampling.fps, run_arms(best_of), ["unguided", "guided", best_of.label])
    if maps:
        add_maps(cfg, pair, out, result, estimators, (BEST_OF,))
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


def run_shard(cfg: GeCoConfig, pairs: Sequence[Pair], out: Path, maps: bool, tag: str, redo: bool = False,
              on_loaded: Callable[[], None] = lambda: None, agreement: bool = False,
              best_of: BestOf | None = None) -> None:
    """Run the pairs of this process that are not complete yet (all of them with ``redo``), add
    the best-of arm to complete pairs that lack it, and with ``maps`` make the maps of complete
    pairs that have none (models load only if needed: for maps alone, the estimators;
    ``on_loaded`` runs once they did). With ``agreement`` and ``guidance.decoder=tiny``, the tiny
    decoder is measured against the VAE on the first pair (:func:`measure_decoder_agreement`)
    unless the folder holds that measurement already (a run stopped before it measures it when
    resumed). Outside a terminal, where no progress bar shows, one stderr line says which pair and
    arm runs."""
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
    # loaded once for every prompt's subjects
    subjects = any(pair.prompt.subjects is not None for pair in [*todo, *extend, *unmapped])
    if subjects:
        print(f"loading segmenter: {cfg.estimators.segmenter} ...", file=sys.stderr, flush=True)
    models = None
    print(generation.loading_line(cfg) if todo or extend or measure else
          f"loading models: geometry {cfg.estimators.geometry}, flow {cfg.estimators.flow} ...", file=sys.stderr,
          flush=True)
    estimators = load_estimators(cfg.estimators, resolve_device(cfg.model.device), segmenter=subjects)
    if todo or extend or measure:
        models = generation.load_models(cfg, estimators=estimators)
        estimators = models.estimators
    on_loaded()
    if unmapped:
        print(f"{tag}making the maps of {len(unmapped)} complete pair(s) that have none", flush=True)
    for pair in unmapped:
        add_maps(cfg, pair, out, finished[pair.name], estimators, ARMS if pair in extend else run_arms(best_of))
    if extend:
        print(f"{tag}adding the {best_of.label} arm to {len(extend)} complete pair(s) that lack it", flush=True)
    lines = not sys.stderr.isatty()
    work = [(pair, finished[pair.name]) for pair in extend] + [(pair, None) for pair in todo]
    for index, (pair, result) in enumerate(work, start=1):
        where = f"{tag}[{index}/{len(work)}] {pair.name}"
        warm_up = index == 1  # the first calls of the models compile kernels and allocate memory
        if result is None:
            result = run_pair(models, cfg, pair, out, maps, estimators, where if lines else None, warm_up)
        if best_of is not None:
            result = add_best_of(models, cfg, pair, out, result, best_of, maps, estimators, where if lines else None, redo,
                                 warm_up)
        print(f"{where}: {_pair_line(result, best_of)}", flush=True)
    if measure:
        measure_decoder_agreement(models, cfg, pairs[0], out)


# ----------------------------------------------------------------------------------------------
# the best-of arm's N


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
    ``memory_plan=auto`` picks for the card (as ``geco bench cost --gpu``)."""
    from ..perf.cost import cost_report, cost_settings
    from ..perf.plans import KNOWN_MODELS, card_plan

    preset = next((known["preset"] for known in KNOWN_MODELS.values() if cfg.model.id in known["model_ids"]), None)
    if preset is None:
        ids = ", ".join(model_id for known in KNOWN_MODELS.values() for model_id in known["model_ids"])
        raise InputError(f"--best-of matched: the cost model knows the models {ids}, not model.id {cfg.model.id!r}; "
                         "pass an integer --best-of N")
    s, guidance = cfg.sampling, cfg.guidance
    mode = "faithful" if guidance.denoiser_grad else "fast"
    card = card_plan(gpu, mode, guidance.decoder, s.num_frames, s.height, s.width)
    if card["plan"] is None:
        raise InputError(f"--best-of matched: no guided run of this config fits the {gpu}: {card['reason']}")
    settings = cost_settings(preset=preset, steps=s.num_inference_steps, frames=s.num_frames, height=s.height,
                             width=s.width, dtype=None, decoder=guidance.decoder, plan=card["plan"])
    settings.update(repeats=guidance.repeats, time_travel=list(guidance.time_travel or []) or None)
    return float(cost_report(settings, mode)["roofline"]["ratio_guided_over_unguided"][gpu])


def choose_best_of(value: str | None, gpu: str | None, cfg: GeCoConfig, seeds: Sequence[int]) -> BestOf | None:
    """The best-of arm ``--best-of`` and ``--gpu`` ask for (None: no third arm); one
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
        ratio = predicted_ratio(cfg, card)
        best_of = BestOf(max(2, round(ratio)), card, ratio)
    else:
        if gpu is not None:
            raise InputError("--gpu is for --best-of matched; an integer --best-of N needs no card")
        try:
            n = int(value)
        except ValueError:
            raise InputError(f"--best-of takes an integer >= 2 or 'matched', got {value!r}") from None
        if n < 2:
            raise InputError(f"--best-of takes an integer >= 2 or 'matched', got {n} (best-of-1 is the unguided arm)")
        best_of = BestOf(n)
    if max(seeds) + best_of.n - 1 > MAX_SEED:
        raise InputError(f"--best-of {best_of.n} from seed {max(seeds)} runs past the last seed, 2**63 - 1")
    return best_of


# ----------------------------------------------------------------------------------------------
# CLI


def build_parser(prog: str = PROG) -> argparse.ArgumentParser:
    p = Parser(
        prog=prog,
        description="A/B test of GeCo guidance: unguided vs guided video per prompt x seed, from the same noise.",
    )
    p.add_argument("--prompts", required=True,
                   help="text file: one prompt per line, or JSON lines {id, prompt[, subjects]}; or the paper's suite: "
                        "geco-eval, geco-eval:indoor, geco-eval:fast, geco-eval:outdoor:slow, ...; or ours with moving "
                        "subjects: dynamic, dynamic:indoor, ...")
    p.add_argument("--seeds", required=True, nargs="+", metavar="SEED", help="sampling seeds (integers)")
    p.add_argument("--out", required=True, help="output folder (reuse it to resume)")
    add_config_flags(p, preset_help="a preset of configs/: tiny, cogvideox-5b, cogvideox-5b-fused")
    p.add_argument("--maps", action="store_true", help="also write each arm's GeCo maps video")
    p.add_argument("--best-of", default=None, metavar="N|matched",
                   help="a third arm, selection: per pair N unguided seeds (seed .. seed+N-1), each scored with the "
                        "GeCo protocol, the least fused kept; 'matched': N = the guided / unguided time ratio the cost "
                        "model predicts for this config on --gpu")
    p.add_argument("--gpu", default=None, metavar="CARD",
                   help="the card --best-of matched predicts for (H200, H100, L40S, A6000, RTX4090, L4; default: the "
                        "local GPU when it is one of them)")
    p.add_argument("--overwrite", action="store_true",
                   help="redo every pair, replacing what --out holds (also another config's or prompt's results)")
    p.add_argument("overrides", nargs="*", metavar="key=value", help="config overrides, e.g. guidance.step_size=2.0")
    return p


@dataclass
class Inputs:
    cfg: GeCoConfig
    pairs: list[Pair]
    out: Path
    best_of: BestOf | None = None


def validate_inputs(args: argparse.Namespace) -> Inputs:
    """Every check that needs no model: prompts, seeds, config (what generate checks before loading),
    the best-of arm, output folder."""
    prompts = read_prompts(args.prompts)
    seeds = parse_seeds(args.seeds)
    cfg = config_from_args(args, args.overrides)
    if not cfg.guidance.enabled:
        raise InputError("guidance.enabled=false leaves nothing to compare: the guided arm needs guidance")
    # what generate checks before loading, here before run.json is pinned or any video written
    cfg = generation.check_generation(cfg, prompts[0].text)
    best_of = choose_best_of(args.best_of, args.gpu, cfg, seeds)
    pairs = plan_pairs(prompts, seeds)
    out = Path(args.out)
    check_output_folder(out, cfg, pairs, args.overwrite, best_of)
    return Inputs(cfg, pairs, out, best_of)


def versions() -> dict[str, str]:
    import accelerate

    return {**generation.versions(), "accelerate": accelerate.__version__}


# ----------------------------------------------------------------------------------------------
# one run per output folder


def command(prog: str = PROG) -> Callable[[list[str] | None], int]:
    """The command's ``main(argv)`` under the name ``prog`` (its usage line, and the report's
    command line when ``argv`` is given; without, the process's own command line)."""

    @interruptible("finished pairs are kept (each pair is written whole or not at all); rerun the same command to "
                   "resume")
    def main(argv: list[str] | None = None) -> int:
        args = build_parser(prog).parse_args(argv)
        _IMPLEMENTATION.load()
        log_to_stderr()  # the library's warnings (a pair or candidate redone) as lines of the command
        try:
            inputs = validate_inputs(args)
            with run_lock(inputs.out, "A/B"):
                return run(args, inputs, ["python", *sys.argv] if argv is None else [*shlex.split(prog), *argv])
        except (ValueError, FileNotFoundError) as err:
            print(f"error: {err}", file=sys.stderr)
            return 2

    return main


main = command()


def run(args: argparse.Namespace, inputs: Inputs, command: Sequence[str]) -> int:
    """Every process's share of the pairs, then on the main process the report."""
    cfg, pairs, out, best_of = inputs.cfg, inputs.pairs, inputs.out, inputs.best_of
    state = process_state(cfg)
    tag = f"[rank {state.process_index} of {state.num_processes}] " if state.num_processes > 1 else ""
    if best_of is not None and state.is_main_process:
        print(f"{best_of.label}: N = {best_of.n}, {best_of.how}", flush=True)
    try:
        run_shard(process_config(cfg, state), shard(pairs, state.process_index, state.num_processes), out, args.maps,
                  tag, redo=args.overwrite, agreement=state.is_main_process, best_of=best_of,
                  # once the models loaded: missing weights leave no run.json behind
                  on_loaded=partial(pin_config, out, cfg) if state.is_main_process else lambda: None)
        state.wait_for_everyone()
        if not state.is_main_process:
            return 0
        summary = write_report(out, pairs, cfg, shlex.join(command), versions(), best_of)
    except (ValueError, FileNotFoundError, WriteError) as err:  # diverged sampling, weights not there, disk full
        print(f"error: {err}", file=sys.stderr)
        return 2
    fused = summary["paired_differences"]["fused"]
    if summary["tiny_models"]:
        print(TINY_GUIDANCE_NOTE)
    selected = ""
    if best_of is not None:
        diff = summary[BEST_OF]["vs_unguided"]["paired_differences"]["fused"]
        selected = (f"; {best_of.label} - unguided = {fmt(diff['mean_diff'])}, 95% CI "
                    f"{interval_text(diff['ci95'], diff['n'], 'pair')}")
    print(f"{plural(summary['pairs'], 'pair')}: fused guided - unguided = {fmt(fused['mean_diff'])}, 95% CI "
          f"{interval_text(fused['ci95'], fused['n'], 'pair')}{selected}; report: {out / 'report.md'}")
    return 0 if not summary["missing_pairs"] else 1
