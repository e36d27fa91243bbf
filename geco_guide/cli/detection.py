"""``python -m geco_guide.detection``: per-frame detection maps (:mod:`geco_guide.metric.detection`).

    python -m geco_guide.detection clip.mp4 --out maps                  # VGGT-1B + UFM-Base, mp4
    python -m geco_guide.detection frames/ --preset tiny --window 8 --anchor end --format gif png
"""

from __future__ import annotations

import argparse
import math
import sys
from dataclasses import asdict
from pathlib import Path

from ..estimators import estimator_id, load_estimators
from ..io.files import write_json_atomic
from ..io.video import read_frames
from ..metric.detection import (
    ANCHORS,
    FORMATS,
    detection_maps,
    frame_scores,
    render_detection,
    write_detection,
)
from .kit import Parser, add_config_flags, config_from_args, split_overrides


def build_parser() -> argparse.ArgumentParser:
    p = Parser(prog="python -m geco_guide.detection", description="Per-frame GeCo detection maps (a window per frame).")
    p.add_argument("inputs", nargs="+", metavar="VIDEO|FRAMES_DIR|key=value")
    p.add_argument("--out", default="detection", help="output folder")
    p.add_argument("--window", type=int, default=20, help="frames per window (the demo's default: 20)")
    p.add_argument("--anchor", choices=ANCHORS, default="center", help="where the frame sits in its window")
    p.add_argument("--one-way", action="store_true", help="structure occlusion test in one direction only")
    p.add_argument("--format", nargs="+", choices=FORMATS, default=["mp4"], dest="formats")
    p.add_argument("--fps", type=float, default=None, help="output frame rate (default: the input's)")
    add_config_flags(p)
    return p


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    overrides, videos = split_overrides(args.inputs)
    try:
        if not videos:
            raise ValueError("no input video given")
        if args.window < 2:
            raise ValueError(f"--window must be >= 2, got {args.window}")
        if args.fps is not None and not (math.isfinite(args.fps) and args.fps > 0):
            raise ValueError(f"--fps must be a finite number > 0, got {args.fps}")
        cfg = config_from_args(args, overrides)
        geometry, flow = load_estimators(cfg.estimators, cfg.evaluation.device)
    except (ValueError, FileNotFoundError) as err:
        print(f"error: {err}", file=sys.stderr)
        return 2
    failed = 0
    for video in videos:
        try:
            clip = read_frames(video, min_frames=2)
            maps = detection_maps(clip.frames, geometry, flow, cfg.evaluation.loss, window=args.window,
                                  anchor=args.anchor, two_way=not args.one_way,
                                  flow_batch_size=cfg.evaluation.flow_batch_size)
            scores = frame_scores(maps)
            stem = Path(args.out) / (Path(video).stem or Path(video).name)
            written = write_detection(render_detection(maps, scores), stem, args.formats, args.fps or clip.fps)
            write_json_atomic(stem.with_name(f"{stem.name}.detection.json"), {
                "source": video, "window": min(args.window, clip.num_frames), "anchor": args.anchor,
                "two_way": not args.one_way, "frames": [{"index": k, **row} for k, row in enumerate(scores)],
                "estimators": {"geometry": estimator_id(geometry), "flow": estimator_id(flow)},
                "loss": asdict(cfg.evaluation.loss)})
        except (ValueError, OSError, RuntimeError) as err:  # one bad input must not stop the others
            failed += 1
            print(f"error: {video}: {str(err).splitlines()[0] if str(err) else type(err).__name__}", file=sys.stderr)
            continue
        worst = max(range(len(scores)), key=lambda k: -1.0 if scores[k]["fused"] is None else scores[k]["fused"])
        print(f"{video}: {len(scores)} frames, least consistent frame {worst} -> {', '.join(map(str, written))}")
    return 1 if failed == len(videos) else 0

