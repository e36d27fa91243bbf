"""Generate a GeCo-guided video: ``python -m geco_guide.generate --prompt "..."``.

    python -m geco_guide.generate --preset tiny --prompt "a marble bust"
    python -m geco_guide.generate --preset cogvideox-5b --prompt "..." --seed 3 \\
        guidance.step_size=2.0 guidance.loss.cue=motion

Writes ``<name>.mp4`` and a JSON sidecar ``<name>.json`` (resolved config, seed, scheduler,
versions, timings, guidance log, GeCo scores of the anchor frames of the final video), each
atomically. The default name is ``<prompt slug>-<video key>-seed<N>[-unguided]``, the key a hash
of the prompt and of the config that makes the frames (:func:`video_key`), so two runs share a name
only when they make the same video; an existing output is refused without ``--overwrite``.
Trailing ``key=value`` arguments override the config (unknown keys are rejected).
"""

from __future__ import annotations

import argparse
import contextlib
import functools
import hashlib
import json
import math
import os
import platform
import re
import sys
import time
from collections.abc import Iterator
from dataclasses import asdict, dataclass, replace
from datetime import datetime, timezone
from pathlib import Path
from typing import TYPE_CHECKING, Any

from .. import __version__
from ..io.files import WriteError, output_lock, write_json_atomic
from .kit import DeferredImports, Parser, add_config_flags, config_from_args, interruptible

if TYPE_CHECKING:
    import torch

    from ..config import GeCoConfig

__all__ = ["SCORES_NOTE", "SELECTION_SCORE", "best_candidate", "build_pipeline", "check_video_fits",
           "default_name", "generate", "main", "output_paths", "slugify", "versions", "video_key"]

# Each module that imports torch is imported where it is used, so that parsing the arguments needs
# none of them; ``loading`` stays an attribute of this module, imported on first use.
__getattr__ = DeferredImports(__name__, {"..sampler": ("loading",)}).attribute

# --------------------------------------------------------------------------------------------
# building the pipeline from a config


def build_pipeline(cfg: GeCoConfig):
    """:func:`geco_guide.sampler.loading.build_pipeline` with the tiny models when the config asks
    for them, after one stderr line naming them (loading takes minutes)."""
    from ..sampler import loading
    from ..tiny import video_components

    print(loading_line(cfg), file=sys.stderr, flush=True)
    return loading.build_pipeline(cfg, components=video_components(cfg))


def load_dynamic_masks(cfg: GeCoConfig):
    """The mask source of ``guidance.dynamic`` (``None`` without), after one stderr line naming
    the segmenter when there is one to load: before the video model, so that missing weights end
    the run at once."""
    from ..sampler import loading

    dynamic = cfg.guidance.dynamic if cfg.guidance.enabled else None
    if dynamic is not None and dynamic != "auto":
        print(f"loading segmenter: {cfg.estimators.segmenter} for {dynamic!r} ...", file=sys.stderr, flush=True)
    return loading.load_dynamic_masks(cfg)


def loading_line(cfg: GeCoConfig) -> str:
    return (f"loading models: CogVideoX {cfg.model.id}, geometry {cfg.estimators.geometry}, "
            f"flow {cfg.estimators.flow} ...")


# --------------------------------------------------------------------------------------------
# outputs


#: What ``--out`` may end with: a video file of these suffixes (the writer picks the format by
#: it), or no suffix (a folder).
OUT_SUFFIXES = (".mp4", ".gif")
#: Config sections that cannot change the frames, left out of :func:`video_key`: where the files
#: go, whether the anchors are scored afterwards, the evaluation protocol.
KEYLESS_SECTIONS = ("output", "evaluation")
#: The moving-subject options, which make no frame while ``guidance.dynamic`` is null: left out of
#: :func:`video_key` then, so that every video made before they existed keeps its name.
DYNAMIC_KEYS = ("dynamic", "dynamic_dilation", "dynamic_refresh")
#: Longest name a temporary of an atomic write adds to ``<name>``: ``.<name>.<8 random>.tmp``
#: before the suffix (see :func:`geco_guide.io.files.atomic_path`).
TEMP_NAME_EXTRA = len("..12345678.tmp")
SCORES_NOTE = ("These are the anchor frames' scores with the guidance loss' settings; "
               "python -m geco_guide evaluate scores the whole video with the paper's protocol (a different number).")


def slugify(text: str, max_len: int = 48) -> str:
    slug = re.sub(r"[^a-z0-9]+", "-", text.lower()).strip("-")
    return slug[:max_len].rstrip("-") or "video"


def video_key(config: dict[str, Any], prompt: str) -> str:
    """8 hex characters of SHA-256 over the prompt and the config that makes the frames
    (``config``: :func:`geco_guide.config.config_to_dict`'s form, e.g. a sidecar's ``config``).

    Left out: :data:`KEYLESS_SECTIONS`, ``model.device``, and the ``run`` section (how this machine
    runs guidance: memory plans and devices give the same frames) except its
    :data:`~geco_guide.sampler.run_options.FRAME_ROUNDING_KEYS` where they differ from their
    defaults: those can change the frames to float rounding and so name another video. The device can change the bytes
    (CPU and GPU kernels round differently), but a video moved to another device is the same
    experiment, so it does not rename it. Left out too while unused: the :data:`DYNAMIC_KEYS` of
    a null ``guidance.dynamic`` (or of a video made without guidance), ``guidance.loss.movers`` at
    its default ``drop``, and ``estimators.segmenter`` unless ``guidance.dynamic`` names subjects. The JSON is canonical (sorted keys), so the key is the same in every process and on
    every machine.
    """
    from ..sampler.run_options import FRAME_ROUNDING_KEYS, RunOptions

    kept = {section: value for section, value in config.items() if section not in KEYLESS_SECTIONS}
    kept["model"] = {key: value for key, value in kept.get("model", {}).items() if key != "device"}
    if "run" in kept:  # the options that round frames, where set: a new one renames no video
        defaults = asdict(RunOptions())
        kept["run"] = {key: value for key, value in kept["run"].items()
                       if key in FRAME_ROUNDING_KEYS and value != defaults[key]}
        if not kept["run"]:
            del kept["run"]
    guidance = kept.get("guidance", {})
    dynamic = guidance.get("dynamic") if guidance.get("enabled", True) else None
    if dynamic is None and "guidance" in kept:
        kept["guidance"] = {key: value for key, value in kept["guidance"].items() if key not in DYNAMIC_KEYS}
    loss = kept.get("guidance", {}).get("loss")
    if isinstance(loss, dict) and loss.get("movers") == "drop":  # the default (no mover scored) renames no video
        kept["guidance"] = {**kept["guidance"], "loss": {key: value for key, value in loss.items() if key != "movers"}}
    if dynamic in (None, "auto") and "estimators" in kept:
        kept["estimators"] = {key: value for key, value in kept["estimators"].items() if key != "segmenter"}
    text = json.dumps({"prompt": prompt, "config": kept}, sort_keys=True, separators=(",", ":"))
    return hashlib.sha256(text.encode("utf-8")).hexdigest()[:8]


def default_name(cfg: GeCoConfig, prompt: str) -> str:
    """``<slug>-<video key>-seed<N>``, with ``-unguided`` when guidance is off."""
    from ..config import config_to_dict

    suffix = "" if cfg.guidance.enabled else "-unguided"
    return f"{slugify(prompt)}-{video_key(config_to_dict(cfg), prompt)}-seed{cfg.seed}{suffix}"


def output_paths(cfg: GeCoConfig, prompt: str, out: str | os.PathLike | None = None) -> tuple[Path, Path]:
    """``(video, sidecar.json)``: ``out`` (a .mp4 or .gif path, or a folder: no suffix) or
    ``output.dir/name.mp4``; ValueError (one line) for an ``out`` of another suffix."""
    name = cfg.output.name or default_name(cfg, prompt)
    if out is None:
        video = Path(cfg.output.dir) / f"{name}.mp4"
    else:
        out = Path(out)
        suffix = out.suffix.lower()
        if suffix and suffix not in OUT_SUFFIXES:
            raise ValueError(_suffix_problem(out))
        video = out if suffix else out / f"{name}.mp4"
    return video, video.with_suffix(".json")


def _suffix_problem(out: Path) -> str:
    return (f"--out {str(out)!r}: a video path must end with {' or '.join(OUT_SUFFIXES)}; a path without a suffix "
            "is a folder (the default name inside it)")


def with_resolved_device(cfg: GeCoConfig) -> GeCoConfig:
    """``cfg`` with ``model.device`` resolved once (``auto``: cuda where there is one, else cpu), so
    that the memory planner, the loaders and the sidecar all see the same real device.

    Raises:
        ValueError: (one line naming ``model.device``) a device this machine lacks.
    """
    from ..io.devices import check_device

    device = check_device(cfg.model.device)
    return replace(cfg, model=replace(cfg.model, device=str(device)))


def check_video_fits(cfg: GeCoConfig) -> None:
    """ValueError (one line) for a video size that cannot fit the device, before any model loads:
    the decoded video alone, in float32, is a lower bound of the run's peak (the models, latents
    and activations come on top), so a refusal is certain."""
    from ..io.devices import check_memory_fits

    s = cfg.sampling
    nbytes = s.num_frames * 3 * s.height * s.width * 4
    check_memory_fits(nbytes, cfg.model.device,
                      f"a {s.num_frames}-frame {s.height}x{s.width} video (sampling.num_frames/height/width)")


def _nearest_existing(path: Path) -> Path:
    """``path``'s nearest ancestor that exists (the folder an atomic write would create the rest in)."""
    return next((parent for parent in path.parents if os.path.exists(parent)), Path.cwd())


def _name_max(folder: Path) -> int:
    try:
        return os.pathconf(folder, "PC_NAME_MAX")
    except (OSError, ValueError):  # no pathconf for this file system: the common limit
        return 255


def _name_problem(path: Path, existing: Path) -> str | None:
    """Why a name of ``path`` below ``existing`` is too long for the file system (the file's with
    the temporary name its atomic write uses), or None."""
    limit = _name_max(existing)
    too_long = next((part for part in path.parent.parts[len(existing.parts):] if len(part.encode()) > limit), None)
    if too_long is not None:
        return (f"the folder name {too_long[:24]!r}... is {len(too_long.encode())} bytes, over the {limit} this "
                "file system allows")
    if len(path.name.encode()) + TEMP_NAME_EXTRA > limit:
        return (f"the name is {len(path.name.encode())} bytes, over the {limit - TEMP_NAME_EXTRA} this file system "
                "allows (a shorter output.name or --out)")
    return None


def check_outputs(paths: tuple[Path, ...], overwrite: bool = False) -> None:
    """ValueError (one line) for anything that would make writing ``paths`` fail after sampling:
    a name too long for the file system, a file where a folder must be, a folder or (without
    ``overwrite``) a file under an output's name, a folder that cannot be written."""
    for path in paths:
        existing = _nearest_existing(path)
        problem = _name_problem(path, existing)
        if problem is None and not existing.is_dir():
            problem = f"{str(existing)!r} is a file, not a folder"
        if problem is None and path.is_dir():
            problem = "a folder of that name is in the way"
        if problem is None and not os.access(existing, os.W_OK | os.X_OK):
            problem = f"the folder {str(existing)!r} is not writable"
        if problem is not None:
            raise ValueError(f"cannot write {str(path)!r}: {problem}")
        if path.exists() and not overwrite:
            raise ValueError(f"{str(path)!r} already exists; pass --overwrite to replace it, or choose another "
                             "--out or output.name")


@contextlib.contextmanager
def removed_on_failure(*paths: Path) -> Iterator[None]:
    """Remove ``paths`` when the block fails or is interrupted. Around a sidecar's write it removes
    the video just written (and an old sidecar under the name, whose video that replaced), so that
    no video is left without its own sidecar."""
    try:
        yield
    except BaseException:
        for path in paths:
            path.unlink(missing_ok=True)
        raise


def versions() -> dict[str, str]:
    from importlib.metadata import PackageNotFoundError, version

    import diffusers
    import numpy
    import torch
    import transformers

    try:
        geco_version = version("geco_guide")
    except PackageNotFoundError:  # not installed (running from a checkout)
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
    #: the pipeline that made the video (loaded, or the one passed in), for a caller's next video
    pipe: Any = None
    #: the mask source of ``guidance.dynamic`` it used (``None`` without), likewise
    dynamic_masks: Any = None


def check_prompt(prompt: str) -> None:
    """ValueError (one line) for a prompt that is empty or not UTF-8 text (before any model loads:
    the tokenizer would fail on it after loading them all)."""
    if not prompt or not prompt.strip():
        raise ValueError("prompt must not be empty")
    try:
        prompt.encode("utf-8")
    except UnicodeEncodeError as err:  # bytes the terminal could not decode reach Python as surrogates
        raise ValueError(f"the prompt is not valid UTF-8 text (an undecodable byte at character {err.start + 1}); "
                         "check the encoding of the terminal or file it came from") from None


def generate(cfg: GeCoConfig, prompt: str, out: str | os.PathLike | None = None, pipe=None,
             overwrite: bool = False, dynamic_masks: Any = None) -> GenerationResult:
    """Run one generation of ``cfg`` and write the mp4 + JSON sidecar. ``pipe`` skips loading, and
    ``dynamic_masks`` (the mask source of ``guidance.dynamic``, e.g. a text segmenter of loaded
    models) loading the segmenter; existing outputs are replaced only with ``overwrite`` (checked
    before anything loads).

    Once every check passed, the run holds its video's :func:`~geco_guide.io.files.output_lock`: a
    second run of the same output name at the same time is refused (one line naming the first's
    pid), and the existence check, made again under the lock, holds until the files are written.
    """
    from ..io.video import check_fps
    from ..sampler import loading
    from ..sampler.multi_device import resolve_devices

    check_prompt(prompt)
    video_path, sidecar_path = output_paths(cfg, prompt, out)
    check_outputs((video_path, sidecar_path), overwrite)
    check_fps(cfg.sampling.fps, video_path.suffix)
    cfg = with_resolved_device(cfg)
    if cfg.guidance.enabled:
        resolve_devices(cfg.run.devices)  # a device this machine lacks: one line before loading
    check_video_fits(cfg)
    timings: dict[str, float] = {}
    start = time.perf_counter()
    if pipe is None:
        # weights that are not there first (the problem a fresh machine has), then a budget no memory
        # plan fits, a schedule or decoder that cannot work: all before loading
        loading.check_weights_before_loading(cfg)
        s = cfg.sampling
        loading.check_guidance_before_loading(cfg, model_id=cfg.model.id, num_frames=s.num_frames, height=s.height,
                                              width=s.width, num_steps=s.num_inference_steps)
    with output_lock(video_path):  # every check passed: from here on the name is this run's
        check_outputs((video_path, sidecar_path), overwrite)  # again: a run that ended meanwhile wrote it
        return _load_sample_and_write(cfg, prompt, video_path, sidecar_path, pipe, dynamic_masks, timings, start)


def _load_sample_and_write(cfg: GeCoConfig, prompt: str, video_path: Path, sidecar_path: Path, pipe: Any,
                           masks: Any, timings: dict[str, float], start: float) -> GenerationResult:
    """The heavy part of :func:`generate`, once every check passed and the output name is held."""
    import torch

    from ..io.video import write_video
    from ..loss.geco import GeCoLoss
    from ..sampler.dynamic import RefreshedMasks
    from ..sampler.step import score_anchor_frames
    from ..types import NonFiniteFramesError, check_frame_values

    if masks is None:
        masks = load_dynamic_masks(cfg)
    if pipe is None:
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
        run_options=cfg.run,
        dynamic_masks=masks,
    )
    timings["sampling_s"] = time.perf_counter() - start
    frames = output.frames  # [1, F, 3, H, W] in [0, 1]
    try:
        check_frame_values(frames, "the sampled video")
    except NonFiniteFramesError as err:  # the VAE's clamp would write NaN as black and score it 0
        raise ValueError(
            f"sampling diverged, nothing was written: {err} (lower sampling.guidance_scale or guidance.step_size)"
        ) from None

    scores = None
    if cfg.output.score_anchors:
        start = time.perf_counter()
        loss = GeCoLoss(pipe.geometry_estimator, pipe.flow_estimator, cfg.guidance.loss)
        if masks is not None:  # the anchors scored as guidance scored them: without what moves
            loss = functools.partial(loss, dynamic_masks=RefreshedMasks(masks, dilation=cfg.guidance.dynamic_dilation))
        scores = score_anchor_frames(frames, cfg.guidance.anchors, loss)
        timings["scoring_s"] = time.perf_counter() - start

    start = time.perf_counter()
    write_video(video_path, frames[0], fps=s.fps)
    timings["write_video_s"] = time.perf_counter() - start
    with removed_on_failure(video_path, sidecar_path):
        sidecar = sidecar_of(cfg, prompt, pipe, frames, video_path.name, timings, scores, output.guidance_log or [])
        if masks is not None:
            sidecar["dynamic_masks"] = masks.source_name
        write_json_atomic(sidecar_path, sidecar)
    return GenerationResult(video_path=video_path, sidecar_path=sidecar_path, scores=scores, sidecar=sidecar, pipe=pipe,
                            dynamic_masks=masks)


#: The score best-of-N selection keeps the lowest of: the fused map under the GeCo protocol.
SELECTION_SCORE = "fused"


def best_candidate(scores: list[float]) -> int:
    """The index of the candidate best-of-N selection keeps among their :data:`SELECTION_SCORE`
    ``scores``: the least (a NaN ranks last, ties go to the earlier seed)."""
    return min(range(len(scores)), key=lambda k: (not math.isfinite(scores[k]), scores[k] if math.isfinite(scores[k]) else 0))


def generate_best_of(cfg: GeCoConfig, prompt: str, count: int, out: str | os.PathLike | None = None,
                     overwrite: bool = False, on_candidate: Any = None) -> GenerationResult:
    """Selection, the other way to spend compute on geometry: ``count`` videos of the seeds
    ``cfg.seed`` .. ``cfg.seed + count - 1`` (guided or not, as ``cfg`` says), each scored with the
    GeCo protocol (:func:`~geco_guide.metric.evaluate.evaluate_video`, the config's ``evaluation``
    section); the one of least fused score is kept (a NaN score ranks last, ties go to the
    earlier seed).

    Writes the kept video and its sidecar, which adds ``best_of``: every candidate's seed and
    protocol scores and the seed kept. The default name ends in ``-best-of-<count>``. The
    candidates are made in a hidden folder beside the output and removed however the run ends.
    ``on_candidate(k, seed, result)`` is called after each candidate is scored.

    Raises:
        ValueError: (one line, before any model loads) ``count`` below 1, and what :func:`generate`
            refuses.
    """
    import shutil

    from ..metric.evaluate import evaluate_video, finite_or_none

    if isinstance(count, bool) or not isinstance(count, int) or count < 1:
        raise ValueError(f"--best-of must be an integer >= 1, got {count!r}")
    check_prompt(prompt)
    if not cfg.output.name:
        cfg = replace(cfg, output=replace(cfg.output, name=f"{default_name(cfg, prompt)}-best-of-{count}"))
    video_path, sidecar_path = output_paths(cfg, prompt, out)
    check_outputs((video_path, sidecar_path), overwrite)
    work = video_path.with_name(f".{video_path.stem}.candidates")
    pipe, masks, candidates = None, None, []
    with output_lock(video_path):
        check_outputs((video_path, sidecar_path), overwrite)
        shutil.rmtree(work, ignore_errors=True)  # the candidates of a killed run
        try:
            for k in range(count):
                seed_cfg = replace(cfg, seed=cfg.seed + k, output=replace(cfg.output, name=None))
                result = generate(seed_cfg, prompt, out=work / f"seed{seed_cfg.seed}.mp4", pipe=pipe,
                                  dynamic_masks=masks)
                pipe, masks = result.pipe, result.dynamic_masks  # loaded once, for every candidate
                scored = evaluate_video(result.video_path, estimators=pipe.estimators, config=cfg)
                candidates.append((result, scored))
                if on_candidate is not None:
                    on_candidate(k, seed_cfg.seed, scored)
            best = best_candidate([getattr(scored, SELECTION_SCORE) for _, scored in candidates])
            kept, _ = candidates[best]
            sidecar = {**kept.sidecar, "video": video_path.name, "best_of": {
                "n": count, "kept_seed": kept.sidecar["seed"], "score": f"{SELECTION_SCORE} (the GeCo protocol, evaluation.*)",
                "candidates": [{"seed": result.sidecar["seed"], **{key: finite_or_none(getattr(scored, key))
                                                                   for key in ("fused", "motion", "structure")}}
                               for result, scored in candidates]}}
            os.replace(kept.video_path, video_path)
            with removed_on_failure(video_path, sidecar_path):
                write_json_atomic(sidecar_path, sidecar)
        finally:
            shutil.rmtree(work, ignore_errors=True)
    return GenerationResult(video_path=video_path, sidecar_path=sidecar_path, scores=kept.scores, sidecar=sidecar,
                            pipe=pipe, dynamic_masks=masks)


def sidecar_of(cfg: GeCoConfig, prompt: str, pipe: Any, frames: torch.Tensor, video_name: str,
               timings: dict[str, float], scores: dict[str, float] | None, log: list[dict[str, Any]]) -> dict[str, Any]:
    """The sidecar of a video ``frames [1, F, 3, H, W]``: what made it and how long it took."""
    from ..config import config_to_dict

    return {
        "prompt": prompt,
        "seed": cfg.seed,
        "video": video_name,
        "video_key": video_key(config_to_dict(cfg), prompt),
        "num_frames": int(frames.shape[1]),
        "fps": cfg.sampling.fps,
        "created": datetime.now(timezone.utc).isoformat(timespec="seconds"),
        "config": config_to_dict(cfg),
        "scheduler": getattr(pipe, "geco_scheduler_note", None) or type(pipe.scheduler).__name__,
        "guidance_decoder": getattr(pipe, "geco_decoder_note", None),
        "memory_plan": getattr(pipe, "geco_memory_plan", None),
        "guidance_devices": getattr(pipe, "geco_devices", None),
        "device": str(pipe.device),
        "versions": versions(),
        "timings": {**timings, "guidance_s": sum(r["seconds"] for r in log)},
        "geco_scores": {"anchors": list(cfg.guidance.anchors), **scores} if scores is not None else None,
        "guidance_log": log,
    }


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
    p.add_argument("--dynamic", default=None, metavar="SUBJECTS",
                   help="leave what moves on its own out of the guidance loss: 'auto' (detected from depth and flow) "
                        "or the moving subjects, e.g. 'a dog, a person' (segmented by estimators.segmenter, SAM 3); "
                        "sets guidance.dynamic")
    p.add_argument("--out", default=None,
                   help="output path ending in .mp4 or .gif (the sidecar: the same path with .json), or a folder (no suffix) "
                        "for the default name <prompt slug>-<8 hex of prompt and config>-seed<N>[-unguided].mp4; "
                        "default: output.dir")
    p.add_argument("--overwrite", action="store_true", help="replace an existing video and sidecar of the same name")
    p.add_argument("--devices", nargs="+", default=None, metavar="DEVICE",
                   help="deal the guidance's anchor decode over these devices, e.g. cuda:0 cuda:1 (or auto: every "
                        "GPU), each with a replica of the decoder; sets run.devices")
    p.add_argument("--best-of", type=int, default=None, metavar="N",
                   help="selection: make N videos (seeds --seed .. --seed+N-1), score each with the GeCo protocol and "
                        "keep the one of least fused score; its sidecar lists every candidate's scores")
    p.add_argument("overrides", nargs="*", metavar="key=value", help="config overrides, e.g. guidance.step_size=2.0")
    return p


def _print_candidate(count: int) -> Any:
    def show(k: int, seed: int, scored: Any) -> None:
        print(f"candidate {k + 1}/{count} (seed {seed}): protocol fused={scored.fused:.4f} motion={scored.motion:.4f} "
              f"structure={scored.structure:.4f}", file=sys.stderr, flush=True)
    return show


@interruptible("nothing was written (outputs are written atomically)")
def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    options = {"seed": args.seed, "guidance.enabled": "false" if args.no_guidance else None,
               "guidance.dynamic": args.dynamic,
               "run.devices": f"[{','.join(args.devices)}]" if args.devices else None}
    try:
        cfg = config_from_args(args, args.overrides, options)
        if args.best_of is None:
            result = generate(cfg, args.prompt, out=args.out, overwrite=args.overwrite)
        else:
            result = generate_best_of(cfg, args.prompt, args.best_of, out=args.out, overwrite=args.overwrite,
                                      on_candidate=_print_candidate(args.best_of))
    except (ValueError, FileNotFoundError, WriteError) as err:  # WeightsNotFoundError: a FileNotFoundError
        print(f"error: {err}", file=sys.stderr)
        return 2
    print(f"wrote video:   {result.video_path}")
    print(f"wrote sidecar: {result.sidecar_path}")
    if "best_of" in result.sidecar:
        chosen = result.sidecar["best_of"]
        print(f"best of {chosen['n']}: kept seed {chosen['kept_seed']} (least fused score under the GeCo protocol; "
              "every candidate's scores are in the sidecar)")
    if result.scores is not None:
        s = result.scores
        print(
            f"GeCo scores of anchor frames {list(cfg.guidance.anchors)}: "
            f"fused={s['fused']:.4f} motion={s['motion']:.4f} structure={s['structure']:.4f}"
        )
        print(SCORES_NOTE)
    log = result.sidecar["guidance_log"]
    if log:
        from ..types import plural

        # the progress bar counts denoising steps; a guided step makes R_t (0 or more) updates
        steps = plural(cfg.sampling.num_inference_steps, "denoising step")
        print(f"guidance: {plural(len(log), 'update')} over {steps} in "
              f"{result.sidecar['timings']['guidance_s']:.1f} s (the progress bar counts steps)")
        idle = [r for r in log if r["skipped"] or not math.isfinite(r["loss"])]
        if idle:  # a NaN decode or gradient leaves the latents unchanged (see GeCoLoss check_values)
            steps = sorted({r["step"] for r in idle})
            print(f"warning: {len(idle)} guidance update(s) moved nothing (non-finite loss or gradient) at steps "
                  f"{steps}", file=sys.stderr)
    else:
        print("guidance: off")
    return 0

