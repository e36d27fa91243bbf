"""``python -m geco_guide geco-eval --models ... --out DIR``: the GeCo-Eval benchmark
(:mod:`geco_guide.bench.geco_eval`).

    python -m geco_guide geco-eval --models cogvideox-5b wan2.1-t2v-1.3b --seeds 0 1 2 3 --out bench
    python -m geco_guide geco-eval --models cogvideox-5b --guided --scenario indoor --out bench
    python -m geco_guide geco-eval --videos sora-2=downloads/sora --out bench
    python -m geco_guide geco-eval --suite dynamic --models cogvideox-5b --guided --out bench-dynamic
    python -m geco_guide geco-eval --preset tiny --models cogvideox-5b wan2.1-t2v-1.3b --limit 2 --out bench-tiny

The same command resumes a stopped run; ``--overwrite`` starts afresh in its folder.
"""

from __future__ import annotations

import argparse
import math
import shlex
import sys
from collections.abc import Sequence
from dataclasses import dataclass, replace
from functools import partial
from pathlib import Path
from typing import TYPE_CHECKING

from .. import __version__
from ..bench.models import MODELS
from ..bench.suites import CAMERAS, DYNAMIC_SUITE, PROMPT_FILES, SCENARIOS, SUITE
from ..io.files import WriteError
from .kit import DeferredImports, Parser, add_config_flags, config_from_args, interruptible

if TYPE_CHECKING:  # GeCoConfig: annotations only; the rest bound at run time by _IMPLEMENTATION
    from ..bench.geco_eval import (
        Job,
        check_guided_models,
        check_model_weights,
        existing_video_jobs,
        load_prompts,
        prompts_without_video,
        remove_run_outputs,
        run_jobs,
        write_report,
    )
    from ..bench.runs import check_output_folder, pin_config, process_config, process_state, run_lock, shard
    from ..config import SEED_RANGE, GeCoConfig
    from ..io.devices import check_device
    from ..types import plural

__all__ = ["main"]

#: What main runs on, imported once the arguments parsed: it loads torch.
_IMPLEMENTATION = DeferredImports(__name__, {
    "..bench.geco_eval": ("Job", "check_guided_models", "check_model_weights", "existing_video_jobs", "load_prompts",
                          "prompts_without_video", "remove_run_outputs", "run_jobs", "write_report"),
    "..bench.runs": ("check_output_folder", "pin_config", "process_config", "process_state", "run_lock", "shard"),
    "..config": ("SEED_RANGE",),
    "..io.devices": ("check_device",),
    "..types": ("plural",),
})
__getattr__ = _IMPLEMENTATION.attribute


def build_parser() -> argparse.ArgumentParser:
    p = Parser(prog="python -m geco_guide geco-eval",
                description="GeCo-Eval: generate the paper's 80 prompts with video models and score them with GeCo.")
    p.add_argument("--version", action="version", version=f"geco_guide {__version__}")
    p.add_argument("--models", nargs="+", default=[], metavar="NAME", help=f"models to generate with: {', '.join(MODELS)}")
    p.add_argument("--videos", nargs="+", default=[], metavar="NAME=DIR",
                   help="score existing videos: DIR/<prompt_id>-s<seed>.mp4 or DIR/<prompt_id>/*.mp4, timed at "
                        "NAME's native frame rate (evaluation.model_fps) unless --fps")
    p.add_argument("--seeds", nargs="+", type=int, default=[0, 1, 2, 3], help="sampling seeds (default: 0 1 2 3, the paper's 4)")
    p.add_argument("--guided", action="store_true", help="also generate every video with GeCo guidance")
    p.add_argument("--suite", choices=tuple(PROMPT_FILES), default=SUITE,
                   help=f"the prompts: {SUITE} (the paper's 80, default) or {DYNAMIC_SUITE} (our 24 with moving "
                        "subjects, scored and guided with the subjects' masks from estimators.segmenter)")
    p.add_argument("--scenario", choices=SCENARIOS, default=None, help="only this scenario")
    p.add_argument("--camera", choices=CAMERAS, default=None, help="only this camera speed")
    p.add_argument("--limit", type=int, default=None, help="only the first N prompts of the selection")
    p.add_argument("--weights", nargs="+", default=[], metavar="NAME=DIR", help="a local folder for a model's weights")
    p.add_argument("--fps", type=float, default=None, help="frame rate of the --videos inputs (overrides the table)")
    p.add_argument("--out", required=True, help="output folder (reuse it to resume)")
    p.add_argument("--overwrite", action="store_true",
                   help="start afresh in --out: delete the videos, results and report an earlier run wrote there "
                        "(other files stay), even of another config")
    add_config_flags(p, preset_help="a config preset (tiny: every model is a tiny random model, CPU, offline)")
    p.add_argument("overrides", nargs="*", metavar="key=value", help="config overrides, e.g. evaluation.loss.pairs=center")
    return p


def _pairs(values: Sequence[str], option: str) -> dict[str, str]:
    parsed = {}
    for value in values:
        name, sep, path = value.partition("=")
        if not sep or not name or not path:
            raise ValueError(f"{option} takes NAME=DIR, got {value!r}")
        parsed[name] = path
    return parsed


@dataclass
class Plan:
    """What a run does, checked before any model loads: the config, the jobs, the ``--weights``
    folders and the prompts a ``--videos`` folder has no video for."""

    cfg: GeCoConfig
    jobs: list[Job]
    weights: dict[str, str]
    no_video: list[str]


def _check_seeds(seeds: Sequence[int]) -> None:
    """Seeds name the videos (``-s<seed>``) and seed a ``torch.Generator``: distinct, from 0 to
    the config's largest seed."""
    low, high = 0, SEED_RANGE[1]
    bad = next((s for s in seeds if not low <= s <= high), None)
    if bad is not None:
        raise ValueError(f"--seeds takes integers from {low} to {high}, got {bad}")
    if len(set(seeds)) != len(seeds):
        raise ValueError(f"--seeds must be distinct, got {list(seeds)}")


def plan(args: argparse.Namespace) -> Plan:
    """Every check that needs no model: config, selection, model names, folders."""
    cfg = config_from_args(args, args.overrides)
    unknown = [m for m in args.models if m not in MODELS]
    if unknown:
        raise ValueError(f"unknown model {unknown[0]!r}; known: {list(MODELS)}")
    videos = _pairs(args.videos, "--videos")
    weights = _pairs(args.weights, "--weights")
    if not args.models and not videos:
        raise ValueError("nothing to do: give --models and/or --videos NAME=DIR")
    if args.limit is not None and args.limit < 1:
        raise ValueError(f"--limit must be >= 1, got {args.limit}")
    _check_seeds(args.seeds)
    if args.fps is not None:
        if not (args.fps > 0 and math.isfinite(args.fps)):
            raise ValueError(f"--fps must be a finite number > 0, got {args.fps}")
        cfg = replace(cfg, evaluation=replace(cfg.evaluation, model_fps={**cfg.evaluation.model_fps,
                                                                         **{n: args.fps for n in videos}}))
    for name in [*args.models, *videos]:
        cfg.evaluation.fps_of_model(name)  # every model needs its native frame rate
    prompts = load_prompts(args.scenario, args.camera, args.suite)[: args.limit]
    if not prompts:
        raise ValueError("the selection holds no prompt")
    jobs = [Job(m, p, s, guided) for m in args.models for guided in ((False, True) if args.guided else (False,))
            for p in prompts for s in args.seeds]
    no_video = []
    for name, folder in videos.items():
        found = existing_video_jobs(name, Path(folder), prompts)
        jobs += found
        no_video += prompts_without_video(name, found, prompts)
    return Plan(cfg, jobs, weights, no_video)


@interruptible("finished videos and scores are kept; rerun the same command to resume")
def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    _IMPLEMENTATION.load()
    try:
        run = plan(args)
        cfg, out = run.cfg, Path(args.out)
        check_output_folder(out, cfg, overwrite=args.overwrite)
        check_device(cfg.model.device)
        check_device(cfg.evaluation.device, "evaluation.device")
        check_model_weights(cfg, args.models, run.weights)  # what a fresh machine lacks first, as generate
        if args.guided:
            check_guided_models(cfg, args.models)
        with run_lock(out, "GeCo-Eval"):
            return execute(args, run, out, argv)
    except (ValueError, FileNotFoundError) as err:
        print(f"error: {err}", file=sys.stderr)
        return 2


def execute(args: argparse.Namespace, run: Plan, out: Path, argv: list[str] | None) -> int:
    """Every process's share of the jobs, then on the main process the report; the exit code."""
    cfg = run.cfg

    try:
        state = process_state(cfg)
        tag = f"[rank {state.process_index} of {state.num_processes}] " if state.num_processes > 1 else ""
        if args.overwrite and state.is_main_process:
            remove_run_outputs(out)
        state.wait_for_everyone()  # no process reads results before they are removed
        # run.json once the models loaded: a run stopped by missing weights leaves none
        run_jobs(shard(run.jobs, state.process_index, state.num_processes), out, process_config(cfg, state),
                 run.weights, tag, on_loaded=partial(pin_config, out, cfg) if state.is_main_process else None)
        state.wait_for_everyone()
        if not state.is_main_process:
            return 0
        command = shlex.join(["python", "-m", "geco_guide", "geco-eval", *(sys.argv[1:] if argv is None else argv)])
        summary = write_report(out, run.jobs, cfg, command, run.weights, run.no_video)
    except (FileNotFoundError, WriteError) as err:  # weights not available (WeightsNotFoundError), disk full
        print(f"error: {err}", file=sys.stderr)
        return 2
    failed, missing = len(summary["failed"]), len(summary["missing"]) + len(summary["no_video"])
    print(f"{plural(summary['videos'], 'video')} scored ({failed} failed, {missing} missing); report: {out / 'report.md'}")
    return 0 if not failed and not missing else 1
