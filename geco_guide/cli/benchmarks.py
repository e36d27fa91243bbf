"""``geco benchmarks``: build WarpBench/OccluBench clips (:mod:`geco_guide.bench.datasets`).

    geco benchmarks warp clip.mp4 frames/ --out bench/warp --mode frame --seeds 0 1 2
    geco benchmarks warp clip.mp4 --mask object.png --out bench/warp-clip
    geco benchmarks occlusion clip.mp4 --object duck.png --out bench/occlusion
    geco benchmarks warp synthetic --out bench/synthetic-warp --seeds 0 1 2   # offline, exact ground truth
    geco benchmarks occlusion synthetic-3d --out bench/synthetic-occlusion-3d
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from ..io.files import WriteError, check_output_dir, unique_names
from .command_line import command_main
from .kit import check_choice, interruptible, output_folder

__all__ = ["DESCRIPTION", "SUMMARY", "main", "register_subcommand", "run"]

SUMMARY = "build WarpBench/OccluBench-style clips with ground truth"
DESCRIPTION = "Build WarpBench/OccluBench-style clips with ground truth."


def register_subcommand(p: argparse.ArgumentParser) -> argparse.ArgumentParser:
    """The options of ``geco benchmarks`` on ``p`` (the warp's defaults: :class:`~geco_guide.bench.warp.WarpParams`'s)."""
    p.add_argument("kind", metavar="KIND", help="which benchmark's clips to build: warp or occlusion")
    p.add_argument("inputs", nargs="+", metavar="VIDEO|FRAMES_DIR|synthetic|synthetic-3d",
                   help="clips to edit; synthetic: the gallery scene with exact ground truth; synthetic-3d "
                        "(occlusion only): a pillar hides a wall region that re-appears with another box, in 3D")
    p.add_argument("--out", type=output_folder, required=True, help="output folder (one sub-folder per clip and seed)")
    p.add_argument("--seeds", type=int, nargs="+", default=[0], help="one clip per input and seed")
    p.add_argument("--max-frames", type=int, default=20, help="frames kept per input, evenly spaced (paper: 20)")
    p.add_argument("--synthetic-size", type=int, nargs=3, default=(9, 48, 64), metavar=("FRAMES", "H", "W"),
                   help="size of the synthetic scenes: frames, height, width (default: 9 48 64)")
    warp = p.add_argument_group("warp")
    warp.add_argument("--mode", choices=("clip", "frame"), default="clip",
                      help="clip: warp every frame (Task 2); frame: replace one random frame (Task 1)")
    warp.add_argument("--mask", default=None, help="foreground mask image, or folder/video of per-frame masks")
    warp.add_argument("--controls", type=int, default=None,
                      help="thin-plate-spline control points of the warp, at least 3 (default: 12)")
    warp.add_argument("--amplitude", type=float, default=None, help="control displacement std in px (default: 4)")
    warp.add_argument("--beta", type=float, default=None, help="EMA factor over time (default: 0.5)")
    warp.add_argument("--feather", type=float, default=None,
                      help="feather width in px (default: a quarter of the mask's largest inscribed radius)")
    warp.add_argument("--mask-threshold", type=float, default=None,
                      help="artifact pixels move more than this, in px (default: 0.1)")
    occ = p.add_argument_group("occlusion")
    occ.add_argument("--object", default=None, help="the re-revealed object: an image, or a video / frame folder (its middle frame); default procedural")
    occ.add_argument("--object-mask", default=None, help="its alpha mask image (default: an ellipse)")
    occ.add_argument("--region", type=int, nargs=4, default=None, metavar=("LEFT", "TOP", "RIGHT", "BOTTOM"),
                     help="the object's box in pixels, right and bottom exclusive (default: a "
                          "central box of 35 %% of the height and width)")
    return p


@interruptible("the clip folders finished so far (each complete with its meta.json); a folder without meta.json is incomplete")
def run(args: argparse.Namespace) -> int:
    """Build the clips ``args`` ask for; 0, 1 (every input failed), or 2 after one line on stderr."""
    from ..bench.datasets import (
        KINDS,
        SYNTHETIC,
        SYNTHETIC_3D,
        build_one,
        check_synthetic_size,
        load_clip,
        output_stem,
        write_benchmark,
    )

    try:
        check_choice("the benchmark kind", args.kind, KINDS)
        if args.max_frames < 3:
            raise ValueError(f"--max-frames must be >= 3, got {args.max_frames}")
        if any(source in (SYNTHETIC, SYNTHETIC_3D) for source in args.inputs):
            check_synthetic_size(tuple(args.synthetic_size))
        check_output_dir(args.out)
    except (ValueError, WriteError) as err:
        print(f"error: {err}", file=sys.stderr)
        return 2
    failed = 0
    # Inputs that share a stem (two clip.mp4 of different folders) get folders of their own.
    for source, stem in zip(args.inputs, unique_names(output_stem(source) for source in args.inputs)):
        try:
            frames, synthetic = load_clip(source, args.max_frames, tuple(args.synthetic_size))
            for seed in args.seeds:
                edited, truth, meta = build_one(args.kind, source, frames, synthetic, seed, args)
                folder = Path(args.out) / f"{stem}-s{seed}"
                write_benchmark(folder, edited, truth, meta)
                note = f", anomalous frame {meta['anomalous_frame']}" if meta["anomalous_frame"] is not None else ""
                print(f"{folder}: {args.kind} ({meta['mode']}), {int(truth['mask'].sum())} artifact pixels{note}")
        except (ValueError, OSError, RuntimeError) as err:  # one bad input must not stop the others
            failed += 1
            print(f"error: {source}: {str(err).splitlines()[0] if str(err) else type(err).__name__}", file=sys.stderr)
    return 1 if failed == len(args.inputs) else 0


main = command_main("geco benchmarks", DESCRIPTION, register_subcommand, run)
