"""Loading video pipelines: the config's ``model`` section (:class:`ModelConfig`: a registry
model, its weights as a hub id or a local folder, the dtype and device), with a clear one-line
error when the weights are not there; the scheduler that ``sampling.scheduler`` names; the tiny
decoder of ``guidance.decoder=tiny`` (``estimators.tiny_decoder``); the checks a command makes
before anything loads.

Each function takes the config section it uses, never the whole config (the config module sits
above the sampler). diffusers is imported inside the functions, so importing this module stays
light.
"""

from __future__ import annotations

import contextlib
import logging
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Optional

import torch

from ..estimators import (
    TINY_RANDOM,
    EstimatorsConfig,
    tiny_random_decoder,
    with_config_key,
)
from ..families import DEFAULT_MODEL, VideoModel, model_named
from ..estimators.loading import (
    CHECKPOINT_SUFFIXES,
    WeightsNotFoundError,
    pretrained_or_one_line,
    quiet_hub_retries,
)
from ..io.devices import resolve_device
from .config import GuidanceConfig
from .memory_plan import PlanChoice, plan_before_loading
from .run_options import RunOptions
from .search import SearchConfig, check_search_before_loading

__all__ = ["CHECKPOINT_SCHEDULER", "PIPELINE_INDEX", "SCHEDULERS", "LoadedPipeline", "ModelConfig", "cast_model", "check_before_loading",
           "check_guidance_before_loading", "check_tiny_decoder", "choose_scheduler", "load_tiny_decoder",
           "load_video_pipeline", "missing_weights", "pipeline_from_pretrained", "quiet_hub_logs",
           "uses_tiny_decoder", "warn_idle_options"]

logger = logging.getLogger(__name__)


@dataclass
class ModelConfig:
    """The config's ``model`` section: which registry model (:mod:`geco_guide.families`), its
    weights, and where and how they run.

    Attributes:
        name: the registry name (``--model NAME``); its call defaults fill ``sampling``.
        id: the weights: a hub id or a local folder (``save_pretrained`` layout), or
            ``tiny-random`` (the family's tiny random stand-in, offline); ``None``: the
            registry's hub id.
        revision: of the hub id.
        dtype: of the video model's weights.
        device: ``auto`` (cuda if there is one, else cpu), ``cpu``, ``cuda[:N]`` or ``mps``.
        init_seed: the weights' seed of tiny random models.
        vae_tiling, vae_slicing: the VAE's own tiling and slicing of the final decode.
    """

    name: str = DEFAULT_MODEL
    id: Optional[str] = None
    revision: Optional[str] = None
    dtype: str = "bfloat16"
    device: str = "auto"
    init_seed: int = 0
    vae_tiling: bool = False
    vae_slicing: bool = False

    @property
    def video_model(self) -> VideoModel:
        """The registry entry of :attr:`name`."""
        return model_named(self.name)

    @property
    def source(self) -> str:
        """Where the weights come from: :attr:`id`, else the registry's hub id."""
        return self.id or self.video_model.hub_id


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


def missing_weights(model: ModelConfig, estimators: EstimatorsConfig, *, tiny_decoder: bool = False,
                    segmenter: bool = False) -> None:
    """Every model's weights a run needs, looked up before any model loads (a cache look-up or one
    metadata request each, instead of minutes of loading first): the video model, the geometry and
    flow estimators, and where they are used the segmenter and the tiny decoder. All that are
    missing are named in one line, each with its config key.

    Raises:
        WeightsNotFoundError: one line naming every missing model: its repo id, the config key and
            how to pass a local path.
        ValueError: the tiny decoder is asked for but the model has none, or it is not named.
    """
    from ..estimators import check_weights
    from ..estimators.loading import WeightsSource

    rows = [] if model.source == TINY_RANDOM else [
        WeightsSource("model.id", model.source, model.name, (PIPELINE_INDEX,), model.revision)]
    if tiny_decoder:
        check_tiny_decoder_source(estimators, model.video_model)
    check_weights(estimators, segmenter=segmenter, extra=rows)


@dataclass
class LoadedPipeline:
    """A loaded video pipeline and what its loading decided.

    Attributes:
        pipe: the pipeline, on the model's device: a ``GeCoCogVideoXPipeline`` for the models
            guided by the paper's loop, the stock diffusers pipeline for the others.
        model: its registry entry.
        scheduler: which scheduler it samples with and why (:func:`choose_scheduler`).
    """

    pipe: Any
    model: VideoModel
    scheduler: str


def load_video_pipeline(model: ModelConfig, scheduler: str | None = None,
                        components: dict[str, Any] | None = None) -> LoadedPipeline:
    """The pipeline of ``model`` (its registry entry's class; ``GeCoCogVideoXPipeline`` for the
    models the paper's loop guides) in ``model.dtype`` on ``model.device``, with the scheduler
    ``scheduler`` names (:func:`choose_scheduler`).

    ``components`` (the pipeline's models, e.g. of :func:`geco_guide.tiny.tiny_video_components`)
    are used instead of loading ``model.source``; ``tiny-random`` requires them, since the tiny
    models are built above this floor.

    Raises:
        WeightsNotFoundError: one line naming the model id, ``model.id`` and how to pass a local
            folder, when the weights are neither in a local folder nor in the hub cache / reachable.
    """
    import diffusers

    entry = model.video_model
    if entry.guided_by == "pipeline":
        from .pipeline_cogvideox import GeCoCogVideoXPipeline as cls
    else:
        cls = getattr(diffusers, entry.pipeline)
    dtype = getattr(torch, model.dtype)
    if components is not None:
        pipe = cls(**components)
        if dtype != torch.float32:
            for component in pipe.components.values():
                if isinstance(component, torch.nn.Module):
                    cast_model(component, dtype)
    elif model.source == TINY_RANDOM:
        raise ValueError(f"model.id={TINY_RANDOM} needs its components (geco_guide.tiny.tiny_video_components)")
    else:
        folder = model.source.rstrip("/").split("/")[-1]
        pipe = pipeline_from_pretrained(cls, model.source, entry.name, f"model.id=/path/to/{folder}", dtype=dtype,
                                        revision=model.revision)
    note = choose_scheduler(pipe, scheduler, entry)
    if model.vae_tiling and hasattr(pipe.vae, "enable_tiling"):
        pipe.vae.enable_tiling()
    if model.vae_slicing and hasattr(pipe.vae, "enable_slicing"):
        pipe.vae.enable_slicing()
    pipe.set_progress_bar_config(desc=entry.name)
    return LoadedPipeline(pipe.to(resolve_device(model.device)), entry, note)


#: ``sampling.scheduler`` -> the scheduler class it builds from the checkpoint's scheduler config
#: (CogVideoX's: the paper samples with deterministic DDIM, and CogVideoX-5B ships DPM).
SCHEDULERS = {"ddim": "CogVideoXDDIMScheduler", "dpm": "CogVideoXDPMScheduler"}
#: ``sampling.scheduler`` that keeps the checkpoint's own scheduler (the default of every family
#: but CogVideoX's, whose default is the paper's DDIM)
CHECKPOINT_SCHEDULER = "checkpoint"


def choose_scheduler(pipe: Any, name: str | None, model: VideoModel) -> str:
    """Give ``pipe`` the scheduler ``sampling.scheduler`` names; returns the sidecar's note.

    ``ddim`` / ``dpm`` (CogVideoX models only): CogVideoX's DDIM / DPM scheduler built from the
    checkpoint's scheduler config; ``checkpoint`` or ``None``: the checkpoint's own scheduler,
    untouched. The pipeline itself never replaces a scheduler.
    """
    shipped = type(pipe.scheduler).__name__
    if name in (None, CHECKPOINT_SCHEDULER):
        return f"{shipped} (the checkpoint's)"
    if name not in SCHEDULERS:
        raise ValueError(f"sampling.scheduler must be one of {sorted(SCHEDULERS)}, {CHECKPOINT_SCHEDULER} or null, "
                         f"got {name!r}")
    if not model.cogvideox_vae:
        raise ValueError(f"sampling.scheduler={name} is CogVideoX's; {model.name} samples with its own scheduler: "
                         f"use sampling.scheduler={CHECKPOINT_SCHEDULER}")
    import diffusers

    cls = getattr(diffusers, SCHEDULERS[name])
    if type(pipe.scheduler) is cls:
        return f"{cls.__name__} (sampling.scheduler={name}, the checkpoint's)"
    pipe.scheduler = cls.from_config(pipe.scheduler.config)
    return f"{cls.__name__} (sampling.scheduler={name}, built from the checkpoint's {shipped} config)"


def uses_tiny_decoder(guidance: GuidanceConfig, searching: bool = False) -> bool:
    """Whether the guidance (or a search, ``searching``: it decodes the same anchors) decodes its
    anchor frames with the tiny decoder."""
    return bool((guidance.enabled or searching) and guidance.decoder == "tiny")


def check_tiny_decoder_source(estimators: EstimatorsConfig, model: VideoModel) -> Any:
    """The :class:`~geco_guide.estimators.tiny_decoder.TinyDecoderVariant` of ``model``'s latents,
    once its weights are named and there: one line, before any model loads, otherwise, naming the
    file of ``model``'s variant.

    Raises:
        ValueError: ``model`` has no tiny decoder, or ``estimators.tiny_decoder`` is not set.
        WeightsNotFoundError: it names a checkpoint file that does not exist.
    """
    from ..estimators.tiny_decoder import WEIGHTS_URL, resolve_variant

    if model.tiny_decoder is None:
        raise ValueError(f"guidance.decoder=tiny: there is no tiny decoder for {model.name}'s latents; use "
                         "guidance.decoder=vae")
    variant = resolve_variant(model.tiny_decoder)
    file = f"{variant.checkpoint}.pth"
    source = estimators.tiny_decoder
    if not source:
        raise ValueError(f"guidance.decoder=tiny needs the tiny decoder's weights: download {file} (for {model.name}) "
                         f"from {WEIGHTS_URL} and set estimators.tiny_decoder=/path/to/{file} (or use "
                         "guidance.decoder=vae)")
    path = Path(source).expanduser()
    if source != TINY_RANDOM and path.suffix.lower() in CHECKPOINT_SUFFIXES and not path.is_file():
        raise WeightsNotFoundError(f"estimators.tiny_decoder={source}: no such file (download {file} from {WEIGHTS_URL} "
                                   f"and set estimators.tiny_decoder=/path/to/{file})")
    return variant


def check_tiny_decoder(estimators: EstimatorsConfig, model: VideoModel) -> Any:
    """The :class:`~geco_guide.estimators.tiny_decoder.TinyDecoderVariant` of ``model``'s latents;
    ValueError (one line) when the model has none, its weights are not named
    (:func:`check_tiny_decoder_source`), or the checkpoint file of ``estimators.tiny_decoder`` is
    named for another model's (a name that tells no variant is left to the strict load, which
    checks the keys)."""
    from ..estimators.tiny_decoder import variant_from_filename

    variant = check_tiny_decoder_source(estimators, model)
    source = estimators.tiny_decoder
    path = Path(source).expanduser()
    try:
        named = variant_from_filename(path) if source != TINY_RANDOM and path.is_file() else None
    except ValueError:
        named = None
    if named is not None and named.name != variant.name:
        raise ValueError(f"estimators.tiny_decoder={source} is the tiny decoder of {named.models}; "
                         f"{model.name} needs {variant.checkpoint}.pth")
    return variant


def load_tiny_decoder(estimators: EstimatorsConfig, model: VideoModel, latent_channels: int,
                      dtype: torch.dtype) -> Any:
    """The tiny decoder of ``estimators.tiny_decoder`` for ``model``'s latents (a file, a folder or
    a hub id; ``tiny-random``: a random one of ``latent_channels``, the VAE's, seeded with
    ``estimators.init_seed``), frozen, in ``dtype`` on the CPU (the caller moves it), with the
    ``geco_estimator_id`` its records name it by.

    Raises:
        WeightsNotFoundError: one line naming the source and the config key.
        ValueError: the model has no tiny decoder, or the file is the tiny decoder of another model.
    """
    from ..estimators.tiny_decoder import TinyDecoder

    variant = check_tiny_decoder(estimators, model)
    source = estimators.tiny_decoder
    if source == TINY_RANDOM:
        decoder = tiny_random_decoder(variant.name, estimators.init_seed, latent_channels).to(dtype=dtype)
        decoder.geco_estimator_id = f"{TINY_RANDOM}(seed={estimators.init_seed})"
        return decoder
    try:
        return TinyDecoder.from_pretrained(source, variant.name, dtype=dtype)
    except WeightsNotFoundError as err:
        raise with_config_key(err, "estimators.tiny_decoder", f"/path/to/{variant.checkpoint}.pth") from None


def check_guidance_before_loading(guidance: GuidanceConfig, run: RunOptions, estimators: EstimatorsConfig,
                                  model: VideoModel, *, model_id: str, num_frames: int, height: int, width: int,
                                  num_steps: int, device: str) -> PlanChoice | None:
    """Every check of the guidance that needs no model, for a command to make before any model
    loads and before it writes anything: the loss, the anchors and the schedule for the call, the
    decode layout for the model's VAE, the tiny decoder's weights (named, there, of this model),
    and a memory plan that fits (:func:`~.memory_plan.plan_before_loading` for a
    ``num_frames x height x width`` video of ``model_id`` on ``device``). Returns the predicted
    plan (``None`` without guidance).

    Raises:
        ValueError: one line naming the option.
        WeightsNotFoundError: ``estimators.tiny_decoder`` names a file that does not exist.
    """
    if guidance.enabled:
        guidance.check_loss()
        guidance.schedule(num_steps)
        guidance.anchor_chunks(num_frames, model.temporal_compression)
        if run.split_cfg and model.guided_by != "pipeline":
            raise ValueError(f"run.split_cfg splits the denoiser calls of GeCoCogVideoXPipeline; {model.name} is "
                             "guided by the hooks, which leave its pipeline's own denoiser calls as they are: use "
                             "run.split_cfg=false")
        if run.decode_layout != "default" and not model.cogvideox_vae:
            raise ValueError(f"run.decode_layout={run.decode_layout} is written for the CogVideoX VAE, not "
                             f"{model.name}'s: use run.decode_layout=default")
        if guidance.decoder == "tiny":
            check_tiny_decoder(estimators, model)
    return plan_before_loading(guidance, run, model_id, num_frames, height, width, device)


def warn_idle_options(model: VideoModel, sampling: Any, guidance: GuidanceConfig, run: RunOptions,
                      search: SearchConfig | None = None) -> None:
    """One warning line for each option set that cannot act on the run (it changes neither the
    frames nor the video's name): ``guidance.dynamic`` without guidance or search, ``run.split_cfg``
    without guidance or without CFG (on a model the hooks guide, a guided call refuses it before
    loading), ``run.particle_batch`` without a search."""
    searching = search is not None and search.enabled
    if guidance.dynamic is not None and not guidance.enabled and not searching:
        logger.warning("guidance.dynamic=%r does nothing without guidance (--no-guidance): nothing is masked",
                       guidance.dynamic)
    if run.particle_batch is not None and not searching:
        logger.warning("run.particle_batch=%d does nothing without a search (search.particles): one video is one "
                       "batch", run.particle_batch)
    if run.split_cfg and guidance.enabled and sampling.guidance_scale <= 1.0:
        logger.warning("run.split_cfg does nothing without CFG (sampling.guidance_scale <= 1): the frames are those "
                       "of one call")
    elif run.split_cfg and not guidance.enabled:
        logger.warning("run.split_cfg does nothing without guidance: the frames are those of one call")


def check_before_loading(model: ModelConfig, sampling: Any, guidance: GuidanceConfig, run: RunOptions,
                         estimators: EstimatorsConfig, *, weights: bool = True,
                         search: SearchConfig | None = None) -> torch.device:
    """Every check of a run that its config alone can fail, in one pass before anything loads: the
    device, then with ``weights`` every model's weights (all missing ones named at once: the
    problem a fresh machine has, named before what its memory could not hold), the guidance against
    the model (loss, schedule, anchors, decode layout, tiny decoder, a memory plan that fits),
    options that cannot act (a warning each), the devices of ``run.devices``, and the video's size
    against the device's memory; with a ``search`` its particles against the memory
    (:func:`~.search.check_search_before_loading`). Returns the device ``model.device`` stands for
    (``auto`` resolved), what the loaders and the sidecar then use.

    Raises:
        ValueError: one line naming the option.
        WeightsNotFoundError: one line naming every missing model and how to pass a local path.
    """
    from ..io.devices import check_device, check_memory_fits
    from .multi_device import resolve_devices

    entry = model.video_model
    device = check_device(model.device)
    searching = search is not None and search.enabled
    if weights:
        missing_weights(model, estimators, tiny_decoder=uses_tiny_decoder(guidance, searching),
                        segmenter=(guidance.enabled or searching) and guidance.subjects is not None)
    check_guidance_before_loading(guidance, run, estimators, entry, model_id=model.source,
                                  num_frames=sampling.num_frames, height=sampling.height, width=sampling.width,
                                  num_steps=sampling.num_inference_steps, device=str(device))
    warn_idle_options(entry, sampling, guidance, run, search)
    if guidance.enabled or searching:
        resolve_devices(run.devices)  # a device this machine lacks: one line before loading
    # the decoded video alone, in float32, is a lower bound of the run's peak: a refusal is certain
    check_memory_fits(sampling.num_frames * 3 * sampling.height * sampling.width * 4, device,
                      f"a {sampling.num_frames}-frame {sampling.height}x{sampling.width} video "
                      "(sampling.num_frames/height/width)")
    if searching:
        if not guidance.enabled:  # the search decodes and scores guidance's anchors
            guidance.anchor_chunks(sampling.num_frames, entry.temporal_compression)
            if guidance.decoder == "tiny":
                check_tiny_decoder(estimators, entry)
        check_search_before_loading(search, guidance, run, model_id=model.source, frames=sampling.num_frames,
                                    height=sampling.height, width=sampling.width, device=str(device))
    return device
