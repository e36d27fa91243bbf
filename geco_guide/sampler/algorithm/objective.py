"""What a guided update minimises: decode the anchor frames of the clean estimate, then score them.

:class:`AnchorObjective` is the ``objective`` of :func:`~.step.guided_step`, ``x0 -> (loss,
terms)``, built from parts that each do one thing: the model's latent layout
(``latent_frames``), the anchor decode strategy of the memory plan
(:mod:`.anchor_decode`), the GeCo loss and the call's dynamic masks. A fallback to another plan
makes a new objective with another decode (:meth:`AnchorObjective.with_decode`); the loss, and
the estimators in it, stay.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, replace
from typing import Any

from torch import Tensor

from .dynamic import RefreshedMasks
from .step import loss_terms

__all__ = ["AnchorObjective"]


@dataclass(frozen=True)
class AnchorObjective:
    """The GeCo loss of the anchor frames decoded from a clean estimate.

    Attributes:
        decode: ``latents [B, F, C, h, w] -> anchor frames [B, S, 3, H, W]`` in ``[0, 1]``
            (differentiable): a strategy of :mod:`.anchor_decode`.
        latent_frames: ``x0 -> [B, F, C, h, w]``: the video's latents, frames first, of the model's
            clean estimate (drops padding frames, reorders channels).
        loss_fn: ``frames -> GeCoResult`` (a :class:`~geco_guide.loss.geco.GeCoLoss`).
        dynamic_masks: what moves on its own, left out of the loss, or ``None`` (the paper).
    """

    decode: Callable[[Tensor], Tensor]
    latent_frames: Callable[[Tensor], Tensor]
    loss_fn: Callable[..., Any]
    dynamic_masks: RefreshedMasks | None = None

    def __call__(self, x0: Tensor) -> tuple[Tensor, dict[str, Tensor]]:
        """``x0 -> (loss, terms)``: the loss to differentiate and the 0-dim tensors of the record."""
        return self.score(self.decode(self.latent_frames(x0)))

    def score(self, frames: Tensor) -> tuple[Tensor, dict[str, Tensor]]:
        """The loss and terms of anchor ``frames [B, S, 3, H, W]``; with dynamic masks, one update of
        theirs (:meth:`~.dynamic.RefreshedMasks.start_update`)."""
        if self.dynamic_masks is None:
            return loss_terms(self.loss_fn(frames))
        self.dynamic_masks.start_update()
        if self.dynamic_masks.movers is None:
            return loss_terms(self.loss_fn(frames, dynamic_masks=self.dynamic_masks))
        return loss_terms(self.loss_fn(frames, dynamic_masks=self.dynamic_masks, movers=self.dynamic_masks.movers))

    def with_decode(self, decode: Callable[[Tensor], Tensor]) -> AnchorObjective:
        """The same objective with another anchor decode (another plan's)."""
        return replace(self, decode=decode)
