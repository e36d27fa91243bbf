"""Frozen GeCo backbones, and the one function that builds them from a config.

:func:`load_estimators` is shared by ``python -m geco_guide.generate`` and
``geco evaluate``: hub ids, local folders, or ``tiny-random`` for the tiny,
randomly initialised offline models of :func:`tiny_estimators`, returned as one
:class:`~.bundle.Estimators` (geometry, flow and, when asked for, the text segmenter). This module stays light (no
model code is imported until an estimator is built), because every ``geco_guide.estimators.*``
import runs it.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any, Optional

import json
from pathlib import Path

import torch

from ..io.devices import resolve_device
from ..types import OptionError
from . import dynamic_masks  # noqa: F401  (names the mask sources the loss takes by name: "auto")
from .bundle import Estimators, estimator_id
from .loading import WeightsNotFoundError, WeightsSource, check_weight_sources
from .waft_config import DEFAULT_REPO_ID as WAFT_REPO_ID

__all__ = ["FLOW_ESTIMATORS", "GEOMETRY_BACKBONES", "TINY_RANDOM", "TINY_RANDOM_DA3", "TINY_RANDOM_WAFT", "Estimators",
           "EstimatorsConfig", "check_weights", "estimator_id", "estimator_ids", "estimator_weight_sources",
           "flow_architecture", "flow_source", "geometry_architecture", "geometry_source", "load_estimators",
           "load_segmenter", "segmenter_id", "tiny_estimators", "tiny_random_decoder", "with_config_key"]

TINY_RANDOM = "tiny-random"
#: The tiny random Depth Anything 3 (``estimators.geometry``); ``tiny-random`` is the tiny VGGT.
TINY_RANDOM_DA3 = "tiny-random-da3"
#: The tiny random WAFT (``estimators.flow``); ``tiny-random`` is the tiny UFM.
TINY_RANDOM_WAFT = "tiny-random-waft"

#: The published geometry backbones ``estimators.geometry`` names, with their hub ids. VGGT-1B's
#: weights are CC-BY-NC-4.0; DA3-SMALL's and DA3-BASE's are Apache-2.0 (docs/metric.md).
GEOMETRY_BACKBONES = {"vggt-1b": "facebook/VGGT-1B", "da3-small": "depth-anything/DA3-SMALL",
                      "da3-base": "depth-anything/DA3-BASE"}
#: The flow estimators ``estimators.flow`` names, with their hub ids. UFM-Base's weights are
#: CC-BY-NC-4.0; WAFT's are BSD-3-Clause (its Depth Anything V2 Small part Apache-2.0).
FLOW_ESTIMATORS = {"ufm-base": "infinity1096/UFM-Base", "waft": WAFT_REPO_ID}
#: ``estimators.flow=waft:ID_OR_PATH``: WAFT weights that carry no config.json (the authors' ``.pth`` files).
WAFT_PREFIX = "waft:"


@dataclass
class EstimatorsConfig:
    """The frozen GeCo backbones: hub ids or local folders, or ``tiny-random``.

    ``geometry`` is a backbone of :data:`GEOMETRY_BACKBONES` by name (``vggt-1b``, ``da3-small``,
    ``da3-base``: their hub ids), a hub id, a local folder (VGGT, or Depth Anything 3 when its
    ``config.json`` is one: :func:`geometry_architecture`), ``tiny-random`` (a tiny random VGGT)
    or ``tiny-random-da3`` (a tiny random Depth Anything 3); the default is VGGT-1B.
    ``flow`` is a flow estimator of :data:`FLOW_ESTIMATORS` by name (``ufm-base``, ``waft``), a hub
    id, a local folder (UFM, or WAFT when its ``config.json`` is one: :func:`flow_architecture`),
    ``waft:ID_OR_PATH`` (WAFT weights without a ``config.json``, e.g. the authors' ``.pth``),
    ``tiny-random`` (a tiny random UFM) or ``tiny-random-waft`` (a tiny random WAFT); the default
    is UFM-Base.
    ``dtype`` is the storage dtype of their ViT trunks (``trunk_to``): bfloat16 halves their
    memory and speeds them up on a GPU; the heads, outputs and the GeCo loss stay float32.
    ``gradient_checkpointing`` recomputes their trunks' blocks in the guidance backward: less
    activation memory (how much: docs/performance.md) for one more trunk forward.
    ``tiny_decoder`` is the weights of the tiny decoder that ``guidance.decoder=tiny`` decodes the
    anchor frames with: a ``.pth`` / ``.safetensors`` file (``taecvx.pth`` for CogVideoX, from
    :data:`~geco_guide.estimators.tiny_decoder.WEIGHTS_URL`), a folder holding it, a hub id, or
    ``tiny-random``; unused (and not loaded) with ``guidance.decoder=vae``.
    ``segmenter`` is the weights of the text segmenter that masks the subjects named by
    ``guidance.dynamic`` (:mod:`~geco_guide.estimators.segmenters`, SAM 3 video): a hub id, a
    local folder or ``tiny-random``; unused (and not loaded) unless ``guidance.dynamic`` names
    subjects.
    """

    geometry: str = "facebook/VGGT-1B"
    flow: str = "infinity1096/UFM-Base"
    dtype: str = "bfloat16"
    gradient_checkpointing: bool = False
    init_seed: int = 0
    tiny_decoder: Optional[str] = None
    segmenter: str = "facebook/sam3"


def tiny_estimators(seed: int = 0, geometry: str = "vggt", **more: Any) -> Estimators:
    """Tiny random geometry (``geometry``: ``"vggt"`` or ``"da3"``, Depth Anything 3) and UFM of
    the real architectures, seeded, as one :class:`Estimators` (with ``more`` of its fields:
    ``segmenter``, ``tiny_decoder``): what the ``tiny-random`` ids load (offline, CPU, seconds)."""
    from .ufm import UFM, UFMConfig

    if geometry == "da3":
        from .da3 import DA3, DA3Config

        geometry_model = DA3.random(DA3Config.tiny(), seed=seed)
    elif geometry == "vggt":
        from .vggt import VGGT, VGGTConfig

        geometry_model = VGGT.random(VGGTConfig.tiny(), seed=seed)
    else:
        raise ValueError(f"tiny geometry estimator {geometry!r}: one of 'vggt', 'da3'")
    return Estimators(geometry_model, UFM.random(UFMConfig.tiny(), seed=seed), **more)


def geometry_source(geometry: str) -> str:
    """What ``estimators.geometry`` loads: a backbone name's hub id (:data:`GEOMETRY_BACKBONES`),
    else the value itself (a hub id, a folder, a tiny id)."""
    return GEOMETRY_BACKBONES.get(geometry.lower(), geometry)


def geometry_architecture(geometry: str) -> str:
    """``"da3"`` or ``"vggt"``: the architecture ``estimators.geometry`` loads, known without
    loading it: a Depth Anything 3 name, tiny id or hub id (``depth-anything/DA3...``), or a local
    folder (or a file in one) whose ``config.json`` is a Depth Anything 3 one; anything else is
    VGGT."""
    source = geometry_source(geometry)
    if source == TINY_RANDOM_DA3 or source.lower().startswith("depth-anything/da3"):
        return "da3"
    path = Path(source).expanduser()
    config = (path.parent if path.is_file() else path) / "config.json"
    if not config.is_file():
        return "vggt"
    try:
        raw = json.loads(config.read_text(encoding="utf-8"))
    except (UnicodeDecodeError, json.JSONDecodeError):
        return "vggt"  # the VGGT loader names the unreadable file
    # the published files' ``model_name`` / ``config``, or our own save's ``alt_start``
    return "da3" if isinstance(raw, dict) and ({"model_name", "config", "alt_start"} & set(raw)) else "vggt"


def flow_source(flow: str) -> str:
    """What ``estimators.flow`` loads: a flow estimator name's hub id (:data:`FLOW_ESTIMATORS`),
    the weights after ``waft:``, else the value itself (a hub id, a folder, a tiny id).

    Raises:
        OptionError: ``waft:`` with nothing after it.
    """
    if flow.startswith(WAFT_PREFIX):
        if not flow[len(WAFT_PREFIX):].strip():
            raise OptionError("estimators.flow", "'waft:' needs a hub id or a local path after it")
        return flow[len(WAFT_PREFIX):]
    return FLOW_ESTIMATORS.get(flow.lower(), flow)


def flow_architecture(flow: str) -> str:
    """``"waft"`` or ``"ufm"``: the architecture ``estimators.flow`` loads, known without loading
    it: ``waft`` names, ``waft:...``, the tiny WAFT, the WAFT hub id, or a local folder (or a file
    in one) whose ``config.json`` says ``"architecture": "waft"``; anything else is UFM."""
    source = flow_source(flow)
    if flow.startswith(WAFT_PREFIX) or source in (TINY_RANDOM_WAFT, FLOW_ESTIMATORS["waft"]):
        return "waft"
    path = Path(source).expanduser()
    config = (path.parent if path.is_file() else path) / "config.json"
    try:
        raw = json.loads(config.read_text(encoding="utf-8")) if config.is_file() else None
    except (UnicodeDecodeError, json.JSONDecodeError):
        return "ufm"  # the UFM loader names the unreadable file
    return "waft" if isinstance(raw, dict) and raw.get("architecture") == "waft" else "ufm"


def _flow_class(flow: str) -> Any:
    if flow_architecture(flow) == "waft":
        from .waft import WAFT

        return WAFT
    from .ufm import UFM

    return UFM


def _load_flow(estimators_cfg: EstimatorsConfig, dtype: torch.dtype, device: torch.device) -> Any:
    """The flow estimator of ``estimators.flow`` (not ``tiny-random``), its trunk in ``dtype``."""
    if estimators_cfg.flow == TINY_RANDOM_WAFT:
        from .waft import WAFT, WAFTConfig

        return WAFT.random(WAFTConfig.tiny(), seed=estimators_cfg.init_seed).to(device).trunk_to(dtype)
    source = flow_source(estimators_cfg.flow)
    flow_class = _flow_class(estimators_cfg.flow)
    try:
        return flow_class.from_pretrained(source, dtype=dtype, device=device)
    except WeightsNotFoundError as err:
        example = "waft:/path/to/WAFT" if flow_class.model_name == "WAFT" else "/path/to/UFM-Base"
        raise with_config_key(err, "estimators.flow", example) from None


def _geometry_class(geometry: str) -> Any:
    if geometry_architecture(geometry) == "da3":
        from .da3 import DA3

        return DA3
    from .vggt import VGGT

    return VGGT


def tiny_random_decoder(variant: str | None = None, seed: int = 0, latent_channels: int | None = None) -> Any:
    """A tiny random :class:`~.tiny_decoder.TinyDecoder` of ``variant`` (default: the default
    model's, :data:`~.tiny_decoder.DEFAULT_VARIANT`) (frozen, float32): what
    ``estimators.tiny_decoder=tiny-random`` loads. ``latent_channels``: the latents it takes when
    they are not the variant's (the tiny models' VAE makes 4; the published variants take 16 or
    more)."""
    from dataclasses import replace

    from .tiny_decoder import DEFAULT_VARIANT, TinyDecoder, resolve_variant

    spec = resolve_variant(DEFAULT_VARIANT if variant is None else variant)
    if latent_channels is not None:
        spec = replace(spec, latent_channels=latent_channels)
    return TinyDecoder.tiny(spec, seed)


def with_config_key(err: Exception, key: str, example: str) -> WeightsNotFoundError:
    """``err``'s one line, ending with the config key that points at local weights instead."""
    return WeightsNotFoundError(f"{err} (config: {key}={example})")


def estimator_ids(estimators_cfg: EstimatorsConfig, segmenter: bool = False) -> dict[str, str]:
    """The ids :func:`load_estimators` gives the models of ``estimators_cfg`` (``segmenter``: also
    the text segmenter's), without loading them: a report written without the models names them
    as a loaded :class:`Estimators` does (:meth:`Estimators.ids`)."""
    names = {"geometry": geometry_source(estimators_cfg.geometry), "flow": flow_source(estimators_cfg.flow)}
    if segmenter:
        names["segmenter"] = estimators_cfg.segmenter
    # tiny random models are only reproducible with their seed
    return {key: f"{name}(seed={estimators_cfg.init_seed})" if name.startswith(TINY_RANDOM) else name
            for key, name in names.items()}


def estimator_weight_sources(estimators_cfg: EstimatorsConfig, segmenter: bool = False) -> list[WeightsSource]:
    """The :class:`~.loading.WeightsSource` of every model ``estimators_cfg`` names: geometry, flow
    and, with ``segmenter``, the text segmenter's one or two; ``tiny-random`` models have none."""
    from .segmenters import segmenter_weight_sources

    geometry, flow = _geometry_class(estimators_cfg.geometry), _flow_class(estimators_cfg.flow)
    # WAFT weights may come without a config.json (the authors' .pth files): its weights files say it
    flow_files = tuple(flow.checkpoint_files) if flow.model_name == "WAFT" else ("config.json",)
    rows = [WeightsSource("estimators.geometry", geometry_source(estimators_cfg.geometry), geometry.model_name,
                          tuple(geometry.checkpoint_files)),
            WeightsSource("estimators.flow", flow_source(estimators_cfg.flow), flow.model_name, flow_files,
                          example="waft:/path/to/WAFT" if flow.model_name == "WAFT" else None)]
    rows = [row for row in rows if row.source not in (TINY_RANDOM, TINY_RANDOM_DA3, TINY_RANDOM_WAFT)]
    return rows + (segmenter_weight_sources(estimators_cfg.segmenter) if segmenter else [])


def check_weights(estimators_cfg: EstimatorsConfig, *, segmenter: bool = False,
                  extra: Sequence[WeightsSource] = ()) -> None:
    """Whether every model a run loads can find its weights, found out before any loads: the
    ``extra`` ones (a generating command's video model, say) and the estimators of
    ``estimators_cfg`` (:func:`estimator_weight_sources`), in that order.

    Raises:
        WeightsNotFoundError: one line naming every model whose weights are missing
            (:func:`~.loading.check_weight_sources`: each as loading it would say it, with the
            config key that points at a local path instead).
    """
    check_weight_sources([*extra, *estimator_weight_sources(estimators_cfg, segmenter)])


def load_segmenter(estimators_cfg: EstimatorsConfig, device: str | torch.device = "auto") -> Any:
    """The text segmenter of ``estimators.segmenter`` in ``estimators.dtype`` on ``device``, loaded
    once for any subject text (:func:`~geco_guide.estimators.segmenters.segmenters_from_spec`):
    what :meth:`Estimators.with_segmenter` takes, with its id (:func:`segmenter_id`).

    Raises:
        WeightsNotFoundError: one line naming the repo id, ``estimators.segmenter`` and how to
            pass a local folder.
    """
    from .segmenters import segmenters_from_spec

    return segmenters_from_spec(estimators_cfg.segmenter, device=resolve_device(device),
                                dtype=getattr(torch, estimators_cfg.dtype), seed=estimators_cfg.init_seed)


def segmenter_id(estimators_cfg: EstimatorsConfig) -> str:
    """The id of the text segmenter :func:`load_segmenter` loads (:func:`estimator_ids`)."""
    return estimator_ids(estimators_cfg, segmenter=True)["segmenter"]


def load_estimators(estimators_cfg: EstimatorsConfig, device: str | torch.device = "auto", *,
                    segmenter: bool = False) -> Estimators:
    """The :class:`Estimators` of ``estimators_cfg``: frozen, in eval mode, on ``device``.

    Args:
        estimators_cfg: :class:`~geco_guide.config.EstimatorsConfig` (``geometry`` / ``flow``: a
            hub id, a local folder or ``tiny-random``; ``dtype`` of their trunks, the heads and
            outputs stay float32; ``gradient_checkpointing`` of their trunks; ``init_seed`` of
            tiny models; ``segmenter``: the text segmenter's weights).
        device: a torch device or ``"auto"``.
        segmenter: also load the text segmenter of ``estimators.segmenter`` (:func:`load_segmenter`)
            as the bundle's ``segmenter``; without it the bundle has none.

    The bundle keeps the id each model came from (:func:`estimator_ids`) so results can name
    their models (:meth:`Estimators.ids`).

    Raises:
        WeightsNotFoundError: one line naming the repo id and the config key to point at a local
            folder instead, when the weights are unavailable.
    """
    dtype = getattr(torch, estimators_cfg.dtype)
    ids = estimator_ids(estimators_cfg, segmenter=segmenter)
    tiny = None
    if estimators_cfg.geometry in (TINY_RANDOM, TINY_RANDOM_DA3) or estimators_cfg.flow == TINY_RANDOM:
        tiny = tiny_estimators(estimators_cfg.init_seed, geometry_architecture(estimators_cfg.geometry))
    # the segmenter before the larger models: its missing weights end the run before they load
    segment = load_segmenter(estimators_cfg, device) if segmenter else None
    device = resolve_device(device)
    if estimators_cfg.geometry in (TINY_RANDOM, TINY_RANDOM_DA3):
        geometry = tiny.geometry.to(device).trunk_to(dtype)
    else:
        source = geometry_source(estimators_cfg.geometry)
        try:
            geometry = _geometry_class(source).from_pretrained(source, dtype=dtype, device=device)
        except WeightsNotFoundError as err:
            example = "/path/to/DA3-BASE" if geometry_architecture(source) == "da3" else "/path/to/VGGT-1B"
            raise with_config_key(err, "estimators.geometry", example) from None
    if estimators_cfg.flow == TINY_RANDOM:
        flow = tiny.flow.to(device).trunk_to(dtype)
    else:
        flow = _load_flow(estimators_cfg, dtype, device)
    for model in (geometry, flow):
        model.eval().requires_grad_(False)
        model.gradient_checkpointing = estimators_cfg.gradient_checkpointing
    return Estimators(geometry, flow, segment, sources=ids)
