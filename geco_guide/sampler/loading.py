"""Loading video pipelines: a hub id or a local folder, in a dtype, with a clear one-line error
when the weights are not there, and the scheduler that ``sampling.scheduler`` names.

diffusers is imported inside the functions, so importing this module stays light. The config is
duck-typed (``cfg.model``, ``cfg.sampling``, ``cfg.guidance``, ``cfg.estimators`` of a
:class:`~geco_guide.config.GeCoConfig`): the config module sits above the sampler.
"""

from __future__ import annotations

import contextlib
import os
from pathlib import Path
from typing import Any

import torch

from ..estimators import TINY_RANDOM, load_estimators
from ..estimators.loading import WeightsNotFoundError
from ..io.devices import resolve_device


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
                model.to(dtype)
    elif model_id == TINY_RANDOM:
        raise ValueError(f"model.id={TINY_RANDOM} needs its components (geco_guide.tiny.tiny_cogvideox_components)")
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


def build_pipeline(cfg: Any, components: dict[str, Any] | None = None):
    """Estimators + video pipeline of a config (estimators first: they are the cheaper failure)."""
    geometry, flow = load_estimators(cfg.estimators, resolve_device(cfg.model.device))
    return load_video_pipeline(cfg, geometry, flow, components=components)
