"""Generate a GeCo-guided video: ``python -m geco_guide.generate --prompt "..."``.

    python -m geco_guide.generate --preset tiny --prompt "a marble bust"
    python -m geco_guide.generate --preset cogvideox-5b --prompt "..." --seed 3 \\
        guidance.eta=2.0 guidance.loss.cue=motion

Writes ``<name>.mp4`` and a JSON sidecar ``<name>.json`` (resolved config, seed, scheduler,
versions, timings, guidance log, GeCo scores of the anchor frames of the final video), each
atomically. Trailing ``key=value`` arguments override the config (unknown keys are rejected).
"""

from __future__ import annotations

import argparse
import math
import os
import platform
import re
import sys
import time
from dataclasses import dataclass
from datetime import datetime, timezone
from pathlib import Path
from typing import Any

import torch

from .. import __version__
from ..config import GeCoConfig, config_to_dict
from ..estimators import TINY_RANDOM
from ..io.devices import check_device
from ..io.files import WriteError, write_json_atomic
from ..sampler import loading
from ..types import NonFiniteFramesError, check_frame_values
from .kit import Parser, add_config_flags, config_from_args

# --------------------------------------------------------------------------------------------
# building the pipeline from a config


def video_components(cfg: GeCoConfig) -> dict[str, Any] | None:
    """The tiny random CogVideoX models for ``model.id=tiny-random``, else ``None`` (load the id)."""
    if cfg.model.id != TINY_RANDOM:
        return None
    from ..tiny import tiny_cogvideox_components

    return tiny_cogvideox_components(cfg.model.init_seed)


def build_pipeline(cfg: GeCoConfig):
    """:func:`geco_guide.sampler.loading.build_pipeline` with the tiny models when the config asks for them."""
    return loading.build_pipeline(cfg, components=video_components(cfg))


# --------------------------------------------------------------------------------------------
# outputs


def slugify(text: str, max_len: int = 48) -> str:
    slug = re.sub(r"[^a-z0-9]+", "-", text.lower()).strip("-")
    return slug[:max_len].rstrip("-") or "video"


def output_paths(cfg: GeCoConfig, prompt: str, out: str | os.PathLike | None = None) -> tuple[Path, Path]:
    """``(video.mp4, sidecar.json)``: ``out`` (a .mp4 path or a folder) or ``output.dir/name``."""
    suffix = "" if cfg.guidance.enabled else "-unguided"
    name = cfg.output.name or f"{slugify(prompt)}-seed{cfg.seed}{suffix}"
    if out is not None:
        out = Path(out)
        video = out if out.suffix.lower() == ".mp4" else out / f"{name}.mp4"
    else:
        video = Path(cfg.output.dir) / f"{name}.mp4"
    return video, video.with_suffix(".json")


def check_output_location(video: Path) -> None:
    """ValueError (one line) if ``video``'s folder cannot exist because a file is in the way.

    Checked before the models load, so that a bad ``--out`` does not fail after sampling.
    """
    for parent in video.parents:
        if parent.exists():
            if not parent.is_dir():
                raise ValueError(f"cannot write {str(video)!r}: {str(parent)!r} is a file, not a folder")
            return


def versions() -> dict[str, str]:
    import diffusers
    import numpy
    import transformers

    try:
        from importlib.metadata import version

        geco_version = version("geco_guide")
    except Exception:  # not installed (running from a checkout)
        geco_version = "unknown"
    return {
        "geco_guide": geco_version,
        "python": platform.python_version(),
        "torch": torch.__version__,
        "diffusers": diffusers.__version__,
        "transformers": transformers.__version__,
        "numpy": numpy.__version__,
    }


@dataclass
class GenerationResult:
    video_path: Path
    sidecar_path: Path
    scores: dict[str, float] | None
    sidecar: dict[str, Any]


def generate(cfg: GeCoConfig, prompt: str, out: str | os.PathLike | None = None, pipe=None) -> GenerationResult:
    """Run one generation of ``cfg`` and write the mp4 + JSON sidecar. ``pipe`` skips loading."""
    from ..io.video import write_video
    from ..loss.geco import GeCoLoss
    from ..sampler.step import score_anchor_frames

    if not prompt or not prompt.strip():
        raise ValueError("prompt must not be empty")
    video_path, sidecar_path = output_paths(cfg, prompt, out)
    check_output_location(video_path)
    timings: dict[str, float] = {}
    start = time.perf_counter()
    if pipe is None:
        check_device(cfg.model.device)
        pipe = build_pipeline(cfg)
    timings["load_s"] = time.perf_counter() - start

    s = cfg.sampling
    generator = torch.Generator(device="cpu").manual_seed(cfg.seed)
    start = time.perf_counter()
    output = pipe(
        prompt=prompt,
        negative_prompt=s.negative_prompt,
        height=s.height,
        width=s.width,
        num_frames=s.num_frames,
        num_inference_steps=s.num_inference_steps,
        guidance_scale=s.guidance_scale,
        use_dynamic_cfg=s.use_dynamic_cfg,
        generator=generator,
        output_type="pt",
        max_sequence_length=s.max_sequence_length,
        guidance=cfg.guidance,
    )
    timings["sampling_s"] = time.perf_counter() - start
    frames = output.frames  # [1, F, 3, H, W] in [0, 1]
    try:
        check_frame_values(frames, "the sampled video")
    except NonFiniteFramesError as err:  # the VAE's clamp would write NaN as black and score it 0
        raise ValueError(
            f"sampling diverged, nothing was written: {err} (lower sampling.guidance_scale or guidance.eta)"
        ) from None

    scores = None
    if cfg.output.score_anchors:
        start = time.perf_counter()
        loss = GeCoLoss(pipe.geometry_estimator, pipe.flow_estimator, cfg.guidance.loss)
        scores = score_anchor_frames(frames, cfg.guidance.anchors, loss)
        timings["scoring_s"] = time.perf_counter() - start

    start = time.perf_counter()
    write_video(video_path, frames[0], fps=s.fps)
    timings["write_video_s"] = time.perf_counter() - start
    log = output.guidance_log or []
    timings["guidance_s"] = sum(r["seconds"] for r in log)
    sidecar = {
        "prompt": prompt,
        "seed": cfg.seed,
        "video": video_path.name,
        "num_frames": int(frames.shape[1]),
        "fps": s.fps,
        "created": datetime.now(timezone.utc).isoformat(timespec="seconds"),
        "config": config_to_dict(cfg),
        "scheduler": getattr(pipe, "geco_scheduler_note", None) or type(pipe.scheduler).__name__,
        "device": str(pipe.device),
        "versions": versions(),
        "timings": timings,
        "geco_scores": {"anchors": list(cfg.guidance.anchors), **scores} if scores is not None else None,
        "guidance_log": log,
    }
    write_json_atomic(sidecar_path, sidecar)
    return GenerationResult(video_path=video_path, sidecar_path=sidecar_path, scores=scores, sidecar=sidecar)


# --------------------------------------------------------------------------------------------
# CLI


def build_parser() -> argparse.ArgumentParser:
    p = Parser(
        prog="python -m geco_guide.generate",
        description="Generate a video with GeCo geometric-consistency guidance (CogVideoX).",
    )
    p.add_argument("--version", action="version", version=f"geco_guide {__version__}")
    p.add_argument("--prompt", required=True, help="text prompt")
    add_config_flags(p, preset_help="a preset of configs/: tiny, cogvideox-5b, cogvideox-5b-fused")
    p.add_argument("--seed", type=int, default=None, help="sampling seed (overrides the config's seed)")
    p.add_argument("--no-guidance", action="store_true", help="sample without GeCo guidance")
    p.add_argument("--out", default=None, help="output .mp4 path or folder (sidecar next to it, .json)")
    p.add_argument("overrides", nargs="*", metavar="key=value", help="config overrides, e.g. guidance.eta=2.0")
    return p


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    options = {"seed": args.seed, "guidance.enabled": "false" if args.no_guidance else None}
    try:
        cfg = config_from_args(args, args.overrides, options)
        result = generate(cfg, args.prompt, out=args.out)
    except (ValueError, FileNotFoundError, WriteError) as err:  # WeightsNotFoundError: a FileNotFoundError
        print(f"error: {err}", file=sys.stderr)
        return 2
    print(f"wrote video:   {result.video_path}")
    print(f"wrote sidecar: {result.sidecar_path}")
    if result.scores is not None:
        s = result.scores
        print(
            f"GeCo scores of anchor frames {list(cfg.guidance.anchors)}: "
            f"fused={s['fused']:.4f} motion={s['motion']:.4f} structure={s['structure']:.4f}"
        )
    log = result.sidecar["guidance_log"]
    if log:
        print(f"guidance: {len(log)} updates in {result.sidecar['timings']['guidance_s']:.1f} s")
        idle = [r for r in log if r["skipped"] or not math.isfinite(r["loss"])]
        if idle:  # a NaN decode or gradient leaves the latents unchanged (see GeCoLoss check_values)
            steps = sorted({r["step"] for r in idle})
            print(f"warning: {len(idle)} guidance update(s) moved nothing (non-finite loss or gradient) at steps "
                  f"{steps}", file=sys.stderr)
    else:
        print("guidance: off")
    return 0

