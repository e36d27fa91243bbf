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
import os
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Optional

import torch

from ...estimators import (
    TINY_RANDOM,
    EstimatorsConfig,
    tiny_random_decoder,
    with_config_key,
)
from ...estimators.loading import (
    CHECKPOINT_SUFFIXES,
    WeightsNotFoundError,
    pretrained_or_one_line,
    quiet_hub_retries,
    short_reason,
)
from ...families import DEFAULT_MODEL, VideoModel, model_named, scheduler_names
from ...io.devices import resolve_device
from ..algorithm.config import GuidanceConfig
from ..diffusers_private import dtype_keyword, keeps_in_fp32
from ..running.context_parallel import check_context_parallel_before_loading, context_parallel_degree
from ..running.memory_plan import plan_before_loading
from ..running.run_options import RunOptions
from ..search.particle_search import SearchConfig, check_search_before_loading
from .adapters import adapter_for_class
from .model_folder import PIPELINE_INDEX, ModelFolderError, check_cached_model, check_model_folder

__all__ = ["CHECKPOINT_SCHEDULER", "PIPELINE_INDEX", "SCHEDULERS", "LoadedPipeline", "ModelConfig", "cast_model", "check_before_loading",
           "check_guidance_before_loading", "check_tiny_decoder", "load_tiny_decoder", "tiny_decoder_id", "check_model_source",
           "local_folder",
           "load_video_pipeline", "missing_weights", "pipeline_from_pretrained", "quiet_hub_logs",
           "scheduler_class", "uses_tiny_decoder"]

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
    if keeps_in_fp32(model):
        return model.to(dtype)
    return torch.nn.Module.to(model, dtype)


def pipeline_from_pretrained(cls, model_id: str, name: str, folder_hint: str, *, dtype: torch.dtype,
                             revision: str | None = None, **kwargs: Any):
    """``cls.from_pretrained`` of a hub id or a local folder, in ``dtype``.

    Raises:
        WeightsNotFoundError: one line naming ``model_id``, the ``hf download`` command and
            ``folder_hint`` (how to pass a local folder), when the folder does not exist or the
            weights are neither in the hub cache nor reachable.
        ModelFolderError: one line naming the folder and the reader's error, where a local folder
            does not load (what is wrong is the folder's, not the hub's).
    """
    folder = local_folder(model_id)
    with quiet_hub_logs():
        if folder is not None:
            try:
                return cls.from_pretrained(str(folder), **{dtype_keyword(): dtype}, **kwargs)
            except OSError as err:
                raise ModelFolderError(f"{name}: the folder {folder} does not load: {short_reason(err)}") from None
        return pretrained_or_one_line(
            lambda source: cls.from_pretrained(source, revision=revision, **{dtype_keyword(): dtype}, **kwargs),
            model_id, model_name=name, folder_hint=folder_hint)


def check_model_source(model: ModelConfig) -> None:
    """``model.id``, where it is not the registry's hub id, checked to be the registry model's before
    it loads: a local folder whole and the model's (:func:`~.model_folder.check_model_folder`), a
    hub id by its configs in the hub cache, where they are there (nothing is downloaded).

    Raises:
        ModelFolderError: one line naming the file, or both models.
    """
    entry = model.video_model
    if model.source in (TINY_RANDOM, entry.hub_id, *entry.hub_aliases):
        return
    folder = local_folder(model.source)
    if folder is not None:
        check_model_folder(entry, folder)
        return
    check_cached_model(entry, model.source, model.revision)


def local_folder(source: str) -> Path | None:
    """``source`` as a local folder, ``None`` for a hub id (or a path that is not there)."""
    path = Path(source).expanduser()
    return path if path.is_dir() else None


def missing_weights(model: ModelConfig, estimators: EstimatorsConfig, *, tiny_decoder: bool = False,
                    segmenter: bool = False) -> None:
    """Every model's weights a run needs, looked up before any model loads (a cache look-up or one
    metadata request each, instead of minutes of loading first): the video model, the geometry and
    flow estimators, and where they are used the segmenter and the tiny decoder. All that are
    missing are named in one line, each with its config key. A local folder of the video model is
    then checked whole and the registry model's (:func:`~.model_folder.check_model_folder`).

    Raises:
        WeightsNotFoundError: one line naming every missing model: its repo id, the config key and
            how to pass a local path.
        ValueError: the tiny decoder is asked for but the model has none, it is not named, or its
            file is another model's (:func:`check_tiny_decoder`).
        ModelFolderError: the video model's local folder is damaged or another model's.
    """
    from ...estimators import check_weights
    from ...estimators.loading import WeightsSource

    rows = [] if model.source == TINY_RANDOM else [
        WeightsSource("model.id", model.source, model.name, (PIPELINE_INDEX,), model.revision)]
    if tiny_decoder:
        check_tiny_decoder(estimators, model.video_model)
    check_weights(estimators, segmenter=segmenter, extra=rows)
    check_model_source(model)


@dataclass
class LoadedPipeline:
    """A loaded video pipeline and what its loading decided.

    Attributes:
        pipe: the pipeline, on the model's device: a ``GeCoCogVideoXPipeline`` for the models
            guided by the paper's loop, the stock diffusers pipeline for the others.
        model: its registry entry.
        scheduler: which scheduler it samples with and why (:func:`scheduler_class`).
        call_extras: what its calls need beyond the config's sampling (a tiny stand-in's:
            :func:`geco_guide.tiny.tiny_call_extras`).
    """

    pipe: Any
    model: VideoModel
    scheduler: str
    call_extras: dict[str, Any] = field(default_factory=dict)


def load_video_pipeline(model: ModelConfig, scheduler: str | None = None,
                        components: dict[str, Any] | None = None) -> LoadedPipeline:
    """The pipeline of ``model`` (its registry entry's class; ``GeCoCogVideoXPipeline`` for the
    models the paper's loop guides) in ``model.dtype`` on ``model.device``, with the scheduler
    ``scheduler`` names (:func:`scheduler_class`).

    ``components`` (the pipeline's models, e.g. of :func:`geco_guide.tiny.tiny_video_components`)
    are used instead of loading ``model.source``; ``tiny-random`` requires them, since the tiny
    models are built above this floor.

    Raises:
        ValueError: (one line, before anything loads) a ``scheduler`` the model has not.
        WeightsNotFoundError: one line naming the model id, ``model.id`` and how to pass a local
            folder, when the weights are neither in a local folder nor in the hub cache / reachable.
        ModelFolderError: a local folder that is damaged or another model's, before it loads
            (:func:`~.model_folder.check_model_folder`).
    """
    import diffusers

    entry = model.video_model
    if entry.guided_by == "pipeline":
        from .pipeline_cogvideox import GeCoCogVideoXPipeline as cls
    else:
        cls = getattr(diffusers, entry.pipeline)
    scheduler_cls = scheduler_class(scheduler, entry)
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
        folder = local_folder(model.source)
        if folder is not None:
            check_model_folder(entry, folder)
        hint = f"model.id=/path/to/{model.source.rstrip('/').split('/')[-1]}"
        pipe = pipeline_from_pretrained(cls, model.source, entry.name, hint, dtype=dtype, revision=model.revision)
    shipped = type(pipe.scheduler).__name__
    if scheduler_cls is None:
        note = f"{shipped} (the checkpoint's)"
    elif type(pipe.scheduler) is scheduler_cls:
        note = f"{shipped} (sampling.scheduler={scheduler}, the checkpoint's)"
    else:
        pipe.scheduler = scheduler_cls.from_config(pipe.scheduler.config)
        note = (f"{scheduler_cls.__name__} (sampling.scheduler={scheduler}, built from the checkpoint's {shipped} "
                "config)")
    if model.vae_tiling and hasattr(pipe.vae, "enable_tiling"):
        pipe.vae.enable_tiling()
    if model.vae_slicing and hasattr(pipe.vae, "enable_slicing"):
        pipe.vae.enable_slicing()
    pipe.set_progress_bar_config(desc=entry.name)
    return LoadedPipeline(pipe.to(resolve_device(model.device)), entry, note)


#: The ``sampling.scheduler`` names some model samples with besides its checkpoint's own (each
#: registry entry's ``schedulers`` names the classes they build for it).
SCHEDULERS = scheduler_names()
#: ``sampling.scheduler`` that keeps the checkpoint's own scheduler (the default of every family
#: but CogVideoX's, whose default is the paper's DDIM)
CHECKPOINT_SCHEDULER = "checkpoint"


def scheduler_class(name: str | None, model: VideoModel) -> type | None:
    """The scheduler class ``sampling.scheduler`` names for ``model``, checked before its pipeline
    loads: a name of the model's registry ``schedulers`` (CogVideoX's ``ddim`` / ``dpm``), its class
    built from the checkpoint's scheduler config once the pipeline is loaded; ``checkpoint`` or ``None``:
    ``None``, the checkpoint's own scheduler, untouched. The pipeline itself never replaces a
    scheduler.

    Raises:
        ValueError: (one line) an unknown name, or another family's scheduler.
    """
    if name in (None, CHECKPOINT_SCHEDULER):
        return None
    if name not in SCHEDULERS:
        raise ValueError(f"sampling.scheduler must be one of {sorted(SCHEDULERS)}, {CHECKPOINT_SCHEDULER} or null, "
                         f"got {name!r}")
    if name not in model.schedulers:
        raise ValueError(f"sampling.scheduler={name} is another family's; {model.name} samples with its own scheduler: "
                         f"use sampling.scheduler={CHECKPOINT_SCHEDULER}")
    import diffusers

    return getattr(diffusers, model.schedulers[name])


def uses_tiny_decoder(guidance: GuidanceConfig, searching: bool = False) -> bool:
    """Whether the guidance (or a search, ``searching``: it decodes the same anchors) decodes its
    anchor frames with the tiny decoder."""
    return bool((guidance.enabled or searching) and guidance.decoder == "tiny")


def check_tiny_decoder(estimators: EstimatorsConfig, model: VideoModel) -> Any:
    """The :class:`~geco_guide.estimators.tiny_decoder.TinyDecoderVariant` of ``model``'s latents,
    once its weights are named, there, and not another model's: one line, before any model loads,
    otherwise, naming the file of ``model``'s variant (a file name that tells no variant is left to
    the strict load, which checks the keys).

    Raises:
        ValueError: ``model`` has no tiny decoder, ``estimators.tiny_decoder`` is not set, or it
            names the checkpoint file of another model's.
        WeightsNotFoundError: it names a checkpoint file that does not exist.
    """
    from ...estimators.tiny_decoder import WEIGHTS_URL, resolve_variant, variant_from_filename

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
    try:
        named = variant_from_filename(path) if source != TINY_RANDOM and path.is_file() else None
    except ValueError:
        named = None
    if named is not None and named.name != variant.name:
        raise ValueError(f"estimators.tiny_decoder={source} is the tiny decoder of {named.models}; "
                         f"{model.name} needs {file}")
    return variant


def tiny_decoder_id(estimators: EstimatorsConfig) -> str:
    """The id of the tiny decoder :func:`load_tiny_decoder` loads: its source (a random one's
    with its seed: only then is it reproducible)."""
    source = estimators.tiny_decoder
    return f"{TINY_RANDOM}(seed={estimators.init_seed})" if source == TINY_RANDOM else source


def load_tiny_decoder(estimators: EstimatorsConfig, model: VideoModel, latent_channels: int,
                      dtype: torch.dtype) -> Any:
    """The tiny decoder of ``estimators.tiny_decoder`` for ``model``'s latents (a file, a folder or
    a hub id; ``tiny-random``: a random one of ``latent_channels``, the VAE's, seeded with
    ``estimators.init_seed``), frozen, in ``dtype`` on the CPU (the caller moves it): what
    :meth:`~geco_guide.estimators.Estimators.with_tiny_decoder` takes, with its id
    (:func:`tiny_decoder_id`).

    Raises:
        WeightsNotFoundError: one line naming the source and the config key.
        ValueError: the model has no tiny decoder, or the file is the tiny decoder of another model.
    """
    from ...estimators.tiny_decoder import TinyDecoder

    variant = check_tiny_decoder(estimators, model)
    source = estimators.tiny_decoder
    if source == TINY_RANDOM:
        return tiny_random_decoder(variant.name, estimators.init_seed, latent_channels).to(dtype=dtype)
    try:
        return TinyDecoder.from_pretrained(source, variant.name, dtype=dtype)
    except WeightsNotFoundError as err:
        raise with_config_key(err, "estimators.tiny_decoder", f"/path/to/{variant.checkpoint}.pth") from None


def check_guidance_before_loading(guidance: GuidanceConfig, run: RunOptions, model: VideoModel, *,
                                  num_frames: int, num_steps: int) -> None:
    """What the guidance computes, checked against ``model`` before any model loads: with guidance
    on, the loss, the schedule over ``num_steps`` steps and the run options the model's guidance
    can act on; the anchors of a ``num_frames`` video (decoded by a search too, guided or not).

    Raises:
        ValueError: one line naming the option.
    """
    if guidance.enabled:
        guidance.check_loss()
        guidance.schedule(num_steps)
        if run.split_cfg and model.guided_by != "pipeline":
            raise ValueError(f"run.split_cfg splits the denoiser calls of GeCoCogVideoXPipeline; {model.name} is "
                             "guided by the hooks, which leave its pipeline's own denoiser calls as they are: use "
                             "run.split_cfg=false")
        if run.decode_layout != "default" and not model.cogvideox_vae:
            raise ValueError(f"run.decode_layout={run.decode_layout} is written for the CogVideoX VAE, not "
                             f"{model.name}'s: use run.decode_layout=default")
    guidance.anchor_chunks(num_frames, model.temporal_compression)


def check_before_loading(model: ModelConfig, sampling: Any, guidance: GuidanceConfig, run: RunOptions,
                         estimators: EstimatorsConfig, *, weights: bool = True,
                         search: SearchConfig | None = None) -> torch.device:
    """Every check of a run that its config alone can fail, in one pass before anything loads, from
    what a fresh machine lacks to what the run asks of the machine it has:

    1. with ``weights`` (the models are not loaded yet), every model's weights, the tiny decoder's
       where the guidance decodes with it (all missing ones named at once), then a local folder
       of the video model: whole, and the registry model's (:mod:`.model_folder`);
    2. the devices (``model.device``, ``run.devices``) and the memory a plan budgets for;
    3. the memory plan that fits
       (:func:`~.memory_plan.plan_before_loading`), a ``search``'s particles beside it
       (:func:`~.search.check_search_before_loading`), and what the guidance computes
       (:func:`check_guidance_before_loading`: loss, schedule, decode options, anchors);
    4. the decoded videos (the search's particles: on the device and on the host until the
       selection) against the device's memory: a lower bound of the run's peak, so a refusal is
       certain.

    Returns the device ``model.device`` stands for (``auto`` resolved), what the loaders and the
    sidecar then use.

    Raises:
        ValueError: one line naming the option.
        WeightsNotFoundError: one line naming every missing model and how to pass a local path.
    """
    from ...io.devices import check_device, check_memory_fits, planning_memory_gb, resolve_devices

    entry = model.video_model
    searching = search is not None and search.enabled
    anchored = guidance.enabled or searching  # a search decodes and scores guidance's anchors too
    tiny_decoder = uses_tiny_decoder(guidance, searching)
    segmenter = anchored and guidance.subjects is not None
    if weights:
        missing_weights(model, estimators, tiny_decoder=tiny_decoder, segmenter=segmenter)
    devices = resolve_devices(run.devices) if anchored else None
    device = check_device(model.device)
    check_model_context_parallel(run, entry, model_device=model.device,
                                 differentiates=guidance.enabled and guidance.denoiser_grad)
    device_gb = planning_memory_gb(device, devices)
    frames, height, width = sampling.num_frames, sampling.height, sampling.width
    plan = plan_before_loading(guidance, run, model.source, frames, height, width, device_gb)
    if searching:
        check_search_before_loading(search, guidance, run, plan, model_id=model.source, frames=frames, height=height,
                                    width=width, device_gb=device_gb, devices=len(devices) if devices else 1)
    if anchored:
        check_guidance_before_loading(guidance, run, entry, num_frames=frames, num_steps=sampling.num_inference_steps)
    video = frames * 3 * height * width * 4  # float32
    if searching:
        what = f"search.particles={search.particles} videos of {frames}x{height}x{width}"
        for where in (device, "cpu"):
            check_memory_fits(search.particles * video, where, what)
    check_memory_fits(video, device, f"a {frames}-frame {height}x{width} video (sampling.num_frames/height/width)")
    return device


def check_model_context_parallel(run: Any, model: Any, *, model_device: str, differentiates: bool) -> None:
    """:func:`check_context_parallel_before_loading` for the registry's ``model``
    (:class:`~geco_guide.families.VideoModel`), from its pipeline class alone; then this process
    takes the GPU of its ``LOCAL_RANK``, the one ``model.device=auto`` (or ``cuda``) loads on."""
    if context_parallel_degree(run) == 1:
        return
    import diffusers

    pipeline_class = getattr(diffusers, model.pipeline)
    check_context_parallel_before_loading(run, adapter_for_class(pipeline_class), model_device=model_device,
                                          differentiates=differentiates)
    if torch.cuda.is_available():
        torch.cuda.set_device(int(os.environ.get("LOCAL_RANK", "0")))
