"""The run of ``geco ab`` (:mod:`geco_guide.cli.ab`), once its arguments passed their checks: the
output folder checked against what other runs left, the models of a process loaded when first
needed, a process's share of the pairs, the search arm's K matched on this machine, the report.
The arms of one pair are :mod:`geco_guide.bench.ab_arms`.

A run goes in two phases, so that ``--search matched`` can measure the arms it matches before it
searches, in one process or in several (``accelerate launch``): first every process makes its
pairs' unguided and guided arms (and best-of arms); then, once every process is done, the main
process matches K (:func:`match_search`) and every process adds the search arm to its pairs.
The lines of the run's progress go to a ``say`` callable (the command prints them), the loading
and measuring notes to the log.
"""

from __future__ import annotations

import json
import logging
import sys
from collections.abc import Callable, Sequence
from dataclasses import dataclass, replace
from datetime import datetime, timezone
from functools import partial
from pathlib import Path
from typing import Any

from .. import generation
from ..config import GeCoConfig, config_to_dict
from ..estimators import Estimators, load_estimators, load_segmenter, segmenter_id
from ..io.devices import resolve_device
from ..io.files import write_json_atomic
from ..types import plural
from .ab import (
    ARMS,
    BEST_OF,
    MATCHED_SEARCH_FILE,
    MAX_SEED,
    SEARCH,
    TINY_GUIDANCE_NOTE,
    WARM_UP,
    BestOf,
    InputError,
    Pair,
    SearchArm,
    arm_config,
    best_of_problem,
    candidate_paths,
    expected_search_s,
    has_maps,
    matched_particles,
    pair_dir,
    read_agreement,
    read_matched_search,
    read_result,
    run_arms,
    search_problem,
)
from .ab_arms import AgreementProbe, add_best_of, add_maps, add_search, measure_decoder_agreement, run_pair
from .ab_report import write_report
from .report import fmt, interval_text
from .runs import check_output_folder as check_run_folder
from .runs import pin_config, process_config, process_state, read_finished, shard

__all__ = ["PROBE_STEPS", "Finished", "Inputs", "ProcessModels", "SearchRequest", "add_search_arms",
           "check_output_folder", "choose_search", "count_arm", "execute", "foreign_video", "make_pairs", "match_search", "measure_particle_scoring",
           "versions"]

logger = logging.getLogger(__name__)

#: The probe that measures one particle's scoring at a resampling step (:func:`measure_particle_scoring`):
#: a search of one particle over this many denoising steps, resampled at each.
PROBE_STEPS = 2


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


def count_arm(value: str, flag: str, one: str) -> int:
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
        particles = count_arm(value, "--search", "a search of one particle is the unguided arm")
    if max(seeds) + (particles or 2) - 1 > MAX_SEED:
        raise InputError(f"--search {particles or 2} from seed {max(seeds)} runs past the last seed, 2**63 - 1")
    return SearchRequest(particles, guided)


def check_output_folder(out: Path, cfg: GeCoConfig, pairs: Sequence[Pair], overwrite: bool = False,
                        best_of: BestOf | None = None, search: SearchRequest | None = None) -> None:
    """Refuse an output folder that holds results of another config or other prompt texts, or
    videos another run left (their sidecars name another prompt or config), unless ``overwrite``."""
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
            logger.info("loading segmenter: %s ...", cfg.estimators.segmenter)
        if self.estimators is None:
            logger.info(generation.loading_line(cfg) if generate else
                        f"loading models: geometry {cfg.estimators.geometry}, flow {cfg.estimators.flow} ...")
            self.estimators = load_estimators(cfg.estimators, device, segmenter=segmenter)
        elif generate and self.models is None:
            logger.info(generation.loading_line(cfg, estimators=False))
        if segmenter and self.estimators.segmenter is None:
            self.estimators = self.estimators.with_segmenter(load_segmenter(cfg.estimators, device),
                                                             segmenter_id(cfg.estimators))
            if self.models is not None:
                self.models.estimators = self.models.estimators.with_segmenter(
                    self.estimators.segmenter, self.estimators.ids()["segmenter"])
        if generate and self.models is None:
            self.models = generation.load_models(cfg, estimators=self.estimators)
            self.estimators = self.models.estimators
        return self.estimators


def _subjects(pairs: Sequence[Pair]) -> bool:
    return any(pair.prompt.subjects is not None for pair in pairs)


def make_pairs(loaded: ProcessModels, pairs: Sequence[Pair], out: Path, maps: bool, tag: str, redo: bool = False,
               on_loaded: Callable[[], None] = lambda: None, agreement: AgreementProbe | None = None,
               best_of: BestOf | None = None, search: bool = False, say: Callable[[str], None] = logger.info) -> None:
    """The first phase of this process: its pairs that are not complete yet (all of them with
    ``redo``), the best-of arm added to complete pairs that lack it, and with ``maps`` the maps of
    complete pairs that have none (models load only if needed: for maps alone, the estimators;
    ``on_loaded`` runs once they did). ``search``: the run has a search arm, which the side by
    sides show where a pair holds one. With ``agreement`` and ``guidance.decoder=tiny``, the tiny
    decoder is measured against the VAE on the first pair by ``agreement``
    (:func:`~geco_guide.bench.ab_arms.measure_decoder_agreement`) unless the folder holds that
    measurement already (a run stopped before it measures it when resumed). Outside a terminal,
    where no progress bar shows, one log record says which pair and arm runs; ``say`` gets the
    lines of the run's progress (the command prints them)."""
    cfg = loaded.cfg
    finished = {pair.name: None if redo else read_result(out, pair, warn=True, verify=True) for pair in pairs}
    todo = [pair for pair in pairs if finished[pair.name] is None]
    extend = [pair for pair in pairs if best_of is not None and finished[pair.name] is not None
              and best_of_problem(out, pair, finished[pair.name], best_of, verify=True) is not None]
    unmapped = [pair for pair in pairs if maps and finished[pair.name] is not None
                and not has_maps(out, pair, ARMS if pair in extend else run_arms(best_of))]
    measure = (agreement is not None and bool(pairs) and cfg.guidance.decoder == "tiny"
               and (redo or read_agreement(out, warn=True) is None))
    say(f"{tag}{len(pairs) - len(todo) - len(extend)} of {plural(len(pairs), 'pair')} already complete")
    if not todo and not extend and not unmapped and not measure:
        on_loaded()
        return
    estimators = loaded.get(generate=bool(todo or extend or measure), segmenter=_subjects([*todo, *extend, *unmapped]))
    on_loaded()
    if unmapped:
        say(f"{tag}making the maps of {len(unmapped)} complete pair(s) that have none")
    for pair in unmapped:
        add_maps(cfg, pair, out, finished[pair.name], estimators, ARMS if pair in extend else run_arms(best_of))
    if extend:
        say(f"{tag}adding the {best_of.label} arm to {len(extend)} complete pair(s) that lack it")
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
        say(f"{where}: {_pair_line(result, best_of)}")
    if measure:
        measure_decoder_agreement(loaded.models, cfg, pairs[0], out, agreement)


def add_search_arms(loaded: ProcessModels, pairs: Sequence[Pair], out: Path, maps: bool, tag: str, search: SearchArm,
                    redo: bool = False, best_of: BestOf | None = None,
                    say: Callable[[str], None] = logger.info) -> None:
    """The second phase of this process: the search arm added to its complete pairs that lack a
    whole one of ``search``'s particles (all of them with ``redo``), and with ``maps`` the search
    arm's maps where a complete one has none. Its first search is timed as a warm-up: its first
    calls at the particles' batch allocate memory and pick kernels anew. ``say``: as
    :func:`make_pairs`."""
    cfg = loaded.cfg
    finished = [(pair, read_result(out, pair)) for pair in pairs]
    complete = [(pair, result) for pair, result in finished if result is not None]
    todo = [(pair, result) for pair, result in complete
            if redo or search_problem(out, pair, result, search, verify=True) is not None]
    redone = {pair.name for pair, _ in todo}
    unmapped = [(pair, result) for pair, result in complete if maps and pair.name not in redone
                and not has_maps(out, pair, (SEARCH,))]
    say(f"{tag}{len(complete) - len(todo)} of {plural(len(pairs), 'pair')} already have the {search.label} arm")
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
        say(f"{where}: {search.label} fused {arm['fused']:.4f} (kept particle {arm[SEARCH]['kept']}, seed "
            f"{arm[SEARCH]['kept_seed']}; sampling {arm['generation_s']:.1f} s, the guided arm {times['guided']:.1f} s)")


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
    logger.info("measuring one particle's scoring at a resampling step on %s (a %d-step search of one particle) ...",
                pair.name, PROBE_STEPS)
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


def execute(inputs: Inputs, maps: bool, overwrite: bool, command: str, agreement: AgreementProbe | None = None,
            say: Callable[[str], None] = logger.info) -> Finished | None:
    """Every process's share of the pairs (:func:`make_pairs`), then with a search arm K where it is
    matched and every process's search arms (:func:`add_search_arms`), then on the main process
    the report: what it says (None on the other processes). ``agreement`` measures the tiny
    decoder against the VAE (:func:`make_pairs`); ``say`` gets the lines of the run's progress.

    Raises:
        ValueError, FileNotFoundError, WriteError: diverged sampling, weights not there, a full disk.
    """
    cfg, pairs, out, best_of, request = inputs.cfg, inputs.pairs, inputs.out, inputs.best_of, inputs.search
    state = process_state(cfg)
    main = state.is_main_process
    tag = f"[rank {state.process_index} of {state.num_processes}] " if state.num_processes > 1 else ""
    loaded = ProcessModels(process_config(cfg, state))
    mine = shard(pairs, state.process_index, state.num_processes)
    if best_of is not None and main:
        say(f"{best_of.label}: N = {best_of.n}, {best_of.how}")
    make_pairs(loaded, mine, out, maps, tag, redo=overwrite, agreement=agreement if main else None, best_of=best_of,
               search=request is not None, say=say,
               # once the models loaded: missing weights leave no run.json behind
               on_loaded=partial(pin_config, out, cfg) if main else lambda: None)
    search = None
    if request is not None:
        search = _search_arm(loaded, state, pairs, out, request, overwrite)
        if main:
            say(f"{search.label}: K = {search.particles}, {search.how}")
        add_search_arms(loaded, mine, out, maps, tag, search, overwrite, best_of, say=say)
    state.wait_for_everyone()
    if not main:
        return None
    return Finished(write_report(out, pairs, cfg, command, versions(), best_of, search), search)


def _search_arm(loaded: ProcessModels, state: Any, pairs: Sequence[Pair], out: Path, request: SearchRequest,
                overwrite: bool) -> SearchArm:
    """The search arm of ``request``: K as given, or matched by the main process on the pairs every
    process made (:func:`match_search`) and read back by the others."""
    if request.particles is not None:
        return SearchArm(request.particles, request.guided)
    state.wait_for_everyone()
    search = match_search(loaded, pairs, out, overwrite) if state.is_main_process else None
    state.wait_for_everyone()
    if search is None:
        recorded = read_matched_search(out)
        search = SearchArm(recorded["particles"], False, recorded)
    return search


@dataclass(frozen=True)
class Finished:
    """What a finished run's report says (its ``summary.json``) and the search arm it ran."""

    summary: dict[str, Any]
    search: SearchArm | None

    def last_line(self, out: Path, best_of: BestOf | None) -> str:
        """The tiny models' note, if any, then one sentence: each arm against the unguided one."""
        summary = self.summary

        def versus(label: str, diff: dict[str, Any]) -> str:
            return (f"{label} - unguided = {fmt(diff['mean_diff'])}, 95% CI "
                    f"{interval_text(diff['ci95'], diff['n'], 'pair')}")

        parts = [versus("fused guided", summary["paired_differences"]["fused"])]
        for arm, chosen in ((BEST_OF, best_of), (SEARCH, self.search)):
            if chosen is not None:
                parts.append(versus(chosen.label, summary[arm]["vs_unguided"]["paired_differences"]["fused"]))
        note = f"{TINY_GUIDANCE_NOTE}\n" if summary["tiny_models"] else ""
        return f"{note}{plural(summary['pairs'], 'pair')}: {'; '.join(parts)}; report: {out / 'report.md'}"
