"""Loading video pipelines: a hub id or a local folder, in a dtype, with a clear one-line error
when the weights are not there, the scheduler that ``sampling.scheduler`` names, and the tiny
decoder of ``guidance.decoder=tiny`` (``estimators.tiny_decoder``).

diffusers is imported inside the functions, so importing this module stays light. The config is
duck-typed (``cfg.model``, ``cfg.sampling``, ``cfg.guidance``, ``cfg.estimators`` of a
:class:`~geco_guide.config.GeCoConfig`): the config module sits above the sampler.
"""

from __future__ import annotations

import contextlib
from pathlib import Path
from typing import Any

import torch

from ..estimators import (
    TINY_RANDOM,
    load_estimators,
    tiny_random_decoder,
    with_config_key,
)
from ..estimators.loading import (
    CHECKPOINT_SUFFIXES,
    WeightsNotFoundError,
    check_weights_available,
    pretrained_or_one_line,
    quiet_hub_retries,
)
from ..io.devices import resolve_device
from .memory_plan import plan_before_loading

__all__ = ["PIPELINE_INDEX", "TINY_DECODER_VARIANTS", "build_pipeline", "cast_model",
           "check_guidance_before_loading", "check_tiny_decoder_source", "check_weights_before_loading",
           "choose_scheduler", "load_dynamic_masks", "load_tiny_decoder", "load_video_pipeline",
           "pipeline_from_pretrained", "quiet_hub_logs", "tiny_decoder_note"]


@contextlib.contextmanager
def quiet_hub_logs():
    """diffusers/transformers and huggingface_hub print several lines while failing to reach the
    hub; keep one error."""
    from diffusers.utils import logging as dlogging

    level = dlogging.get_verbosity()
    dlogging.set_verbosity_error()
    try:
        with quiet_hub_retries():
            yield
    finally:
        dlogging.set_verbosity(level)


def cast_model(model: torch.nn.Module, dtype: torch.dtype) -> torch.nn.Module:
    """``model`` cast to ``dtype`` in place (and returned). diffusers' ``ModelMixin.to(dtype)``
    warns about the modules it should keep in float32 even when the model names none (an empty
    list, at every cast); such a model is cast without the warning, one that names some keeps it."""
    if getattr(model, "_keep_in_fp32_modules", None):
        return model.to(dtype)
    return torch.nn.Module.to(model, dtype)


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
    with quiet_hub_logs():
        return pretrained_or_one_line(
            lambda source: cls.from_pretrained(source, revision=revision, **{_dtype_kwarg(): dtype}, **kwargs),
            model_id, model_name=name, folder_hint=folder_hint)


#: The file whose presence says a diffusers pipeline folder or repo is there.
PIPELINE_INDEX = "model_index.json"


def check_weights_before_loading(cfg: Any) -> None:
    """The missing-weights line of :func:`build_pipeline`, found before any model loads (a cache
    look-up or one metadata request per model, instead of minutes of loading first): the video
    model, the two estimators and, where the guidance decodes with it, the tiny decoder.

    Raises:
        WeightsNotFoundError: one line naming the repo id, the config key and how to pass a local
            path.
        ValueError: the tiny decoder is asked for but not named.
    """
    from ..estimators.ufm import UFM
    from ..estimators.vggt import VGGT

    checks = [("model.id", cfg.model.id, "CogVideoX", (PIPELINE_INDEX,), cfg.model.revision),
              ("estimators.geometry", cfg.estimators.geometry, VGGT.model_name, VGGT.checkpoint_files, None),
              ("estimators.flow", cfg.estimators.flow, UFM.model_name, ("config.json",), None)]
    for key, source, name, filenames, revision in checks:
        if source == TINY_RANDOM:
            continue
        try:
            check_weights_available(source, filenames, model_name=name, revision=revision)
        except WeightsNotFoundError as err:
            raise with_config_key(err, key, f"/path/to/{Path(str(source)).name}") from None
    if wants_tiny_decoder(cfg):
        check_tiny_decoder_source(cfg)


def load_video_pipeline(cfg: Any, geometry_estimator=None, flow_estimator=None,
                        components: dict[str, Any] | None = None):
    """The GeCoCogVideoXPipeline of ``cfg.model`` on its device (estimators attached, the scheduler
    of ``sampling.scheduler``: DDIM in the presets, see :func:`choose_scheduler`).

    ``components`` (the pipeline's models, e.g. :func:`geco_guide.tiny.tiny_cogvideox_components`)
    are used instead of loading ``cfg.model.id``; ``model.id=tiny-random`` requires them, since
    the tiny models are built above this floor.

    Raises:
        WeightsNotFoundError: one line naming the model id and how to pass a local folder, when
            the weights are neither in a local folder nor in the hub cache / reachable.
    """
    from .pipeline_cogvideox import GeCoCogVideoXPipeline

    dtype = getattr(torch, cfg.model.dtype)
    device = resolve_device(cfg.model.device)
    model_id = cfg.model.id
    extra = dict(geometry_estimator=geometry_estimator, flow_estimator=flow_estimator, guidance_config=cfg.guidance)
    if components is not None:
        pipe = GeCoCogVideoXPipeline(**components, **extra)
        if dtype != torch.float32:
            for model in (pipe.text_encoder, pipe.transformer, pipe.vae):
                cast_model(model, dtype)
    elif model_id == TINY_RANDOM:
        raise ValueError(f"model.id={TINY_RANDOM} needs its components (geco_guide.tiny.tiny_cogvideox_components)")
    else:
        pipe = pipeline_from_pretrained(
            GeCoCogVideoXPipeline, model_id, "CogVideoX", f"model.id=/path/to/{model_id.split('/')[-1]}",
            dtype=dtype, revision=cfg.model.revision, **extra,
        )
    pipe.run_options = cfg.run
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


def load_dynamic_masks(cfg: Any) -> Any:
    """The mask source of ``guidance.dynamic`` (:func:`~.dynamic.load_mask_source`), on
    ``model.device``: ``None`` without guidance or without ``guidance.dynamic``; a text segmenter
    loads ``estimators.segmenter`` in ``estimators.dtype`` (``tiny-random``: seeded with
    ``estimators.init_seed``).

    Raises:
        WeightsNotFoundError: one line naming the segmenter's repo id, ``estimators.segmenter``
            and how to pass a local folder.
    """
    from .dynamic import load_mask_source

    if not cfg.guidance.enabled:
        return None
    return load_mask_source(cfg.guidance, cfg.estimators.segmenter, device=resolve_device(cfg.model.device),
                            dtype=getattr(torch, cfg.estimators.dtype), seed=cfg.estimators.init_seed)


def wants_tiny_decoder(cfg: Any) -> bool:
    """Whether the config's guidance decodes its anchor frames with the tiny decoder."""
    return bool(cfg.guidance.enabled and cfg.guidance.decoder == "tiny")


def check_tiny_decoder_source(cfg: Any) -> None:
    """One line, before any model loads, when the tiny decoder's weights are not named or not there.

    Raises:
        ValueError: ``estimators.tiny_decoder`` is not set.
        WeightsNotFoundError: it names a checkpoint file that does not exist.
    """
    from ..estimators.tiny_decoder import WEIGHTS_URL

    source = cfg.estimators.tiny_decoder
    if not source:
        raise ValueError(
            f"guidance.decoder=tiny needs the tiny decoder's weights: download taecvx.pth from {WEIGHTS_URL} and "
            "set estimators.tiny_decoder=/path/to/taecvx.pth (or use guidance.decoder=vae)"
        )
    path = Path(source).expanduser()
    if source != TINY_RANDOM and path.suffix.lower() in CHECKPOINT_SUFFIXES and not path.is_file():
        raise WeightsNotFoundError(
            f"estimators.tiny_decoder={source}: no such file (download taecvx.pth from {WEIGHTS_URL} and set "
            "estimators.tiny_decoder=/path/to/taecvx.pth)"
        )


def load_tiny_decoder(cfg: Any, family: str = "cogvideox") -> Any:
    """The tiny decoder of ``estimators.tiny_decoder`` (a file, a folder or a hub id; ``tiny-random``
    is built by :func:`build_pipeline`, which knows the VAE's latent channels) for the video
    ``family`` (:data:`TINY_DECODER_VARIANTS`), in ``model.dtype`` on the CPU (the pipeline moves
    it). A file must be that family's variant.

    Raises:
        WeightsNotFoundError: one line naming the source and the config key.
        ValueError: the family has no tiny decoder, or the file is the tiny decoder of another model.
    """
    from ..estimators.tiny_decoder import TinyDecoder

    check_tiny_decoder_source(cfg)
    variant = check_tiny_decoder_family(cfg.estimators.tiny_decoder, family)
    try:
        return TinyDecoder.from_pretrained(cfg.estimators.tiny_decoder, variant.name, dtype=getattr(torch, cfg.model.dtype))
    except WeightsNotFoundError as err:
        raise with_config_key(err, "estimators.tiny_decoder", f"/path/to/{variant.checkpoint}.pth") from None


#: The tiny decoder variant that decodes each video family's latents (the families of the
#: GeCo-Eval model registry); LTX-Video has none.
TINY_DECODER_VARIANTS = {"cogvideox": "cogvideox", "cogvideox1.5": "cogvideox", "wan": "wan2.1",
                         "hunyuan": "hunyuanvideo"}
#: How messages name the families.
FAMILY_NAMES = {"cogvideox": "CogVideoX", "cogvideox1.5": "CogVideoX 1.5", "wan": "Wan", "hunyuan": "HunyuanVideo",
                "ltx": "LTX-Video"}
#: The families whose VAE ``run.decode_layout=channels_last`` is written for (the CogVideoX VAE).
CHANNELS_LAST_FAMILIES = ("cogvideox", "cogvideox1.5")


def check_tiny_decoder_family(source: str, family: str) -> Any:
    """The :class:`~geco_guide.estimators.tiny_decoder.TinyDecoderVariant` of ``family``; ValueError
    (one line) when the family has none or the checkpoint file ``source`` is named for another
    model's (a name that tells no variant is left to the strict load, which checks the keys)."""
    from ..estimators.tiny_decoder import resolve_variant, variant_from_filename

    if family not in TINY_DECODER_VARIANTS:
        raise ValueError(f"guidance.decoder=tiny: there is no tiny decoder for {FAMILY_NAMES.get(family, family)} "
                         "latents; use guidance.decoder=vae")
    variant = resolve_variant(TINY_DECODER_VARIANTS[family])
    path = Path(source).expanduser()
    try:
        named = variant_from_filename(path) if source != TINY_RANDOM and path.is_file() else None
    except ValueError:
        named = None
    if named is not None and named.name != variant.name:
        raise ValueError(f"estimators.tiny_decoder={source} is the tiny decoder of {named.models}; "
                         f"{FAMILY_NAMES.get(family, family)} needs {variant.checkpoint}.pth")
    return variant


def check_guidance_before_loading(cfg: Any, *, model_id: str, num_frames: int, height: int, width: int,
                                  num_steps: int, family: str = "cogvideox") -> Any:
    """Every check of the config's guidance that needs no model, for a command to make before any
    model loads and before it writes anything: the loss, the schedule for ``num_steps``, the decode
    layout for the ``family``'s VAE, the tiny decoder's weights (named, there, of this family) and a
    memory plan that fits (:func:`~.memory_plan.plan_before_loading` for a ``num_frames x height x
    width`` video of ``model_id`` on ``model.device``). Returns the predicted plan (None without
    guidance).

    Raises:
        ValueError: one line naming the option.
        WeightsNotFoundError: ``estimators.tiny_decoder`` names a file that does not exist.
    """
    guidance, run = cfg.guidance, cfg.run
    if guidance.enabled:
        guidance.check_loss()
        guidance.schedule(num_steps)
        if run.decode_layout != "default" and family not in CHANNELS_LAST_FAMILIES:
            raise ValueError(f"run.decode_layout={run.decode_layout} is written for the CogVideoX VAE, not "
                             f"{FAMILY_NAMES.get(family, family)}'s: use run.decode_layout=default")
        if guidance.decoder == "tiny":
            check_tiny_decoder_source(cfg)
            check_tiny_decoder_family(cfg.estimators.tiny_decoder, family)
    return plan_before_loading(guidance, run, model_id, num_frames, height, width, cfg.model.device)


def tiny_decoder_note(decoder: Any, init_seed: int) -> str:
    """Which tiny decoder this is, for the run's record: its variant and the file it came from."""
    origin = decoder.checkpoint_file or f"{TINY_RANDOM}(seed={init_seed})"
    return f"TinyDecoder({decoder.variant.name}) from {origin}"


def decoder_note(pipe: Any, cfg: Any) -> str:
    """What decodes the loss' anchor frames, for the run's record: the VAE, or the tiny decoder
    (:func:`tiny_decoder_note`)."""
    decoder = getattr(pipe, "guidance_decoder", None)
    if cfg.guidance.decoder != "tiny" or decoder is None:
        return "vae (the model's own)"
    return tiny_decoder_note(decoder, cfg.estimators.init_seed)


def build_pipeline(cfg: Any, components: dict[str, Any] | None = None, *, tiny_decoder: bool | None = None):
    """Estimators, tiny decoder and video pipeline of a config, cheapest failure first.

    ``tiny_decoder``: attach ``estimators.tiny_decoder`` as the pipeline's ``guidance_decoder``;
    default: when the guidance uses it (:func:`wants_tiny_decoder`). A checkpoint file loads
    before the video model; ``tiny-random`` is built after it, for its VAE's latent channels.
    ``pipe.geco_decoder_note`` says what decodes the anchor frames (:func:`decoder_note`);
    ``pipe.estimators`` is the loaded :class:`~geco_guide.estimators.Estimators`, whose models are
    the pipeline's ``geometry_estimator`` / ``flow_estimator`` components.
    """
    tiny_decoder = wants_tiny_decoder(cfg) if tiny_decoder is None else tiny_decoder
    if tiny_decoder:
        check_tiny_decoder_source(cfg)
    estimators = load_estimators(cfg.estimators, resolve_device(cfg.model.device))
    tiny_random = cfg.estimators.tiny_decoder == TINY_RANDOM
    decoder = load_tiny_decoder(cfg) if tiny_decoder and not tiny_random else None
    pipe = load_video_pipeline(cfg, estimators.geometry, estimators.flow, components=components)
    if tiny_decoder:
        if tiny_random:
            decoder = tiny_random_decoder("cogvideox", cfg.estimators.init_seed, pipe.vae.config.latent_channels)
        pipe.register_modules(guidance_decoder=decoder.to(device=pipe.device, dtype=getattr(torch, cfg.model.dtype)))
    pipe.geco_decoder_note = decoder_note(pipe, cfg)
    return pipe
