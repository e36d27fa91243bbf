"""``geco generate``: a GeCo-guided video of any registry model (also ``python -m geco_guide.generate``).

    geco generate --preset tiny --prompt "a marble bust"
    geco generate --model wan2.2-t2v-a14b --prompt "..." --seed 3 guidance.step_size=2.0
    geco generate --preset tiny --prompt "a marble bust" --search 4 --no-guidance

Writes ``<name>.mp4`` and a JSON sidecar ``<name>.json`` (resolved config, seed, scheduler,
versions, timings, guidance log, GeCo scores of the anchor frames of the final video), each
atomically, through the one generation path (:mod:`geco_guide.generation`). The default name is
``<prompt slug>-<video key>-seed<N>[-unguided]``, the key a hash of the prompt and of the config that
makes the frames, so two runs share a name only when they make the same video; an existing output
is refused without ``--overwrite``. Trailing ``key=value`` arguments override the config (unknown
keys are refused).
"""

from __future__ import annotations

import argparse
import math
import sys
from typing import Any

from .. import __version__
from ..loss.modes import MOVER_MODES
from .command_line import command_main
from .kit import add_config_flags, add_model_flag, config_from_args, interruptible, parse_count, print_error

__all__ = ["DESCRIPTION", "SUMMARY", "main", "register_subcommand", "run"]

SUMMARY = "generate a video with GeCo guidance (or without: --no-guidance)"
DESCRIPTION = "Generate a video with GeCo geometric-consistency guidance (or without: --no-guidance)."


def register_subcommand(parser: argparse.ArgumentParser) -> argparse.ArgumentParser:
    """The options of ``geco generate`` on ``parser`` (a subcommand's, or a program's own)."""
    parser.add_argument("--version", action="version", version=f"geco_guide {__version__}")
    parser.add_argument("--prompt", required=True, help="text prompt")
    add_config_flags(parser, preset_help="a preset of configs/: tiny, cogvideox-5b, cogvideox-5b-fused, or a model's")
    add_model_flag(parser)
    parser.add_argument("--image", default=None, metavar="PATH",
                        help="the conditioning image of an image-to-video model (a PNG or JPEG)")
    parser.add_argument("--seed", type=int, default=None, help="sampling seed (overrides the config's seed)")
    parser.add_argument("--no-guidance", action="store_true", help="sample without GeCo guidance")
    parser.add_argument("--dynamic", default=None, metavar="SUBJECTS",
                        help="leave what moves on its own out of the guidance loss: 'auto' (detected from depth and "
                             "flow) or the moving subjects, e.g. 'a dog, a person' (segmented by estimators.segmenter, "
                             "SAM 3); sets guidance.dynamic")
    parser.add_argument("--movers", default=None, choices=MOVER_MODES,
                        help="with --dynamic: leave the movers out of the guidance loss (drop, the default) or score "
                             "each mover that one rigid motion explains against that motion (rigid: guidance keeps "
                             "its shape); sets guidance.loss.movers")
    parser.add_argument("--out", default=None,
                        help="output path ending in .mp4 or .gif (the sidecar: the same path with .json), or a folder "
                             "(no suffix) for the default name <prompt slug>-<8 hex of prompt and config>-seed<N>"
                             "[-unguided].mp4; default: output.dir")
    parser.add_argument("--overwrite", action="store_true", help="replace an existing video and sidecar of the same name")
    parser.add_argument("--devices", nargs="+", default=None, metavar="DEVICE",
                        help="deal the guidance's anchor decode over these devices, e.g. cuda:0 cuda:1 (or auto: every "
                             "GPU), each with a replica of the decoder; sets run.devices")
    parser.add_argument("--best-of", type=parse_count, default=None, metavar="N",
                        help="selection: make N videos (seeds --seed .. --seed+N-1), score each with the GeCo protocol "
                             "and keep the one of least fused score; its sidecar lists every candidate's scores")
    parser.add_argument("--search", type=parse_count, default=None, metavar="K",
                        help="particle search: K videos (seeds --seed .. --seed+K-1) in one batch, scored by GeCo on their "
                             "clean estimates and resampled at search.resample_steps, then the one of least fused score "
                             "under the GeCo protocol kept (guided too unless --no-guidance); sets search.particles")
    parser.add_argument("--context-parallel", type=parse_count, default=None, metavar="N",
                        help="split each denoiser's tokens over the N processes of a launch (torchrun --nproc-per-node N "
                             "-m geco_guide.generate ...): diffusers' context parallelism, forward and backward; rank 0 "
                             "writes the outputs (docs/context_parallel.md); sets run.context_parallel")
    parser.add_argument("overrides", nargs="*", metavar="key=value", help="config overrides, e.g. guidance.step_size=2.0")
    return parser


def _print_candidate(count: int) -> Any:
    def show(k: int, seed: int, scored: Any) -> None:
        print(f"candidate {k + 1}/{count} (seed {seed}): protocol fused={scored.fused:.4f} motion={scored.motion:.4f} "
              f"structure={scored.structure:.4f}", file=sys.stderr, flush=True)
    return show


def _announce(line: str) -> None:
    print(line, file=sys.stderr, flush=True)


@interruptible("nothing was written (outputs are written atomically)")
def run(args: argparse.Namespace) -> int:
    """Generate the video ``args`` ask for; 0, or 2 after one line on stderr."""
    from ..estimators.loading import WeightsNotFoundError
    from ..generation import SCORES_NOTE, check_generation, generate, generate_best_of, load_models, sample
    from ..io.files import WriteError
    from ..io.video import read_image
    from ..sampler.running.context_parallel import is_writing_process

    options = {"seed": args.seed, "guidance.enabled": False if args.no_guidance else None,
               "guidance.dynamic": args.dynamic, "guidance.loss.movers": args.movers, "run.devices": args.devices,
               "search.particles": args.search, "run.context_parallel": args.context_parallel}
    try:
        cfg = config_from_args(args, args.overrides, options)
        image = read_image(args.image) if args.image is not None else None
        if args.best_of is not None and cfg.run.context_parallel:
            raise ValueError("--best-of writes each candidate from one process; under run.context_parallel use "
                             "--search K (the candidates as one call's particles) or one launch per seed")
        if not is_writing_process(cfg.run):  # rank 0 of the launch writes and says so; the others sample along
            cfg = check_generation(cfg, args.prompt, image=image is not None)
            sample(load_models(cfg, estimators=cfg.guidance.enabled or cfg.search.enabled), cfg, args.prompt,
                   image=image, progress=False)
            return 0
        if args.best_of is None:
            result = generate(cfg, args.prompt, out=args.out, overwrite=args.overwrite, image=image, announce=_announce)
        else:
            result = generate_best_of(cfg, args.prompt, args.best_of, out=args.out, overwrite=args.overwrite,
                                      image=image, on_candidate=_print_candidate(args.best_of), announce=_announce)
    except (ValueError, WeightsNotFoundError, FileNotFoundError, WriteError) as err:
        return print_error(err)
    sidecar = result.sidecar
    print(f"wrote video:   {result.video_path}")
    print(f"wrote sidecar: {result.sidecar_path}")
    if "best_of" in sidecar:
        chosen = sidecar["best_of"]
        print(f"best of {chosen['n']}: kept seed {chosen['kept_seed']} (least fused score under the GeCo protocol; "
              "every candidate's scores are in the sidecar)")
    if "search" in sidecar:
        _print_search(sidecar["search"])
    if sidecar["dynamic_masks"] is not None:
        fraction = sidecar["masked_fraction"]
        shown = f"{fraction:.1%} of the anchor frames' pixels on average" if fraction is not None else "nothing"
        print(f"dynamic masks: {sidecar['dynamic_masks']}, masked {shown}")
    scores = result.scores
    if scores is not None:
        anchors = sidecar["geco_scores"]["anchors"]
        print(f"GeCo scores of anchor frames {anchors}: fused={scores['fused']:.4f} motion={scores['motion']:.4f} "
              f"structure={scores['structure']:.4f}")
        if scores.get("nan_reason"):
            print(f"  (NaN: {scores['nan_reason']})")
        print(SCORES_NOTE)
    _print_guidance(sidecar)
    return 0


def _print_search(search: dict[str, Any]) -> None:
    from ..types import plural

    for final in search["final_particles"]:
        fused = "nan" if final["fused"] is None else f"{final['fused']:.4f}"
        print(f"particle {final['particle']} (from seed {final['seed']}, lineage {final['lineage']}): protocol "
              f"fused={fused}")
    resampled = sum(record["resampled"] for record in search["resamplings"])
    print(f"search of {plural(search['particles'], 'particle')}: resampled at {plural(resampled, 'step')} "
          f"{search['resample_steps']}, {search['particle_batch']['size']} per call; kept particle {search['kept']} "
          f"(least fused score under the GeCo protocol)")


def _print_guidance(sidecar: dict[str, Any]) -> None:
    from ..types import plural

    log = sidecar["guidance_log"]
    if not sidecar["config"]["guidance"]["enabled"]:
        print("guidance: off")
        return
    # the progress bar counts denoising steps; a guided step makes R_t (0 or more) updates
    steps = plural(sidecar["config"]["sampling"]["num_inference_steps"], "denoising step")
    print(f"guidance: {plural(len(log), 'update')} over {steps} in {sidecar['timings']['guidance_s']:.1f} s "
          "(the progress bar counts steps)")
    idle = [r for r in log if r["skipped"] or not math.isfinite(r["loss"])]
    if idle:  # a NaN decode or gradient leaves the latents unchanged (see GeCoLoss check_values)
        print(f"warning: {len(idle)} guidance update(s) moved nothing (non-finite loss or gradient) at steps "
              f"{sorted({r['step'] for r in idle})}", file=sys.stderr)
    empty = [r for r in log if not r["skipped"] and r.get("valid_fraction") == 0]
    if empty:
        print(f"warning: {len(empty)} guidance update(s) saw no valid pixel (everything masked or invalid: loss 0, "
              f"zero gradient) at steps {sorted({r['step'] for r in empty})}", file=sys.stderr)


main = command_main("geco generate", DESCRIPTION, register_subcommand, run)
