"""Dynamic masks while guiding: what moves on its own, kept out of the GeCo loss.

``guidance.dynamic`` names what moves (``"auto"`` or subjects, ``"a dog, a person"``); the
guided call makes its :class:`~geco_guide.types.DynamicMaskSource` (the automatic detector, or the
estimators' text segmenter of the subjects: :func:`guidance_mask_source`) and wraps it in
:class:`RefreshedMasks`, which the
GeCo loss asks for each clip's masks at every update. The refresh rule: the source runs at the
first update of every ``dynamic_refresh``-th guided step, on that update's anchor frames (decoded
from x0-hat, detached), and its masks, grown by ``dynamic_dilation`` pixels, are reused until the
next refresh. A step's repeats therefore share its masks, and no gradient reaches the source.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import torch
from torch import Tensor

from ...estimators.bundle import Estimators
from ...estimators.dynamic_masks import AUTO, mask_source
from ...estimators.motion_masks import dilate
from ...loss.movers import RefreshedMovers
from ...types import Correspondences, DynamicMaskSource, SceneGeometry
from .config import GuidanceConfig

__all__ = ["RefreshedMasks", "automatic_source", "guidance_mask_source"]


class RefreshedMasks:
    """A :class:`~geco_guide.types.DynamicMaskSource` that asks ``source`` only when a refresh is
    due and answers from its last masks otherwise (see the module docstring).

    The guidance marks the start of each step with :meth:`start_step` and of each update with
    :meth:`start_update`; within an update the loss asks once per clip, in order, so the ``k``-th
    question of an update gets the ``k``-th clip's masks (of a search's sub-batch of particles
    from ``first_clip`` on, the ``first_clip + k``-th). A search's resampling carries each
    particle's masks to its slots (:meth:`reorder`).

    Args:
        source: the masks' source.
        refresh: recompute at every ``refresh``-th guided step (1: every step).
        dilation: pixels by which the masks grow.
        movers: the movers' fit of ``guidance.loss.movers="rigid"``
            (:class:`~geco_guide.loss.movers.RefreshedMovers`), refitted whenever the masks are
            recomputed; ``None``: the masks only leave their content out.
    """

    def __init__(self, source: DynamicMaskSource, refresh: int = 1, dilation: int = 0,
                 movers: RefreshedMovers | None = None):
        self.source, self.refresh, self.dilation, self.movers = source, refresh, dilation, movers
        self.source_name = source.source_name
        self._masks: list[Tensor | None] = []  # per clip, the last computed
        self._guided_steps = 0
        self._step: int | None = None
        self._step_refreshes = True
        self._due = True  # the step's first update recomputes
        self._fresh = True  # this update recomputes
        self._asked = 0
        self._first = 0

    def start_step(self, step: int, first_clip: int = 0) -> None:
        """Guided step ``step`` begins for the clips from ``first_clip`` on (a search's sub-batch of
        particles; 0: the whole batch): its first update recomputes the masks when a refresh is
        due. The same step again (the retry after an out-of-memory fallback, or the step's next
        sub-batch) starts over."""
        if step != self._step:
            self._step, self._step_refreshes = step, self._guided_steps % self.refresh == 0
            self._guided_steps += 1
        self._due, self._first = self._step_refreshes, first_clip

    def start_update(self) -> None:
        """An update begins: the clips are asked for again from the first."""
        self._fresh, self._due, self._asked = self._due, False, 0

    def dynamic_masks(self, frames: Tensor, geometry: SceneGeometry | None = None, flow: Correspondences | None = None,
                      pairs: Sequence[tuple[int, int]] | None = None) -> Tensor:
        """``frames [S, 3, H, W]`` -> ``[S, H, W]`` bool: the source's masks of ``frames``
        (dilated) at a refresh, else the ones last computed for this clip."""
        clip = self._first + self._asked
        self._asked += 1
        if self._fresh or clip >= len(self._masks) or self._masks[clip] is None:
            with torch.no_grad():
                masks = dilate(self.source.dynamic_masks(frames.detach(), geometry, flow, pairs), self.dilation)
            self._masks.extend([None] * (clip + 1 - len(self._masks)))
            self._masks[clip] = masks
            if self.movers is not None:
                self.movers.refresh()
        return self._masks[clip]

    def reorder(self, ancestors: Sequence[int]) -> None:
        """A search's resampling: slot ``k`` keeps the masks last computed for particle
        ``ancestors[k]`` (none where that particle has none yet)."""
        self._masks = [self._masks[a] if a < len(self._masks) else None for a in ancestors]


def guidance_mask_source(config: GuidanceConfig, estimators: Estimators,
                         device: torch.device | str = "cpu") -> RefreshedMasks | None:
    """The masks of a guided call: ``None`` without ``config.dynamic``; for ``"auto"`` the
    automatic detector, for subjects the mask source the estimators' segmenter makes of them
    (:meth:`Estimators.masks_for <geco_guide.estimators.Estimators.masks_for>`, which checks that a
    segmenter made for one text was made for these subjects); under the config's refresh rule.

    Raises:
        ValueError: (one line) subjects without a segmenter in ``estimators``, or a segmenter of
            other subjects.
    """
    if config.dynamic is None:
        return None
    if config.dynamic == AUTO:
        source = automatic_source(device)
    else:
        if getattr(estimators, "segmenter", None) is None:
            raise ValueError(f"guidance.dynamic={config.dynamic!r} needs a text segmenter: give the estimators one "
                             "(Estimators(..., segmenter=text_segmenter(...)) or load_estimators(..., segmenter=True)), "
                             "or generate from a config, which loads estimators.segmenter")
        source = estimators.masks_for(config.dynamic)
    if not isinstance(source, DynamicMaskSource):
        raise ValueError(f"the segmenter must make a DynamicMaskSource (source_name and dynamic_masks(frames, ...)), "
                         f"got {type(source).__name__}")
    movers = RefreshedMovers() if config.loss.movers == "rigid" else None
    return RefreshedMasks(source, refresh=config.dynamic_refresh, dilation=config.dynamic_dilation, movers=movers)


def automatic_source(device: torch.device | str = "cpu") -> DynamicMaskSource:
    """The training-free detector of moving content on GeCo's own depth and flow
    (:class:`~geco_guide.estimators.motion_masks.MotionMasks`, its defaults)."""
    return mask_source(AUTO, device=device)
