"""``geco ab``: A/B test of GeCo guidance on your prompts: unguided vs guided video from the same
noise, and at matched compute selection (``--best-of``) and particle search (``--search``).

    geco ab --prompts prompts.txt --seeds 0 1 2 --out ab/ --preset tiny
    geco ab --prompts prompts.jsonl --seeds 0 --out ab/ --config my.yaml guidance.step_size=2.0
    geco ab --prompts prompts.jsonl --seeds 0 10 20 --out ab/ --preset cogvideox-5b --search matched
    geco ab --prompts prompts.txt --seeds 0 1 --out ab/ --model wan2.2-t2v-a14b
    accelerate launch -m geco_guide ab --prompts prompts.txt --seeds 0 1 --out ab/ --preset cogvideox-5b

The prompts file holds one prompt per line, or JSON lines ``{"id": "bust", "prompt": "..."}``
(``id`` optional; blank lines and ``#`` comments are skipped). A prompt's id (its slug when not
given) names its output folders, so ids must be unique and filesystem-safe. A JSON line's optional
``"subjects": "a dog, a ball"`` (what moves on its own; ``--prompts dynamic``: our suite) are masked
in every arm's scores, in the guided arm's guidance and in the search's scoring of its particles,
by the segmenter of ``estimators.segmenter``.

For every prompt x seed ("pair"), the arms run :func:`geco_guide.generation.generate` with the same
config and seed, so they start from the same initial noise (``torch.Generator("cpu").manual_seed
(seed)``); the unguided arm is exactly ``geco generate --no-guidance --seed S``. Every video is
scored by :func:`geco_guide.metric.evaluate.evaluate_video` with the same estimators and the
config's ``evaluation`` protocol. ``<out>/pairs/<id>-s<seed>/`` then holds ``unguided.mp4``,
``guided.mp4`` (each with its generation sidecar ``.json``), ``side_by_side.mp4``, with ``--maps``
the maps videos, and last ``result.json``, whose presence marks the pair complete.

``--best-of N`` adds selection: the unguided seeds ``seed .. seed + N - 1`` (the first is the
unguided arm's video; the others in ``candidates/``), each scored with the same protocol, the one
:func:`geco_guide.generation.best_candidate` picks copied to ``best_of.mp4`` (its sidecar lists
every candidate). ``--best-of matched`` takes N = round of the guided / unguided sampling time
ratio the cost model predicts for the run's config on ``--gpu`` (default: the local GPU, when it is
a card the model knows), capped at the least spacing of ``--seeds`` (at least 2), so that one
pair's candidates are not the next pair's videos; the cap, and seeds closer than N, are said
before anything is generated.

``--search K`` adds particle search with GeCo as the verifier (the config's ``search.*``): ``K``
particles of the seeds ``seed .. seed + K - 1`` (particle 0 from the pair's own noise), unguided
unless ``--search-guided``, resampled by their GeCo scores, the final one of least protocol score
kept as ``search.mp4``. ``--search matched`` measures K on this machine: once every pair's two arms
are made, K = the largest K >= 2 whose expected time (the unguided arm's measured sampling time x
K, plus one particle's scoring, measured, at every resampling step of every particle) does not
exceed the guided arm's measured sampling time, from the first complete pair not timed with the
models' warm-up; K, how it was chosen and those times go to ``<out>/search_matched.json``, which a
resumed run reuses.

Every file is written atomically, so killing the run at any moment loses at most the arm (or
best-of candidate) in progress and never leaves a truncated file; a rerun skips complete pairs,
arms and candidates and redoes, with a warning naming the file, one whose result is damaged or
lacks fields, or whose videos or sidecars are gone or unreadable; adding ``--best-of`` or
``--search`` to a finished run adds the arm to its pairs without redoing the others. Outputs
another run left in a pair folder (their sidecar names another prompt or config) are refused
unless ``--overwrite``, which redoes every pair. While a run works in a folder it holds
``<out>/.run.lock`` (its pid): a second run there is refused, and the lock of a run that was killed
is taken over. ``--maps`` on a resumed folder also makes the maps of complete pairs that have none
(their videos are scored again; only the estimators load), and with ``guidance.decoder=tiny`` a
folder without a whole ``decoder_agreement.json`` gets it measured, whatever the pairs' state.
Under ``accelerate launch -m geco_guide ab ...`` the pairs are dealt round-robin to the processes;
at the end the main process rebuilds ``results.csv`` (one row per pair and arm), ``summary.json``,
``report.md`` and ``pareto.png`` from the pairs' ``result.json`` files; scores that are not finite
are left out of its statistics and named. ``run.json`` pins the config: reusing an output folder
with a different config is refused (unless ``--overwrite``).
"""

from __future__ import annotations

import argparse
import sys
from collections.abc import Sequence
from functools import partial
from pathlib import Path
from typing import TYPE_CHECKING

from .command_line import command_main
from .kit import add_config_flags, add_model_flag, interruptible, output_folder, print_error

if TYPE_CHECKING:
    from ..bench.ab import BestOf
    from ..bench.ab_run import Inputs
    from ..config import GeCoConfig

__all__ = ["DESCRIPTION", "SUMMARY", "choose_best_of", "main", "register_subcommand", "run", "validate_inputs"]

SUMMARY = "A/B test on your prompts: unguided vs guided video from the same noise, with best-of-N and search arms"
DESCRIPTION = """\
A/B test of GeCo guidance: unguided vs guided video per prompt x seed, from the same noise, with
paired statistics; optionally, at matched compute, selection among unguided seeds (--best-of) and
particle search with GeCo as the verifier (--search).

examples:
  geco ab --prompts prompts.txt --seeds 0 1 2 --out ab --preset tiny
  geco ab --prompts prompts.jsonl --seeds 0 10 20 --out ab --preset cogvideox-5b --best-of 4 --search matched
  geco ab --prompts prompts.txt --seeds 0 1 --out ab --model wan2.2-t2v-a14b
  accelerate launch -m geco_guide ab --prompts prompts.txt --seeds 0 1 --out ab --preset cogvideox-5b

Rerun the same command to resume a stopped run; add --best-of or --search to a finished run to add
the arm to its pairs."""


def register_subcommand(parser: argparse.ArgumentParser) -> argparse.ArgumentParser:
    """The options of ``geco ab`` on ``parser`` (a subcommand's, or a program's own)."""
    parser.add_argument("--prompts", required=True,
                        help="text file: one prompt per line, or JSON lines {id, prompt[, subjects]}; or the paper's "
                             "suite: geco-eval, geco-eval:indoor, geco-eval:fast, geco-eval:outdoor:slow, ...; or ours "
                             "with moving subjects: dynamic, dynamic:indoor, ...")
    parser.add_argument("--seeds", required=True, nargs="+", metavar="SEED", help="sampling seeds (integers)")
    parser.add_argument("--out", type=output_folder, required=True, help="output folder (reuse it to resume)")
    add_config_flags(parser, preset_help="a preset of configs/: tiny, cogvideox-5b, cogvideox-5b-fused, or a model's")
    add_model_flag(parser)
    parser.add_argument("--maps", action="store_true", help="also write each arm's GeCo maps video")
    parser.add_argument("--best-of", default=None, metavar="N|matched",
                        help="an arm of selection: per pair N unguided seeds (seed .. seed+N-1), each scored with the "
                             "GeCo protocol, the least fused kept; 'matched': N = the guided / unguided time ratio the "
                             "cost model predicts for this config on --gpu, at most the least spacing of --seeds")
    parser.add_argument("--gpu", default=None, metavar="CARD",
                        help="the card --best-of matched predicts for (H200, H100, L40S, A6000, RTX4090, L4; default: "
                             "the local GPU when it is one of them)")
    parser.add_argument("--search", default=None, metavar="K|matched",
                        help="an arm of particle search (search.* options): per pair K particles (seeds seed .. "
                             "seed+K-1) resampled by their GeCo scores, the least fused kept; 'matched': K measured "
                             "here so that the search costs what the guided arm costs (recorded for the folder)")
    parser.add_argument("--search-guided", action="store_true",
                        help="guide the search arm's particles too (default: unguided particles, search instead of "
                             "guidance); an integer --search K only")
    parser.add_argument("--overwrite", action="store_true",
                        help="redo every pair, replacing what --out holds (also another config's or prompt's results)")
    parser.add_argument("overrides", nargs="*", metavar="key=value", help="config overrides, e.g. guidance.step_size=2.0")
    return parser


@interruptible("finished pairs and arms are kept (each is written whole or not at all); rerun the same command to "
               "resume")
def run(args: argparse.Namespace) -> int:
    """The A/B run ``args`` ask for; 0, 1 (pairs missing), or 2 after one line on stderr."""
    from ..bench.ab_run import execute
    from ..bench.runs import run_lock
    from ..io.files import WriteError
    from ..perf.decoder_agreement import agreement_record

    try:
        inputs = validate_inputs(args)
        with run_lock(inputs.out, "A/B"):
            finished = execute(inputs, args.maps, args.overwrite, args.command_line, agreement=agreement_record,
                               say=partial(print, flush=True))
    except (ValueError, FileNotFoundError, WriteError) as err:  # diverged sampling, weights not there, disk full
        return print_error(err)
    if finished is None:  # not the main process: the main one reports
        return 0
    print(finished.last_line(inputs.out, inputs.best_of))
    return 0 if not finished.summary["missing_pairs"] else 1


def validate_inputs(args: argparse.Namespace) -> Inputs:
    """Every check that needs no model: prompts, seeds, config (what generate checks before loading,
    for the search arm too), the best-of and search arms, output folder."""
    from dataclasses import replace

    from .. import generation
    from ..bench.ab import SEARCH, InputError, Pair, SearchArm, arm_config, parse_seeds, plan_pairs
    from ..bench.ab_run import Inputs, check_output_folder, choose_search
    from .kit import config_from_args
    from .prompt_files import read_prompts

    prompts = read_prompts(args.prompts)
    seeds = parse_seeds(args.seeds)
    cfg = config_from_args(args, args.overrides)
    if not cfg.guidance.enabled:
        raise InputError("guidance.enabled=false leaves nothing to compare: the guided arm needs guidance")
    if cfg.search.particles is not None:
        raise InputError(f"search.particles={cfg.search.particles} would make every arm a search: leave it unset and "
                         f"pass --search {cfg.search.particles} for a search arm (search.* sets its other options)")
    search = choose_search(args.search, args.search_guided, seeds)
    # what generate checks before loading, here before run.json is pinned or any video written: the
    # guided arm (run.particle_batch is the search arm's, checked below); each arm then runs what it
    # can act on (arm_config), and the run keeps its config as given, the device resolved
    guided = cfg if search is None else replace(cfg, run=replace(cfg.run, particle_batch=None))
    cfg = replace(cfg, model=generation.check_generation(guided, prompts[0].text).model)
    best_of = choose_best_of(args.best_of, args.gpu, cfg, seeds)
    if search is not None:  # K particles of the first pair, checked as generate checks them (K >= 2 if matched)
        cfg.search.steps(cfg.sampling.num_inference_steps)  # else found when the search starts, after the pairs
        first = SearchArm(search.particles or 2, search.guided)
        generation.check_generation(arm_config(cfg, Pair(prompts[0], seeds[0]), SEARCH, first), prompts[0].text,
                                    loaded=True)
    pairs = plan_pairs(prompts, seeds)
    out = Path(args.out)
    check_output_folder(out, cfg, pairs, args.overwrite, best_of, search)
    return Inputs(cfg, pairs, out, best_of, search)


def choose_best_of(value: str | None, gpu: str | None, cfg: GeCoConfig, seeds: Sequence[int]) -> BestOf | None:
    """The best-of arm ``--best-of`` and ``--gpu`` ask for (None: no best-of arm); one
    :class:`~geco_guide.bench.ab.InputError` line for a bad value, before anything is generated; a
    cap of ``matched`` (the spacing of the seeds) and candidates pairs share said on stderr."""
    from ..bench.ab import MAX_SEED, BestOf, InputError, matched_best_of, shared_candidates
    from ..bench.ab_run import count_arm
    from ..io.devices import resolve_device
    from ..perf.cards import GPU_SPECS
    from ..perf.guided_ratio import local_card, predicted_ratio

    if gpu is not None and gpu not in GPU_SPECS:
        raise InputError(f"--gpu must be one of {', '.join(GPU_SPECS)}, got {gpu!r}")
    if value is None:
        if gpu is not None:
            raise InputError("--gpu names the card --best-of matched predicts for; pass --best-of matched too")
        return None
    if value == "matched":
        card = gpu or local_card(cfg)
        if card is None:
            raise InputError(f"--best-of matched needs a card the cost model knows ({', '.join(GPU_SPECS)}) and "
                             f"the device here ({resolve_device(cfg.model.device)}) is none: pass --gpu NAME or an "
                             "integer --best-of N")
        best_of = matched_best_of(predicted_ratio(cfg, card), card, seeds)
        if best_of.matched_n is not None:
            print(f"note: --best-of matched: N = {best_of.matched_n} predicted on the {card}, capped at {best_of.n}, the "
                  f"least spacing of --seeds: give seeds at least {best_of.matched_n} apart for N = "
                  f"{best_of.matched_n}", file=sys.stderr)
    else:
        if gpu is not None:
            raise InputError("--gpu is for --best-of matched; an integer --best-of N needs no card")
        best_of = BestOf(count_arm(value, "--best-of", "best-of-1 is the unguided arm"))
    if max(seeds) + best_of.n - 1 > MAX_SEED:
        raise InputError(f"--best-of {best_of.n} from seed {max(seeds)} runs past the last seed, 2**63 - 1")
    shared = shared_candidates(seeds, best_of.n)
    if shared is not None:  # said before the run, not only in its report
        print(f"warning: --best-of {best_of.n}: {shared}", file=sys.stderr)
    return best_of


main = command_main("geco ab", DESCRIPTION, register_subcommand, run)
