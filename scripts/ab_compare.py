"""A/B test of GeCo guidance on your prompts: unguided vs guided video from the same noise.

    python scripts/ab_compare.py --prompts prompts.txt --seeds 0 1 2 --out ab/ --preset tiny
    python scripts/ab_compare.py --prompts prompts.jsonl --seeds 0 --out ab/ --config my.yaml guidance.eta=2.0
    accelerate launch scripts/ab_compare.py --prompts prompts.txt --seeds 0 1 --out ab/ --preset cogvideox-5b

The prompts file holds one prompt per line, or JSON lines ``{"id": "bust", "prompt": "..."}``
(``id`` optional; blank lines and ``#`` comments are skipped). A prompt's id (its slug when not
given) names its output folders, so ids must be unique and filesystem-safe. A JSON line's optional
``"subjects": "a dog, a ball"`` (what moves on its own; ``--prompts dynamic``: our suite) are masked
in both arms' scores and in the guided arm's guidance, by the segmenter of ``estimators.segmenter``.

For every prompt x seed ("pair"), both arms run :func:`geco_guide.cli.generate.generate` with the same
config and seed, so both start from the same initial noise (``torch.Generator("cpu").manual_seed
(seed)``); the unguided arm is exactly ``python -m geco_guide.generate --no-guidance --seed S``.
Both videos are scored by :func:`geco_guide.metric.evaluate.evaluate_video` with the same estimators and
the config's ``evaluation`` protocol. ``<out>/pairs/<id>-s<seed>/`` then holds ``unguided.mp4``,
``guided.mp4`` (each with its generation sidecar ``.json``), ``side_by_side.mp4``, with
``--maps`` the maps videos, and last ``result.json``, whose presence marks the pair complete.

Every file is written atomically, so killing the run at any moment loses at most the pair in
progress and never leaves a truncated file; a rerun skips complete pairs and redoes, with a
warning naming the file, a pair whose ``result.json`` is damaged or lacks fields, or whose videos
or sidecars are gone or unreadable. Outputs another run left in a pair folder (their sidecar names
another prompt or config) are refused unless ``--overwrite``, which redoes every pair. While a run
works in a folder it holds ``<out>/.run.lock`` (its pid): a second run there is refused,
and the lock of a run that was killed is taken over. ``--maps`` on a resumed folder also makes
the maps of complete pairs that have none (their videos are scored again; only the estimators
load), and with ``guidance.decoder=tiny`` a folder without a whole ``decoder_agreement.json`` gets
it measured, whatever the pairs' state. Under ``accelerate launch`` the pairs are dealt round-robin to the processes; at the end
the main process rebuilds ``results.csv`` (one row per pair and arm), ``summary.json``,
``report.md`` and ``pareto.png`` from the pairs' ``result.json`` files; scores that are not finite
are left out of its statistics and named. ``run.json`` pins the config: reusing an output folder
with a different config is refused (unless ``--overwrite``).
"""

from __future__ import annotations

import argparse
import json
import math
import shlex
import sys
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, replace
from datetime import datetime, timezone
from functools import partial
from pathlib import Path
from typing import Any

import numpy as np

from geco_guide.bench import report
from geco_guide.bench.geco_eval import load_segmenters, subject_masks
from geco_guide.bench.report import MIN_INTERVAL_N, TINY_NOTE, fmt, interval_text, markdown_table
from geco_guide.bench.runs import (
    PeakMemory,
    config_fingerprint,
    pin_config,
    process_config,
    process_state,
    read_finished,
    run_lock,
    shard,
)
from geco_guide.bench.runs import check_output_folder as check_run_folder
from geco_guide.cli import generate as generate_cli
from geco_guide.cli.kit import Parser, add_config_flags, config_from_args, interruptible
from geco_guide.cli.prompt_files import Prompt, read_prompts
from geco_guide.config import GeCoConfig, config_to_dict, config_to_yaml
from geco_guide.estimators import load_estimators
from geco_guide.estimators.segmenters import SegmenterFactory
from geco_guide.io.devices import check_device, resolve_device
from geco_guide.io.files import WriteError, remove_temp_files, write_json_atomic
from geco_guide.io.plots import Panel, legend, limits
from geco_guide.io.video import read_frames, read_video, write_video
from geco_guide.loss.geco import CUES
from geco_guide.metric.evaluate import PAPER_NAMES, evaluate_video, write_maps_video
from geco_guide.metric.render import side_by_side
from geco_guide.perf.decoder_agreement import agreement_rows, agreement_summary
from geco_guide.sampler.loading import check_guidance_before_loading, check_weights_before_loading
from geco_guide.types import plural

ARMS = ("unguided", "guided")
METRICS = (*CUES, "total_motion", "mean_motion")
UNIT_STEMS = ("unguided", "guided", "side_by_side", "unguided_maps", "guided_maps", "result")
#: What a complete pair holds besides result.json: a pair missing one of them is redone.
PAIR_OUTPUTS = (*(f"{arm}{ext}" for arm in ARMS for ext in (".mp4", ".json")), "side_by_side.mp4")
REPORT_STEMS = ("results", "summary", "report", "pareto", "run")
BOOTSTRAP_RESAMPLES = 10_000
BOOTSTRAP_SEED = 0
CI_LEVEL = 0.95
MAX_SEED = 2**63 - 1
#: The fields of a result.json that the report reads: a result without one of them is redone.
RESULT_KEYS = ("pair", "prompt_id", "prompt", "seed", "device", "side_by_side", "arms")
ARM_KEYS = ("video", "sidecar", *METRICS, "generation_s", "evaluation_s", "peak_memory_mib", "memory_kind",
            "guidance_updates")
#: With ``guidance.decoder=tiny``: the tiny decoder measured against the VAE on one pair.
AGREEMENT_FILE = "decoder_agreement.json"
TINY_GUIDANCE_NOTE = ("With tiny random models the guidance effect is meaningless: guidance can lower or raise "
                      "the score.")


class InputError(ValueError):
    """A bad command-line input, reported as one line before any model is loaded."""


# ----------------------------------------------------------------------------------------------
# inputs: prompts, seeds, pairs


@dataclass(frozen=True)
class Pair:
    """One prompt x seed: the unit of work, of resuming and of sharding."""

    prompt: Prompt
    seed: int

    @property
    def name(self) -> str:
        return f"{self.prompt.id}-s{self.seed}"


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


def plan_pairs(prompts: Sequence[Prompt], seeds: Sequence[int]) -> list[Pair]:
    return [Pair(prompt, seed) for prompt in prompts for seed in seeds]


def check_output_folder(out: Path, cfg: GeCoConfig, pairs: Sequence[Pair], overwrite: bool = False) -> None:
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
        for arm in ARMS:
            if foreign_video(out, cfg, pair, arm):
                raise InputError(
                    f"{pair_dir(out, pair) / f'{arm}.json'} was made by another run (its prompt or config differ); "
                    "pass --overwrite to replace it, or use a new --out folder"
                )


def arm_config(cfg: GeCoConfig, pair: Pair, arm: str) -> GeCoConfig:
    """The config one arm generates with: the pair's seed, guidance on for the guided arm only,
    with the masks of the prompt's subjects (if any)."""
    guided = arm == "guided"
    dynamic = pair.prompt.subjects if guided and pair.prompt.subjects is not None else cfg.guidance.dynamic
    return replace(cfg, seed=pair.seed, guidance=replace(cfg.guidance, enabled=guided, dynamic=dynamic))


def foreign_video(out: Path, cfg: GeCoConfig, pair: Pair, arm: str) -> bool:
    """Whether the arm's sidecar (if readable) records a video of another prompt or config: its
    :func:`~geco_guide.cli.generate.video_key`, the hash generate's default names carry, differs."""
    try:
        sidecar = json.loads((pair_dir(out, pair) / f"{arm}.json").read_text(encoding="utf-8"))
        made = generate_cli.video_key(sidecar["config"], sidecar["prompt"])
    except (OSError, ValueError, KeyError, TypeError, AttributeError):  # none, or not a sidecar: redone anyway
        return False
    return made != generate_cli.video_key(config_to_dict(arm_config(cfg, pair, arm)), pair.prompt.text)


# ----------------------------------------------------------------------------------------------
# files: atomic writes, pair folders


def pair_dir(out: Path, pair: Pair) -> Path:
    return out / "pairs" / pair.name


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
            print(f"warning: {problem}; pair {pair.name} is redone", file=sys.stderr)
        return None
    for arm in ARMS:
        record = result["arms"][arm]
        record.update({metric: math.nan for metric in METRICS if record[metric] is None})
    return result


def arms_problem(path: Path, arms: Any) -> str | None:
    """What the ``arms`` of the result.json at ``path`` lack that the report reads, or None."""
    if not (isinstance(arms, dict) and all(isinstance(arms.get(arm), dict) for arm in ARMS)):
        return f"{path} lacks 'arms.unguided' or 'arms.guided'"
    lacking = [f"'arms.{arm}.{key}'" for arm in ARMS for key in ARM_KEYS if key not in arms[arm]]
    if lacking:
        return f"{path} lacks {', '.join(lacking[:3])}"
    wrong = [f"'arms.{arm}.{metric}'" for arm in ARMS for metric in METRICS
             if not (arms[arm][metric] is None or isinstance(arms[arm][metric], (int, float)))]
    return f"{path} holds non-numbers in {', '.join(wrong[:3])}" if wrong else None


def videos_problem(folder: Path) -> str | None:
    """Why a pair's videos are not whole (one does not decode, or holds another frame count than
    its sidecar says), or None."""
    try:
        expected = {arm: int(json.loads((folder / f"{arm}.json").read_text(encoding="utf-8"))["num_frames"])
                    for arm in ARMS}
    except (OSError, ValueError, KeyError, TypeError) as err:
        return f"a sidecar in {folder} is damaged ({type(err).__name__})"
    expected["side_by_side"] = expected["guided"]
    for stem, frames in expected.items():
        path = folder / f"{stem}.mp4"
        try:
            found = read_frames(path, select=lambda count, fps: [count - 1]).num_frames
        except (ValueError, OSError) as err:  # VideoReadError is a ValueError
            return str(err).splitlines()[0]
        if found != frames:
            return f"{path} holds {found} frame(s), not {frames}"
    return None


# ----------------------------------------------------------------------------------------------
# one pair


def run_arm(pipe: Any, cfg: GeCoConfig, pair: Pair, arm: str, folder: Path, maps: bool,
            segment: SegmenterFactory | None = None) -> dict[str, Any]:
    """Generate one arm of a pair into ``folder/<arm>.mp4`` (+ sidecar) and score it; what an
    unfinished run of this pair left there is replaced (other runs' outputs were refused before).
    A prompt's subjects are masked in both arms' scores and in the guided arm's guidance."""
    masks = subject_masks(pair.prompt.subjects, segment)
    with PeakMemory(pipe.device) as memory:
        generated = generate_cli.generate(arm_config(cfg, pair, arm), pair.prompt.text, out=folder / f"{arm}.mp4",
                                          pipe=pipe, overwrite=True, dynamic_masks=masks if arm == "guided" else None)
    start = time.perf_counter()
    evaluation = evaluate_video(
        generated.video_path,
        geometry=pipe.geometry_estimator,
        flow=pipe.flow_estimator,
        config=cfg.evaluation,
        maps=maps,
        dynamic_masks=masks,
    )
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
        "evaluation": evaluation.to_dict(),
    }
    if maps:
        record["maps_video"] = write_maps_video(evaluation, folder / f"{arm}_maps.mp4").name
    return record


def has_maps(out: Path, pair: Pair) -> bool:
    return all((pair_dir(out, pair) / f"{arm}_maps.mp4").is_file() for arm in ARMS)


def add_maps(cfg: GeCoConfig, pair: Pair, out: Path, result: dict[str, Any], geometry: Any, flow: Any,
             segment: SegmenterFactory | None = None) -> None:
    """The maps videos of a pair completed without ``--maps``: both videos are scored again with
    maps (deterministic: the scores in ``result.json`` stay), then ``result.json`` names them."""
    folder = pair_dir(out, pair)
    for arm in ARMS:
        evaluation = evaluate_video(folder / f"{arm}.mp4", geometry_estimator=geometry, flow_estimator=flow, config=cfg.evaluation, maps=True,
                                    dynamic_masks=subject_masks(pair.prompt.subjects, segment))
        result["arms"][arm]["maps_video"] = write_maps_video(evaluation, folder / f"{arm}_maps.mp4").name
    write_json_atomic(folder / "result.json", result)


def write_side_by_side(folder: Path, fps: float) -> None:
    """``side_by_side.mp4``: the two arms' videos next to each other, labelled."""
    videos = [read_video(folder / f"{arm}.mp4")[0] for arm in ARMS]
    write_video(folder / "side_by_side.mp4", side_by_side(videos, list(ARMS)), fps=fps)


def run_pair(pipe: Any, cfg: GeCoConfig, pair: Pair, out: Path, maps: bool, where: str | None = None,
             segment: SegmenterFactory | None = None) -> dict[str, Any]:
    """Both arms (with ``where``, a stderr line ``<where>: <arm> arm ...`` before each), the
    side-by-side video, then ``result.json`` (last: it marks the pair complete)."""
    folder = pair_dir(out, pair)
    remove_temp_files(folder, UNIT_STEMS)
    arms = {}
    for arm in ARMS:
        if where is not None:
            print(f"{where}: {arm} arm ...", file=sys.stderr, flush=True)
        arms[arm] = run_arm(pipe, cfg, pair, arm, folder, maps, segment)
    write_side_by_side(folder, cfg.sampling.fps)
    result = {
        "pair": pair.name,
        "prompt_id": pair.prompt.id,
        "prompt": pair.prompt.text,
        **({} if pair.prompt.subjects is None else {"subjects": pair.prompt.subjects}),
        "seed": pair.seed,
        "device": str(pipe.device),
        "side_by_side": "side_by_side.mp4",
        "created": datetime.now(timezone.utc).isoformat(timespec="seconds"),
        "arms": arms,
    }
    write_json_atomic(folder / "result.json", result)
    return result


def measure_decoder_agreement(pipe: Any, cfg: GeCoConfig, pair: Pair, out: Path) -> None:
    """``out/decoder_agreement.json``: one more guided call of ``pair`` in which the VAE and the
    tiny decoder both decode the anchor frames at every update (gradient cosine, both losses,
    anchor PSNR: :func:`geco_guide.perf.decoder_agreement.agreement_rows`)."""
    print(f"measuring the tiny decoder against the VAE on {pair.name} (one more guided call) ...", file=sys.stderr,
          flush=True)
    unmasked = replace(pair, prompt=replace(pair.prompt, subjects=None))  # the decoders compared, without a segmenter
    rows = agreement_rows(pipe, arm_config(cfg, unmasked, "guided"), pair.prompt.text)
    write_json_atomic(out / AGREEMENT_FILE, {"pair": pair.name, "summary": agreement_summary(rows), "updates": rows})


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
            print(f"warning: {path} is damaged; it is measured again", file=sys.stderr)
        return None


def run_shard(cfg: GeCoConfig, pairs: Sequence[Pair], out: Path, maps: bool, tag: str, redo: bool = False,
              on_loaded: Callable[[], None] = lambda: None, agreement: bool = False) -> None:
    """Run the pairs of this process that are not complete yet (all of them with ``redo``), and
    with ``maps`` make the maps of complete pairs that have none (models load only if needed: for
    maps alone, the estimators; ``on_loaded`` runs once they did). With ``agreement`` and
    ``guidance.decoder=tiny``, the tiny decoder is measured against the VAE on the first pair
    (:func:`measure_decoder_agreement`) unless the folder holds that measurement already (a run
    stopped before it measures it when resumed). Outside a terminal, where no progress bar shows,
    one stderr line says which pair and arm runs."""
    finished = {pair.name: None if redo else read_result(out, pair, warn=True, verify=True) for pair in pairs}
    todo = [pair for pair in pairs if finished[pair.name] is None]
    unmapped = [pair for pair in pairs if maps and finished[pair.name] is not None and not has_maps(out, pair)]
    measure = (agreement and bool(pairs) and cfg.guidance.decoder == "tiny"
               and (redo or read_agreement(out, warn=True) is None))
    print(f"{tag}{len(pairs) - len(todo)} of {plural(len(pairs), 'pair')} already complete", flush=True)
    if not todo and not unmapped and not measure:
        on_loaded()
        return
    if todo or measure:
        pipe = generate_cli.build_pipeline(cfg)
        pipe.set_progress_bar_config(disable=not sys.stderr.isatty())
        geometry, flow = pipe.geometry_estimator, pipe.flow_estimator
    else:
        print(f"loading models: geometry {cfg.estimators.geometry}, flow {cfg.estimators.flow} ...", file=sys.stderr,
              flush=True)
        geometry, flow = load_estimators(cfg.estimators, resolve_device(cfg.model.device))
    subjects = any(pair.prompt.subjects is not None for pair in [*todo, *unmapped])
    segment = load_segmenters(cfg, resolve_device(cfg.model.device)) if subjects else None
    on_loaded()
    if unmapped:
        print(f"{tag}making the maps of {len(unmapped)} complete pair(s) that have none", flush=True)
    for pair in unmapped:
        add_maps(cfg, pair, out, finished[pair.name], geometry, flow, segment)
    lines = not sys.stderr.isatty()
    for index, pair in enumerate(todo, start=1):
        result = run_pair(pipe, cfg, pair, out, maps, f"{tag}[{index}/{len(todo)}] {pair.name}" if lines else None,
                          segment)
        unguided, guided = (result["arms"][arm] for arm in ARMS)
        print(
            f"{tag}[{index}/{len(todo)}] {pair.name}: fused {unguided['fused']:.4f} -> {guided['fused']:.4f} "
            f"(sampling {unguided['generation_s']:.1f} s -> {guided['generation_s']:.1f} s)",
            flush=True,
        )
    if measure:
        measure_decoder_agreement(pipe, cfg, pairs[0], out)


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


def paired_difference(results: Sequence[dict[str, Any]], metric: str) -> dict[str, Any]:
    """Mean of ``guided - unguided`` over the pairs where both values are finite, with its CI
    (``None`` below :data:`~geco_guide.bench.report.MIN_INTERVAL_N` such pairs)."""
    diffs = np.array([r["arms"]["guided"][metric] - r["arms"]["unguided"][metric] for r in results], dtype=float)
    diffs = diffs[np.isfinite(diffs)]
    ci = bootstrap_ci(diffs) if len(diffs) >= MIN_INTERVAL_N else None
    return {
        "n": len(diffs),
        "mean_diff": float(diffs.mean()) if len(diffs) else None,
        "ci95": list(ci) if ci is not None else None,
    }


def arm_summary(results: Sequence[dict[str, Any]], arm: str) -> dict[str, Any]:
    """Means of the scores, and time and memory, of one arm over the pairs."""
    records = [r["arms"][arm] for r in results]
    summary: dict[str, Any] = {metric: _finite_mean([rec[metric] for rec in records]) for metric in METRICS}
    summary.update(
        generation_s_mean=float(np.mean([rec["generation_s"] for rec in records])),
        generation_s_total=float(np.sum([rec["generation_s"] for rec in records])),
        evaluation_s_mean=float(np.mean([rec["evaluation_s"] for rec in records])),
        peak_memory_mib_max=float(np.max([rec["peak_memory_mib"] for rec in records])),
        memory_kind=records[0]["memory_kind"],
    )
    return summary


def _finite_mean(values: Sequence[float]) -> float | None:
    """Mean over the finite values (a video without valid pixels scores NaN); None if there are none."""
    finite = [v for v in values if np.isfinite(v)]
    return float(np.mean(finite)) if finite else None


def non_finite_scores(results: Sequence[dict[str, Any]]) -> dict[str, list[str]]:
    """``{pair: ["unguided fused", ...]}`` for the pairs with a NaN/inf score (a video without valid
    pixels), which the means, differences and counts leave out."""
    found = {r["pair"]: [f"{arm} {metric}" for arm in ARMS for metric in METRICS
                         if not np.isfinite(r["arms"][arm][metric])] for r in results}
    return {pair: scores for pair, scores in found.items() if scores}


def summarize(results: Sequence[dict[str, Any]], pairs: Sequence[Pair], cfg: GeCoConfig) -> dict[str, Any]:
    """Everything ``summary.json`` and ``report.md`` say, from the complete pairs' results."""
    done = {r["pair"] for r in results}
    fused = [(r["arms"]["unguided"]["fused"], r["arms"]["guided"]["fused"]) for r in results]
    lowered = [guided < unguided for unguided, guided in fused if np.isfinite([unguided, guided]).all()]
    return {
        "pairs": len(results),
        "pairs_planned": len(pairs),
        "missing_pairs": [p.name for p in pairs if p.name not in done],
        "non_finite_scores": non_finite_scores(results),
        "prompts": len({p.prompt.id for p in pairs}),
        "seeds": sorted({p.seed for p in pairs}),
        "arms": {arm: arm_summary(results, arm) for arm in ARMS} if results else {},
        "paired_differences": {metric: paired_difference(results, metric) for metric in METRICS},
        "guidance_lowered_fused": {
            "count": int(sum(lowered)),
            "n": len(lowered),
            "fraction": sum(lowered) / len(lowered) if lowered else None,
        },
        "bootstrap": {"resamples": BOOTSTRAP_RESAMPLES, "seed": BOOTSTRAP_SEED, "level": CI_LEVEL},
        "config_sha": config_fingerprint(cfg),
        "models": {"video": cfg.model.id, "geometry": cfg.estimators.geometry, "flow": cfg.estimators.flow},
        "tiny_models": report.uses_tiny_models(cfg),
        "config": config_to_dict(cfg),
        "devices": sorted({r["device"] for r in results}),
        "versions": _versions(),
        "created": datetime.now(timezone.utc).isoformat(timespec="seconds"),
    }


def _versions() -> dict[str, str]:
    import accelerate

    return {**generate_cli.versions(), "accelerate": accelerate.__version__}


# ----------------------------------------------------------------------------------------------
# report files


def csv_text(results: Sequence[dict[str, Any]]) -> str:
    """``results.csv``: one row per pair and arm."""
    columns = ["pair", "prompt_id", "seed", "arm", *METRICS, "generation_s", "evaluation_s",
               "peak_memory_mib", "memory_kind", "guidance_updates", "video", "prompt",
               *(["subjects"] if any("subjects" in result for result in results) else [])]
    rows = [{**result, **result["arms"][arm], "arm": arm, "video": f"pairs/{result['pair']}/{result['arms'][arm]['video']}"}
            for result in results for arm in ARMS]
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


def report_markdown(summary: dict[str, Any], results: Sequence[dict[str, Any]], config_yaml: str, command: str,
                    models: Sequence[str] = ()) -> str:
    """``report.md``: scores, paired differences, cost, the plot, per-pair table, config, versions."""
    n = summary["pairs"]
    lowered = summary["guidance_lowered_fused"]
    lines = [
        "# GeCo guidance A/B: unguided vs guided",
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
    arms, paired = summary["arms"], summary["paired_differences"]
    level = int(summary["bootstrap"]["level"] * 100)
    share = f"{fmt(100 * lowered['fraction'], 3)} %" if lowered["n"] else "-"
    rows = []
    for metric in METRICS:
        diff = paired[metric]
        label = f"{metric} ({PAPER_NAMES[metric]})" if metric in CUES else PAPER_NAMES[metric]
        rows.append([label, fmt(arms["unguided"][metric]), fmt(arms["guided"][metric]),
                     fmt(diff["mean_diff"]), interval_text(diff["ci95"], diff["n"], "pair")])
    lines += [
        "## Scores (mean over pairs; lower fused/motion/structure is more consistent)",
        "",
        *markdown_table(["metric", "unguided", "guided", "guided - unguided", f"{level}% CI (paired bootstrap)"], rows),
        "",
        *_non_finite_note(summary["non_finite_scores"]),
        (f"Guidance lowered the fused score in **{lowered['count']} of {lowered['n']}** pairs "
         f"({share}).{' ' + TINY_GUIDANCE_NOTE if summary.get('tiny_models') else ''} "
         f"Bootstrap: {summary['bootstrap']['resamples']} resamples of "
         f"the pairs, seed {summary['bootstrap']['seed']}. Total/Mean Motion measure how much the video "
         "moves: a lower score at similar motion is the better trade-off (right panel of the plot)."),
        "",
        *_agreement_note(summary.get("decoder_agreement")),
        "## Cost per arm",
        "",
        *markdown_table(
            ["arm", "sampling s (mean)", "sampling s (total)", "scoring s (mean)", "peak memory MiB (max)"],
            [[arm, fmt(arms[arm]["generation_s_mean"], 3), fmt(arms[arm]["generation_s_total"], 3),
              fmt(arms[arm]["evaluation_s_mean"], 3),
              f"{fmt(arms[arm]['peak_memory_mib_max'], 4)} ({arms[arm]['memory_kind']})"] for arm in ARMS],
        ),
        "",
        "![fused score: guided vs unguided per pair, and vs Total Motion](pareto.png)",
        "",
        "## Pairs",
        "",
        *markdown_table(
            ["pair", "fused unguided", "fused guided", "TM unguided", "TM guided", "video"],
            [[r["pair"], fmt(r["arms"]["unguided"]["fused"]), fmt(r["arms"]["guided"]["fused"]),
              fmt(r["arms"]["unguided"]["total_motion"]), fmt(r["arms"]["guided"]["total_motion"]),
              f"[side by side](pairs/{r['pair']}/{r['side_by_side']})"] for r in results],
        ),
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

UNGUIDED_COLOR, GUIDED_COLOR = (60, 110, 200), (235, 125, 30)
BETTER_COLOR, WORSE_COLOR, GREY = (40, 160, 70), (210, 50, 50), (170, 170, 170)


def plot_png(results: Sequence[dict[str, Any]]) -> bytes:
    """``pareto.png``: left, guided vs unguided fused score per pair (below the diagonal: guidance
    helped); right, fused score vs Total Motion of both arms, each pair joined by a line."""
    from PIL import Image, ImageDraw

    image = Image.new("RGB", (860, 430), (255, 255, 255))
    draw = ImageDraw.Draw(image)
    pairs = [(r["arms"]["unguided"], r["arms"]["guided"]) for r in results
             if all(np.isfinite([r["arms"][a][k] for a in ARMS for k in ("fused", "total_motion")]))]
    fused = [rec["fused"] for pair in pairs for rec in pair] or [0.0]
    motion = [rec["total_motion"] for pair in pairs for rec in pair] or [0.0]

    left = Panel((70, 80, 400, 360), limits(fused), limits(fused))
    left.draw_axes(draw, "fused score per pair (below the line: guidance helped)", "unguided fused", "guided fused")
    draw.line([left.to_pixel(left.xlim[0], left.ylim[0]), left.to_pixel(left.xlim[1], left.ylim[1])], fill=GREY)
    for unguided, guided in pairs:
        color = BETTER_COLOR if guided["fused"] < unguided["fused"] else WORSE_COLOR
        left.dot(draw, unguided["fused"], guided["fused"], color)

    right = Panel((510, 80, 840, 360), limits(motion), limits(fused))
    right.draw_axes(draw, "fused score vs Total Motion (lower-right is better)", "Total Motion (%)", "fused")
    for unguided, guided in pairs:
        draw.line([right.to_pixel(unguided["total_motion"], unguided["fused"]),
                   right.to_pixel(guided["total_motion"], guided["fused"])], fill=GREY)
    for unguided, guided in pairs:
        right.dot(draw, unguided["total_motion"], unguided["fused"], UNGUIDED_COLOR)
        right.dot(draw, guided["total_motion"], guided["fused"], GUIDED_COLOR)
    legend(draw, left, (("guidance lowered fused", BETTER_COLOR), ("guidance raised fused", WORSE_COLOR)))
    legend(draw, right, (("unguided", UNGUIDED_COLOR), ("guided", GUIDED_COLOR)))
    return report.png_bytes(image)


def write_report(out: Path, pairs: Sequence[Pair], cfg: GeCoConfig, command: str) -> dict[str, Any]:
    """Rebuild the four report files from the pairs' ``result.json`` files; returns the summary."""
    remove_temp_files(out, REPORT_STEMS)
    results = [r for r in (read_result(out, pair) for pair in pairs) if r is not None]
    summary = summarize(results, pairs, cfg)
    measured = read_agreement(out) if cfg.guidance.decoder == "tiny" else None
    if measured is not None:
        summary["decoder_agreement"] = measured
    markdown = report_markdown(summary, results, config_to_yaml(cfg), command, report.models_section(cfg))
    report.write_report_files(out, table=csv_text(results), summary=summary, plot=plot_png(results), markdown=markdown)
    return summary


# ----------------------------------------------------------------------------------------------
# CLI


def build_parser() -> argparse.ArgumentParser:
    p = Parser(
        prog="scripts/ab_compare.py",
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
    p.add_argument("--overwrite", action="store_true",
                   help="redo every pair, replacing what --out holds (also another config's or prompt's results)")
    p.add_argument("overrides", nargs="*", metavar="key=value", help="config overrides, e.g. guidance.eta=2.0")
    return p


@dataclass
class Inputs:
    cfg: GeCoConfig
    pairs: list[Pair]
    out: Path


def validate_inputs(args: argparse.Namespace) -> Inputs:
    """Every check that needs no model: prompts, seeds, config (what generate checks before loading),
    output folder."""
    prompts = read_prompts(args.prompts)
    seeds = parse_seeds(args.seeds)
    cfg = config_from_args(args, args.overrides)
    if not cfg.guidance.enabled:
        raise InputError("guidance.enabled=false leaves nothing to compare: the guided arm needs guidance")
    check_device(cfg.model.device)
    # what generate checks before loading, here before run.json is pinned or any video written
    s = cfg.sampling
    check_weights_before_loading(cfg)
    check_guidance_before_loading(cfg, model_id=cfg.model.id, num_frames=s.num_frames, height=s.height, width=s.width,
                                  num_steps=s.num_inference_steps)
    pairs = plan_pairs(prompts, seeds)
    out = Path(args.out)
    check_output_folder(out, cfg, pairs, args.overwrite)
    return Inputs(cfg, pairs, out)


# ----------------------------------------------------------------------------------------------
# one run per output folder


@interruptible("finished pairs are kept (each pair is written whole or not at all); rerun the same command to resume")
def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    try:
        inputs = validate_inputs(args)
        with run_lock(inputs.out, "A/B"):
            return run(args, inputs, argv)
    except (ValueError, FileNotFoundError) as err:
        print(f"error: {err}", file=sys.stderr)
        return 2


def run(args: argparse.Namespace, inputs: Inputs, argv: list[str] | None) -> int:
    """Every process's share of the pairs, then on the main process the report."""
    cfg, pairs, out = inputs.cfg, inputs.pairs, inputs.out
    state = process_state(cfg)
    tag = f"[rank {state.process_index} of {state.num_processes}] " if state.num_processes > 1 else ""
    try:
        run_shard(process_config(cfg, state), shard(pairs, state.process_index, state.num_processes), out, args.maps,
                  tag, redo=args.overwrite, agreement=state.is_main_process,
                  # once the models loaded: missing weights leave no run.json behind
                  on_loaded=partial(pin_config, out, cfg) if state.is_main_process else lambda: None)
        state.wait_for_everyone()
        if not state.is_main_process:
            return 0
        command = shlex.join(["python", *sys.argv] if argv is None else ["scripts/ab_compare.py", *argv])
        summary = write_report(out, pairs, cfg, command)
    except (ValueError, FileNotFoundError, WriteError) as err:  # diverged sampling, weights not there, disk full
        print(f"error: {err}", file=sys.stderr)
        return 2
    fused = summary["paired_differences"]["fused"]
    if summary["tiny_models"]:
        print(TINY_GUIDANCE_NOTE)
    print(f"{plural(summary['pairs'], 'pair')}: fused guided - unguided = {fmt(fused['mean_diff'])}, 95% CI "
          f"{interval_text(fused['ci95'], fused['n'], 'pair')}; report: {out / 'report.md'}")
    return 0 if not summary["missing_pairs"] else 1


if __name__ == "__main__":
    sys.exit(main())
