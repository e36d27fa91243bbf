"""Where dynamic masks come from: one factory, :func:`mask_source`, for given, automatic and text masks.

Every source meets :class:`~geco_guide.types.DynamicMaskSource`: frames ``[S, 3, H, W]`` (plus
the geometry and flow GeCo estimated on them) -> a boolean ``[S, H, W]`` mask, true where content
may move on its own. The three kinds:

- **given** (:class:`GivenMasks`): a tensor, a mask video, a folder of PNGs or an ``.npz``
  (:mod:`geco_guide.io.masks`), resized (nearest) to the frames;
- **automatic** (``"auto"``, :class:`~.motion_masks.MotionMasks`): regions whose residual flow a
  rigid motion of their own explains, found from GeCo's own depth, cameras and flow;
- **text** (``"a dog, a person"``): an open-vocabulary video segmenter,
  :func:`geco_guide.estimators.segmenters.text_segmenter`.
"""

from __future__ import annotations

import inspect
import os
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

import torch
from torch import Tensor

from ..io.masks import MASK_SUFFIXES, MaskReadError, check_masks, fit_masks, mask_file_name, read_masks
from ..io.video import IMAGE_SUFFIXES, VIDEO_SUFFIXES
from ..types import NAMED_MASK_SOURCES, Correspondences, DynamicMaskSource, SceneGeometry

__all__ = ["AUTO", "GivenMasks", "looks_like_path", "mask_source"]

AUTO = "auto"


class GivenMasks:
    """Masks known in advance, as a :class:`DynamicMaskSource`.

    Args:
        masks: ``[S, H, W]`` bool (or 0/1) for the ``S`` frames the source will be asked about;
            any size of the frames' aspect ratio (resized, nearest, to the frames).
        source_name: what results call them (``"given"``, ``"given: masks.npz"``).
        path: the mask file they were read from, or ``None``: messages about them name it.
    """

    def __init__(self, masks: Tensor, source_name: str = "given", path: str | os.PathLike | None = None) -> None:
        self.masks = check_masks(masks).cpu()
        self.source_name = source_name
        self.path = None if path is None else os.fspath(path)

    @property
    def name(self) -> str:
        """What messages call them: ``mask file '...'``, or ``dynamic masks (<source name>)``."""
        return f"dynamic masks ({self.source_name})" if self.path is None else mask_file_name(self.path)

    @classmethod
    def from_path(cls, path: str | os.PathLike, select: Sequence[int] | None = None) -> GivenMasks:
        """Masks read from a mask video, PNG folder or ``.npz`` (:func:`~geco_guide.io.masks.read_masks`);
        ``select`` keeps those source frames only."""
        masks, _ = read_masks(path, select)
        return cls(masks, f"given: {path}", path)

    def at(self, indices: Sequence[int], num_frames: int) -> GivenMasks:
        """The masks of source frames ``indices`` of a video of ``num_frames`` frames (the
        protocol's selection), after checking that the masks cover that video frame for frame."""
        if self.masks.shape[0] != num_frames:
            raise MaskReadError(f"{self.name} {'hold' if self.path is None else 'holds'} {self.masks.shape[0]} "
                                f"frame(s), the video {num_frames}")
        return GivenMasks(self.masks[list(indices)], self.source_name, self.path)

    def dynamic_masks(self, frames: Tensor, geometry: SceneGeometry | None = None,
                      flow: Correspondences | None = None,
                      pairs: Sequence[tuple[int, int]] | None = None) -> Tensor:
        """``frames [S, 3, H, W]`` -> the given masks ``[S, H, W]`` bool at ``H x W``, on the
        frames' device (MaskReadError when ``S`` differs)."""
        masks = fit_masks(self.masks, frames.shape[-4], tuple(frames.shape[-2:]), self.name)
        return masks.to(frames.device)


def looks_like_path(spec: str) -> bool:
    """Whether ``spec`` names a mask file or folder rather than text: it exists, holds a path
    separator or ends in a mask, video or image suffix (or ``.npy``, to be refused as a mask
    file). An empty or blank string is none: ``Path("")`` is the working folder."""
    suffixes = MASK_SUFFIXES + VIDEO_SUFFIXES + IMAGE_SUFFIXES + (".npy",)
    return bool(spec.strip()) and (Path(spec).exists() or os.sep in spec or spec.lower().endswith(suffixes))


def mask_source(spec: Any, *, device: str | torch.device = "cpu", **options: Any) -> DynamicMaskSource | None:
    """The dynamic-mask source that ``spec`` names.

    Args:
        spec: ``None`` (no masks: GeCo as in the paper) -> ``None``; a
            :class:`~geco_guide.types.DynamicMaskSource` -> itself; a tensor ``[S, H, W]`` ->
            :class:`GivenMasks`; ``"auto"`` -> :class:`~.motion_masks.MotionMasks`; a path (an
            existing file or folder, or a string with a path separator or a mask/video/image
            suffix) -> :class:`GivenMasks` read from it; any other string is text naming what
            moves (``"a dog, a person"``) for the text segmenter.
        device: where a text segmenter runs (given and automatic masks follow the frames).
        **options: the chosen source's options: ``dilation`` (pixels), ``seed`` ... of
            :class:`~.motion_masks.MotionMasks`; ``source`` (weights), ``dtype`` ... of
            :func:`~geco_guide.estimators.segmenters.text_segmenter`. None for given masks.

    Raises:
        MaskReadError: an unreadable or invalid mask file or tensor (one line, before any model
            loads); ValueError: options the source does not take, or an empty spec.
    """
    if spec is None:
        return None
    if isinstance(spec, Tensor):
        _no_options("given masks", options)
        return GivenMasks(spec)
    if isinstance(spec, DynamicMaskSource):
        _no_options(spec.source_name, options)
        return spec
    if isinstance(spec, os.PathLike):
        spec = os.fspath(spec)
    if not isinstance(spec, str):
        raise ValueError(f"dynamic masks must be None, a tensor, a path, 'auto', text or a mask source, got {type(spec).__name__}")
    text = spec.strip()
    if not text:
        raise ValueError("dynamic masks must not be an empty string: give a path, 'auto' or what moves (e.g. 'a dog')")
    if text == AUTO:
        from .motion_masks import MotionMasks

        return MotionMasks(**_known_options("the automatic mask source", MotionMasks, options))
    if looks_like_path(text):
        _no_options("given masks", options)
        return GivenMasks.from_path(text)
    try:
        from .segmenters import text_segmenter
    except ModuleNotFoundError as err:
        if err.name != f"{__package__}.segmenters":
            raise
        raise ValueError(f"text dynamic masks ({text!r}) need a text segmenter, which this install lacks; "
                         "pass a mask file or 'auto' instead") from None
    return text_segmenter(text, device=device, **_known_options("a text segmenter", text_segmenter, options))


def _no_options(what: str, options: dict[str, Any]) -> None:
    if options:
        raise ValueError(f"{what} take no options, got {sorted(options)}")


def _known_options(what: str, factory: Callable[..., Any], options: dict[str, Any]) -> dict[str, Any]:
    """``options`` after checking that ``factory`` takes each as a keyword (its keyword-only
    parameters, less ``device``, which :func:`mask_source` passes itself): ValueError naming
    the unknown ones and the known, not the TypeError of the call."""
    known = [name for name, parameter in inspect.signature(factory).parameters.items()
             if parameter.kind is inspect.Parameter.KEYWORD_ONLY and name != "device"]
    unknown = sorted(set(options) - set(known))
    if unknown:
        raise ValueError(f"{what} takes no option(s) {unknown}; its options: {', '.join(known)}")
    return options


NAMED_MASK_SOURCES[AUTO] = lambda: mask_source(AUTO)
