"""The models GeCo runs with, as one object: :class:`Estimators`.

The geometry and flow estimators always travel together (every loss, score and guided call needs
both), the text segmenter of moving subjects goes wherever they go when a run masks subjects, and
the tiny decoder goes with them when guidance decodes its anchor frames with it. One object is
the only way they enter the loss, the metric, the pipeline and the hooks: it keeps them from
being passed as a positional pair, whose order a caller can swap without an error, and gives
reports one place to read the models' ids from.
"""

from __future__ import annotations

from dataclasses import dataclass, fields, replace
from typing import Any

from ..types import DynamicMaskSource

__all__ = ["Estimators", "estimator_id"]


def estimator_id(model: Any) -> str:
    """What produced a model's numbers: the id it was loaded from, a mask source's name, else its
    class name."""
    return (getattr(model, "geco_estimator_id", None) or getattr(model, "source_name", None)
            or type(model).__name__)


@dataclass(frozen=True, eq=False)
class Estimators:
    """The frozen models of GeCo: what :func:`~geco_guide.estimators.load_estimators` returns.

    Attributes:
        geometry: the :class:`~geco_guide.types.GeometryEstimator` (e.g. VGGT).
        flow: the :class:`~geco_guide.types.FlowEstimator` (e.g. UFM).
        segmenter: the text segmenter of moving subjects, or ``None``: a
            :class:`~geco_guide.types.DynamicMaskSource` made for one text, or a
            :data:`~geco_guide.estimators.segmenters.SegmenterFactory` whose models, loaded once,
            make the mask source of any subject text (a suite whose prompts name their own
            subjects). :meth:`masks_for` gives the mask source of a text either way.
        tiny_decoder: the :class:`~geco_guide.estimators.tiny_decoder.TinyDecoder` that decodes
            the loss' anchor frames with ``guidance.decoder="tiny"`` (an approximation of the
            VAE; the video is always the VAE's), or ``None``.

    The bundle is not a pair: ``geometry, flow = estimators`` is refused (it was the return value
    of ``load_estimators`` once).
    """

    geometry: Any
    flow: Any
    segmenter: Any = None
    tiny_decoder: Any = None

    def ids(self) -> dict[str, str]:
        """The id of every model present (:func:`estimator_id`), by field name: what reports and
        sidecars name the models with."""
        return {f.name: estimator_id(getattr(self, f.name)) for f in fields(self) if getattr(self, f.name) is not None}

    def __repr__(self) -> str:
        return f"Estimators({', '.join(f'{name}={value}' for name, value in self.ids().items())})"

    def with_segmenter(self, segmenter: Any) -> Estimators:
        """The same estimators with ``segmenter`` (``None``: without one)."""
        return replace(self, segmenter=segmenter)

    def with_tiny_decoder(self, tiny_decoder: Any) -> Estimators:
        """The same estimators with ``tiny_decoder`` (``None``: without one)."""
        return replace(self, tiny_decoder=tiny_decoder)

    def modules(self) -> list[Any]:
        """Every model present, in field order: what a guided call freezes and moves."""
        return [getattr(self, f.name) for f in fields(self) if getattr(self, f.name) is not None]

    def masks_for(self, subjects: str | None) -> DynamicMaskSource | None:
        """The mask source of ``subjects`` (``"a dog, a person"``), made by the segmenter: ``None``
        for ``None`` (nothing named moves). A segmenter made for one text is that text's source.

        Raises:
            ValueError: subjects are named and there is no segmenter, a segmenter that is neither
                a mask source nor a factory of one, or a segmenter made for other subjects.
        """
        if subjects is None:
            return None
        if self.segmenter is None:
            raise ValueError(f"the subjects {subjects!r} need a segmenter, and none was loaded")
        if not isinstance(self.segmenter, DynamicMaskSource):
            if not callable(self.segmenter):  # else Python's "object is not callable", naming nothing
                raise ValueError("the segmenter must be a DynamicMaskSource (source_name and dynamic_masks(frames, "
                                 "...)) or a factory making one of a subject text, got "
                                 f"{type(self.segmenter).__name__}")
            return self.segmenter(subjects)
        from .segmenters import subjects_of

        made_for = getattr(self.segmenter, "subjects", None)
        if made_for is not None and list(made_for) != subjects_of(subjects):
            raise ValueError(f"the segmenter {estimator_id(self.segmenter)!r} masks {', '.join(made_for)}, "
                             f"not {subjects!r}: give the estimators a segmenter of those subjects")
        return self.segmenter

    def __iter__(self):
        raise TypeError("Estimators is not a (geometry, flow) pair: use estimators.geometry and estimators.flow")
