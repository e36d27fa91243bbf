"""The A/B comparison of GeCo guidance, without the generation: prompt x seed pairs, the files of
a pair folder and when they make a complete pair, and the paired statistics of the report.

A pair holds the unguided and the guided arm (same config and seed, so the same initial noise)
and, with best-of-N, a third arm: the unguided seeds ``seed .. seed + N - 1`` (the seeds
``generate --best-of N`` takes; the first is the unguided arm's own video), each scored with the
GeCo protocol, the least fused kept. The generation itself is :mod:`geco_guide.cli.ab`'s.
"""

from __future__ import annotations

import json
import logging
import math
from collections.abc import Sequence
from dataclasses import dataclass, replace
from datetime import datetime, timezone
from pathlib import Path
from typing import Any

import numpy as np

from ..config import GeCoConfig, config_to_dict
from ..estimators import estimator_ids
from ..io.video import read_frames
from ..loss.geco import CUES
from .report import MIN_INTERVAL_N, uses_tiny_models
from .runs import config_fingerprint, read_finished

__all__ = ["AGREEMENT_FILE", "ARMS", "BEST_OF", "MAX_SEED", "METRICS", "PAIR_OUTPUTS", "TINY_GUIDANCE_NOTE",
           "UNIT_STEMS", "WARM_UP", "BestOf", "InputError", "Pair", "arm_config", "arm_label", "best_of_problem",
           "bootstrap_ci", "candidate_paths", "has_maps", "lowered_fused", "non_finite_scores",
           "paired_difference", "pair_dir", "parse_seeds", "plan_pairs", "read_agreement", "read_candidate",
           "read_result", "read_run_result", "run_arms", "summarize", "warm_up_pairs"]

logger = logging.getLogger(__name__)

ARMS = ("unguided", "guided")
#: The third arm's key in result.json and results.csv: selection among unguided seeds.
BEST_OF = "best_of"
METRICS = (*CUES, "total_motion", "mean_motion")
UNIT_STEMS = ("unguided", "guided", BEST_OF, "side_by_side", "unguided_maps", "guided_maps", f"{BEST_OF}_maps",
              "result")
#: What a complete pair holds besides result.json: a pair missing one of them is redone.
PAIR_OUTPUTS = (*(f"{arm}{ext}" for arm in ARMS for ext in (".mp4", ".json")), "side_by_side.mp4")
#: The best-of candidates beyond the unguided arm's own video, one ``seed<S>`` video, sidecar and
#: scores each: kept between runs, so a resumed run makes only the missing ones.
CANDIDATES = "candidates"
BOOTSTRAP_RESAMPLES = 10_000
BOOTSTRAP_SEED = 0
CI_LEVEL = 0.95
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
    ``n`` was matched to the guided arm's cost (both None when ``n`` was given)."""

    n: int
    gpu: str | None = None
    predicted_ratio: float | None = None

    @property
    def label(self) -> str:
        return f"best-of-{self.n}"

    @property
    def how(self) -> str:
        if self.predicted_ratio is None:
            return "given (--best-of)"
        return (f"matched: round({self.predicted_ratio:.3g}), the guided / unguided sampling time ratio the cost "
                f"model predicts for this config on the {self.gpu}")

    def seeds(self, pair: Pair) -> list[int]:
        return [pair.seed + k for k in range(self.n)]

    def to_dict(self) -> dict[str, Any]:
        return {"n": self.n, "chosen": "given" if self.predicted_ratio is None else "matched", "gpu": self.gpu,
                "predicted_ratio": self.predicted_ratio}


def run_arms(best_of: BestOf | None) -> tuple[str, ...]:
    return ARMS if best_of is None else (*ARMS, BEST_OF)


def arm_label(arm: str, best_of: BestOf | None) -> str:
    return best_of.label if arm == BEST_OF and best_of is not None else arm


def parse_seeds(values: Sequence[str]) -> list[int]:
    """Distinct integer seeds in ``[0, 2**63)``, in the given order."""
    seeds = []
    for value in values:
        try:
            seed = int(value)
        except ValueError:
            hint = " (put key=value overrides before --seeds, or after another option)" if "=" in value else ""
            raise InputError(f"--seeds takes integers, got {value!r}{hint}") from None
        if not 0 <= seed <= MAX_SEED:
            raise InputError(f"--seeds must be in [0, 2**63), got {seed}")
        if seed in seeds:
            raise InputError(f"--seeds lists {seed} twice")
        seeds.append(seed)
    return seeds


def plan_pairs(prompts: Sequence[Any], seeds: Sequence[int]) -> list[Pair]:
    return [Pair(prompt, seed) for prompt in prompts for seed in seeds]


def arm_config(cfg: GeCoConfig, pair: Pair, arm: str) -> GeCoConfig:
    """The config one arm generates with: the pair's seed, guidance on for the guided arm only,
    with the masks of the prompt's subjects (if any). A best-of candidate is the unguided arm of
    its seed's pair."""
    guided = arm == "guided"
    dynamic = pair.prompt.subjects if guided and pair.prompt.subjects is not None else cfg.guidance.dynamic
    return replace(cfg, seed=pair.seed, guidance=replace(cfg.guidance, enabled=guided, dynamic=dynamic))


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


def read_run_result(out: Path, pair: Pair, best_of: BestOf | None) -> dict[str, Any] | None:
    """The pair's result when it holds every arm of the run, else None (read quietly, for the report)."""
    result = read_result(out, pair)
    if result is None or (best_of is not None and best_of_problem(out, pair, result, best_of) is not None):
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


# ----------------------------------------------------------------------------------------------
# statistics


def bootstrap_ci(diffs: np.ndarray, resamples: int = BOOTSTRAP_RESAMPLES, seed: int = BOOTSTRAP_SEED,
                 level: float = CI_LEVEL) -> tuple[float, float] | None:
    """Percentile bootstrap confidence interval of the mean of ``diffs``; None below 2 values."""
    if len(diffs) < 2:
        return None
    rng = np.random.default_rng(seed)
    means = diffs[rng.integers(0, len(diffs), size=(resamples, len(diffs)))].mean(axis=1)
    low, high = np.quantile(means, [(1 - level) / 2, (1 + level) / 2])
    return float(low), float(high)


def paired_difference(results: Sequence[dict[str, Any]], metric: str, arm: str = "guided",
                      baseline: str = "unguided") -> dict[str, Any]:
    """Mean of ``arm - baseline`` over the pairs where both values are finite, with its CI
    (``None`` below :data:`~geco_guide.bench.report.MIN_INTERVAL_N` such pairs)."""
    diffs = np.array([r["arms"][arm][metric] - r["arms"][baseline][metric] for r in results], dtype=float)
    diffs = diffs[np.isfinite(diffs)]
    ci = bootstrap_ci(diffs) if len(diffs) >= MIN_INTERVAL_N else None
    return {
        "n": len(diffs),
        "mean_diff": float(diffs.mean()) if len(diffs) else None,
        "ci95": list(ci) if ci is not None else None,
    }


def lowered_fused(results: Sequence[dict[str, Any]], arm: str = "guided", baseline: str = "unguided") -> dict[str, Any]:
    """In how many pairs (with both fused scores finite) ``arm`` scored a lower fused than ``baseline``."""
    fused = [(r["arms"][baseline]["fused"], r["arms"][arm]["fused"]) for r in results]
    lowered = [score < base for base, score in fused if np.isfinite([base, score]).all()]
    return {"count": int(sum(lowered)), "n": len(lowered), "fraction": sum(lowered) / len(lowered) if lowered else None}


def comparison(results: Sequence[dict[str, Any]], arm: str, baseline: str) -> dict[str, Any]:
    return {"paired_differences": {metric: paired_difference(results, metric, arm, baseline) for metric in METRICS},
            "lowered_fused": lowered_fused(results, arm, baseline)}


def arm_summary(results: Sequence[dict[str, Any]], arm: str) -> dict[str, Any]:
    """Means of the scores, and time and memory, of one arm over the pairs. The time means leave
    out the arms made with the models' warm-up (:data:`WARM_UP`), unless every arm was
    (``timing_includes_warm_up``); the total is every arm's."""
    records = [r["arms"][arm] for r in results]
    timed = [rec for rec in records if not rec.get(WARM_UP, False)]
    summary: dict[str, Any] = {metric: _finite_mean([rec[metric] for rec in records]) for metric in METRICS}
    summary.update(
        generation_s_mean=float(np.mean([rec["generation_s"] for rec in timed or records])),
        generation_s_total=float(np.sum([rec["generation_s"] for rec in records])),
        evaluation_s_mean=float(np.mean([rec["evaluation_s"] for rec in timed or records])),
        timed_pairs=len(timed or records),
        timing_includes_warm_up=not timed,
        peak_memory_mib_max=float(np.max([rec["peak_memory_mib"] for rec in records])),
        memory_kind=records[0]["memory_kind"],
    )
    return summary


def warm_up_pairs(results: Sequence[dict[str, Any]], arms: Sequence[str] = ARMS) -> list[str]:
    """The pairs with an arm made with the models' warm-up (:data:`WARM_UP`)."""
    return [r["pair"] for r in results if any(r["arms"][arm].get(WARM_UP, False) for arm in arms)]


def _finite_mean(values: Sequence[float]) -> float | None:
    """Mean over the finite values (a video without valid pixels scores NaN); None if there are none."""
    finite = [v for v in values if np.isfinite(v)]
    return float(np.mean(finite)) if finite else None


def non_finite_scores(results: Sequence[dict[str, Any]], arms: Sequence[str] = ARMS) -> dict[str, list[str]]:
    """``{pair: ["unguided fused", ...]}`` for the pairs with a NaN/inf score (a video without valid
    pixels), which the means, differences and counts leave out."""
    found = {r["pair"]: [f"{arm} {metric}" for arm in arms for metric in METRICS
                         if not np.isfinite(r["arms"][arm][metric])] for r in results}
    return {pair: scores for pair, scores in found.items() if scores}


def summarize(results: Sequence[dict[str, Any]], pairs: Sequence[Pair], cfg: GeCoConfig, versions: dict[str, str],
              best_of: BestOf | None = None) -> dict[str, Any]:
    """Everything ``summary.json`` and ``report.md`` say, from the complete pairs' results; with
    ``best_of``, the third arm against each of the others (``best_of``)."""
    done = {r["pair"] for r in results}
    arms = run_arms(best_of)
    summary = {
        "pairs": len(results),
        "pairs_planned": len(pairs),
        "missing_pairs": [p.name for p in pairs if p.name not in done],
        "non_finite_scores": non_finite_scores(results, arms),
        "warm_up_pairs": warm_up_pairs(results, arms),
        "prompts": len({p.prompt.id for p in pairs}),
        "seeds": sorted({p.seed for p in pairs}),
        "arms": {arm: arm_summary(results, arm) for arm in arms} if results else {},
        "paired_differences": {metric: paired_difference(results, metric) for metric in METRICS},
        "guidance_lowered_fused": lowered_fused(results),
        "bootstrap": {"resamples": BOOTSTRAP_RESAMPLES, "seed": BOOTSTRAP_SEED, "level": CI_LEVEL},
        "config_sha": config_fingerprint(cfg),
        "models": {"video": cfg.model.id,
                   **estimator_ids(cfg.estimators, segmenter=any(p.prompt.subjects is not None for p in pairs))},
        "tiny_models": uses_tiny_models(cfg),
        "config": config_to_dict(cfg),
        "devices": sorted({r["device"] for r in results}),
        "versions": versions,
        "created": datetime.now(timezone.utc).isoformat(timespec="seconds"),
    }
    if best_of is not None:
        summary[BEST_OF] = {**best_of.to_dict(), "vs_unguided": comparison(results, BEST_OF, "unguided"),
                            "guided_vs_best_of": comparison(results, "guided", BEST_OF)}
    return summary
