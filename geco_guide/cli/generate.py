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
import contextlib
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
from ..config import GeCoConfig, config_to_dict, load_config
from ..estimators import TINY_RANDOM, load_estimators
from ..estimators.loading import WeightsNotFoundError
from ..io.devices import check_device, resolve_device
from ..io.files import WriteError, write_json_atomic
from ..types import NonFiniteFramesError, check_frame_values

# --------------------------------------------------------------------------------------------
# building the pipeline from a config


@contextlib.contextmanager
def quiet_hub_logs():
    """diffusers/transformers print several lines while failing to reach the hub; keep one error."""
    from diffusers.utils import logging as dlogging

    level = dlogging.get_verbosity()
    dlogging.set_verbosity_error()
    try:
        yield
    finally:
        dlogging.set_verbosity(level)


def _looks_like_path(model_id: str) -> bool:
    return model_id.startswith((".", "/", "~")) or model_id.count("/") > 1 or os.sep in model_id.replace("/", "")


def _dtype_kwarg() -> str:
    """diffusers renamed ``torch_dtype`` to ``dtype``; use whichever this version reads."""
    from diffusers.pipelines import pipeline_utils

    return "dtype" if hasattr(pipeline_utils, "_resolve_dtype") else "torch_dtype"


def pipeline_from_pretrained(cls, model_id: str, name: str, folder_hint: str, *, dtype: torch.dtype,
                             revision: str | None = None, **kwargs: Any):
    """``cls.from_pretrained`` of a hub id or a local folder, in ``dtype``.

    Raises:
        WeightsNotFoundError: one line naming ``model_id``, the ``hf download`` command and
            ``folder_hint`` (how to pass a local folder), when the folder does not exist or the
            weights are neither in the hub cache nor reachable.
    """
    path = Path(model_id).expanduser()
    if _looks_like_path(model_id) and not path.is_dir():
        raise WeightsNotFoundError(f"{name}: local folder {model_id!r} does not exist (pass an existing folder or a "
                                   f"hub id: {folder_hint})")
    try:
        with quiet_hub_logs():
            return cls.from_pretrained(str(path) if path.is_dir() else model_id, revision=revision,
                                       **{_dtype_kwarg(): dtype}, **kwargs)
    except (OSError, ValueError) as err:
        if isinstance(err, ValueError) and type(err).__name__ != "HFValidationError":
            raise
        raise WeightsNotFoundError(
            f"{name} weights {model_id!r} are not available: not in the local Hugging Face cache and the hub "
            f"cannot be reached (offline?). Download them once with `hf download {model_id}` (huggingface_hub "
            f"< 0.34: `huggingface-cli download`) or pass a local folder: {folder_hint}"
        ) from None


def load_video_pipeline(cfg: GeCoConfig, geometry_estimator=None, flow_estimator=None):
    """The GeCoCogVideoXPipeline of ``cfg.model`` on its device (estimators attached, the scheduler
    of ``sampling.scheduler``: DDIM in the presets, see :func:`choose_scheduler`).

    Raises:
        WeightsNotFoundError: one line naming the model id and how to pass a local folder, when
            the weights are neither in a local folder nor in the hub cache / reachable.
    """
    from ..sampler.pipeline_cogvideox import GeCoCogVideoXPipeline

    dtype = getattr(torch, cfg.model.dtype)
    device = resolve_device(cfg.model.device)
    model_id = cfg.model.id
    extra = dict(geometry_estimator=geometry_estimator, flow_estimator=flow_estimator, guidance_config=cfg.guidance)
    if model_id == TINY_RANDOM:
        from ..tiny import tiny_cogvideox_components

        components = tiny_cogvideox_components(cfg.model.init_seed)
        pipe = GeCoCogVideoXPipeline(**components, **extra)
        if dtype != torch.float32:
            for model in (pipe.text_encoder, pipe.transformer, pipe.vae):
                model.to(dtype)
    else:
        pipe = pipeline_from_pretrained(
            GeCoCogVideoXPipeline, model_id, "CogVideoX", f"model.id=/path/to/{model_id.split('/')[-1]}",
            dtype=dtype, revision=cfg.model.revision, **extra,
        )
    pipe.geco_scheduler_note = choose_scheduler(pipe, cfg.sampling.scheduler)
    if cfg.model.vae_tiling:
        pipe.vae.enable_tiling()
    if cfg.model.vae_slicing:
        pipe.vae.enable_slicing()
    pipe.to(device)
    return pipe


SCHEDULERS = {"ddim": "CogVideoXDDIMScheduler", "dpm": "CogVideoXDPMScheduler"}


def choose_scheduler(pipe, name: str | None) -> str:
    """Give ``pipe`` the scheduler ``sampling.scheduler`` names; returns the sidecar's note.

    ``ddim`` / ``dpm``: CogVideoX's DDIM / DPM scheduler built from the checkpoint's scheduler
    config (the paper samples with deterministic DDIM, and CogVideoX-5B ships DPM); ``None``: the
    checkpoint's own scheduler, untouched. The pipeline itself never replaces a scheduler.
    """
    shipped = type(pipe.scheduler).__name__
    if name is None:
        return f"{shipped} (the checkpoint's)"
    if name not in SCHEDULERS:
        raise ValueError(f"sampling.scheduler must be one of {sorted(SCHEDULERS)} or null, got {name!r}")
    import diffusers

    cls = getattr(diffusers, SCHEDULERS[name])
    if type(pipe.scheduler) is cls:
        return f"{cls.__name__} (sampling.scheduler={name}, the checkpoint's)"
    pipe.scheduler = cls.from_config(pipe.scheduler.config)
    return f"{cls.__name__} (sampling.scheduler={name}, built from the checkpoint's {shipped} config)"


def build_pipeline(cfg: GeCoConfig):
    """Estimators + video pipeline of a config (estimators first: they are the cheaper failure)."""
    geometry, flow = load_estimators(cfg.estimators, resolve_device(cfg.model.device))
    return load_video_pipeline(cfg, geometry, flow)


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
    p = argparse.ArgumentParser(
        prog="python -m geco_guide.generate",
        description="Generate a video with GeCo geometric-consistency guidance (CogVideoX).",
    )
    p.add_argument("--version", action="version", version=f"geco_guide {__version__}")
    p.add_argument("--prompt", required=True, help="text prompt")
    p.add_argument("--config", default=None, help="YAML config file (applied after --preset)")
    p.add_argument("--preset", default=None, help="a preset of configs/: tiny, cogvideox-5b, cogvideox-5b-fused")
    p.add_argument("--seed", type=int, default=None, help="sampling seed (overrides the config's seed)")
    p.add_argument("--no-guidance", action="store_true", help="sample without GeCo guidance")
    p.add_argument("--out", default=None, help="output .mp4 path or folder (sidecar next to it, .json)")
    p.add_argument("overrides", nargs="*", metavar="key=value", help="config overrides, e.g. guidance.eta=2.0")
    return p


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    overrides = list(args.overrides)
    if args.seed is not None:
        overrides.append(f"seed={args.seed}")
    if args.no_guidance:
        overrides.append("guidance.enabled=false")
    try:
        cfg = load_config(args.config, args.preset, overrides)
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

