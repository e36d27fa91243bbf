"""GeCo-Eval, the paper's benchmark: prompts, jobs, the runner and the report (the command is
:mod:`geco_guide.cli.geco_eval`).

The suite is the paper's 80 prompts (supplement, "List of Text Prompt"; shipped as
``geco_guide/bench/data/geco_eval_prompts.jsonl``): four scenarios (object-centric, indoor, outdoor,
appearance-complex) x slow / fast camera x 10. Each job is one (model, prompt, seed, guided?):
the model generates the video at its documented default settings (the model registry,
:data:`geco_guide.families.MODELS`) through the one generation path (:mod:`geco_guide.generation`),
written at its native frame rate, and :func:`geco_guide.metric.evaluate.evaluate_video` scores it with
the GeCo-Eval protocol (the config's ``evaluation`` section, the model's native rate from
``evaluation.model_fps``). ``--videos NAME=DIR`` scores videos that exist already.

``DIR/videos/<model>[-guided]/<prompt_id>-s<seed>.mp4`` holds each video, ``.json`` beside it its
scores and timings (written last: a complete one marks the job done, so a killed run resumes where
it stopped). A job whose video cannot be scored (unreadable, too short, non-finite) leaves
``<prompt_id>-s<seed>.failed.json`` with the reason instead, and the run goes on with the others;
a rerun tries it again. The report is rebuilt from every job's JSON at the end: ``results.csv``
(one row per video, failed ones with their reason), ``summary.json`` and ``report.md`` (per model:
all, per scenario, slow vs fast; mean and standard deviation of each score, as the paper's tables)
and ``pareto.png`` (fused score vs Mean Motion, one point per model; one panel per scenario with
data). ``run.json`` pins the config.

The ``dynamic`` suite is ours, not the paper's: 24 prompts (ids m1..m24, shipped as
``geco_guide/bench/data/geco_eval_dynamic_prompts.jsonl``) over the same four scenarios and two
camera speeds, each naming its moving subjects in a ``subjects`` field (``"a dog, a frisbee"``).
Its videos are scored with the dynamic masks of those subjects (the text segmenter of
``estimators.segmenter``), and its guided videos are guided with them (``guidance.dynamic``). Under ``accelerate launch`` the jobs are dealt round-robin to
the processes and the main process writes the report once all are done.
"""

from __future__ import annotations

import json
import logging
import math
import re
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field, replace
from datetime import datetime, timezone
from importlib import resources
from pathlib import Path
from typing import Any

from ..config import GeCoConfig, config_to_yaml, to_config
from ..estimators import TINY_RANDOM, Estimators, estimator_ids, load_estimators
from ..families import MODELS
from ..generation import Models, load_models, sample
from ..io.devices import planning_memory_gb, resolve_device, resolve_devices
from ..io.files import (
    WriteError,
    remove_temp_files,
    write_json_atomic,
)
from ..io.plots import Panel, legend, legend_width, limits, text
from ..io.video import VIDEO_SUFFIXES, SoundTrack, write_video
from ..loss.cues import CUES, MAP_ORDER
from ..metric.evaluate import PAPER_NAMES, evaluate_video
from ..sampler.pipelines.loading import check_guidance_before_loading, check_tiny_decoder, quiet_hub_logs
from ..sampler.pipelines.sampling import SamplingConfig, fit_to_model
from ..sampler.running.memory_plan import plan_before_loading
from ..types import plural
from . import report
from .report import fmt
from .runs import (
    PeakMemory,
    config_fingerprint,
    read_finished,
)

__all__ = ["CAMERAS", "DYNAMIC_SUITE", "PARETO_LEFT", "PROMPT_FILES", "SCENARIOS", "SUITE", "Job",
           "check_guided_models", "check_model_weights", "csv_text", "existing_video_jobs", "job_config", "load_prompts",
           "movers_cell", "plot_png", "prompts_without_video", "remove_run_outputs", "run_jobs", "select_prompts",
           "write_report"]

SCENARIOS = ("object-centric", "indoor", "outdoor", "appearance-complex")
CAMERAS = ("slow", "fast")
#: The paper's 80 prompts.
SUITE = "geco-eval"
#: Our own prompts with moving subjects (not the paper's): scored and guided with their masks.
DYNAMIC_SUITE = "dynamic"
#: suite -> its JSON-lines file, package data of :mod:`geco_guide.bench`
PROMPT_FILES = {SUITE: "data/geco_eval_prompts.jsonl", DYNAMIC_SUITE: "data/geco_eval_dynamic_prompts.jsonl"}

logger = logging.getLogger(__name__)

METRICS = (*CUES, "total_motion", "mean_motion")
REPORT_STEMS = ("results", "summary", "report", "pareto", "run")
REPORT_FILES = ("results.csv", "summary.json", "report.md", "pareto.png", "run.json")
#: What the report reads of a job's result JSON: one without them is redone.
RESULT_KEYS = ("model", "guided", "prompt_id", "scenario", "camera", "seed", *METRICS, "generation_s",
               "peak_memory_mib", "video")


# ----------------------------------------------------------------------------------------------
# the prompt suite


def load_prompts(scenario: str | None = None, camera: str | None = None, suite: str = SUITE) -> list[dict[str, str]]:
    """The prompts of ``suite`` (``id``, ``scenario``, ``camera``, ``prompt``; the dynamic suite's
    also ``subjects``), optionally of one scenario and/or camera speed, in file order (the
    paper's: a1..a20, b1..., c1..., d1...; ours: m1..m24)."""
    if suite not in PROMPT_FILES:
        raise ValueError(f"unknown prompt suite {suite!r}; known: {list(PROMPT_FILES)}")
    if scenario is not None and scenario not in SCENARIOS:
        raise ValueError(f"unknown scenario {scenario!r}; known: {list(SCENARIOS)}")
    if camera is not None and camera not in CAMERAS:
        raise ValueError(f"unknown camera speed {camera!r}; known: {list(CAMERAS)}")
    text = resources.files("geco_guide.bench").joinpath(PROMPT_FILES[suite]).read_text(encoding="utf-8")
    prompts = [json.loads(line) for line in text.splitlines() if line.strip()]
    return [p for p in prompts if scenario in (None, p["scenario"]) and camera in (None, p["camera"])]


def select_prompts(spec: str) -> list[dict[str, str]]:
    """``geco-eval``, ``geco-eval:indoor``, ``geco-eval:fast``, ``geco-eval:indoor:fast``; the
    same with ``dynamic`` (our suite of moving subjects)."""
    name, *filters = spec.split(":")
    if name not in PROMPT_FILES:
        raise ValueError(f"a prompt suite is named {SUITE} or {DYNAMIC_SUITE}, then [:SCENARIO][:CAMERA], got {spec!r}")
    scenario = next((f for f in filters if f in SCENARIOS), None)
    camera = next((f for f in filters if f in CAMERAS), None)
    unknown = [f for f in filters if f not in SCENARIOS + CAMERAS]
    if unknown:
        raise ValueError(f"unknown filter {unknown[0]!r} in {spec!r}; scenarios {list(SCENARIOS)}, cameras {list(CAMERAS)}")
    return load_prompts(scenario, camera, name)


# ----------------------------------------------------------------------------------------------
# loading the models


def job_config(cfg: GeCoConfig, name: str, *, guided: bool = False, weights: str | None = None,
               subjects: str | None = None) -> GeCoConfig:
    """The config the videos of model ``name`` are made with: ``cfg`` for that model, its weights
    (``weights``: a ``--weights`` folder; ``model.id=tiny-random`` keeps its tiny stand-in; else
    the registry's hub id), its model card's call (with tiny random weights the config's short
    call, at the model's size multiple), guidance on (``guided``, with anchors spread over its
    video and the prompt's ``subjects`` masked) or off."""
    from ..tiny import tiny_sampling

    model = MODELS[name]
    tiny = cfg.model.id == TINY_RANDOM
    # the scheduler is the model's (the config filled CogVideoX's ddim for the tiny preset's model)
    sampling = (fit_to_model(replace(cfg.sampling, **tiny_sampling(model), scheduler=None), model) if tiny
                else SamplingConfig())
    guidance = replace(cfg.guidance, enabled=guided, anchors=None, dynamic=subjects if guided else None)
    return to_config(replace(cfg, model=replace(cfg.model, name=name, id=TINY_RANDOM if tiny else weights),
                             sampling=sampling, guidance=guidance))


# ----------------------------------------------------------------------------------------------
# jobs


@dataclass(frozen=True)
class Job:
    """One video: the unit of work, of resuming and of sharding. ``video`` is set for scoring an
    existing file (``--videos``) and ``None`` for generating one."""

    model: str
    prompt: dict[str, str] = field(hash=False, compare=False)
    seed: int
    guided: bool = False
    video: Path | None = None

    @property
    def arm(self) -> str:
        return f"{self.model}-guided" if self.guided else self.model

    @property
    def name(self) -> str:
        return f"{self.prompt['id']}-s{self.seed}"


def job_paths(out: Path, job: Job) -> tuple[Path, Path]:
    """``(video.mp4, result.json)`` of a job under ``out/videos/<arm>/``."""
    folder = out / "videos" / job.arm
    return folder / f"{job.name}.mp4", folder / f"{job.name}.json"


def failure_path(out: Path, job: Job) -> Path:
    """``<prompt_id>-s<seed>.failed.json`` beside the job's result: why its video could not be scored."""
    return out / "videos" / job.arm / f"{job.name}.failed.json"


def job_video(out: Path, job: Job) -> str:
    """The video a job's result points at: the ``--videos`` file as given, or the generated one
    relative to ``out``."""
    return str(job.video) if job.video is not None else str(job_paths(out, job)[0].relative_to(out))


def read_job_result(out: Path, job: Job, warn: bool = True) -> dict[str, Any] | None:
    """A finished job's result, or None. A damaged result JSON, one that lacks a field the report
    reads (:data:`RESULT_KEYS`) or points at another video, or a video that is gone or unreadable,
    means the job is redone (with a warning naming the file)."""
    video, path = job_paths(out, job)
    unit = f"job {job.arm}/{job.name}"
    result = read_finished(path, [video if job.video is None else job.video], unit, warn=warn, required=RESULT_KEYS)
    if result is not None and result["video"] != job_video(out, job):
        if warn:
            logger.warning("warning: %s scores %r, not %r; %s is redone", path, result["video"], job_video(out, job),
                           unit)
        return None
    return result


def read_job_failure(out: Path, job: Job) -> dict[str, Any] | None:
    """The failure record of a job that has no result (:func:`failure_path`), or None."""
    return read_finished(failure_path(out, job), [], f"job {job.arm}/{job.name}", warn=False, required=("error",))


PROMPT_FILE_ID = re.compile(r"^(?P<id>[a-dm]\d{1,2})-s(?P<seed>\d+)$")


def existing_video_jobs(name: str, folder: Path, prompts: Sequence[dict[str, str]]) -> list[Job]:
    """Jobs for the videos of ``folder``: ``<prompt_id>-s<seed>.<ext>``, or ``<prompt_id>/*.<ext>``
    (seeds numbered in file-name order); only prompts of the selection."""
    if not folder.is_dir():
        raise ValueError(f"--videos {name}={folder}: no such folder")
    by_id = {p["id"]: p for p in prompts}
    jobs: list[Job] = []
    for path in sorted(folder.iterdir()):
        match = PROMPT_FILE_ID.match(path.stem) if path.is_file() and path.suffix.lower() in VIDEO_SUFFIXES else None
        if match and match["id"] in by_id:
            jobs.append(Job(name, by_id[match["id"]], int(match["seed"]), video=path))
        elif path.is_dir() and path.name in by_id:
            files = sorted(p for p in path.iterdir() if p.is_file() and p.suffix.lower() in VIDEO_SUFFIXES)
            jobs.extend(Job(name, by_id[path.name], seed, video=p) for seed, p in enumerate(files))
    if not jobs:
        raise ValueError(f"--videos {name}={folder}: no video named <prompt_id>-s<seed>.mp4 or <prompt_id>/*.mp4 "
                         "for the selected prompts")
    return jobs


def prompts_without_video(name: str, jobs: Sequence[Job], prompts: Sequence[dict[str, str]]) -> list[str]:
    """``<name>/<prompt_id>`` of each selected prompt that no job of ``--videos NAME=DIR`` covers."""
    covered = {job.prompt["id"] for job in jobs if job.model == name}
    return [f"{name}/{p['id']}" for p in prompts if p["id"] not in covered]


def remove_run_outputs(out: Path) -> None:
    """Delete what a GeCo-Eval run wrote in ``out`` (``--overwrite``): the report files,
    ``run.json`` and under ``videos/<arm>/`` the ``<prompt_id>-s<seed>`` videos, results and
    failure records; folders left empty go too, any other file stays.

    Raises:
        WriteError: one line naming what could not be removed.
    """
    videos = out / "videos"
    try:
        for name in REPORT_FILES:
            (out / name).unlink(missing_ok=True)
        for arm in [arm for arm in videos.iterdir() if arm.is_dir()] if videos.is_dir() else []:
            for path in arm.iterdir():
                if path.is_file() and PROMPT_FILE_ID.match(path.name.split(".", 1)[0]) and (
                        path.suffix in (".json", *VIDEO_SUFFIXES)):
                    path.unlink()
            if not any(arm.iterdir()):
                arm.rmdir()
        if videos.is_dir() and not any(videos.iterdir()):
            videos.rmdir()
    except OSError as err:
        raise WriteError(f"--overwrite cannot remove {err.filename!r} in {str(out)!r}: {err.strerror}") from None


def check_guided_models(cfg: GeCoConfig, names: Sequence[str]) -> None:
    """What a guided call of each model would refuse and ``generate`` checks before loading (the
    tiny decoder for its latents, a memory plan that fits, the loss, the schedule, the decode
    layout for its VAE, the anchors), before any model loads or any file is written.

    Raises:
        ValueError: one line naming the model.
        WeightsNotFoundError: ``estimators.tiny_decoder`` names a file that does not exist.
    """
    for name in names:
        try:
            guided = job_config(cfg, name, guided=True)
            s, g = guided.sampling, guided.guidance
            if g.decoder == "tiny":
                check_tiny_decoder(guided.estimators, MODELS[name])
            device_gb = planning_memory_gb(guided.model.device, resolve_devices(guided.run.devices))
            plan_before_loading(g, guided.run, guided.model.source, s.num_frames, s.height, s.width, device_gb)
            check_guidance_before_loading(g, guided.run, MODELS[name], num_frames=s.num_frames,
                                          num_steps=s.num_inference_steps)
        except ValueError as err:
            raise ValueError(f"{name} guided: {err}") from None


def check_model_weights(cfg: GeCoConfig, names: Sequence[str], weights: dict[str, str]) -> None:
    """The missing-weights line of the video models to generate and of the estimators, before any
    model loads (a cache look-up or one metadata request per model), every missing one named at
    once, so that a run never stops at its second model after hours of the first.

    Raises:
        WeightsNotFoundError: one line naming each missing model and how to pass a local folder.
    """
    from ..estimators import check_weights
    from ..estimators.loading import WeightsSource
    from ..sampler.pipelines.loading import PIPELINE_INDEX

    rows = [] if cfg.model.id == TINY_RANDOM else [
        WeightsSource(f"--weights {name}", weights.get(name, MODELS[name].hub_id), name, (PIPELINE_INDEX,),
                      example=f"/path/to/{Path(MODELS[name].hub_id).name}") for name in names]
    check_weights(cfg.estimators, extra=rows)


def _video_models(cfg: GeCoConfig, name: str, weights: str | None, estimators: Estimators, guided: bool) -> Models:
    """Model ``name``'s pipeline, loaded once for its jobs, with the run's ``estimators`` (and, for
    guided jobs with ``guidance.decoder=tiny``, the tiny decoder of its latents)."""
    model_cfg = job_config(cfg, name, guided=guided, weights=weights)
    loaded = load_models(model_cfg, estimators=estimators)
    loaded.pipe.set_progress_bar_config(disable=True)
    return loaded


def _generate(job: Job, cfg: GeCoConfig, models: Models, weights: str | None,
              fps: float) -> tuple[Any, SoundTrack | None, float, float, int]:
    """``(frames [F, 3, H, W] in [0, 1], sound, sampling seconds, peak MiB, guidance updates)`` of
    ``job``, its video to be written at ``fps``. The sound is the one the model made (LTX-2's),
    kept where it was made for ``fps`` (it then lasts as long as the video; a real model's call
    rate is its protocol rate), ``None`` otherwise or without one."""
    job_cfg = job_config(cfg, job.model, guided=job.guided, weights=weights,
                         subjects=job.prompt.get("subjects"))
    with PeakMemory(models.pipe.device) as memory, quiet_hub_logs():  # no prompt-truncation warnings
        made = sample(models, job_cfg, job.prompt["prompt"], seed=job.seed, progress=False)
    audio = made.audio
    if audio is not None and job_cfg.sampling.fps != fps:
        logger.info("%s: the sound was made for %g fps, the video is written at the protocol's %g fps: "
                    "written without it", f"{job.model} {job.name}", job_cfg.sampling.fps, fps)
        audio = None
    return made.frames[0], audio, made.seconds, memory.peak_mib, len(made.report.log)


def run_job(job: Job, out: Path, cfg: GeCoConfig, estimators: Estimators, models: Models | None,
            weights: str | None = None) -> dict[str, Any]:
    """Generate (for a job without ``video``) and score one job; its result JSON is written last
    (and a failure record of an earlier try removed). A prompt with ``subjects`` is scored with
    their masks (made by the segmenter of ``estimators``).

    Raises:
        ValueError, FileNotFoundError: this video cannot be scored (unreadable, too short,
            non-finite frames) or generated (non-finite frames); the caller records it.
    """
    video, result_path = job_paths(out, job)
    remove_temp_files(video.parent, (job.name,))
    fps = cfg.evaluation.fps_of_model(job.model)
    timing: dict[str, Any] = {"generation_s": None, "peak_memory_mib": None, "guidance_updates": 0}
    if job.video is None:
        frames, audio, seconds, peak, updates = _generate(job, cfg, models, weights, fps)
        write_video(video, frames, fps=fps, audio=audio)
        timing = {"generation_s": seconds, "peak_memory_mib": peak, "guidance_updates": updates}
    source = job.video or video
    start = time.perf_counter()
    evaluation = evaluate_video(source, estimators, cfg.evaluation, model=job.model,
                                dynamic_masks=estimators.masks_for(job.prompt.get("subjects")))
    result = {
        **job_identity(job), **{metric: evaluation.to_dict()[metric] for metric in METRICS},
        **({} if evaluation.movers is None else {"movers": movers_cell(evaluation.movers)}),
        **timing, "evaluation_s": time.perf_counter() - start,
        "video": job_video(out, job),
        "created": datetime.now(timezone.utc).isoformat(timespec="seconds"),
        "evaluation": evaluation.to_dict(),
    }
    write_json_atomic(result_path, result)
    failure_path(out, job).unlink(missing_ok=True)
    return result


def job_identity(job: Job) -> dict[str, Any]:
    """The fields that name a job in its result and failure record (and in ``results.csv``)."""
    identity = {"model": job.model, "guided": job.guided, "prompt_id": job.prompt["id"],
                "scenario": job.prompt["scenario"], "camera": job.prompt["camera"], "seed": job.seed}
    if "subjects" in job.prompt:
        identity["subjects"] = job.prompt["subjects"]
    return identity


def record_failure(out: Path, job: Job, err: Exception) -> str:
    """Write the job's failure record (its reason, the first line of ``err``); returns the reason."""
    reason = (str(err).strip().splitlines() or [type(err).__name__])[0]
    write_json_atomic(failure_path(out, job), {**job_identity(job), "video": job_video(out, job), "error": reason,
                                               "created": datetime.now(timezone.utc).isoformat(timespec="seconds")})
    return reason


def run_jobs(jobs: Sequence[Job], out: Path, cfg: GeCoConfig, weights: dict[str, str], tag: str = "",
             on_loaded: Callable[[], None] | None = None) -> None:
    """Run the jobs not done yet, one model at a time (models and estimators load only if needed).

    A job whose video cannot be scored or generated (ValueError, FileNotFoundError, or a TypeError
    of an option its pipeline refuses) is recorded as failed (:func:`record_failure`) and the
    others go on. Progress is logged, one line per job. ``on_loaded`` is called
    once, when the first model needed has loaded (or at once when nothing is left to do), before
    any job writes a file: the caller pins the run there, so that a run stopped by missing weights
    leaves nothing behind.
    """
    todo = [job for job in jobs if read_job_result(out, job) is None]
    retried = sum(1 for job in todo if failure_path(out, job).is_file())
    logger.info("%s%d of %s already done%s", tag, len(jobs) - len(todo), plural(len(jobs), "video"),
                f"; {retried} that failed before are tried again" if retried else "")
    if not todo:
        if on_loaded is not None:
            on_loaded()
        return
    logger.info("%sloading models: geometry %s, flow %s", tag, cfg.estimators.geometry, cfg.estimators.flow)
    subjects = any("subjects" in job.prompt for job in todo)
    if subjects:  # loaded once for every prompt's subjects
        logger.info("%sloading segmenter: %s", tag, cfg.estimators.segmenter)
    estimators = load_estimators(cfg.estimators, resolve_device(cfg.evaluation.device), segmenter=subjects)
    done = 0
    for name in dict.fromkeys(job.model for job in todo):
        models = None
        if any(job.video is None for job in todo if job.model == name):
            logger.info("%sloading models: %s (%s)", tag, name, model_weights(cfg, [name], weights)[name])
            models = _video_models(cfg, name, weights.get(name), estimators,
                                   guided=any(job.guided for job in todo if job.model == name))
        if done == 0 and on_loaded is not None:
            on_loaded()
        for job in (j for j in todo if j.model == name):
            done += 1
            start = time.perf_counter()
            try:
                result = run_job(job, out, cfg, estimators, models, weights.get(name))
                outcome = f"fused {fmt(result['fused'])}, TM {fmt(result['total_motion'])} %"
            # this video only: unreadable, too short, non-finite, or an option its pipeline refuses (TypeError)
            except (ValueError, TypeError, FileNotFoundError) as err:
                outcome = f"failed: {record_failure(out, job, err)}"
            logger.info("%s[%d/%d] %s %s seed %s: %s in %.1f s, %s", tag, done, len(todo), job.arm, job.prompt["id"],
                        job.seed, "scored" if job.video is not None else "generated and scored",
                        time.perf_counter() - start, outcome)
        del models


# ----------------------------------------------------------------------------------------------
# the report


def _stats(values: Sequence[float | None]) -> dict[str, Any]:
    """Mean and sample standard deviation over the finite values, and their count."""
    finite = [v for v in values if v is not None and math.isfinite(v)]
    n = len(finite)
    mean = sum(finite) / n if n else None
    std = math.sqrt(sum((v - mean) ** 2 for v in finite) / (n - 1)) if n > 1 else None
    return {"mean": mean, "std": std, "n": n}


def summarize(results: Sequence[dict[str, Any]]) -> dict[str, Any]:
    """Per arm (model, guided or not): every metric's mean/std over all videos, per scenario and
    per camera speed."""
    arms: dict[str, Any] = {}
    for arm in dict.fromkeys(f"{r['model']}-guided" if r["guided"] else r["model"] for r in results):
        rows = [r for r in results if (f"{r['model']}-guided" if r["guided"] else r["model"]) == arm]
        groups = {"all": rows,
                  **{s: [r for r in rows if r["scenario"] == s] for s in SCENARIOS},
                  **{c: [r for r in rows if r["camera"] == c] for c in CAMERAS}}
        arms[arm] = {
            "model": rows[0]["model"], "guided": rows[0]["guided"], "videos": len(rows),
            "groups": {g: {m: _stats([r[m] for r in members]) for m in METRICS} for g, members in groups.items() if members},
            "generation_s_mean": _stats([r["generation_s"] for r in rows])["mean"],
            "peak_memory_mib_max": max((r["peak_memory_mib"] for r in rows if r["peak_memory_mib"] is not None), default=None),
        }
    return {"arms": arms, "videos": len(results), "paper_names": PAPER_NAMES}


CSV_COLUMNS = ("model", "guided", "prompt_id", "scenario", "camera", "seed", *METRICS, "generation_s",
               "evaluation_s", "peak_memory_mib", "guidance_updates", "video", "error")


def csv_text(results: Sequence[dict[str, Any]]) -> str:
    """``results.csv``; the dynamic suite's rows add their ``subjects``, and with
    ``evaluation.loss.movers=rigid`` their ``movers`` (:func:`movers_cell`)."""
    extra = tuple(column for column in ("subjects", "movers") if any(column in r for r in results))
    return report.csv_text(results, (*CSV_COLUMNS, *extra))


def movers_cell(movers: dict[str, Any]) -> str:
    """One video's movers in a word (its evaluation's ``movers``): ``"2 rigid, 1 non-rigid, 31.0 % of
    fused"``, the movers counted over the windows, with their share of the fused score."""
    return (f"{movers['rigid']} rigid, {movers['non_rigid']} non-rigid, "
            f"{100 * movers['share']:.1f} % of fused")


def _cell(stats: dict[str, Any]) -> str:
    if stats["mean"] is None:
        return "-"
    return fmt(stats["mean"]) + ("" if stats["std"] is None else f" ± {fmt(stats['std'], 3)}")


def _listed(names: Sequence[str], limit: int = 20) -> str:
    return ", ".join(names[:limit]) + (" ..." if len(names) > limit else "")


def report_markdown(summary: dict[str, Any], missing: Sequence[str], config_yaml: str, command: str,
                    models: Sequence[str] = ()) -> str:
    """``report.md``; ``missing``: the jobs not finished; ``models``: the lines of
    :func:`geco_guide.bench.report.models_section`. The summary's ``failed`` (job, reason) and
    ``no_video`` (prompts a ``--videos`` folder lacks) are listed too."""
    lines = ["# GeCo-Eval", "",
             f"{plural(summary['videos'], 'video')} scored; command: `{command}`", ""]
    if summary.get("tiny_models"):
        lines += [f"**{report.TINY_NOTE}.**", ""]
    if summary.get("suite") is not None:
        lines += [f"**{DYNAMIC_SUITE_NOTE}** (segmenter: {summary['suite']['segmenter']})", ""]
    lines += [*models,
             (f"Scores: mean ± standard deviation over videos (lower {' / '.join(MAP_ORDER)} is more "
             "consistent). TM = Total Motion (%), MM = Mean Motion (%/s): read the scores next to them, "
             "a static video is trivially consistent."), ""]
    if missing:
        lines += [f"**Missing videos** (rerun the same command to finish them): {_listed(missing)}", ""]
    if summary.get("no_video"):
        lines += [f"**No video** in the --videos folder for: {_listed(summary['no_video'])}", ""]
    if summary.get("failed"):
        lines += ["**Failed videos** (left out of the scores; a rerun tries them again):", "",
                  *(f"- {f['job']}: {f['error']}" for f in summary["failed"][:20]),
                  *(["- ..."] if len(summary["failed"]) > 20 else []), ""]
    header = ["group", "n", *(f"{m} ({PAPER_NAMES[m]})" if m in CUES else PAPER_NAMES[m] for m in METRICS)]
    for arm, data in summary["arms"].items():
        rows = [[group, str(stats["fused"]["n"]), *(_cell(stats[m]) for m in METRICS)]
                for group, stats in data["groups"].items()]
        lines += [f"## {arm}", "", *report.markdown_table(header, rows)]
        cost = f"sampling {fmt(data['generation_s_mean'], 3)} s per video" if data["generation_s_mean"] is not None else ""
        lines += ["", cost, ""] if cost else [""]
    lines += ["![fused score vs Mean Motion per model](pareto.png)", "", "## Configuration", "", "```yaml",
              config_yaml.rstrip(), "```"]
    return "\n".join(lines) + "\n"


#: What the report says of the dynamic suite.
DYNAMIC_SUITE_NOTE = ("The dynamic suite: 24 prompts of our own with moving subjects, not the paper's GeCo-Eval; "
                      "each video is scored (and a guided one guided) with the dynamic masks of its prompt's "
                      "subjects, so its numbers are not comparable with the paper's.")


COLORS = [(60, 110, 200), (235, 125, 30), (40, 160, 70), (210, 50, 50), (140, 90, 190), (120, 80, 60),
          (220, 110, 180), (110, 110, 110), (180, 180, 40), (30, 170, 190)]


#: ``pareto.png``'s layout in pixels: the first panel's left edge (room for the y labels), the
#: distance from one panel to the next, a panel's width, and the margin right of the last.
PARETO_LEFT, PARETO_PITCH, PARETO_PANEL_W, PARETO_RIGHT = 70, 290, 220, 40


def plot_png(summary: dict[str, Any]) -> bytes:
    """``pareto.png``: fused score vs Mean Motion, one point per model (arm); left all prompts,
    then one small panel per scenario with data (a run of one scenario draws no empty panels;
    "all" without any point says "no data")."""
    from PIL import Image, ImageDraw

    arms = list(summary["arms"].items())
    points = {g: [(data["groups"][g]["mean_motion"]["mean"], data["groups"][g]["fused"]["mean"], k)
                  for k, (_, data) in enumerate(arms) if g in data["groups"]] for g in ("all", *SCENARIOS)}
    points = {g: [p for p in pts if p[0] is not None and p[1] is not None] for g, pts in points.items()}
    groups = ["all", *(g for g in SCENARIOS if points[g])]
    # a canvas as wide as the panels drawn and the legend under them, not as all five panels
    probe = ImageDraw.Draw(Image.new("RGB", (1, 1)))
    width = max(PARETO_LEFT + (len(groups) - 1) * PARETO_PITCH + PARETO_PANEL_W,
                PARETO_LEFT + legend_width(probe, [arm for arm, _ in arms])) + PARETO_RIGHT
    image = Image.new("RGB", (width, 480), (255, 255, 255))
    draw = ImageDraw.Draw(image)
    for column, group in enumerate(groups):
        xs = [p[0] for p in points[group]] or [0.0]
        ys = [p[1] for p in points[group]] or [0.0]
        left = PARETO_LEFT + column * PARETO_PITCH
        panel = Panel((left, 80, left + PARETO_PANEL_W, 360), limits(xs), limits(ys))
        panel.draw_axes(draw, group, "Mean Motion (%/s)", "fused")
        if not points[group]:
            text(draw, (left + PARETO_PANEL_W / 2, 220), "no data", "mm")
        for x, y, k in points[group]:
            panel.dot(draw, x, y, COLORS[k % len(COLORS)])
    legend(draw, Panel((PARETO_LEFT, 80, width - PARETO_RIGHT, 380), (0, 1), (0, 1)),
           [(arm, COLORS[k % len(COLORS)]) for k, (arm, _) in enumerate(arms)])
    return report.png_bytes(image)


def model_weights(cfg: GeCoConfig, names: Sequence[str], weights: dict[str, str] | None = None) -> dict[str, str]:
    """``{model: the weights it ran with}``: a ``--weights`` folder, the hub id, or the tiny random family."""
    weights = weights or {}
    found = {}
    for name in names:
        model = MODELS.get(name)
        if model is None or not model.generates:
            found[name] = "existing videos (--videos)"
        elif cfg.model.id == TINY_RANDOM:
            found[name] = f"{TINY_RANDOM} ({model.family} family, init seed {cfg.model.init_seed})"
        else:
            found[name] = weights.get(name, model.hub_id)
    return found


def write_report(out: Path, jobs: Sequence[Job], cfg: GeCoConfig, command: str,
                 weights: dict[str, str] | None = None, no_video: Sequence[str] = ()) -> dict[str, Any]:
    """Rebuild the report files from the jobs' result JSON files and failure records; returns the
    summary. ``no_video``: the prompts a ``--videos`` folder has no video for
    (:func:`prompts_without_video`)."""
    remove_temp_files(out, REPORT_STEMS)
    results, failures, missing = [], [], []
    for job in jobs:
        result = read_job_result(out, job, warn=False)  # run_jobs warned
        failure = read_job_failure(out, job) if result is None else None
        if result is not None:
            results.append(result)
        elif failure is not None:
            failures.append({**job_identity(job), "video": job_video(out, job), "error": failure["error"]})
        else:
            missing.append(f"{job.arm}/{job.name}")
    failed = [{"job": f"{f['model']}{'-guided' if f['guided'] else ''}/{f['prompt_id']}-s{f['seed']}",
               "video": f["video"], "error": f["error"]} for f in failures]
    models = model_weights(cfg, list(dict.fromkeys(job.model for job in jobs)), weights)
    dynamic = any("subjects" in job.prompt for job in jobs)
    summary = {**summarize(results), "missing": missing, "failed": failed, "no_video": list(no_video),
               "config_sha": config_fingerprint(cfg),
               "models": models, "estimators": estimator_ids(cfg.estimators, dynamic),
               "tiny_models": report.uses_tiny_models(cfg),
               "created": datetime.now(timezone.utc).isoformat(timespec="seconds")}
    if dynamic:
        summary["suite"] = {"name": DYNAMIC_SUITE, "ours": True, "segmenter": cfg.estimators.segmenter}
    markdown = report_markdown(summary, missing, config_to_yaml(cfg), command,
                               report.models_section(cfg, models))
    report.write_report_files(out, table=csv_text([*results, *failures]), summary=summary, plot=plot_png(summary), markdown=markdown)
    return summary
