"""The models GeCo runs with, as one object: :class:`Estimators`.

The geometry and flow estimators always travel together (every loss, score and guided call needs
both), the text segmenter of moving subjects goes wherever they go when a run masks subjects, and
the tiny decoder goes with them when guidance decodes its anchor frames with it. One object is
the only way they enter the loss, the metric, the pipeline and the hooks: it keeps them from
being passed as a positional pair, whose order a caller can swap without an error, and gives
reports one place to read the models' ids from.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field, fields, replace
from typing import Any

from ..types import DynamicMaskSource

__all__ = ["Estimators", "estimator_id"]


def estimator_id(model: Any) -> str:
    """What produced the numbers of a model the bundle knows no source of: a mask source's name,
    else its class name."""
    return getattr(model, "source_name", None) or type(model).__name__


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
        sources: the id each model was loaded from, by field name (``{"geometry":
            "facebook/VGGT-1B", "flow": "tiny-random(seed=0)"}``): what :meth:`ids` names them
            by; a model without one is named by :func:`estimator_id`. The loaders fill it.

    The bundle is not a pair: ``geometry, flow = estimators`` is refused (it was the return value
    of ``load_estimators`` once).
    """

    geometry: Any
    flow: Any
    segmenter: Any = None
    tiny_decoder: Any = None
    sources: Mapping[str, str] = field(default_factory=dict)

    def ids(self, *names: str) -> dict[str, str]:
        """The id of every model present (of the fields ``names`` alone where given), by field
        name: its source where the bundle has one, else :func:`estimator_id`. What reports and
        sidecars name the models with."""
        return {name: self.sources.get(name) or estimator_id(model) for name, model in self._models().items()
                if not names or name in names}

    def _models(self) -> dict[str, Any]:
        """Every model present, by field name, in field order."""
        models = {f.name: getattr(self, f.name) for f in fields(self) if f.name != "sources"}
        return {name: model for name, model in models.items() if model is not None}

    def _with(self, name: str, model: Any, source: str | None) -> Estimators:
        sources = {key: value for key, value in self.sources.items() if key != name}
        if model is not None and source is not None:
            sources[name] = source
        return replace(self, **{name: model}, sources=sources)

    def __repr__(self) -> str:
        return f"Estimators({', '.join(f'{name}={value}' for name, value in self.ids().items())})"

    def with_segmenter(self, segmenter: Any, source: str | None = None) -> Estimators:
        """The same estimators with ``segmenter`` (``None``: without one), loaded from ``source``
        (its id; ``None``: none known)."""
        return self._with("segmenter", segmenter, source)

    def with_tiny_decoder(self, tiny_decoder: Any, source: str | None = None) -> Estimators:
        """The same estimators with ``tiny_decoder`` (``None``: without one), loaded from
        ``source`` (its id; ``None``: none known)."""
        return self._with("tiny_decoder", tiny_decoder, source)

    def modules(self) -> list[Any]:
        """Every model present, in field order: what a guided call freezes and moves."""
        return list(self._models().values())

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
