"""The paired statistics of the A/B report (:mod:`geco_guide.bench.ab_report`): each arm against
the unguided one over the pairs (mean difference with a percentile bootstrap interval, how often
the fused score went down, the change of motion), each arm's times and memory, and the summary
that ``summary.json`` holds."""

from __future__ import annotations

from collections.abc import Sequence
from datetime import datetime, timezone
from typing import Any

import numpy as np

from ..config import GeCoConfig, config_to_dict
from ..estimators import estimator_ids
from .ab import ARMS, BEST_OF, METRICS, MOTION_DROP, SEARCH, WARM_UP, BestOf, Pair, SearchArm, run_arms
from .report import MIN_INTERVAL_N, uses_tiny_models
from .runs import config_fingerprint

__all__ = ["BOOTSTRAP_RESAMPLES", "BOOTSTRAP_SEED", "CI_LEVEL", "arm_summary", "bootstrap_ci", "comparison",
           "lowered_fused", "motion_change", "non_finite_scores", "paired_difference", "summarize", "warm_up_pairs"]

BOOTSTRAP_RESAMPLES = 10_000
BOOTSTRAP_SEED = 0
CI_LEVEL = 0.95


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


def motion_change(results: Sequence[dict[str, Any]], arm: str, baseline: str = "unguided") -> dict[str, Any]:
    """How much less (or more) ``arm`` moves than ``baseline``: the mean paired Total Motion
    difference over the pairs where both are finite, relative to ``baseline``'s mean over those
    pairs (``relative``, None without such pairs or with a baseline that does not move), and
    ``flagged`` where it drops by :data:`MOTION_DROP` or more: a method can look steadier by
    moving less."""
    both = np.array([(r["arms"][baseline]["total_motion"], r["arms"][arm]["total_motion"]) for r in results],
                    dtype=float).reshape(-1, 2)
    both = both[np.isfinite(both).all(axis=1)]
    base = float(both[:, 0].mean()) if len(both) else 0.0
    relative = float((both[:, 1] - both[:, 0]).mean() / base) if base > 0 else None
    return {"n": len(both), "relative": relative, "flagged": relative is not None and relative <= -MOTION_DROP}


def comparison(results: Sequence[dict[str, Any]], arm: str, baseline: str) -> dict[str, Any]:
    """``arm`` against ``baseline``, pair by pair: every metric's paired difference, the pairs where
    ``arm`` scored the lower fused, and its change of Total Motion (:func:`motion_change`)."""
    return {"paired_differences": {metric: paired_difference(results, metric, arm, baseline) for metric in METRICS},
            "lowered_fused": lowered_fused(results, arm, baseline),
            "total_motion_change": motion_change(results, arm, baseline)}


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
    if arm == SEARCH:  # its sampling includes the resampling steps: the particles' scoring, the copies' re-noising
        summary["resampling_s_mean"] = float(np.mean([rec[SEARCH]["resampling_s"] for rec in timed or records]))
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
              best_of: BestOf | None = None, search: SearchArm | None = None) -> dict[str, Any]:
    """Everything ``summary.json`` and ``report.md`` say, from the complete pairs' results: guided
    against unguided (``paired_differences``, ``guidance_lowered_fused``,
    ``guidance_total_motion_change``); with ``best_of`` and ``search``, each of those arms against
    the unguided arm and the guided arm against it (``best_of``, ``search``)."""
    done = {r["pair"] for r in results}
    arms = run_arms(best_of, search)
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
        "guidance_total_motion_change": motion_change(results, "guided"),
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
    if search is not None:
        summary[SEARCH] = {**search.to_dict(), "vs_unguided": comparison(results, SEARCH, "unguided"),
                           "guided_vs_search": comparison(results, "guided", SEARCH)}
    return summary
