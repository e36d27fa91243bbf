"""The A/B report: ``results.csv``, ``summary.json``, ``report.md`` and ``pareto.png``, rebuilt
from the complete pairs' ``result.json`` files (:mod:`geco_guide.bench.ab`)."""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

from ..config import GeCoConfig, config_to_yaml
from ..io.files import remove_temp_files
from ..io.plots import Panel, legend, limits
from ..loss.geco import CUES
from ..metric.evaluate import PAPER_NAMES
from ..types import plural
from . import report
from .ab import (
    AGREEMENT_FILE,
    ARMS,
    BEST_OF,
    METRICS,
    TINY_GUIDANCE_NOTE,
    WARM_UP,
    BestOf,
    Pair,
    arm_label,
    read_agreement,
    read_run_result,
    run_arms,
    summarize,
)
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
    return [(f"The means leave out the first pair of each process ({', '.join(warm)}): its times include the models' "
             f"warm-up (the first calls compile kernels and allocate memory); they are in results.csv "
             f"({WARM_UP} = True). The totals include them."), ""]


def _share(lowered: dict[str, Any]) -> str:
    return f"{fmt(100 * lowered['fraction'], 3)} %" if lowered["n"] else "-"


def _best_of_of(summary: dict[str, Any]) -> BestOf | None:
    chosen = summary.get(BEST_OF)
    return None if chosen is None else BestOf(chosen["n"], chosen["gpu"], chosen["predicted_ratio"])


def _comparisons(summary: dict[str, Any], best_of: BestOf | None) -> list[tuple[str, dict[str, Any]]]:
    """``(title, {paired_differences, lowered_fused})`` of each pair of arms the report compares."""
    found = [("guided - unguided", {"paired_differences": summary["paired_differences"],
                                     "lowered_fused": summary["guidance_lowered_fused"]})]
    if best_of is not None:
        found += [(f"{best_of.label} - unguided", summary[BEST_OF]["vs_unguided"]),
                  (f"guided - {best_of.label}", summary[BEST_OF]["guided_vs_best_of"])]
    return found


def _scores_table(summary: dict[str, Any], best_of: BestOf | None) -> list[str]:
    arms, level = run_arms(best_of), int(summary["bootstrap"]["level"] * 100)
    comparisons = _comparisons(summary, best_of)
    header = ["metric", *(arm_label(arm, best_of) for arm in arms)]
    for title, _ in comparisons:
        header += [title, f"{level}% CI (paired bootstrap)"]
    rows = []
    for metric in METRICS:
        label = f"{metric} ({PAPER_NAMES[metric]})" if metric in CUES else PAPER_NAMES[metric]
        row = [label, *(fmt(summary["arms"][arm][metric]) for arm in arms)]
        for _, compared in comparisons:
            diff = compared["paired_differences"][metric]
            row += [fmt(diff["mean_diff"]), interval_text(diff["ci95"], diff["n"], "pair")]
        rows.append(row)
    return markdown_table(header, rows)


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
    _, vs_unguided = _comparisons(summary, best_of)[1]
    _, vs_best = _comparisons(summary, best_of)[2]
    seeds = summary["seeds"]
    shared = (f" Seeds less than {best_of.n} apart share candidates (pair s0's seed 1 is pair s1's unguided video): "
              f"for independent pairs give seeds at least {best_of.n} apart."
              if any(b - a < best_of.n for a, b in zip(seeds, seeds[1:])) else "")
    return [
        (f"**{best_of.label}** (selection among unguided seeds): per pair the unguided seeds seed .. seed+{best_of.n - 1}"
         f", each scored with the GeCo protocol, the least fused kept. N = {best_of.n}, {best_of.how}"
         f"{' (predicted, not measured)' if best_of.predicted_ratio is not None else ''}; {measured}. "
         f"Selection lowered the fused score below the unguided arm's in **{vs_unguided['lowered_fused']['count']} of "
         f"{vs_unguided['lowered_fused']['n']}** pairs ({_share(vs_unguided['lowered_fused'])}); guidance scored below "
         f"{best_of.label} in **{vs_best['lowered_fused']['count']} of {vs_best['lowered_fused']['n']}** pairs "
         f"({_share(vs_best['lowered_fused'])}).{shared}"),
        "",
    ]


def _pair_row(result: dict[str, Any], best_of: BestOf | None) -> list[str]:
    arms = result["arms"]
    return [result["pair"], *(fmt(arms[arm]["fused"]) for arm in run_arms(best_of)),
            fmt(arms["unguided"]["total_motion"]), fmt(arms["guided"]["total_motion"]),
            *([str(arms[BEST_OF][BEST_OF]["kept_seed"])] if best_of is not None else []),
            f"[side by side](pairs/{result['pair']}/{result['side_by_side']})"]


def report_markdown(summary: dict[str, Any], results: Sequence[dict[str, Any]], config_yaml: str, command: str,
                    models: Sequence[str] = ()) -> str:
    """``report.md``: scores, paired differences, cost, the plot, per-pair table, config, versions."""
    n = summary["pairs"]
    lowered = summary["guidance_lowered_fused"]
    best_of = _best_of_of(summary)
    arms = run_arms(best_of)
    title = "unguided vs guided" if best_of is None else f"unguided vs guided vs {best_of.label}"
    lines = [
        f"# GeCo guidance A/B: {title}",
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
    pair_columns = ["pair", *(f"fused {arm_label(arm, best_of)}" for arm in arms), "TM unguided", "TM guided",
                    *([f"kept seed ({best_of.label})"] if best_of is not None else []), "video"]
    lines += [
        "## Scores (mean over pairs; lower fused/motion/structure is more consistent)",
        "",
        *_scores_table(summary, best_of),
        "",
        *_non_finite_note(summary["non_finite_scores"]),
        (f"Guidance lowered the fused score in **{lowered['count']} of {lowered['n']}** pairs "
         f"({_share(lowered)}).{' ' + TINY_GUIDANCE_NOTE if summary.get('tiny_models') else ''} "
         f"Bootstrap: {summary['bootstrap']['resamples']} resamples of "
         f"the pairs, seed {summary['bootstrap']['seed']}. Total/Mean Motion measure how much the video "
         "moves: a lower score at similar motion is the better trade-off (right panel of the plot)."),
        "",
        *_best_of_lines(summary, best_of),
        *_agreement_note(summary.get("decoder_agreement")),
        "## Cost per arm",
        "",
        *markdown_table(
            ["arm", "sampling s (mean)", "sampling s (total)", "scoring s (mean)", "peak memory MiB (max)"],
            [[arm_label(arm, best_of), fmt(summary["arms"][arm]["generation_s_mean"], 3),
              fmt(summary["arms"][arm]["generation_s_total"], 3), fmt(summary["arms"][arm]["evaluation_s_mean"], 3),
              f"{fmt(summary['arms'][arm]['peak_memory_mib_max'], 4)} ({summary['arms'][arm]['memory_kind']})"]
             for arm in arms],
        ),
        "",
        *_timing_note(summary),
        "![fused score: guided vs unguided per pair, and vs Total Motion](pareto.png)",
        "",
        "## Pairs",
        "",
        *markdown_table(pair_columns, [_pair_row(r, best_of) for r in results]),
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

UNGUIDED_COLOR, GUIDED_COLOR, BEST_OF_COLOR = (60, 110, 200), (235, 125, 30), (140, 70, 170)
BETTER_COLOR, WORSE_COLOR, GREY = (40, 160, 70), (210, 50, 50), (170, 170, 170)


def plot_png(results: Sequence[dict[str, Any]], best_of: BestOf | None = None) -> bytes:
    """``pareto.png``: left, guided vs unguided fused score per pair (below the diagonal: guidance
    helped); right, fused score vs Total Motion of every arm, each pair joined by a line."""
    from PIL import Image, ImageDraw

    arms = run_arms(best_of)
    image = Image.new("RGB", (860, 430), (255, 255, 255))
    draw = ImageDraw.Draw(image)
    pairs = [[r["arms"][arm] for arm in arms] for r in results
             if all(np.isfinite([r["arms"][a][k] for a in arms for k in ("fused", "total_motion")]))]
    fused = [rec["fused"] for pair in pairs for rec in pair] or [0.0]
    motion = [rec["total_motion"] for pair in pairs for rec in pair] or [0.0]

    left = Panel((70, 80, 400, 360), limits(fused), limits(fused))
    left.draw_axes(draw, "fused score per pair (below the line: guidance helped)", "unguided fused", "guided fused")
    draw.line([left.to_pixel(left.xlim[0], left.ylim[0]), left.to_pixel(left.xlim[1], left.ylim[1])], fill=GREY)
    for unguided, guided, *_ in pairs:
        color = BETTER_COLOR if guided["fused"] < unguided["fused"] else WORSE_COLOR
        left.dot(draw, unguided["fused"], guided["fused"], color)

    right = Panel((510, 80, 840, 360), limits(motion), limits(fused))
    right.draw_axes(draw, "fused score vs Total Motion (lower-right is better)", "Total Motion (%)", "fused")
    for records in pairs:
        draw.line([right.to_pixel(rec["total_motion"], rec["fused"]) for rec in records], fill=GREY)
    colors = (UNGUIDED_COLOR, GUIDED_COLOR, BEST_OF_COLOR)
    for records in pairs:
        for rec, color in zip(records, colors):
            right.dot(draw, rec["total_motion"], rec["fused"], color)
    legend(draw, left, (("guidance lowered fused", BETTER_COLOR), ("guidance raised fused", WORSE_COLOR)))
    legend(draw, right, tuple((arm_label(arm, best_of), color) for arm, color in zip(arms, colors)))
    return report.png_bytes(image)


def write_report(out: Path, pairs: Sequence[Pair], cfg: GeCoConfig, command: str, versions: dict[str, str],
                 best_of: BestOf | None = None) -> dict[str, Any]:
    """Rebuild the four report files from the pairs' ``result.json`` files; returns the summary."""
    remove_temp_files(out, REPORT_STEMS)
    results = [r for r in (read_run_result(out, pair, best_of) for pair in pairs) if r is not None]
    summary = summarize(results, pairs, cfg, versions, best_of)
    measured = read_agreement(out) if cfg.guidance.decoder == "tiny" else None
    if measured is not None:
        summary["decoder_agreement"] = measured
    markdown = report_markdown(summary, results, config_to_yaml(cfg), command, report.models_section(cfg))
    report.write_report_files(out, table=csv_text(results, run_arms(best_of)), summary=summary,
                              plot=plot_png(results, best_of), markdown=markdown)
    return summary
