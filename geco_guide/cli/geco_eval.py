"""``geco geco-eval --models ... --out DIR``: the GeCo-Eval benchmark
(:mod:`geco_guide.bench.geco_eval`).

    geco geco-eval --models cogvideox-5b wan2.1-t2v-1.3b --seeds 0 1 2 3 --out bench
    geco geco-eval --models cogvideox-5b --guided --scenario indoor --out bench
    geco geco-eval --videos sora-2=downloads/sora --out bench
    geco geco-eval --suite dynamic --models cogvideox-5b --guided --out bench-dynamic
    geco geco-eval --preset tiny --models cogvideox-5b wan2.1-t2v-1.3b --limit 2 --out bench-tiny

The same command resumes a stopped run; ``--overwrite`` starts afresh in its folder.
"""

from __future__ import annotations

import argparse
import math
from collections.abc import Sequence
from dataclasses import dataclass, replace
from functools import partial
from pathlib import Path
from typing import TYPE_CHECKING

from .. import __version__
from ..io.files import WriteError
from .command_line import command_main
from .kit import (
    add_config_flags,
    check_flags_agree,
    config_from_args,
    interruptible,
    output_folder,
    print_error,
)

if TYPE_CHECKING:
    from ..bench.geco_eval import Job
    from ..config import GeCoConfig

__all__ = ["DESCRIPTION", "SUMMARY", "main", "register_subcommand", "run"]

SUMMARY = "run the GeCo-Eval benchmark: generate its prompts with video models and score them"
DESCRIPTION = "GeCo-Eval: generate the paper's 80 prompts with video models and score them with GeCo."


def register_subcommand(parser: argparse.ArgumentParser) -> argparse.ArgumentParser:
    """The options of ``geco geco-eval`` on ``parser``."""
    from ..families import SCORED_ONLY, video_models

    parser.add_argument("--version", action="version", version=f"geco_guide {__version__}")
    parser.add_argument("--models", nargs="+", default=[], metavar="NAME",
                        help=f"models to generate with: {', '.join(video_models())}")
    parser.add_argument("--videos", nargs="+", default=[], metavar="NAME=DIR",
                        help=f"score existing videos (e.g. of {' or '.join(SCORED_ONLY)}): DIR/<prompt_id>-s<seed>.mp4 or "
                             "DIR/<prompt_id>/*.mp4, timed at NAME's native frame rate (evaluation.model_fps) unless --fps")
    parser.add_argument("--seeds", nargs="+", type=int, default=[0, 1, 2, 3],
                        help="sampling seeds (default: 0 1 2 3, the paper's 4)")
    parser.add_argument("--guided", action="store_true", help="also generate every video with GeCo guidance")
    parser.add_argument("--suite", default="geco-eval",
                        help="the prompts: geco-eval (the paper's 80, default) or dynamic (our 24 with moving "
                             "subjects, scored and guided with the subjects' masks from estimators.segmenter)")
    parser.add_argument("--scenario", default=None,
                        help="only this scenario: object-centric, indoor, outdoor or appearance-complex")
    parser.add_argument("--camera", default=None, help="only this camera speed: slow or fast")
    parser.add_argument("--limit", type=int, default=None, help="only the first N prompts of the selection")
    parser.add_argument("--weights", nargs="+", default=[], metavar="NAME=DIR", help="a local folder for a model's weights")
    parser.add_argument("--fps", type=float, default=None, help="frame rate of the --videos inputs (overrides the table)")
    parser.add_argument("--out", type=output_folder, required=True, help="output folder (reuse it to resume)")
    parser.add_argument("--overwrite", action="store_true",
                        help="start afresh in --out: delete the videos, results and report an earlier run wrote there "
                             "(other files stay), even of another config")
    add_config_flags(parser, preset_help="a config preset (tiny: every model is a tiny random model, CPU, offline)")
    parser.add_argument("overrides", nargs="*", metavar="key=value",
                        help="config overrides, e.g. evaluation.loss.pairs=center")
    return parser


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
    from ..config import SEED_RANGE

    low, high = 0, SEED_RANGE[1]
    bad = next((s for s in seeds if not low <= s <= high), None)
    if bad is not None:
        raise ValueError(f"--seeds takes integers from {low} to {high}, got {bad}")
    if len(set(seeds)) != len(seeds):
        raise ValueError(f"--seeds must be distinct, got {list(seeds)}")


def plan(args: argparse.Namespace) -> Plan:
    """Every check that needs no model: config, selection, model names, folders."""
    from ..bench.geco_eval import Job, existing_video_jobs, load_prompts, prompts_without_video
    from ..families import generating_model
    from ..io.devices import resolve_devices

    if args.models:  # each job's model.name is one of --models
        check_flags_agree(args.overrides, {"model.name": args.models[0] if len(args.models) == 1 else args.models},
                          {"model.name": "--models"})
    cfg = config_from_args(args, args.overrides)
    resolve_devices(cfg.run.devices)  # what it names must be here, whether a job uses it or not (as generate)
    conditioned = [m for m in args.models if generating_model(m).image_to_video]
    if conditioned:
        raise ValueError(f"--models {conditioned[0]} is an image-to-video model and GeCo-Eval's prompts are text only: "
                         "generate its videos with geco generate --image and score them with --videos NAME=DIR")
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
def run(args: argparse.Namespace) -> int:
    """The benchmark ``args`` ask for; 0, 1 (videos failed or missing), or 2 after one line on stderr."""
    from ..bench.geco_eval import check_guided_models, check_model_weights
    from ..bench.runs import check_output_folder, run_lock
    from ..io.devices import check_device

    try:
        planned = plan(args)
        cfg, out = planned.cfg, Path(args.out)
        check_output_folder(out, cfg, overwrite=args.overwrite)
        check_device(cfg.model.device)
        check_device(cfg.evaluation.device, "evaluation.device")
        check_model_weights(cfg, args.models, planned.weights)  # what a fresh machine lacks first, as generate
        if args.guided:
            check_guided_models(cfg, args.models)
        with run_lock(out, "GeCo-Eval"):
            return execute(args, planned, out)
    except (ValueError, FileNotFoundError) as err:
        return print_error(err)


def execute(args: argparse.Namespace, planned: Plan, out: Path) -> int:
    """Every process's share of the jobs, then on the main process the report; the exit code."""
    from ..bench.geco_eval import remove_run_outputs, run_jobs, write_report
    from ..bench.runs import pin_config, process_config, process_state, shard
    from ..types import plural

    cfg = planned.cfg

    try:
        state = process_state(cfg)
        tag = f"[rank {state.process_index} of {state.num_processes}] " if state.num_processes > 1 else ""
        if args.overwrite and state.is_main_process:
            remove_run_outputs(out)
        state.wait_for_everyone()  # no process reads results before they are removed
        # run.json once the models loaded: a run stopped by missing weights leaves none
        run_jobs(shard(planned.jobs, state.process_index, state.num_processes), out, process_config(cfg, state),
                 planned.weights, tag, on_loaded=partial(pin_config, out, cfg) if state.is_main_process else None)
        state.wait_for_everyone()
        if not state.is_main_process:
            return 0
        summary = write_report(out, planned.jobs, cfg, args.command_line, planned.weights, planned.no_video)
    except (FileNotFoundError, WriteError) as err:  # weights not available (WeightsNotFoundError), disk full
        return print_error(err)
    failed, missing = len(summary["failed"]), len(summary["missing"]) + len(summary["no_video"])
    print(f"{plural(summary['videos'], 'video')} scored ({failed} failed, {missing} missing); report: {out / 'report.md'}")
    return 0 if not failed and not missing else 1


main = command_main("geco geco-eval", DESCRIPTION, register_subcommand, run)
