"""The checks of ``geco bench``'s options that argparse cannot make alone, made before any work:
a device that is here, frame counts and video sides a model's VAE and denoiser take, options that
go together (``cost --gpu``, ``--split-cfg``, ``--all-models``, ``--context-parallel``), the
memory plans and decoders that exist, the config of ``decoder-agreement``. A bad one is one
:class:`BadOption` line."""

from __future__ import annotations

import argparse
from typing import Any

from ..families import DEFAULT_MODEL

__all__ = ["PIPELINE_SIDE_MULTIPLE", "TRACE_OPTIONS", "VAE_SIDE_MULTIPLE", "BadOption", "agreement_config",
           "check_all_models", "check_context_parallel", "check_cost", "check_frames", "check_options",
           "check_sampling", "check_sides", "check_torch_device", "size_multiple"]


class BadOption(ValueError):
    """An option value the parser could not refuse alone (one line)."""


#: A video side the CogVideoX pipeline takes (its VAE's 8x and the transformer's 2x2 patches), and the VAE's.
PIPELINE_SIDE_MULTIPLE, VAE_SIDE_MULTIPLE = 16, 8


def check_torch_device(device: str) -> None:
    """``--device``: a torch device that is here."""
    import torch

    try:
        kind = torch.device(device).type
    except (RuntimeError, ValueError):
        raise BadOption(f"--device {device!r} is not a torch device (e.g. cpu, cuda, cuda:1)") from None
    if kind == "cuda" and not torch.cuda.is_available():
        raise BadOption(f"--device {device}: no CUDA GPU is available here (use --device cpu)")


def check_frames(frames: int, guided: bool, model: str = DEFAULT_MODEL) -> None:
    """A frame count registry ``model``'s VAE makes (its ``frame_multiple k + 1``); the CogVideoX
    VAE 4k+1, and with guidance (anchors decoded in latent pairs) 8k+1."""
    from ..families import frames_problem, model_named
    from ..sampler.algorithm.slicing import check_num_frames, check_paired_latent_frames

    entry = model_named(model)
    if not entry.cogvideox_vae:
        problem = frames_problem(frames, entry.frame_multiple)
        if problem is not None:
            raise BadOption(f"--frames {problem}")
        return
    try:
        (check_paired_latent_frames if guided else check_num_frames)(frames, entry.temporal_compression)
    except ValueError as err:
        raise BadOption(f"--frames: {err}") from None


def check_sides(height: int | None, width: int | None, multiple: int) -> None:
    """``--height`` / ``--width``: multiples of ``multiple`` where given."""
    for name, value in (("--height", height), ("--width", width)):
        if value is not None and value % multiple:
            raise BadOption(f"{name} must be a multiple of {multiple}, got {value}")


def size_multiple(model: str) -> int:
    """The multiple of a registry model's video sides."""
    from ..families import model_named

    return model_named(model).size_multiple


#: ``cost`` options that trace one model, which ``--all-models`` (a table of the shipped estimates) does not take.
TRACE_OPTIONS = ("model", "preset", "mode", "steps", "frames", "height", "width", "dtype", "chunk_latents",
                 "vae_checkpointing", "vae_block_checkpointing", "gpu", "denoiser_checkpointing",
                 "estimator_checkpointing", "vae_tiling", "decoder", "no_time_travel", "paper_schedule",
                 "calibration_step_s", "measured", "num_gpus", "split_cfg", "dynamic_masks", "threads", "seed")


def check_all_models(args: argparse.Namespace, parser_defaults: dict[str, Any]) -> None:
    from .measure import unwritable_reason

    given = [f"--{name.replace('_', '-')}" for name in TRACE_OPTIONS if getattr(args, name) != parser_defaults[name]]
    if given:
        raise BadOption(f"--all-models prints the table of the shipped estimates and traces nothing: leave out "
                        f"{', '.join(given)} (or trace one model without --all-models)")
    reason = unwritable_reason(args.json) if args.json else None
    if reason:
        raise BadOption(f"--json: {reason}")


def check_context_parallel(args: argparse.Namespace, parser_defaults: dict[str, Any]) -> None:
    given = [f"--{name.replace('_', '-')}" for name in TRACE_OPTIONS
             if name not in ("model", "mode") and getattr(args, name) != parser_defaults[name]]
    if args.all_models or given:
        raise BadOption(f"--context-parallel predicts from the shipped estimates and traces nothing: leave out "
                        f"{', '.join(given or ['--all-models'])} (the table of --all-models has its 4-GPU columns)")
    check_all_models(args, {**parser_defaults, "model": args.model, "mode": args.mode})  # and --json's path


def check_cost(args: argparse.Namespace, defaults: dict[str, Any]) -> None:
    from .cost import load_measured
    from ..sampler.algorithm.config import DECODERS

    if args.preset == "tiny" and args.model != defaults["model"]:
        raise BadOption(f"--model {args.model} traces a full-size model: leave out --preset tiny (the tiny models "
                        "are CogVideoX's)")
    if args.decoder not in DECODERS:
        raise BadOption(f"--decoder must be one of {', '.join(DECODERS)}, got {args.decoder!r}")
    if args.decoder != "vae" and args.mode == "unguided":
        raise BadOption(f"--decoder {args.decoder} decodes the anchor frames of guidance: use --mode fast or faithful")
    if args.gpu:
        flags = [name for name, value in (("--vae-checkpointing", args.vae_checkpointing),
                                          ("--vae-block-checkpointing", args.vae_block_checkpointing),
                                          ("--denoiser-checkpointing", args.denoiser_checkpointing),
                                          ("--estimator-checkpointing", args.estimator_checkpointing or None))
                 if value is not None]
        if args.mode == "unguided" or args.preset != "full" or flags:
            raise BadOption(f"--gpu chooses the memory plan of guidance for a full-size model: use it with --preset "
                            f"full and --mode fast or faithful, without {', '.join(flags) or 'the checkpointing flags'}")
    if args.steps is not None and args.steps < 1:
        raise BadOption(f"--steps must be >= 1, got {args.steps}")
    if args.split_cfg and (args.num_gpus < 2 or args.mode == "unguided"):
        raise BadOption("--split-cfg puts the CFG halves of a guided run on two GPUs: use it with --num-gpus 2 or "
                        "more and --mode fast or faithful")
    if args.frames is not None:
        check_frames(args.frames, guided=args.mode != "unguided",
                     model=DEFAULT_MODEL if args.preset == "tiny" else args.model)
    check_sides(args.height, args.width, PIPELINE_SIDE_MULTIPLE if args.preset == "tiny" else
                 size_multiple(args.model))
    args.measured_report = load_measured(args.measured) if args.measured else None


def check_options(args: argparse.Namespace, defaults: dict[str, Any]) -> None:
    """The checks argparse cannot make alone, before any work; :class:`BadOption` (one line).
    ``defaults``: the parser's defaults of ``cost``'s options."""
    from .measure import unwritable_reason

    if getattr(args, "device", None) is not None:
        check_torch_device(args.device)
    if getattr(args, "json", None):
        reason = unwritable_reason(args.json)
        if reason:
            raise BadOption(f"--json: {reason}")
    if args.command == "vae":
        check_frames(args.frames, guided=False)
        check_sides(args.height, args.width, VAE_SIDE_MULTIPLE)
    elif args.command == "sampling":
        check_sampling(args)
    elif args.command == "cost":
        check_cost(args, defaults)
    elif args.command == "decoder-agreement":
        args.cfg = agreement_config(args)


def check_sampling(args: argparse.Namespace) -> None:
    import torch

    from ..io.devices import resolve_devices
    from ..sampler.running.memory_plan import PLAN_NAMES
    from ..sampler.algorithm.schedule import PAPER_STEPS

    if args.memory_plan not in PLAN_NAMES:
        raise BadOption(f"--memory-plan must be one of {', '.join(PLAN_NAMES)}, got {args.memory_plan!r}")
    if args.devices:
        resolve_devices(args.devices, "--devices")
    if args.full_size and torch.device(args.device).type == "cpu" and not args.allow_cpu:
        raise BadOption("sampling --full-size on CPU is refused: CogVideoX-5B + VGGT-1B + UFM-Base weights alone are "
                        "about 30 GiB in float32 (7.4 G parameters) and a 49x480x720 step would take hours; run it on "
                        "a GPU (--device cuda) or pass --allow-cpu to insist.")
    if args.steps is not None and not 1 <= args.steps <= PAPER_STEPS:
        raise BadOption(f"--steps must be in [1, {PAPER_STEPS}], got {args.steps}")
    if args.frames is not None:
        check_frames(args.frames, guided=args.mode != "unguided")
    check_sides(args.height, args.width, PIPELINE_SIDE_MULTIPLE)


def agreement_config(args: argparse.Namespace) -> Any:
    """The validated config of ``decoder-agreement`` (preset <- file <- overrides), its device and
    tiny decoder checked."""
    from ..config import load_config
    from ..io.devices import check_device
    from .decoder_agreement import check_agreement_config

    if not args.prompt.strip():
        raise BadOption("--prompt must not be empty")
    cfg = load_config(args.config, args.preset, args.overrides)
    check_device(cfg.model.device)
    check_agreement_config(cfg, args.prompt)
    return cfg
