"""ONE generation path: check, load, sample (guided or not), score, write.

``geco generate``, ``geco ab``, ``--best-of``, GeCo-Eval and the perf harness all make their videos
here, for every model of the registry (:mod:`geco_guide.families`):

1. :func:`check_generation` checks what the config and the files alone can show, in one pass down
   the layers and before anything loads: the prompt and the image, every model's weights (all
   missing ones named at once), the devices and their memory, options that cannot act, the memory
   plan, a search's particles, the guidance against the model (loss, schedule, anchors), the
   video's size against the memory, the outputs.
2. :func:`load_models` loads what the run needs once: the video pipeline of the model (the
   paper's ``GeCoCogVideoXPipeline`` for CogVideoX, the stock diffusers pipeline otherwise) and
   the estimators (with the segmenter and the tiny decoder where the guidance uses them).
3. :func:`sample` makes one video: the pipeline's own call, guided by its loop or through
   :func:`~geco_guide.sampler.pipelines.hooks.attach_geco_guidance`; it returns the frames and what the
   call decided (:class:`~geco_guide.sampler.running.context.GuidanceReport`). With ``search.particles``
   set it is :func:`sample_search`: ``K`` particles in one call, resampled by their GeCo scores,
   and the final one of least score under the evaluation protocol kept.
4. :func:`generate` writes the video and its sidecar, atomically, under an output lock;
   :func:`generate_best_of` makes N and keeps the least inconsistent.
"""

from __future__ import annotations

import contextlib
import functools
import hashlib
import json
import logging
import math
import os
import platform
import re
import shutil
import time
from collections.abc import Callable, Iterator
from operator import attrgetter
from dataclasses import asdict, dataclass, field, replace
from datetime import datetime, timezone
from pathlib import Path
from typing import TYPE_CHECKING, Any

from .config import GeCoConfig, config_to_dict, movers_as_first_spelt, nested
from .estimators import TINY_RANDOM
from .io.files import check_output_paths, output_lock, write_json_atomic
from .types import merge_dataclass

if TYPE_CHECKING:
    import torch

    from .estimators import Estimators
    from .io.video import SoundTrack
    from .sampler.running.context import GuidanceObserver, GuidanceReport
    from .sampler.pipelines.loading import LoadedPipeline

__all__ = ["KEYLESS_SECTIONS", "SCORES_NOTE", "SELECTION_SCORE", "GenerationResult", "Models", "Sample", "acting_config",
           "best_candidate", "check_conditioning", "check_generation", "check_prompt", "default_name", "generate", "generate_best_of",
           "load_models", "loading_line", "output_paths", "particle_scores", "sample", "sample_search", "selection_masks", "slugify", "versions",
           "video_key"]

logger = logging.getLogger(__name__)

#: What ``--out`` may end with: a video file of these suffixes (the writer picks the format by
#: it), or no suffix (a folder).
OUT_SUFFIXES = (".mp4", ".gif")
#: Config sections that cannot change the frames, left out of :func:`video_key`: where the files
#: go, whether the anchors are scored afterwards, the evaluation protocol.
KEYLESS_SECTIONS = ("output", "evaluation")
#: The moving-subject options, which make no frame while ``guidance.dynamic`` is null: left out of
#: :func:`video_key` then, so that every video made before they existed keeps its name.
DYNAMIC_KEYS = ("dynamic", "dynamic_dilation", "dynamic_refresh", "loss.movers")
SCORES_NOTE = ("These are the anchor frames' scores with the guidance loss' settings; "
               "geco evaluate scores the whole video with the paper's protocol (a different number).")
#: The score best-of-N selection keeps the lowest of: the fused map under the GeCo protocol.
SELECTION_SCORE = "fused"
#: What a sidecar adds to the model's name where ``model.id=tiny-random`` made the video: the
#: model's pipeline with tiny random weights, not the model.
TINY_STAND_IN = "tiny random stand-in"
#: The largest N of best-of-N: each candidate is a whole video.
MAX_CANDIDATES = 1000
SEED_RANGE = (-(2**63), 2**64 - 1)


# --------------------------------------------------------------------------------------------
# names


def slugify(text: str, max_len: int = 48) -> str:
    slug = re.sub(r"[^a-z0-9]+", "-", text.lower()).strip("-")
    return slug[:max_len].rstrip("-") or "video"


def video_key(config: dict[str, Any], prompt: str) -> str:
    """8 hex characters of SHA-256 over the prompt and the config that makes the frames
    (``config``: :func:`geco_guide.config.config_to_dict`'s form, e.g. a sidecar's ``config``).

    Left out: :data:`KEYLESS_SECTIONS`, ``model.device``, and the ``run`` section (how this machine
    runs guidance: memory plans and devices give the same frames) except its
    :data:`~geco_guide.sampler.running.run_options.FRAME_ROUNDING_KEYS` where they differ from their
    defaults and act (``split_cfg`` only with guidance and CFG): those can change the frames to float
    rounding and so name another video. The device can change the bytes (CPU and GPU kernels round
    differently), but a video moved to another device is the same experiment, so it does not
    rename it. Left out too while unused: the ``search`` section without a search
    (``search.particles`` null), the :data:`DYNAMIC_KEYS` of a null ``guidance.dynamic`` (or of a
    video made without guidance or search), ``guidance.loss.movers`` at its default ``drop``, and
    ``estimators.segmenter`` unless ``guidance.dynamic`` names subjects. The JSON is canonical (sorted keys), so the key is the
    same in every process and on every machine.
    """
    from .sampler.running.run_options import FRAME_ROUNDING_KEYS, RunOptions

    kept = {section: value for section, value in config.items() if section not in KEYLESS_SECTIONS}
    kept["model"] = {key: value for key, value in kept.get("model", {}).items() if key != "device"}
    guidance = kept.get("guidance", {})
    guided = guidance.get("enabled", True)
    searched = (kept.get("search") or {}).get("particles") is not None
    if not searched:  # a new section renames no video
        kept.pop("search", None)
    if "run" in kept:  # the options that round frames, where set and acting: a new one renames no video
        defaults = asdict(RunOptions())
        sampling = kept.get("sampling", {})
        acting = {"split_cfg": guided and (sampling.get("guidance_scale") or 0) > 1.0, "particle_batch": searched}
        kept["run"] = {key: value for key, value in kept["run"].items()
                       if key in FRAME_ROUNDING_KEYS and value != defaults[key] and acting.get(key, True)}
        if not kept["run"]:
            del kept["run"]
    dynamic = guidance.get("dynamic") if guided or searched else None
    if dynamic is None and "guidance" in kept:
        kept["guidance"] = {key: value for key, value in kept["guidance"].items() if key not in DYNAMIC_KEYS}
    if "guidance" in kept:
        kept["guidance"] = movers_as_first_spelt(kept["guidance"], dynamic is not None)
    if dynamic in (None, "auto") and "estimators" in kept:
        kept["estimators"] = {key: value for key, value in kept["estimators"].items() if key != "segmenter"}
    text = json.dumps({"prompt": prompt, "config": kept}, sort_keys=True, separators=(",", ":"))
    return hashlib.sha256(text.encode("utf-8")).hexdigest()[:8]


def default_name(cfg: GeCoConfig, prompt: str) -> str:
    """``<slug>-<video key>-seed<N>``, with ``-unguided`` when guidance is off and ``-search-<K>``
    for a search of ``K`` particles."""
    suffix = ("" if cfg.guidance.enabled else "-unguided") + (
        f"-search-{cfg.search.particles}" if cfg.search.enabled else "")
    return f"{slugify(prompt)}-{video_key(config_to_dict(cfg), prompt)}-seed{cfg.seed}{suffix}"


def output_paths(cfg: GeCoConfig, prompt: str, out: str | os.PathLike | None = None) -> tuple[Path, Path]:
    """``(video, sidecar.json)``: ``out`` (a .mp4 or .gif path, or a folder: no suffix) or
    ``output.dir/name.mp4``; ValueError (one line) for an ``out`` of another suffix or an empty one."""
    name = cfg.output.name or default_name(cfg, prompt)
    if out is None:
        video = Path(cfg.output.dir) / f"{name}.mp4"
    else:
        if not str(out).strip():
            raise ValueError("--out must name a video file (.mp4 or .gif) or a folder, got an empty string")
        out = Path(out)
        suffix = out.suffix.lower()
        if suffix and suffix not in OUT_SUFFIXES:
            raise ValueError(f"--out {str(out)!r}: a video path must end with {' or '.join(OUT_SUFFIXES)}; a path "
                             "without a suffix is a folder (the default name inside it)")
        video = out if suffix else out / f"{name}.mp4"
    return video, video.with_suffix(".json")


# --------------------------------------------------------------------------------------------
# checks before anything loads


def check_prompt(prompt: str) -> None:
    """ValueError (one line) for a prompt that is empty or not UTF-8 text (before any model loads:
    the tokenizer would fail on it after loading them all)."""
    if not isinstance(prompt, str) or not prompt.strip():
        raise ValueError("prompt must not be empty")
    try:
        prompt.encode("utf-8")
    except UnicodeEncodeError as err:  # bytes the terminal could not decode reach Python as surrogates
        raise ValueError(f"the prompt is not valid UTF-8 text (an undecodable byte at character {err.start + 1}); "
                         "check the encoding of the terminal or file it came from") from None


def check_conditioning(cfg: GeCoConfig, image: bool) -> None:
    """ValueError (one line) where the run's conditioning ``image`` (given or not) and its model
    disagree: an image-to-video model needs one, a text-to-video model takes none, and a search
    is of text-to-video models only (its particles would each need the image's latents)."""
    entry = cfg.model.video_model
    if entry.image_to_video and not image:
        raise ValueError(f"model.name={entry.name} is an image-to-video model: it needs a conditioning image, which "
                         "geco generate --image PATH gives; choose a text-to-video model otherwise")
    if image and not entry.image_to_video:
        raise ValueError(f"model.name={entry.name} is a text-to-video model: it takes no conditioning image; drop "
                         "--image, or choose an image-to-video model")
    if image and cfg.search.enabled:
        raise ValueError("a search of an image-to-video model is not supported: leave search.particles unset with "
                         "--image")


#: The options that act on some runs only: ``(what they need, whether a run lacks it, the keys)``.
#: Without guidance and without a search nothing decodes the anchors: no mask, no mover, no
#: device to deal the decode over; ``run.split_cfg`` splits a guided call's CFG batch.
IDLE_WITHOUT: tuple[tuple[str, Callable[[GeCoConfig], bool], tuple[str, ...]], ...] = (
    ("guidance or a search (--no-guidance)", lambda cfg: not (cfg.guidance.enabled or cfg.search.enabled),
     (*(f"guidance.{key}" for key in DYNAMIC_KEYS), "run.devices")),
    ("guidance (--no-guidance)", lambda cfg: not cfg.guidance.enabled, ("run.split_cfg",)),
    ("CFG (sampling.guidance_scale <= 1)", lambda cfg: (cfg.sampling.guidance_scale or 0) <= 1.0, ("run.split_cfg",)),
    ("a search (search.particles)", lambda cfg: not cfg.search.enabled, ("run.particle_batch",)),
)


def acting_config(cfg: GeCoConfig, *, quiet: bool = False) -> GeCoConfig:
    """``cfg`` as it runs, the one rule of what an option does on a run it cannot act on
    (:data:`IDLE_WITHOUT`): each one set off its default is one warning (none when ``quiet``: a
    caller that made the run unguided itself, as the A/B's unguided arm) and is reset to its
    default, so that the sidecar records what ran (neither the frames nor the video's name change).
    What an option names is checked first, acting or not: ``run.devices`` must be this machine's.

    Raises:
        ValueError: (one line) a device of ``run.devices`` this machine lacks.
    """
    from .io.devices import resolve_devices

    resolve_devices(cfg.run.devices)
    for needed, lacking, keys in IDLE_WITHOUT:
        values = {key: (attrgetter(key)(cfg), attrgetter(key)(GeCoConfig())) for key in keys}  # value, default
        idle = {key: value for key, (value, default) in values.items() if value != default} if lacking(cfg) else {}
        if idle and not quiet:
            shown = ", ".join(key if value is True else f"{key}={value!r}" for key, value in idle.items())
            logger.warning("%s %s nothing without %s: left at the default, as the sidecar records", shown,
                           "does" if len(idle) == 1 else "do", needed)
        if idle:  # merged at once: guidance checks dynamic and loss.movers together
            cfg = merge_dataclass(cfg, nested({key: values[key][1] for key in idle}))
    return cfg


def check_generation(cfg: GeCoConfig, prompt: str, paths: tuple[Path, ...] = (), *, overwrite: bool = False,
                     loaded: bool = False, image: bool = False) -> GeCoConfig:
    """Every check a generation can make before anything loads, in one pass; returns ``cfg`` with
    ``model.device`` resolved (``auto``: cuda where there is one, else cpu), so that the memory
    planner, the loaders and the sidecar all see the same real device.

    Checks the prompt, the conditioning ``image`` (whether one is given) against the model
    (:func:`check_conditioning`), the options that cannot act on the run (:func:`acting_config`:
    a warning each, and left at their defaults in the ``cfg`` returned), the run's config (:func:`~geco_guide.sampler.pipelines.loading.check_before_loading`:
    every model's weights unless the models are ``loaded``, the devices and their memory, the
    memory plan, a search's particles, the guidance
    against the model, the size against the device's memory), the output ``paths`` (refused if
    present without ``overwrite``) and the frame rate for their format.

    Raises:
        ValueError: one line naming the option, file or value.
        WeightsNotFoundError: one line naming every missing model and how to pass a local path.
    """
    from .io.video import check_fps
    from .sampler.pipelines.loading import check_before_loading

    check_prompt(prompt)
    check_conditioning(cfg, image)
    if cfg.search.enabled and cfg.seed + cfg.search.particles - 1 > SEED_RANGE[1]:
        raise ValueError(f"search.particles={cfg.search.particles} from seed {cfg.seed} needs seeds up to "
                         f"{cfg.seed + cfg.search.particles - 1}, over the 64-bit limit {SEED_RANGE[1]}: choose a "
                         "smaller seed")
    cfg = acting_config(cfg)
    device = check_before_loading(cfg.model, cfg.sampling, cfg.guidance, cfg.run, cfg.estimators, weights=not loaded,
                                  search=cfg.search)
    check_output_paths(paths, overwrite)
    for path in paths[:1]:
        check_fps(cfg.sampling.fps, path.suffix)
    return replace(cfg, model=replace(cfg.model, device=str(device)))


# --------------------------------------------------------------------------------------------
# loading


@dataclass
class Models:
    """What a run loads once and every video of it uses.

    Attributes:
        video: the video pipeline and what its loading decided
            (:class:`~geco_guide.sampler.pipelines.loading.LoadedPipeline`).
        estimators: the GeCo models (with the segmenter and the tiny decoder where the guidance
            uses them), ``None`` where the run neither guides nor scores.
    """

    video: LoadedPipeline
    estimators: Estimators | None
    #: the estimators' copies on other devices, by devices (:meth:`estimators_on`)
    _replicas: dict[tuple[str, ...], list[Estimators]] = field(default_factory=dict, repr=False)

    @property
    def pipe(self) -> Any:
        return self.video.pipe

    def estimators_on(self, devices: list[Any]) -> list[Estimators]:
        """The estimators on each of ``devices``: the bundle itself where its geometry and flow
        models live on that device, copies of them elsewhere (made once per run and devices; the
        segmenter is shared). What a search's selection scores its particles with, device by
        device."""
        from torch import nn

        from .sampler.running.multi_device import module_replicas

        key = tuple(str(device) for device in devices)
        if key not in self._replicas:
            estimators = self.estimators
            geometry, flow = (module_replicas(model, devices) if isinstance(model, nn.Module)
                              else [model] * len(devices) for model in (estimators.geometry, estimators.flow))
            self._replicas[key] = [replace(estimators, geometry=g, flow=f, tiny_decoder=None)
                                   for g, f in zip(geometry, flow)]
        return self._replicas[key]


def loading_line(cfg: GeCoConfig, estimators: bool = True) -> str:
    """The line a command prints before loading (which takes minutes): what loads, from where."""
    model = f"{cfg.model.name} {cfg.model.source}"
    if not estimators:
        return f"loading models: {model} ..."
    segmenter = ""
    if cfg.guidance.enabled and cfg.guidance.subjects is not None:
        segmenter = f", segmenter {cfg.estimators.segmenter} for {cfg.guidance.dynamic!r}"
    return f"loading models: {model}, geometry {cfg.estimators.geometry}, flow {cfg.estimators.flow}{segmenter} ..."


def load_models(cfg: GeCoConfig, *, estimators: bool | Estimators = True,
                components: dict[str, Any] | None = None) -> Models:
    """The video pipeline of ``cfg.model`` (its tiny random stand-in with ``model.id=tiny-random``)
    and the GeCo models: ``estimators`` when it is a bundle loaded already (a run that shares it
    across models), loaded when it is ``True`` (with the segmenter where ``guidance.dynamic``
    names subjects), none when ``False``; plus the tiny decoder of the model's latents where the
    guidance decodes with it. On ``model.device``. Every model's weights were looked up before
    (:func:`check_generation`), so the order is the one that needs each model's facts first.
    ``components``: the video pipeline's models built already (the perf harness's full-size models
    with random weights), in place of ``model.id``'s weights."""
    import torch

    from .estimators import Estimators, load_estimators
    from .sampler.algorithm.slicing import vae_latent_channels
    from .sampler.pipelines.loading import load_tiny_decoder, load_video_pipeline, tiny_decoder_id, uses_tiny_decoder
    from .tiny import tiny_call_extras, tiny_video_components

    extras = {}
    if cfg.model.source == TINY_RANDOM:
        extras = tiny_call_extras(cfg.model.video_model.pipeline)
        if components is None:
            components = tiny_video_components(cfg.model.video_model, cfg.model.init_seed)
    video = replace(load_video_pipeline(cfg.model, cfg.sampling.scheduler, components), call_extras=extras)
    decoder = None
    if estimators is not False and uses_tiny_decoder(cfg.guidance, cfg.search.enabled):
        channels = vae_latent_channels(video.pipe.vae)
        decoder = load_tiny_decoder(cfg.estimators, video.model, channels, getattr(torch, cfg.model.dtype))
        decoder = decoder.to(device=video.pipe.device)
    bundle = estimators if isinstance(estimators, Estimators) else None
    if estimators is True:
        segmenter = (cfg.guidance.enabled or cfg.search.enabled) and cfg.guidance.subjects is not None
        bundle = load_estimators(cfg.estimators, cfg.model.device, segmenter=segmenter)
    if bundle is not None and decoder is not None:
        bundle = bundle.with_tiny_decoder(decoder, tiny_decoder_id(cfg.estimators))
    return Models(video, bundle)


# --------------------------------------------------------------------------------------------
# sampling


@dataclass
class Sample:
    """One video as :func:`sample` made it.

    Attributes:
        frames: ``[1, F, 3, H, W]`` in ``[0, 1]``, float32, on the CPU.
        report: what the call decided (:class:`~geco_guide.sampler.running.context.GuidanceReport`).
        seconds: the call's wall time (a search's: with the selection's scoring).
        search: what a search did and chose (:func:`sample_search`), ``None`` without one.
        audio: the sound the model made with the video (LTX-2), ``None`` without.
    """

    frames: torch.Tensor
    report: GuidanceReport
    seconds: float
    search: dict[str, Any] | None = None
    audio: SoundTrack | None = None


def sample(models: Models, cfg: GeCoConfig, prompt: str, *, seed: int | None = None, image: Any = None,
           observer: GuidanceObserver | None = None, progress: bool = True) -> Sample:
    """One video of ``prompt`` with ``cfg``'s sampling and guidance, seeded with ``seed`` (default
    ``cfg.seed``): the pipeline's own call, guided by the paper's loop (``GeCoCogVideoXPipeline``)
    or by :func:`~geco_guide.sampler.pipelines.hooks.attach_geco_guidance` on the stock pipeline;
    ``image`` conditions an image-to-video pipeline.

    With ``search.particles`` set, the video is a search's (:func:`sample_search`).

    Raises:
        ValueError: the sampled frames hold NaN/inf (nothing is made of them), an option the
            pipeline has no argument for, or an ``image`` the model does not take (or lacks:
            :func:`check_conditioning`).
    """
    check_conditioning(cfg, image is not None)
    if cfg.search.enabled:
        return sample_search(models, cfg, prompt, seed=seed, image=image, observer=observer, progress=progress)
    import torch

    from .sampler.running.context import GuidanceReport
    from .sampler.pipelines.sampling import call_arguments, sound_track

    pipe, entry = models.pipe, models.video.model
    generator = torch.Generator(device="cpu").manual_seed(cfg.seed if seed is None else seed)
    extra = dict(models.video.call_extras)
    if image is not None:
        extra["image"] = image
    arguments = call_arguments(pipe, cfg.sampling, prompt=prompt, generator=generator, **extra)
    pipe.set_progress_bar_config(disable=not progress)
    guided = cfg.guidance.enabled
    start = time.perf_counter()
    if entry.guided_by == "pipeline":
        output = pipe(**arguments, guidance=cfg.guidance, run_options=cfg.run,
                      estimators=models.estimators if guided else None, observer=observer)
        report = output.report
    elif guided:
        from .sampler.pipelines.hooks import attach_geco_guidance

        with attach_geco_guidance(pipe, cfg.guidance, models.estimators, cfg.run) as handle:
            handle.observer = observer
            output = pipe(**arguments)
        report = handle.last
    else:
        output = pipe(**arguments)
        report = GuidanceReport(scheduler=type(pipe.scheduler).__name__)
    seconds = time.perf_counter() - start
    frames = output.frames[:1].float().cpu()  # [1, F, 3, H, W] in [0, 1]
    _check_sampled(frames)
    return Sample(frames, report, seconds, audio=sound_track(pipe, output))


def _check_sampled(frames: torch.Tensor) -> None:
    """ValueError (one line) for sampled frames that hold NaN/inf: the VAE's clamp would write NaN
    as black and score it 0."""
    from .types import NonFiniteFramesError, check_frame_values

    try:
        check_frame_values(frames, "the sampled video")
    except NonFiniteFramesError as err:
        raise ValueError(
            f"sampling diverged, nothing was written: {err} (lower sampling.guidance_scale or guidance.step_size)"
        ) from None


def sample_search(models: Models, cfg: GeCoConfig, prompt: str, *, seed: int | None = None, image: Any = None,
                  observer: GuidanceObserver | None = None, progress: bool = True,
                  on_particle: Callable[[int, Any], None] | None = None) -> Sample:
    """A particle search (``cfg.search``, :mod:`geco_guide.sampler.search.particle_search`): ``K =
    search.particles`` videos of ``prompt`` as one call, particle ``k`` seeded with ``seed + k``
    (default ``cfg.seed``; so without a resampling each particle starts as that seed's video),
    guided as ``cfg.guidance`` says, scored by GeCo and resampled at the search's steps (the
    draws from a generator of :func:`~geco_guide.sampler.search.particle_search.search_seed` of ``seed``). Each
    final particle is then scored with the GeCo protocol
    (:func:`~geco_guide.metric.evaluate.evaluate_video`, the config's ``evaluation`` section, at
    ``sampling.fps``, with the run's dynamic masks (:func:`selection_masks`); its frames as
    decoded, where best-of-N scores its written files) and the one of least fused score kept, as
    best-of-N keeps its candidates (a NaN ranks last, ties go to the earlier particle).
    ``on_particle(k, scores)`` is called after each is scored.

    Returns:
        The kept video; its ``search``: the search's record (:meth:`ParticleSearch.report
        <geco_guide.sampler.search.particle_search.ParticleSearch.report>`) with ``final_particles`` (each final
        particle's lineage, the seed it started from and its protocol scores) in place of the
        lineages, ``kept``, ``kept_lineage``, ``score`` (what selects) and ``selection_s``.

    Raises:
        ValueError: (one line) a conditioning ``image`` (a search of an image-to-video model is
            not supported: :func:`check_conditioning`), or the kept video holds NaN/inf.
    """
    import torch

    from .sampler.pipelines.sampling import call_arguments
    from .sampler.search.particle_search import search_seed

    check_conditioning(cfg, image is not None)
    seed = cfg.seed if seed is None else seed
    particles = cfg.search.particles
    pipe, entry = models.pipe, models.video.model
    generators = [torch.Generator(device="cpu").manual_seed(seed + k) for k in range(particles)]
    search_generator = torch.Generator(device="cpu").manual_seed(search_seed(seed))
    extra = dict(models.video.call_extras)
    if entry.guided_by != "pipeline":  # a stock pipeline's batch: its videos per prompt
        extra["num_videos_per_prompt"] = particles
    arguments = call_arguments(pipe, cfg.sampling, prompt=prompt, generator=generators, **extra)
    pipe.set_progress_bar_config(disable=not progress)
    start = time.perf_counter()
    if entry.guided_by == "pipeline":
        output = pipe(**arguments, guidance=cfg.guidance, run_options=cfg.run, estimators=models.estimators,
                      observer=observer, search=cfg.search, search_generator=search_generator)
        report = output.report
    else:
        from .sampler.pipelines.hooks import attach_geco_guidance

        with attach_geco_guidance(pipe, cfg.guidance, models.estimators, cfg.run) as handle:
            handle.observer = observer
            if cfg.search.enabled:
                handle.enable_search(cfg.search, search_generator)
            output = pipe(**arguments)
        report = handle.last
    frames = output.frames.float().cpu()  # [K, F, 3, H, W] in [0, 1]
    selection_start = time.perf_counter()
    scores, selection_devices = particle_scores(frames, cfg, models, on_particle)
    kept = best_candidate([math.nan if s[SELECTION_SCORE] is None else s[SELECTION_SCORE] for s in scores])
    video = frames[kept:kept + 1]
    _check_sampled(video)
    record = report.search
    search = {**record, "score": f"{SELECTION_SCORE} (the GeCo protocol, evaluation.*)", "kept": kept,
              **({"selection_devices": [str(device) for device in selection_devices]} if selection_devices else {}),
              "kept_lineage": record["lineages"][kept], "selection_s": time.perf_counter() - selection_start,
              "final_particles": [{"particle": k, "seed": seed + record["lineages"][k][0],
                                   "lineage": record["lineages"][k], **scores[k]} for k in range(particles)]}
    del search["lineages"]
    return Sample(video, replace(report, search=search), time.perf_counter() - start, search=search)


def particle_scores(frames: torch.Tensor, cfg: GeCoConfig, models: Models,
                    on_particle: Callable[[int, Any], None] | None = None) -> tuple[list[dict[str, float | None]], list[Any]]:
    """A search's selection: each final particle of ``frames [K, F, 3, H, W]`` scored as
    :func:`sample_search` says, dealt over ``run.devices`` where it names several; its scores, and
    the devices they were dealt over (``[]``: one). ``on_particle(k, scores)`` after each."""
    from .io.devices import resolve_devices
    from .metric.evaluate import cue_scores, evaluate_video
    from .sampler.running.multi_device import dealt_work

    masks = selection_masks(cfg, models)
    devices = resolve_devices(cfg.run.devices)
    bundles = models.estimators_on(devices) if devices and len(devices) > 1 else [models.estimators]

    def protocol_scores(k: int, place: int) -> dict[str, float | None]:
        try:
            return cue_scores(evaluate_video(frames[k], bundles[place], cfg.evaluation, fps=cfg.sampling.fps,
                                             dynamic_masks=masks))
        except ValueError:  # NaN frames: the particle ranks last
            return cue_scores(None)

    scores = []
    for k, values in enumerate(dealt_work(cfg.search.particles, len(bundles), protocol_scores)):  # each device its share
        scores.append(values)
        if on_particle is not None:
            on_particle(k, values)
    return scores, devices if len(bundles) > 1 else []


# --------------------------------------------------------------------------------------------
# one video, written


@dataclass
class GenerationResult:
    video_path: Path
    sidecar_path: Path
    scores: dict[str, float] | None
    sidecar: dict[str, Any]
    #: the models that made the video (loaded, or the ones passed in), for a caller's next video
    models: Models | None = None


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


def generate(cfg: GeCoConfig, prompt: str, out: str | os.PathLike | None = None, *, overwrite: bool = False,
             models: Models | None = None, image: Any = None, announce: Callable[[str], None] | None = None,
             progress: bool = True) -> GenerationResult:
    """Run one generation of ``cfg`` and write the video + JSON sidecar. ``models`` skips loading
    (a run's earlier :class:`Models`); existing outputs are replaced only with ``overwrite``
    (checked before anything loads); ``announce`` is told what loads before it does; ``progress``:
    the pipeline's progress bar (off for a log, where it would write a line per step).

    Once every check passed, the run holds its video's :func:`~geco_guide.io.files.output_lock`: a
    second run of the same output name at the same time is refused (one line naming the first's
    pid), and the existence check, made again under the lock, holds until the files are written.
    """
    video_path, sidecar_path = output_paths(cfg, prompt, out)
    cfg = check_generation(cfg, prompt, (video_path, sidecar_path), overwrite=overwrite, loaded=models is not None,
                           image=image is not None)
    with output_lock(video_path):  # every check passed: from here on the name is this run's
        check_output_paths((video_path, sidecar_path), overwrite)  # again: a run that ended meanwhile wrote it
        return _load_sample_and_write(cfg, prompt, video_path, sidecar_path, models, image, announce, progress)


def _scores_needed(cfg: GeCoConfig) -> bool:
    return cfg.output.score_anchors


def _load_sample_and_write(cfg: GeCoConfig, prompt: str, video_path: Path, sidecar_path: Path, models: Models | None,
                           image: Any, announce: Callable[[str], None] | None, progress: bool = True,
                           ) -> GenerationResult:
    """The heavy part of :func:`generate`, once every check passed and the output name is held."""
    from .io.video import write_video

    timings: dict[str, float] = {}
    start = time.perf_counter()
    if models is None:
        needs_estimators = cfg.guidance.enabled or cfg.search.enabled or _scores_needed(cfg)
        if announce is not None:
            announce(loading_line(cfg, needs_estimators))
        models = load_models(cfg, estimators=needs_estimators)
    timings["load_s"] = time.perf_counter() - start
    made = sample(models, cfg, prompt, image=image, progress=progress)
    timings["sampling_s"] = made.seconds
    scores = None
    if _scores_needed(cfg):
        start = time.perf_counter()
        scores = score_anchors(made, cfg, models)
        timings["scoring_s"] = time.perf_counter() - start
    start = time.perf_counter()
    write_video(video_path, made.frames[0], fps=cfg.sampling.fps, audio=made.audio)
    timings["write_video_s"] = time.perf_counter() - start
    with removed_on_failure(video_path, sidecar_path):
        sidecar = sidecar_of(cfg, prompt, models, made, video_path.name, timings, scores)
        write_json_atomic(sidecar_path, sidecar)
    return GenerationResult(video_path=video_path, sidecar_path=sidecar_path, scores=scores, sidecar=sidecar,
                            models=models)


def score_anchors(made: Sample, cfg: GeCoConfig, models: Models) -> dict[str, float]:
    """The GeCo scalars of the final video's anchor frames with the guidance loss' settings, the
    dynamic masks as guidance used them (the sidecar's ``geco_scores``); a score over no valid
    pixel is NaN, with ``nan_reason``."""
    from .loss.geco import GeCoLoss
    from .sampler.algorithm.dynamic import RefreshedMasks, guidance_mask_source
    from .sampler.algorithm.step import score_anchor_frames

    loss = GeCoLoss(models.estimators, cfg.guidance.loss)
    masked = cfg.guidance.enabled or cfg.search.enabled
    masks = guidance_mask_source(cfg.guidance, models.estimators, cfg.model.device) if masked else None
    if masks is not None:  # the anchors scored as guidance scored them: without what moves, or its movers rigid
        masks = RefreshedMasks(masks.source, dilation=cfg.guidance.dynamic_dilation, movers=masks.movers)
        loss = functools.partial(loss, dynamic_masks=masks, **({} if masks.movers is None else {"movers": masks.movers}))
    return score_anchor_frames(made.frames, anchors_of(cfg), loss)


def anchors_of(cfg: GeCoConfig) -> list[int]:
    """The anchors the run guides and scores: ``guidance.anchors``."""
    return list(cfg.guidance.anchors)


def sidecar_of(cfg: GeCoConfig, prompt: str, models: Models, made: Sample, video_name: str,
               timings: dict[str, float], scores: dict[str, float] | None) -> dict[str, Any]:
    """The sidecar of a video: what made it (the config, the models, what the call decided) and
    how long it took."""
    report, config = made.report, config_to_dict(cfg)
    log = report.log
    return {
        "prompt": prompt,
        "seed": cfg.seed,
        "video": video_name,
        "video_key": video_key(config, prompt),
        "model": f"{cfg.model.name} ({TINY_STAND_IN})" if cfg.model.source == TINY_RANDOM else cfg.model.name,
        "num_frames": int(made.frames.shape[1]),
        "fps": cfg.sampling.fps,
        "created": datetime.now(timezone.utc).isoformat(timespec="seconds"),
        "config": config,
        "scheduler": models.video.scheduler,
        "guidance_decoder": report.decoder,
        "memory_plan": report.memory_plan,
        "guidance_devices": report.devices,
        "dynamic_masks": report.mask_source,
        "masked_fraction": report.masked_fraction,
        "device": str(models.pipe.device),
        "versions": versions(),
        "timings": {**timings, "guidance_s": sum(r["seconds"] for r in log)},
        "geco_scores": {"anchors": anchors_of(cfg), **scores} if scores is not None else None,
        "guidance_log": log,
        **({"search": made.search} if made.search is not None else {}),
        **({"audio": made.audio.record(Path(video_name))} if made.audio is not None else {}),
    }


# --------------------------------------------------------------------------------------------
# best of N


def best_candidate(scores: list[float]) -> int:
    """The index of the candidate best-of-N selection keeps among their :data:`SELECTION_SCORE`
    ``scores``: the least (a NaN ranks last, ties go to the earlier seed)."""
    return min(range(len(scores)), key=lambda k: (not math.isfinite(scores[k]), scores[k] if math.isfinite(scores[k]) else 0))


def selection_masks(cfg: GeCoConfig, models: Models) -> Any:
    """The ``dynamic_masks`` the selection of best-of-N and search scores candidates with: what
    moves on its own is left out of the choice as the run's guidance leaves it out
    (``guidance.dynamic``: ``"auto"`` or the subjects, masked by the estimators' segmenter);
    ``None`` without (the paper's protocol)."""
    dynamic = cfg.guidance.dynamic
    if dynamic is None or not (cfg.guidance.enabled or cfg.search.enabled):
        return None
    return dynamic if cfg.guidance.subjects is None else models.estimators.masks_for(cfg.guidance.subjects)


def check_best_of(count: Any, seed: int) -> None:
    """ValueError (one line) unless ``count`` is a whole number in ``[1, MAX_CANDIDATES]`` whose
    seeds ``seed .. seed + count - 1`` all fit 64 bits."""
    if isinstance(count, bool) or not isinstance(count, int) or not 1 <= count <= MAX_CANDIDATES:
        raise ValueError(f"--best-of must be a whole number in [1, {MAX_CANDIDATES}], got {count!r}")
    if seed + count - 1 > SEED_RANGE[1]:
        raise ValueError(f"--best-of {count} from --seed {seed} needs seeds up to {seed + count - 1}, over the 64-bit "
                         f"limit {SEED_RANGE[1]}: choose a smaller --seed")


def generate_best_of(cfg: GeCoConfig, prompt: str, count: int, out: str | os.PathLike | None = None, *,
                     overwrite: bool = False, image: Any = None, on_candidate: Any = None,
                     announce: Callable[[str], None] | None = None) -> GenerationResult:
    """Selection, the other way to spend compute on geometry: ``count`` videos of the seeds
    ``cfg.seed`` .. ``cfg.seed + count - 1`` (guided or not, as ``cfg`` says), each scored with the
    GeCo protocol (:func:`~geco_guide.metric.evaluate.evaluate_video`, the config's ``evaluation``
    section, with the run's dynamic masks: :func:`selection_masks`); the one of least fused score
    is kept (a NaN score ranks last, ties go to the earlier seed). The models load once for every
    candidate.

    Writes the kept video and its sidecar, which adds ``best_of``: every candidate's seed and
    protocol scores and the seed kept. The default name ends in ``-best-of-<count>``. The
    candidates are made in a hidden folder beside the output and removed however the run ends.
    ``on_candidate(k, seed, result)`` is called after each candidate is scored.

    Raises:
        ValueError: (one line, before anything loads) a ``count`` out of range, and what
            :func:`generate` refuses.
    """
    from .metric.evaluate import cue_scores, evaluate_video

    check_best_of(count, cfg.seed)
    if cfg.search.enabled:
        raise ValueError("--best-of and a search (search.particles) are two ways to spend compute on geometry: choose "
                         "one")
    check_prompt(prompt)
    if not cfg.output.name:
        cfg = replace(cfg, output=replace(cfg.output, name=f"{default_name(cfg, prompt)}-best-of-{count}"))
    video_path, sidecar_path = output_paths(cfg, prompt, out)
    cfg = check_generation(cfg, prompt, (video_path, sidecar_path), overwrite=overwrite, image=image is not None)
    work = video_path.with_name(f".{video_path.stem}.candidates")
    models, candidates = None, []
    with output_lock(video_path):
        check_output_paths((video_path, sidecar_path), overwrite)
        shutil.rmtree(work, ignore_errors=True)  # the candidates of a killed run
        try:
            for k in range(count):
                seed_cfg = replace(cfg, seed=cfg.seed + k, output=replace(cfg.output, name=None))
                if models is None:
                    if announce is not None:
                        announce(loading_line(cfg))
                    models = load_models(cfg)
                if announce is not None:
                    announce(f"candidate {k + 1}/{count} (seed {seed_cfg.seed}): sampling ...")
                result = generate(seed_cfg, prompt, out=work / f"seed{seed_cfg.seed}.mp4", models=models, image=image)
                if announce is not None:
                    announce(f"candidate {k + 1}/{count}: scoring it with the GeCo protocol ...")
                scored = evaluate_video(result.video_path, models.estimators, cfg.evaluation,
                                        dynamic_masks=selection_masks(cfg, models))
                candidates.append((result, scored))
                if on_candidate is not None:
                    on_candidate(k, seed_cfg.seed, scored)
            best = best_candidate([getattr(scored, SELECTION_SCORE) for _, scored in candidates])
            kept, _ = candidates[best]
            sidecar = {**kept.sidecar, "video": video_path.name, "best_of": {
                "n": count, "kept_seed": kept.sidecar["seed"], "score": f"{SELECTION_SCORE} (the GeCo protocol, evaluation.*)",
                "candidates": [{"seed": result.sidecar["seed"], **cue_scores(scored)} for result, scored in candidates]}}
            os.replace(kept.video_path, video_path)
            with removed_on_failure(video_path, sidecar_path):
                write_json_atomic(sidecar_path, sidecar)
        finally:
            shutil.rmtree(work, ignore_errors=True)
    return GenerationResult(video_path=video_path, sidecar_path=sidecar_path, scores=kept.scores, sidecar=sidecar,
                            models=models)
