"""The A/B report: ``results.csv``, ``summary.json``, ``report.md`` and ``pareto.png``, rebuilt
from the complete pairs' ``result.json`` files (:mod:`geco_guide.bench.ab`).

Every arm beyond the unguided one (guided, and where the run has them best-of-N and search) is
compared with the unguided arm pair by pair, from the same prompt and initial noise; the arms
spent at matched compute (best-of-N, search) also with the guided arm, head to head. Each arm's
Total Motion sits next to its scores, and an arm that moves notably less is flagged.
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

from ..config import GeCoConfig, config_to_yaml
from ..io.files import remove_temp_files
from ..io.plots import SHAPES, Panel, legend, limits
from ..loss.cues import CUES
from ..metric.evaluate import PAPER_NAMES
from ..types import plural
from . import report
from .ab import (
    AGREEMENT_FILE,
    ARMS,
    BEST_OF,
    METRICS,
    MOTION_DROP,
    SEARCH,
    TINY_GUIDANCE_NOTE,
    WARM_UP,
    BestOf,
    Pair,
    SearchArm,
    arm_label,
    read_agreement,
    read_run_result,
    run_arms,
    shared_candidates,
)
from .ab_stats import summarize
from .report import TINY_NOTE, fmt, interval_text, markdown_table

__all__ = ["REPORT_STEMS", "csv_text", "plot_png", "report_markdown", "write_report"]

REPORT_STEMS = ("results", "summary", "report", "pareto", "run")


def csv_text(results: Sequence[dict[str, Any]], arms: Sequence[str] = ARMS) -> str:
    """``results.csv``: one row per pair and arm."""
    columns = ["pair", "prompt_id", "seed", "arm", *METRICS, "generation_s", "evaluation_s", WARM_UP,
               "peak_memory_mib", "memory_kind", "guidance_updates", "video", "prompt",
               *(["subjects"] if any("subjects" in result for result in results) else [])]
    rows = [{**result, **result["arms"][arm], "arm": arm, "video": f"pairs/{result['pair']}/{result['arms'][arm]['video']}",
             WARM_UP: result["arms"][arm].get(WARM_UP, False)} for result in results for arm in arms]
    return report.csv_text(rows, columns)


def _non_finite_note(found: dict[str, list[str]]) -> list[str]:
    if not found:
        return []
    listed = "; ".join(f"{pair} ({', '.join(scores)})" for pair, scores in found.items())
    return [(f"**Non-finite scores** in {len(found)} pair(s), left out of the means, differences and counts "
             f"(no valid pixels to measure): {listed}"), ""]


def _agreement_note(agreement: dict[str, Any] | None) -> list[str]:
    if agreement is None:
        return []
    return [(f"**Tiny decoder vs VAE** (the guided arm decodes the anchor frames with the tiny decoder, an "
             f"approximation), measured on {agreement['pair']} over {agreement['updates']} updates: gradient cosine "
             f"median {fmt(agreement['cosine_median'])} (min {fmt(agreement['cosine_min'])}), anchor-frame PSNR "
             f"{fmt(agreement['psnr_mean_db'], 3)} dB ([{AGREEMENT_FILE}]({AGREEMENT_FILE}))."), ""]


def _timing_note(summary: dict[str, Any]) -> list[str]:
    """Which pairs' times the means leave out, and why (:data:`~geco_guide.bench.ab.WARM_UP`)."""
    warm = summary.get("warm_up_pairs") or []
    if not warm:
        return []
    if all(arm["timing_includes_warm_up"] for arm in summary["arms"].values()):
        return [(f"Every pair was made with the models' warm-up ({', '.join(warm)}: each process's first pair, whose "
                 "first calls compile kernels and allocate memory): the means include it. Run more pairs for "
                 "times without it."), ""]
    return [(f"The means leave out the arms made with the models' warm-up (in {', '.join(warm)}: each process's first "
             f"pair, and its first search arm): their times include the first calls, which compile kernels and "
             f"allocate memory; they are in results.csv ({WARM_UP} = True). The totals include them."), ""]


def _share(lowered: dict[str, Any]) -> str:
    return f"{fmt(100 * lowered['fraction'], 3)} %" if lowered["n"] else "-"


def _best_of_of(summary: dict[str, Any]) -> BestOf | None:
    chosen = summary.get(BEST_OF)
    return None if chosen is None else BestOf(chosen["n"], chosen["gpu"], chosen["predicted_ratio"],
                                              chosen.get("matched_n"))


def _search_of(summary: dict[str, Any]) -> SearchArm | None:
    chosen = summary.get(SEARCH)
    return None if chosen is None else SearchArm(chosen["particles"], chosen["guided"], chosen["matched"])


def _vs_unguided(summary: dict[str, Any], arm: str) -> dict[str, Any]:
    """``{paired_differences, lowered_fused, total_motion_change}`` of ``arm`` against the unguided arm."""
    if arm == "guided":
        return {"paired_differences": summary["paired_differences"], "lowered_fused": summary["guidance_lowered_fused"],
                "total_motion_change": summary["guidance_total_motion_change"]}
    return summary[arm]["vs_unguided"]


def _differences_table(comparisons: Sequence[tuple[str, dict[str, Any]]], level: int) -> list[str]:
    """One row per metric: each comparison's mean paired difference and its interval."""
    header = ["metric"]
    for title, _ in comparisons:
        header += [title, f"{level}% CI (paired bootstrap)"]
    rows = []
    for metric in METRICS:
        row = [f"{metric} ({PAPER_NAMES[metric]})" if metric in CUES else PAPER_NAMES[metric]]
        for _, compared in comparisons:
            diff = compared["paired_differences"][metric]
            row += [fmt(diff["mean_diff"]), interval_text(diff["ci95"], diff["n"], "pair")]
        rows.append(row)
    return markdown_table(header, rows)


def _scores_table(summary: dict[str, Any], labels: dict[str, str]) -> list[str]:
    rows = [[f"{metric} ({PAPER_NAMES[metric]})" if metric in CUES else PAPER_NAMES[metric],
             *(fmt(summary["arms"][arm][metric]) for arm in labels)] for metric in METRICS]
    return markdown_table(["metric", *labels.values()], rows)


def _lowered_line(summary: dict[str, Any], labels: dict[str, str]) -> str:
    """In how many pairs each arm scored a lower fused than the unguided arm."""
    counts = {arm: _vs_unguided(summary, arm)["lowered_fused"] for arm in labels if arm != "unguided"}
    said = {arm: f"**{c['count']} of {c['n']}** pairs ({_share(c)})" for arm, c in counts.items()}
    others = "".join(f"; {labels[arm]} in {text}" for arm, text in said.items() if arm != "guided")
    return f"Guidance lowered the fused score in {said['guided']}{others}."


def _motion_section(summary: dict[str, Any], labels: dict[str, str]) -> list[str]:
    """Total Motion next to each arm's fused score, its paired change against the unguided arm,
    and a flag where it drops by :data:`~geco_guide.bench.ab.MOTION_DROP` or more."""
    rows, flagged = [], []
    for arm, label in labels.items():
        means = summary["arms"][arm]
        if arm == "unguided":
            rows.append([label, fmt(means["fused"]), fmt(means["total_motion"]), "-", ""])
            continue
        change = _vs_unguided(summary, arm)["total_motion_change"]
        relative = change["relative"]
        shown = "-" if relative is None else f"{100 * relative:+.3g} % ({plural(change['n'], 'pair')})"
        rows.append([label, fmt(means["fused"]), fmt(means["total_motion"]), shown,
                     "**moves less**" if change["flagged"] else ""])
        if change["flagged"]:
            flagged.append(f"{label} ({100 * relative:+.3g} %)")
    drop = f"{100 * MOTION_DROP:.3g} %"
    if flagged:
        note = (f"**Moves notably less than the unguided arm**: {', '.join(flagged)}. A lower score can come from "
                f"moving less rather than from a more consistent scene: compare at similar motion (right panel of "
                f"the plot). Flagged: a paired mean drop of Total Motion of {drop} or more of the unguided arm's.")
    else:
        note = (f"No arm's Total Motion drops by {drop} or more of the unguided arm's (paired mean): the scores "
                "compare videos that move about as much.")
    return [
        "## Total Motion: does an arm look steadier by moving less?",
        "",
        *markdown_table(["arm", "fused", "Total Motion", "Total Motion vs unguided (paired mean)", ""], rows),
        "",
        note,
        "",
    ]


def _head_to_head(summary: dict[str, Any], labels: dict[str, str], level: int) -> list[str]:
    """The guided arm against each arm spent at matched compute (best-of-N, search)."""
    matched = [(arm, summary[arm][f"guided_vs_{arm}"]) for arm in (BEST_OF, SEARCH) if arm in labels]
    if not matched:
        return []
    won = "; ".join(f"below {labels[arm]} in **{c['lowered_fused']['count']} of {c['lowered_fused']['n']}** pairs "
                    f"({_share(c['lowered_fused'])})" for arm, c in matched)
    return [
        "## Guidance against the arms at matched compute (head to head)",
        "",
        *_differences_table([(f"guided - {labels[arm]}", compared) for arm, compared in matched], level),
        "",
        f"Guidance scored {won}.",
        "",
    ]


def _of_guided(summary: dict[str, Any], arm: str) -> str:
    guided = summary["arms"]["guided"]["generation_s_mean"]
    return f"{fmt(summary['arms'][arm]['generation_s_mean'] / guided, 3)}x" if guided > 0 else "-"


def _cost_table(summary: dict[str, Any], labels: dict[str, str]) -> list[str]:
    rows = [[label, fmt(summary["arms"][arm]["generation_s_mean"], 3), _of_guided(summary, arm),
             fmt(summary["arms"][arm]["evaluation_s_mean"], 3), fmt(summary["arms"][arm]["generation_s_total"], 3),
             f"{fmt(summary['arms'][arm]['peak_memory_mib_max'], 4)} ({summary['arms'][arm]['memory_kind']})"]
            for arm, label in labels.items()]
    return markdown_table(["arm", "sampling s (mean)", "of the guided arm's", "protocol scoring s (mean)",
                           "sampling s (total)", "peak memory MiB (max)"], rows)


def _best_of_lines(summary: dict[str, Any], best_of: BestOf | None) -> list[str]:
    """How N was chosen, and what was predicted against what was measured here."""
    if best_of is None:
        return []
    arms = summary["arms"]
    unguided = arms["unguided"]["generation_s_mean"]  # the means: without the warm-up where they can
    measured = (f"measured here: the guided arm sampled for {fmt(arms['guided']['generation_s_mean'] / unguided, 3)}x "
                f"the unguided arm's time, the {best_of.label} arm for "
                f"{fmt(arms[BEST_OF]['generation_s_mean'] / unguided, 3)}x (its {best_of.n} candidates; the first is "
                f"the unguided arm's video), and scoring its candidates took "
                f"{fmt(arms[BEST_OF]['evaluation_s_mean'], 3)} s per pair") if unguided > 0 else "nothing measured"
    shared = shared_candidates(summary["seeds"], best_of.n)
    shared = f" {shared[0].upper()}{shared[1:]}." if shared else ""
    return [
        (f"**{best_of.label}** (selection among unguided seeds): per pair the unguided seeds seed .. seed+{best_of.n - 1}"
         f", each scored with the GeCo protocol, the least fused kept. N = {best_of.n}, {best_of.how}"
         f"{' (predicted, not measured)' if best_of.predicted_ratio is not None else ''}; {measured}.{shared}"),
        "",
    ]


def _search_lines(summary: dict[str, Any], search: SearchArm | None) -> list[str]:
    """How K was chosen (and from which measured times), and what the search arm measured."""
    if search is None:
        return []
    arms = summary["arms"]
    particles = "guided particles (each guided as the guided arm)" if search.guided else "unguided particles"
    return [
        (f"**{search.label}** (particle search with GeCo as the verifier, {particles}): per pair {search.particles} "
         f"particles of the seeds seed .. seed+{search.particles - 1} in one batch (particle 0 from the pair's own "
         f"noise), scored on their clean estimates at the resampling steps and resampled, the final one of least "
         f"fused score under the protocol kept. K = {search.particles}, {search.how}. Measured here: it sampled for "
         f"{fmt(arms[SEARCH]['generation_s_mean'], 3)} s per pair ({_of_guided(summary, SEARCH)} the guided arm's), of "
         f"which {fmt(arms[SEARCH]['resampling_s_mean'], 3)} s at the resampling steps (scoring the particles, "
         f"re-noising the copies); "
         f"the protocol scoring of its final particles (the selection) and of its kept video took "
         f"{fmt(arms[SEARCH]['evaluation_s_mean'], 3)} s."),
        "",
    ]


def _pair_row(result: dict[str, Any], labels: dict[str, str]) -> list[str]:
    arms = result["arms"]
    kept = []
    if BEST_OF in labels:
        kept.append(str(arms[BEST_OF][BEST_OF]["kept_seed"]))
    if SEARCH in labels:
        kept.append(str(arms[SEARCH][SEARCH]["kept_seed"]))
    return [result["pair"], *(fmt(arms[arm]["fused"]) for arm in labels),
            *(fmt(arms[arm]["total_motion"]) for arm in labels), *kept,
            f"[side by side](pairs/{result['pair']}/{result['side_by_side']})"]


def report_markdown(summary: dict[str, Any], results: Sequence[dict[str, Any]], config_yaml: str, command: str,
                    models: Sequence[str] = ()) -> str:
    """``report.md``: scores, each arm against the unguided one, Total Motion, the arms at matched
    compute head to head, cost, the plot, per-pair table, config, versions."""
    n = summary["pairs"]
    best_of, search = _best_of_of(summary), _search_of(summary)
    labels = {arm: arm_label(arm, best_of, search) for arm in run_arms(best_of, search)}
    level = int(summary["bootstrap"]["level"] * 100)
    lines = [
        f"# GeCo guidance A/B: {' vs '.join(labels.values())}",
        "",
        (f"{plural(n, 'pair')} complete of {summary['pairs_planned']} planned ({summary['prompts']} prompts x seeds "
         f"{summary['seeds']}), same initial noise per pair; device {', '.join(summary['devices']) or '-'}; "
         f"config `{summary['config_sha']}`; {summary['created']}."),
        "",
        f"Command: `{command}`",
        "",
    ]
    if summary.get("tiny_models"):
        lines += [f"**{TINY_NOTE}.**", ""]
    lines += list(models)
    if summary["missing_pairs"]:
        lines += [f"**Missing pairs** (rerun the same command to finish them): {', '.join(summary['missing_pairs'])}", ""]
    if not n:
        return "\n".join(lines + ["No complete pairs yet."]) + "\n"
    compared = [(f"{label} - unguided", _vs_unguided(summary, arm)) for arm, label in labels.items() if arm != "unguided"]
    pair_columns = ["pair", *(f"fused {label}" for label in labels.values()),
                    *(f"TM {label}" for label in labels.values()),
                    *([f"kept seed ({labels[BEST_OF]})"] if best_of is not None else []),
                    *([f"kept particle's seed ({labels[SEARCH]})"] if search is not None else []), "video"]
    lines += [
        f"## Scores (mean over pairs; lower {'/'.join(CUES)} is more consistent)",
        "",
        *_scores_table(summary, labels),
        "",
        "## Each arm against the unguided arm (paired: the same prompt and initial noise)",
        "",
        *_differences_table(compared, level),
        "",
        *_non_finite_note(summary["non_finite_scores"]),
        (f"{_lowered_line(summary, labels)}{' ' + TINY_GUIDANCE_NOTE if summary.get('tiny_models') else ''} "
         f"Bootstrap: {summary['bootstrap']['resamples']} resamples of the pairs, seed {summary['bootstrap']['seed']}."),
        "",
        *_motion_section(summary, labels),
        *_head_to_head(summary, labels, level),
        "## Cost per arm (measured; means without the warm-up)",
        "",
        *_cost_table(summary, labels),
        "",
        *_best_of_lines(summary, best_of),
        *_search_lines(summary, search),
        *_timing_note(summary),
        *_agreement_note(summary.get("decoder_agreement")),
        "![fused score: each arm vs unguided per pair, and vs Total Motion](pareto.png)",
        "",
        "## Pairs",
        "",
        *markdown_table(pair_columns, [_pair_row(r, labels) for r in results]),
        "",
        "## Configuration",
        "",
        "```yaml",
        config_yaml.rstrip(),
        "```",
        "",
        "## Versions",
        "",
        *markdown_table(["package", "version"], [[k, v] for k, v in summary["versions"].items()]),
    ]
    return "\n".join(lines) + "\n"


# ----------------------------------------------------------------------------------------------
# the plot: drawn with PIL (an imageio dependency), no matplotlib

#: The arms' colours, in the order of :func:`~geco_guide.bench.ab.run_arms`.
ARM_COLORS = {"unguided": (60, 110, 200), "guided": (235, 125, 30), BEST_OF: (140, 70, 170), SEARCH: (30, 150, 130)}
GREY = (170, 170, 170)


def plot_png(results: Sequence[dict[str, Any]], best_of: BestOf | None = None, search: SearchArm | None = None) -> bytes:
    """``pareto.png``: left, each arm's fused score against the unguided arm's per pair (below the
    diagonal: the arm scored lower); right, fused score vs Total Motion of every arm, each pair
    joined by a line."""
    from PIL import Image, ImageDraw

    arms = run_arms(best_of, search)
    image = Image.new("RGB", (860, 430), (255, 255, 255))
    draw = ImageDraw.Draw(image)
    pairs = [[r["arms"][arm] for arm in arms] for r in results
             if all(np.isfinite([r["arms"][a][k] for a in arms for k in ("fused", "total_motion")]))]
    fused = [rec["fused"] for pair in pairs for rec in pair] or [0.0]
    motion = [rec["total_motion"] for pair in pairs for rec in pair] or [0.0]
    colors = [ARM_COLORS[arm] for arm in arms]
    shapes = SHAPES[:len(arms)]

    left = Panel((70, 80, 400, 360), limits(fused), limits(fused))
    left.draw_axes(draw, "fused score per pair (below the line: lower than unguided)", "unguided fused", "arm fused")
    draw.line([left.to_pixel(left.xlim[0], left.ylim[0]), left.to_pixel(left.xlim[1], left.ylim[1])], fill=GREY)
    for unguided, *others in pairs:
        for rec, color, shape in zip(others, colors[1:], shapes[1:]):
            left.dot(draw, unguided["fused"], rec["fused"], color, shape=shape)

    right = Panel((510, 80, 840, 360), limits(motion), limits(fused))
    right.draw_axes(draw, "fused score vs Total Motion (lower-right is better)", "Total Motion (%)", "fused")
    for records in pairs:
        draw.line([right.to_pixel(rec["total_motion"], rec["fused"]) for rec in records], fill=GREY)
    for records in pairs:
        for rec, color, shape in zip(records, colors, shapes):
            right.dot(draw, rec["total_motion"], rec["fused"], color, shape=shape)
    entries = tuple((arm_label(arm, best_of, search), color) for arm, color in zip(arms, colors))
    legend(draw, left, entries[1:], shapes[1:])
    legend(draw, right, entries, shapes)
    return report.png_bytes(image)


def write_report(out: Path, pairs: Sequence[Pair], cfg: GeCoConfig, command: str, versions: dict[str, str],
                 best_of: BestOf | None = None, search: SearchArm | None = None) -> dict[str, Any]:
    """Rebuild the four report files from the pairs' ``result.json`` files; returns the summary."""
    remove_temp_files(out, REPORT_STEMS)
    results = [r for r in (read_run_result(out, pair, best_of, search) for pair in pairs) if r is not None]
    summary = summarize(results, pairs, cfg, versions, best_of, search)
    measured = read_agreement(out) if cfg.guidance.decoder == "tiny" else None
    if measured is not None:
        summary["decoder_agreement"] = measured
    markdown = report_markdown(summary, results, config_to_yaml(cfg), command, report.models_section(cfg))
    report.write_report_files(out, table=csv_text(results, run_arms(best_of, search)), summary=summary,
                              plot=plot_png(results, best_of, search), markdown=markdown)
    return summary
