"""The pipeline call of a config: its ``sampling`` section (:class:`SamplingConfig`), the model's
defaults where the section leaves a value null, and the arguments a diffusers video pipeline takes.

Every family's pipeline takes the same core arguments (prompt, size, frames, steps, CFG,
generator); the others (a second expert's CFG, CogVideoX's dynamic CFG, the text length, the
conditioning image) only where that pipeline has them. An option set for a pipeline that has no
such argument is refused in one line naming the option and the pipeline, never dropped.
"""

from __future__ import annotations

import inspect
from dataclasses import dataclass, fields, replace
from typing import TYPE_CHECKING, Any, Optional

from ...families import VideoModel, frames_problem

if TYPE_CHECKING:
    from ...io.video import SoundTrack

__all__ = ["SamplingConfig", "call_arguments", "fit_to_model", "sampling_problem", "sound_track", "with_model_defaults"]


@dataclass
class SamplingConfig:
    """The config's ``sampling`` section: the arguments of the pipeline call. ``null`` takes the
    model's default (its registry entry, :mod:`geco_guide.families`); the paper's experiment is
    CogVideoX-5b's: 50 DDIM steps, CFG 6, 49 x 480 x 720, written at 8 fps.

    Attributes:
        num_inference_steps, guidance_scale, num_frames, height, width: the call's.
        guidance_scale_2: the second expert's CFG of a two-expert model (Wan 2.2 A14B).
        fps: the frame rate the video is written at.
        negative_prompt: the CFG's negative text (``null``: the pipeline's default).
        use_dynamic_cfg: CogVideoX's dynamic CFG.
        max_sequence_length: the text encoder's length (``null``: the pipeline's default).
        scheduler: ``ddim`` / ``dpm``: CogVideoX's DDIM / DPM built from the checkpoint's config
            (the paper samples with DDIM); ``checkpoint``: the checkpoint's own scheduler;
            ``null``: the model's default (DDIM for CogVideoX, the checkpoint's for the others).
    """

    num_inference_steps: Optional[int] = None
    guidance_scale: Optional[float] = None
    guidance_scale_2: Optional[float] = None
    num_frames: Optional[int] = None
    height: Optional[int] = None
    width: Optional[int] = None
    fps: Optional[int] = None
    negative_prompt: Optional[str] = None
    use_dynamic_cfg: bool = False
    max_sequence_length: Optional[int] = None
    scheduler: Optional[str] = None


#: The registry's call defaults that fill a null option of the same name.
MODEL_DEFAULTS = ("num_inference_steps", "guidance_scale", "guidance_scale_2", "num_frames", "height", "width")


def with_model_defaults(sampling: SamplingConfig, model: VideoModel) -> SamplingConfig:
    """``sampling`` with every null option the model has a default for filled from its registry
    entry (the call defaults, the frame rate, the scheduler)."""
    defaults = {key: model.call.get(key) for key in MODEL_DEFAULTS}
    defaults.update(fps=model.fps, scheduler=model.scheduler)
    changes = {key: value for key, value in defaults.items() if getattr(sampling, key) is None and value is not None}
    return replace(sampling, **changes)


def fit_to_model(sampling: SamplingConfig, model: VideoModel) -> SamplingConfig:
    """``sampling`` made for any model (the tiny preset's short call) fitted to ``model``: height
    and width rounded up to its size multiple (48 -> 64 for a model of multiples of 32), no text
    length where its pipeline takes none."""
    changes: dict[str, Any] = {}
    for key in ("height", "width"):
        value = getattr(sampling, key)
        if isinstance(value, int) and not isinstance(value, bool) and value > 0 and value % model.size_multiple:
            changes[key] = -(-value // model.size_multiple) * model.size_multiple
    if not model.text_length:
        changes["max_sequence_length"] = None
    return replace(sampling, **changes)


def sampling_problem(sampling: SamplingConfig, model: VideoModel) -> tuple[str, str] | None:
    """``(key, why)`` of the first option of ``sampling`` (filled, :func:`with_model_defaults`)
    that ``model`` cannot make a video with, or ``None``: the VAE's frame-count rule, the size
    multiple, options of another family."""
    problem = frames_problem(sampling.num_frames, model.frame_multiple)
    if problem is not None:
        return "num_frames", f"{problem} ({model.name})"
    for key in ("height", "width"):
        value = getattr(sampling, key)
        if isinstance(value, bool) or not isinstance(value, int) or value <= 0 or value % model.size_multiple:
            return key, (f"must be a positive multiple of {model.size_multiple} for {model.name} (its VAE and patch "
                         f"size), got {value!r}")
    if sampling.guidance_scale_2 is not None and "guidance_scale_2" not in model.call:
        return "guidance_scale_2", f"is the second expert's CFG; {model.name} has one expert (use null)"
    if sampling.max_sequence_length is not None and not model.text_length:
        return "max_sequence_length", f"is not an argument of {model.pipeline}; {model.name} takes none (use null)"
    return None


def call_arguments(pipe: Any, sampling: SamplingConfig, *, prompt: str, generator: Any, output_type: str = "pt",
                   **extra: Any) -> dict[str, Any]:
    """The keyword arguments of ``pipe``'s call for ``sampling`` (filled): the core ones, and each
    other option that is set, where the pipeline takes it; ``extra`` (e.g. ``image``) likewise.

    A pipeline that makes sound with the video (LTX-2: its ``vocoder``) gets ``sampling.fps`` as its
    ``frame_rate``, so that the sound lasts as long as the written video.

    Two families take what the others take as arguments elsewhere: a pipeline whose CFG is a
    ``guider`` component (HunyuanVideo 1.5) gets ``sampling.guidance_scale`` as its guider's scale
    (the component is replaced by a copy of that scale); an image-to-video pipeline that sizes its
    video after the image (HunyuanVideo 1.5's) takes no height and width.

    Raises:
        ValueError: (one line) an option set for a pipeline that has no such argument.
    """
    accepted = inspect.signature(pipe.__call__).parameters
    arguments: dict[str, Any] = dict(prompt=prompt, num_frames=sampling.num_frames,
                                     num_inference_steps=sampling.num_inference_steps, generator=generator,
                                     output_type=output_type)
    if "height" in accepted:
        arguments.update(height=sampling.height, width=sampling.width)
    if "guidance_scale" in accepted:
        arguments["guidance_scale"] = sampling.guidance_scale
    if "frame_rate" in accepted and getattr(pipe, "vocoder", None) is not None and sampling.fps is not None:
        # a pipeline that makes sound with the video (LTX-2) makes as much of it as the frames last at
        # frame_rate: the video is written at sampling.fps, so the sound lasts as long as the video
        arguments["frame_rate"] = float(sampling.fps)
    elif getattr(pipe, "guider", None) is not None and pipe.guider.guidance_scale != sampling.guidance_scale:
        pipe.guider = pipe.guider.new(guidance_scale=sampling.guidance_scale)
    optional = {f"sampling.{f.name}": (f.name, getattr(sampling, f.name)) for f in fields(sampling)
                if f.name in ("negative_prompt", "guidance_scale_2", "max_sequence_length", "use_dynamic_cfg")}
    optional.update({name: (name, value) for name, value in extra.items()})
    for option, (name, value) in optional.items():
        if value is None or value is False:
            continue
        if name not in accepted:
            raise ValueError(f"{option} is not an argument of {type(pipe).__name__}: leave it unset for this model")
        arguments[name] = value
    return arguments


def sound_track(pipe: Any, output: Any) -> SoundTrack | None:
    """The first video's sound where ``pipe``'s call made one (LTX-2: ``output.audio``
    ``[B, C, N]``, its vocoder's waveform at the vocoder's ``output_sampling_rate``), else ``None``."""
    audio = getattr(output, "audio", None)
    if audio is None:
        return None
    import torch

    from ...io.video import SoundTrack

    return SoundTrack(torch.as_tensor(audio[0]).float().cpu(), int(pipe.vocoder.config.output_sampling_rate))
