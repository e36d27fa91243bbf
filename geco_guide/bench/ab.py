"""The A/B comparison of GeCo guidance, without the generation: prompt x seed pairs, the files of
a pair folder and when they make a complete pair, the search arm's matched K (the paired
statistics of the report are :mod:`geco_guide.bench.ab_stats`).

A pair holds the unguided and the guided arm (same config and seed, so the same initial noise)
and, with best-of-N, the unguided seeds ``seed .. seed + N - 1`` (the seeds ``generate --best-of
N`` takes; the first is the unguided arm's own video), each scored with the GeCo protocol, the
least fused kept; with a search, ``K`` particles of the seeds ``seed .. seed + K - 1`` (particle 0
from the pair's own noise, as ``generate --search K`` seeds them) resampled by their GeCo scores.
The generation itself is :mod:`geco_guide.bench.ab_arms` (a pair's arms) and
:mod:`geco_guide.bench.ab_run` (the run).
"""

from __future__ import annotations

import json
import logging
import math
from collections.abc import Sequence
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

from ..config import GeCoConfig
from ..generation import acting_config
from ..io.video import read_frames
from ..loss.geco import CUES
from ..sampler.search.particle_search import MAX_PARTICLES
from .runs import read_finished

__all__ = ["AGREEMENT_FILE", "ARMS", "BEST_OF", "MATCHED_SEARCH_FILE", "MAX_SEED", "METRICS", "MOTION_DROP",
           "PAIR_OUTPUTS", "SEARCH", "TINY_GUIDANCE_NOTE", "UNIT_STEMS", "WARM_UP", "BestOf", "InputError", "Pair",
           "SearchArm", "arm_config", "arm_label", "arm_title", "best_of_problem", "candidate_paths",
           "expected_search_s", "has_maps", "least_spacing", "matched_best_of", "matched_particles", "pair_dir",
           "parse_seeds", "plan_pairs", "read_agreement", "read_candidate", "read_matched_search", "read_result",
           "read_run_result", "run_arms", "search_problem", "shared_candidates"]

logger = logging.getLogger(__name__)

ARMS = ("unguided", "guided")
#: The best-of arm's key in result.json and results.csv: selection among unguided seeds.
BEST_OF = "best_of"
#: The search arm's key in result.json and results.csv: particle search with GeCo as the verifier.
SEARCH = "search"
METRICS = (*CUES, "total_motion", "mean_motion")
UNIT_STEMS = ("unguided", "guided", BEST_OF, SEARCH, "side_by_side", "unguided_maps", "guided_maps",
              f"{BEST_OF}_maps", f"{SEARCH}_maps", "result")
#: What a complete pair holds besides result.json: a pair missing one of them is redone.
PAIR_OUTPUTS = (*(f"{arm}{ext}" for arm in ARMS for ext in (".mp4", ".json")), "side_by_side.mp4")
#: The best-of candidates beyond the unguided arm's own video, one ``seed<S>`` video, sidecar and
#: scores each: kept between runs, so a resumed run makes only the missing ones.
CANDIDATES = "candidates"
MAX_SEED = 2**63 - 1
#: The fields of a result.json that the report reads: a result without one of them is redone.
RESULT_KEYS = ("pair", "prompt_id", "prompt", "seed", "device", "side_by_side", "arms")
ARM_KEYS = ("video", "sidecar", *METRICS, "generation_s", "evaluation_s", "peak_memory_mib", "memory_kind",
            "guidance_updates")
#: An arm record's flag: made in its process's first unit of work (a pair, or a pair's best-of
#: arm), so its times include the models' warm-up (first calls compile kernels, allocate memory,
#: fill caches). Such arms are reported apart and left out of the time means. Records written
#: before the flag existed read as False.
WARM_UP = "warm_up"
#: With ``guidance.decoder=tiny``: the tiny decoder measured against the VAE on one pair.
AGREEMENT_FILE = "decoder_agreement.json"
#: With ``--search matched``: the K chosen, how, and the times it came from; kept for the folder, so
#: that a resumed run searches with the same K.
MATCHED_SEARCH_FILE = "search_matched.json"
#: The fields of :data:`MATCHED_SEARCH_FILE` a resumed run reads: a file without one is measured again.
MATCHED_KEYS = ("particles", "pair", "unguided_s", "guided_s", "scoring_s", "resamplings", "expected_s")
#: An arm whose Total Motion is on average (paired, relative to the unguided arm's mean) this
#: fraction or more below the unguided arm's is flagged: it may score as steadier by moving less.
MOTION_DROP = 0.10
TINY_GUIDANCE_NOTE = ("With tiny random models the guidance effect is meaningless: guidance can lower or raise "
                      "the score.")


class InputError(ValueError):
    """A bad command-line input, reported as one line before any model is loaded."""


# ----------------------------------------------------------------------------------------------
# inputs: prompts, seeds, pairs, the best-of arm


@dataclass(frozen=True)
class Pair:
    """One prompt x seed: the unit of work, of resuming and of sharding."""

    prompt: Any  # a geco_guide.cli.prompt_files.Prompt: id, text, subjects
    seed: int

    @property
    def name(self) -> str:
        return f"{self.prompt.id}-s{self.seed}"


@dataclass(frozen=True)
class BestOf:
    """The best-of-N arm: ``n`` unguided seeds per pair; ``gpu`` and ``predicted_ratio`` say how
    ``n`` was matched to the guided arm's cost (both None when ``n`` was given); ``matched_n``:
    the N the ratio gave where it was capped at the seeds' spacing (:func:`matched_best_of`)."""

    n: int
    gpu: str | None = None
    predicted_ratio: float | None = None
    matched_n: int | None = None

    @property
    def label(self) -> str:
        return f"best-of-{self.n}"

    @property
    def how(self) -> str:
        if self.predicted_ratio is None:
            return "given (--best-of)"
        capped = "" if self.matched_n is None else (
            f", {self.matched_n} capped at {self.n}, the least spacing of the seeds (at least 2), so that the pairs "
            "share as few candidates as they can")
        return (f"matched: round({self.predicted_ratio:.3g}), the guided / unguided sampling time ratio the cost "
                f"model predicts for this config on the {self.gpu}{capped}")

    def seeds(self, pair: Pair) -> list[int]:
        return [pair.seed + k for k in range(self.n)]

    def to_dict(self) -> dict[str, Any]:
        return {"n": self.n, "chosen": "given" if self.predicted_ratio is None else "matched", "gpu": self.gpu,
                "predicted_ratio": self.predicted_ratio, "matched_n": self.matched_n}


def matched_best_of(ratio: float, gpu: str, seeds: Sequence[int]) -> BestOf:
    """The best-of arm of ``--best-of matched``: N = round(``ratio``) (at least 2), the guided /
    unguided time ratio predicted on ``gpu``, capped at the least spacing of ``seeds`` (at least
    2): each pair's candidates are the seeds ``seed .. seed + N - 1``, so a larger N would make
    the candidates of one pair the videos of the next, pairs the run asked for apart."""
    n = max(2, round(ratio))
    spacing = least_spacing(seeds)
    if spacing is None or n <= max(2, spacing):
        return BestOf(n, gpu, ratio)
    return BestOf(max(2, spacing), gpu, ratio, matched_n=n)


def least_spacing(seeds: Sequence[int]) -> int | None:
    """The least distance between two of ``seeds``; None for one seed."""
    ordered = sorted(seeds)
    return min((b - a for a, b in zip(ordered, ordered[1:])), default=None)


def shared_candidates(seeds: Sequence[int], n: int) -> str | None:
    """The sentence on the best-of-``n`` candidates that pairs of ``seeds`` share (seeds less than
    ``n`` apart), or None where they share none: what the report says and a run warns of first."""
    ordered = sorted(seeds)
    close = next(((a, b) for a, b in zip(ordered, ordered[1:]) if b - a < n), None)
    if close is None:
        return None
    a, b = close
    return (f"seeds less than {n} apart share best-of-{n} candidates (seed {b} is a candidate of seed {a}'s pair and "
            f"the unguided video of its own): for independent pairs give seeds at least {n} apart")


@dataclass(frozen=True)
class SearchArm:
    """The search arm: a particle search (:mod:`geco_guide.sampler.search.particle_search`, the config's
    ``search.*`` options) of ``particles`` particles per pair, particle ``k`` from seed ``seed + k``
    (particle 0 from the pair's own noise); its particles unguided (the comparison with guidance at
    matched compute) unless ``guided``. ``matched``: the choice of ``--search matched`` as
    :data:`MATCHED_SEARCH_FILE` records it (K, the pair and the times it came from), ``None``
    when K was given."""

    particles: int
    guided: bool = False
    matched: dict[str, Any] | None = None

    @property
    def label(self) -> str:
        return f"{'guided ' if self.guided else ''}search-{self.particles}"

    @property
    def how(self) -> str:
        if self.matched is None:
            return "given (--search)"
        m = self.matched
        warm = ", timed with the models' warm-up" if m.get("warm_up") else ""
        return (f"matched on this machine: the largest K >= 2 with K x (unguided {m['unguided_s']:.3g} s + "
                f"{m['resamplings']} resampling(s) x one particle's scoring {m['scoring_s']:.3g} s) <= guided "
                f"{m['guided_s']:.3g} s, the times of pair {m['pair']}{warm}; expected {m['expected_s']:.3g} s"
                f"{'' if m.get('fits', True) else ' (even K = 2 exceeds the guided arm: the least search)'}")

    def to_dict(self) -> dict[str, Any]:
        return {"particles": self.particles, "guided": self.guided,
                "chosen": "given" if self.matched is None else "matched", "matched": self.matched}


def arm_title(arm: str, record: dict[str, Any]) -> str:
    """The label of ``arm`` of a pair by its own record (its N, its K): what the pair's side by side
    shows."""
    if arm == BEST_OF:
        return BestOf(record[BEST_OF]["n"]).label
    if arm == SEARCH:
        return SearchArm(record[SEARCH]["particles"], record[SEARCH]["guided"]).label
    return arm


def run_arms(best_of: BestOf | None, search: SearchArm | None = None) -> tuple[str, ...]:
    return (*ARMS, *((BEST_OF,) if best_of is not None else ()), *((SEARCH,) if search is not None else ()))


def arm_label(arm: str, best_of: BestOf | None, search: SearchArm | None = None) -> str:
    if arm == BEST_OF and best_of is not None:
        return best_of.label
    return search.label if arm == SEARCH and search is not None else arm


def parse_seeds(values: Sequence[str]) -> list[int]:
    """Distinct integer seeds in ``[0, 2**63)``, in the given order."""
    seeds = []
    for value in values:
        try:
            seed = int(value)
        except ValueError:
            raise InputError(f"--seeds takes integers, got {value!r}") from None
        if not 0 <= seed <= MAX_SEED:
            raise InputError(f"--seeds must be in [0, 2**63), got {seed}")
        if seed in seeds:
            raise InputError(f"--seeds lists {seed} twice")
        seeds.append(seed)
    return seeds


def plan_pairs(prompts: Sequence[Any], seeds: Sequence[int]) -> list[Pair]:
    return [Pair(prompt, seed) for prompt in prompts for seed in seeds]


def arm_config(cfg: GeCoConfig, pair: Pair, arm: str, search: SearchArm | None = None) -> GeCoConfig:
    """The config one arm generates with: the pair's seed, guidance on for the guided arm (and the
    search arm's particles where ``search.guided``), the masks of the prompt's subjects (if any) in
    the guidance and in the search's scoring of its particles; the search arm ``search.particles``
    particles. A best-of candidate is the unguided arm of its seed's pair."""
    searched = arm == SEARCH
    guided = arm == "guided" or (searched and search.guided)
    masked = (guided or searched) and pair.prompt.subjects is not None
    cfg = replace(cfg, seed=pair.seed, guidance=replace(cfg.guidance, enabled=guided,
                                                        dynamic=pair.prompt.subjects if masked else cfg.guidance.dynamic))
    if searched:
        cfg = replace(cfg, search=replace(cfg.search, particles=search.particles))
    # the run's options that this arm cannot act on (masks, devices without guidance) left at their
    # defaults without a word: the run asked for them for the arms that use them
    return acting_config(cfg, quiet=True)


# ----------------------------------------------------------------------------------------------
# files: pair folders, complete pairs and candidates


def pair_dir(out: Path, pair: Pair) -> Path:
    return out / "pairs" / pair.name


def candidate_paths(out: Path, pair: Pair, seed: int) -> tuple[Path, Path, Path]:
    """``(video, sidecar, scores)`` of the best-of candidate of ``seed``; the first candidate is the
    unguided arm (its scores are in ``result.json``)."""
    if seed == pair.seed:
        folder = pair_dir(out, pair)
        return folder / "unguided.mp4", folder / "unguided.json", folder / "result.json"
    stem = pair_dir(out, pair) / CANDIDATES / f"seed{seed}"
    return stem.with_suffix(".mp4"), stem.with_suffix(".json"), stem.with_name(f"{stem.name}.scores.json")


def read_result(out: Path, pair: Pair, warn: bool = False, verify: bool = False) -> dict[str, Any] | None:
    """The pair's ``result.json``, or None when the pair is not complete: no result, a damaged one,
    one without a field the report reads, one of :data:`PAIR_OUTPUTS` missing or, with ``verify``,
    a video that does not decode to its sidecar's frame count (with ``warn``, a warning names the
    problem: the pair is redone). Scores written as null (not finite) read as NaN."""
    folder = pair_dir(out, pair)
    result = read_finished(folder / "result.json", [folder / name for name in PAIR_OUTPUTS], f"pair {pair.name}", warn,
                           required=RESULT_KEYS)
    if result is None:
        return None
    problem = arms_problem(folder / "result.json", result["arms"]) or (videos_problem(folder) if verify else None)
    if problem is not None:
        if warn:
            logger.warning("warning: %s; pair %s is redone", problem, pair.name)
        return None
    for record in result["arms"].values():
        if isinstance(record, dict):
            record.update({metric: math.nan for metric in METRICS if record.get(metric, 0) is None})
    return result


def arms_problem(path: Path, arms: Any, names: Sequence[str] = ARMS) -> str | None:
    """What the ``arms`` ``names`` of the result.json at ``path`` lack that the report reads, or None."""
    if not (isinstance(arms, dict) and all(isinstance(arms.get(arm), dict) for arm in names)):
        named = " or ".join(f"'arms.{arm}'" for arm in names)
        return f"{path} lacks {named}"
    lacking = [f"'arms.{arm}.{key}'" for arm in names for key in ARM_KEYS if key not in arms[arm]]
    if lacking:
        return f"{path} lacks {', '.join(lacking[:3])}"
    wrong = [f"'arms.{arm}.{metric}'" for arm in names for metric in METRICS
             if not (arms[arm][metric] is None or isinstance(arms[arm][metric], (int, float)))]
    return f"{path} holds non-numbers in {', '.join(wrong[:3])}" if wrong else None


def _sidecar_frames(sidecar: Path) -> int:
    return int(json.loads(sidecar.read_text(encoding="utf-8"))["num_frames"])


def video_problem(video: Path, frames: int) -> str | None:
    """Why ``video`` is not whole (it does not decode, or holds another frame count than
    ``frames``), or None."""
    try:
        found = read_frames(video, select=lambda count, fps: [count - 1]).num_frames
    except (ValueError, OSError) as err:  # VideoReadError is a ValueError
        return str(err).splitlines()[0]
    return f"{video} holds {found} frame(s), not {frames}" if found != frames else None


def videos_problem(folder: Path, stems: Sequence[str] = ARMS) -> str | None:
    """Why a pair's videos ``stems`` and side by side are not whole (one does not decode, or holds
    another frame count than its sidecar says), or None."""
    try:
        expected = {stem: _sidecar_frames(folder / f"{stem}.json") for stem in stems}
    except (OSError, ValueError, KeyError, TypeError) as err:
        return f"a sidecar in {folder} is damaged ({type(err).__name__})"
    expected["side_by_side"] = expected["guided"] if "guided" in expected else max(expected.values())
    return next((problem for stem, frames in expected.items()
                 if (problem := video_problem(folder / f"{stem}.mp4", frames)) is not None), None)


def best_of_problem(out: Path, pair: Pair, result: dict[str, Any], best_of: BestOf, verify: bool = False) -> str | None:
    """Why the complete pair ``result`` lacks a whole best-of arm of ``best_of.n`` candidates (none,
    one of another N, a field or file missing, with ``verify`` a video that does not decode), or None."""
    folder = pair_dir(out, pair)
    record = result["arms"].get(BEST_OF)
    if record is None:
        return f"pair {pair.name} has no {best_of.label} arm"
    problem = arms_problem(folder / "result.json", result["arms"], (BEST_OF,))
    if problem is None and (record.get(BEST_OF) or {}).get("n") != best_of.n:
        problem = f"{folder / 'result.json'} holds a best-of arm of another N"
    if problem is None:
        problem = next((f"{folder / name} is missing" for name in (f"{BEST_OF}.mp4", f"{BEST_OF}.json")
                        if not (folder / name).is_file()), None)
    if problem is None and verify:
        problem = videos_problem(folder, (BEST_OF,))
    return problem


def read_candidate(out: Path, pair: Pair, seed: int, warn: bool = False, verify: bool = False) -> dict[str, Any] | None:
    """The scores of the best-of candidate ``seed`` (beyond the first), or None when it is not
    made whole yet (with ``warn``, a warning names the problem: it is made again)."""
    video, sidecar, scores = candidate_paths(out, pair, seed)
    unit = f"candidate seed {seed} of pair {pair.name}"
    record = read_finished(scores, [video, sidecar], unit, warn, required=ARM_KEYS)
    if record is None:
        return None
    problem = arms_problem(scores, {BEST_OF: record}, (BEST_OF,))
    if problem is None and verify:
        try:
            problem = video_problem(video, _sidecar_frames(sidecar))
        except (OSError, ValueError, KeyError, TypeError) as err:
            problem = f"the sidecar {sidecar} is damaged ({type(err).__name__})"
    if problem is not None:
        if warn:
            logger.warning("warning: %s; %s is made again", problem, unit)
        return None
    record.update({metric: math.nan for metric in METRICS if record[metric] is None})
    return record


def search_problem(out: Path, pair: Pair, result: dict[str, Any], search: SearchArm, verify: bool = False) -> str | None:
    """Why the complete pair ``result`` lacks a whole search arm of ``search.particles`` particles,
    guided as ``search.guided`` says (none, one of another K, a field or file missing, with
    ``verify`` a video that does not decode), or None."""
    folder = pair_dir(out, pair)
    record = result["arms"].get(SEARCH)
    if record is None:
        return f"pair {pair.name} has no {search.label} arm"
    problem = arms_problem(folder / "result.json", result["arms"], (SEARCH,))
    made = record.get(SEARCH) or {}
    if problem is None and (made.get("particles"), made.get("guided")) != (search.particles, search.guided):
        problem = f"{folder / 'result.json'} holds a search arm of other particles"
    if problem is None:
        problem = next((f"{folder / name} is missing" for name in (f"{SEARCH}.mp4", f"{SEARCH}.json")
                        if not (folder / name).is_file()), None)
    if problem is None and verify:
        problem = videos_problem(folder, (SEARCH,))
    return problem


def read_run_result(out: Path, pair: Pair, best_of: BestOf | None,
                    search: SearchArm | None = None) -> dict[str, Any] | None:
    """The pair's result when it holds every arm of the run, else None (read quietly, for the report)."""
    result = read_result(out, pair)
    if result is None or (best_of is not None and best_of_problem(out, pair, result, best_of) is not None):
        return None
    if search is not None and search_problem(out, pair, result, search) is not None:
        return None
    return result


def has_maps(out: Path, pair: Pair, arms: Sequence[str] = ARMS) -> bool:
    return all((pair_dir(out, pair) / f"{arm}_maps.mp4").is_file() for arm in arms)


def read_agreement(out: Path, warn: bool = False) -> dict[str, Any] | None:
    """What ``out/decoder_agreement.json`` measured (``pair`` and the ``summary``), or None when it
    is missing or damaged (with ``warn``, a warning names a damaged one: it is measured again)."""
    path = out / AGREEMENT_FILE
    if not path.is_file():
        return None
    try:
        measured = json.loads(path.read_text(encoding="utf-8"))
        return {"pair": measured["pair"], **measured["summary"]}
    except (OSError, ValueError, KeyError, TypeError):
        if warn:
            logger.warning("warning: %s is damaged; it is measured again", path)
        return None


def read_matched_search(out: Path, warn: bool = False) -> dict[str, Any] | None:
    """The choice of ``--search matched`` recorded in ``out/``:data:`MATCHED_SEARCH_FILE`, or None
    when there is none or it is damaged (with ``warn``, a warning names a damaged one: K is chosen
    again)."""
    path = out / MATCHED_SEARCH_FILE
    if not path.is_file():
        return None
    try:
        chosen = json.loads(path.read_text(encoding="utf-8"))
        whole = isinstance(chosen, dict) and all(key in chosen for key in MATCHED_KEYS)
        particles = chosen["particles"] if whole else None
        if whole and isinstance(particles, int) and not isinstance(particles, bool) and particles >= 2:
            return chosen
    except (OSError, ValueError):
        pass
    if warn:
        logger.warning("warning: %s is damaged; the search's K is matched again", path)
    return None


# ----------------------------------------------------------------------------------------------
# the search arm's K at matched compute


def expected_search_s(particles: int, unguided_s: float, scoring_s: float, resamplings: int) -> float:
    """What a search of ``particles`` unguided particles is expected to take (s): each particle an
    unguided video (``unguided_s``), and each scored at every one of the ``resamplings`` steps
    (``scoring_s``: one particle's decode of its anchor chunks and GeCo loss, no gradient)."""
    return particles * (unguided_s + resamplings * scoring_s)


def matched_particles(unguided_s: float, guided_s: float, scoring_s: float, resamplings: int,
                      most: int = MAX_PARTICLES) -> tuple[int, bool]:
    """``(K, fits)`` of ``--search matched``: the largest ``K >= 2`` (at most ``most``) whose
    :func:`expected_search_s` does not exceed the guided arm's ``guided_s``; where even ``K = 2``
    exceeds it, ``(2, False)``: the least search. Times in seconds, measured on the run's machine.

    Raises:
        ValueError: a time that is not a finite number >= 0, or a per-particle time of 0.
    """
    times = (unguided_s, guided_s, scoring_s)
    if not all(isinstance(t, (int, float)) and math.isfinite(t) and t >= 0 for t in times) or resamplings < 0:
        raise ValueError(f"matched K needs finite times >= 0, got unguided {unguided_s}, guided {guided_s}, scoring "
                         f"{scoring_s} at {resamplings} resampling(s)")
    per_particle = expected_search_s(1, unguided_s, scoring_s, resamplings)
    if per_particle <= 0:
        raise ValueError("matched K needs an unguided arm that took time: its measured time is 0")
    k = min(most, max(2, math.floor(guided_s / per_particle)))
    while k < most and expected_search_s(k + 1, unguided_s, scoring_s, resamplings) <= guided_s:
        k += 1  # the division's rounding
    while k > 2 and expected_search_s(k, unguided_s, scoring_s, resamplings) > guided_s:
        k -= 1
    return k, expected_search_s(k, unguided_s, scoring_s, resamplings) <= guided_s
