"""Dynamic masks while guiding: what moves on its own, kept out of the GeCo loss.

``guidance.dynamic`` names the source (``"auto"`` or subjects, ``"a dog, a person"``); the
guided call gets it as a :class:`~geco_guide.types.DynamicMaskSource` (a text segmenter is loaded
before denoising, see :func:`load_mask_source`) and wraps it in :class:`RefreshedMasks`, which the
GeCo loss asks for each clip's masks at every update. The refresh rule: the source runs at the
first update of every ``dynamic_refresh``-th guided step, on that update's anchor frames (decoded
from x0-hat, detached), and its masks, grown by ``dynamic_dilation`` pixels, are reused until the
next refresh. A step's repeats therefore share its masks, and no gradient reaches the source.
"""

from __future__ import annotations

from collections.abc import Sequence

import torch
from torch import Tensor

from ..estimators.dynamic_masks import AUTO, mask_source
from ..estimators.motion_masks import dilate
from ..types import Correspondences, DynamicMaskSource, SceneGeometry
from .config import GuidanceConfig

__all__ = ["RefreshedMasks", "guidance_mask_source", "load_mask_source"]


class RefreshedMasks:
    """A :class:`~geco_guide.types.DynamicMaskSource` that asks ``source`` only when a refresh is
    due and answers from its last masks otherwise (see the module docstring).

    The guidance marks the start of each step with :meth:`start_step` and of each update with
    :meth:`start_update`; within an update the loss asks once per clip, in order, so the ``k``-th
    question of an update gets the ``k``-th clip's masks.

    Args:
        source: the masks' source.
        refresh: recompute at every ``refresh``-th guided step (1: every step).
        dilation: pixels by which the masks grow.
    """

    def __init__(self, source: DynamicMaskSource, refresh: int = 1, dilation: int = 0):
        self.source, self.refresh, self.dilation = source, refresh, dilation
        self.source_name = source.source_name
        self._masks: list[Tensor] = []  # per clip, the last computed
        self._guided_steps = 0
        self._step: int | None = None
        self._step_refreshes = True
        self._due = True  # the step's first update recomputes
        self._fresh = True  # this update recomputes
        self._asked = 0

    def start_step(self, step: int) -> None:
        """Guided step ``step`` begins: its first update recomputes the masks when a refresh is
        due. The same step again (the retry after an out-of-memory fallback) starts over."""
        if step != self._step:
            self._step, self._step_refreshes = step, self._guided_steps % self.refresh == 0
            self._guided_steps += 1
        self._due = self._step_refreshes

    def start_update(self) -> None:
        """An update begins: the clips are asked for again from the first."""
        self._fresh, self._due, self._asked = self._due, False, 0

    def dynamic_masks(self, frames: Tensor, geometry: SceneGeometry | None = None, flow: Correspondences | None = None,
                      pairs: Sequence[tuple[int, int]] | None = None) -> Tensor:
        """``frames [S, 3, H, W]`` -> ``[S, H, W]`` bool: the source's masks of ``frames``
        (dilated) at a refresh, else the ones last computed for this clip."""
        clip = self._asked
        self._asked += 1
        if self._fresh or clip >= len(self._masks):
            with torch.no_grad():
                masks = dilate(self.source.dynamic_masks(frames.detach(), geometry, flow, pairs), self.dilation)
            self._masks[clip:clip + 1] = [masks]
        return self._masks[clip]


def guidance_mask_source(config: GuidanceConfig, source: DynamicMaskSource | None,
                         device: torch.device | str = "cpu") -> RefreshedMasks | None:
    """The masks of a guided call: ``None`` without ``config.dynamic``; else ``source`` (or, for
    ``"auto"``, the automatic detector when no source is given) under the config's refresh rule.

    Raises:
        ValueError: (one line) a source without ``config.dynamic``, or subjects without a
            source (a text segmenter must be loaded first: :func:`load_mask_source`).
    """
    if config.dynamic is None:
        if source is not None:
            raise ValueError("dynamic_masks were given but guidance.dynamic is null: set guidance.dynamic to 'auto' or "
                             "the subjects the masks are of, so that the config says what was masked")
        return None
    if source is None:
        if config.dynamic != AUTO:
            raise ValueError(f"guidance.dynamic={config.dynamic!r} needs a text segmenter: pass dynamic_masks="
                             "text_segmenter(...) (geco_guide.estimators.segmenters), or generate from a config, which "
                             "loads estimators.segmenter")
        source = automatic_source(device)
    if not isinstance(source, DynamicMaskSource):
        raise ValueError(f"dynamic_masks must be a DynamicMaskSource (source_name and dynamic_masks(frames, ...)), "
                         f"got {type(source).__name__}")
    return RefreshedMasks(source, refresh=config.dynamic_refresh, dilation=config.dynamic_dilation)


def automatic_source(device: torch.device | str = "cpu") -> DynamicMaskSource:
    """The training-free detector of moving content on GeCo's own depth and flow
    (:class:`~geco_guide.estimators.motion_masks.MotionMasks`, its defaults)."""
    return mask_source(AUTO, device=device)


def load_mask_source(config: GuidanceConfig, segmenter: str, *, device: torch.device | str = "cpu",
                     dtype: torch.dtype = torch.float32, seed: int = 0) -> DynamicMaskSource | None:
    """The mask source ``config.dynamic`` asks for, loaded: ``None`` (no masks), the automatic
    detector (``"auto"``), or a text segmenter of the subjects with the weights ``segmenter``
    (``estimators.segmenter``, see :func:`~geco_guide.estimators.segmenters.segmenter_from_spec`).

    Raises:
        WeightsNotFoundError: the segmenter's weights are missing (one line, see
            :func:`~geco_guide.estimators.segmenters.text_segmenter`).
    """
    if config.dynamic is None:
        return None
    if config.dynamic == AUTO:
        return automatic_source(device)
    from ..estimators.segmenters import segmenter_from_spec

    return segmenter_from_spec(config.dynamic, segmenter, device=device, dtype=dtype, seed=seed)
