"""The data both sides of GeCo share, and the checks at its public entry points.

The two small protocols GeCo needs from its frozen backbones: a :class:`GeometryEstimator` turns
a clip into :class:`SceneGeometry` (per-frame depth, intrinsics, extrinsics and optionally a
confidence map), a :class:`FlowEstimator` turns batched image pairs into
:class:`Correspondences` (dense flow and a covisibility probability), both at the resolution of
the frames they are given. ``geco_guide.estimators`` implements them and ``geco_guide.loss``
consumes them; both follow the conventions of
:mod:`geco_guide.geometry` (integer pixel centres, OpenCV camera axes, camera-from-world
extrinsics, z-depth). This module imports nothing of the package, so both layers import it.

Value checks: finite frames in ``[0, 1]`` and finite options. A NaN pixel would otherwise make
every cue of its pairs invalid, so a corrupt clip would score 0.0, "perfectly consistent"; frames
in 0-255 or ``[-1, 1]`` would be scored as if they were ``[0, 1]`` images. Both are errors, raised
once where frames enter (``GeCoLoss``, ``evaluate_video``, the end of ``generate``), naming the
frames.
"""

from __future__ import annotations

import functools
import inspect
import math
import numbers
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, fields, is_dataclass, replace
from typing import Any, Protocol, TypeVar, runtime_checkable

import torch
from torch import Tensor

__all__ = ["ESTIMATOR_KEYWORDS", "NAMED_MASK_SOURCES", "Correspondences", "DynamicMaskSource", "FlowEstimator",
           "GeometryEstimator", "NonFiniteFramesError", "OptionError", "SceneGeometry", "check_estimator_bundle",
           "check_frame_values", "check_frames", "is_integer", "is_number", "merge_dataclass", "missing_estimators",
           "non_finite_fields", "plural", "refuses_earlier_keywords", "refuse_renamed_arguments", "renamed_option"]


@dataclass
class SceneGeometry:
    """Per-frame geometry of a clip.

    Attributes:
        depth: ``[B, S, H, W]`` z-depth, > 0 where valid.
        intrinsics: ``[B, S, 3, 3]`` pinhole K in pixels of the ``H x W`` frames.
        extrinsics: ``[B, S, 3, 4]`` camera-from-world ``[R | t]``.
        confidence: ``[B, S, H, W]`` larger = more reliable, or ``None`` when unavailable.
    """

    depth: Tensor
    intrinsics: Tensor
    extrinsics: Tensor
    confidence: Tensor | None = None


@dataclass
class Correspondences:
    """Dense correspondences from source to target images.

    Attributes:
        flow: ``[N, 2, H, W]`` displacement (du, dv) in pixels, ``target = source + flow``.
        covisibility: ``[N, H, W]`` probability in ``[0, 1]`` that a source pixel is visible
            in the target.
    """

    flow: Tensor
    covisibility: Tensor


@runtime_checkable
class GeometryEstimator(Protocol):
    """Anything that maps frames ``[B, S, 3, H, W]`` in ``[0, 1]`` to :class:`SceneGeometry`."""

    def estimate_geometry(self, frames: Tensor) -> SceneGeometry:
        ...


@runtime_checkable
class FlowEstimator(Protocol):
    """Anything that maps image pairs ``[N, 3, H, W]`` in ``[0, 1]`` to :class:`Correspondences`."""

    def estimate_flow(self, source: Tensor, target: Tensor) -> Correspondences:
        ...


@runtime_checkable
class DynamicMaskSource(Protocol):
    """Anything that says where a clip may move on its own: frames ``[S, 3, H, W]`` in ``[0, 1]``
    (one clip) to a boolean ``[S, H, W]`` dynamic mask, true where content may move by itself
    (GeCo leaves those pixels out). ``geometry`` / ``flow`` are what GeCo already estimated on the
    same frames (``SceneGeometry`` with batch 1, and the ``Correspondences`` of ``pairs``); a
    source that needs them (the automatic detector) reads them, a text segmenter ignores them.
    ``source_name`` says where masks came from, for results and logs (e.g. ``"sam3: a dog"``)."""

    source_name: str

    def dynamic_masks(self, frames: Tensor, geometry: SceneGeometry | None = None,
                      flow: Correspondences | None = None,
                      pairs: Sequence[tuple[int, int]] | None = None) -> Tensor:
        ...


#: The dynamic-mask sources a name stands for (``"auto"``: the automatic detector), name -> a
#: function making one. The sources sit above this floor, in :mod:`geco_guide.estimators`, which
#: fills this table when it is imported; the loss reads it, so that ``GeCoLoss(...)(frames,
#: dynamic_masks="auto")`` means what ``evaluate_video``'s ``"auto"`` means without the loss
#: importing the estimators.
NAMED_MASK_SOURCES: dict[str, Callable[[], DynamicMaskSource]] = {}


def missing_estimators(geometry: Any, flow: Any) -> list[str]:
    """Which of ``"geometry"`` / ``"flow"`` is not a :class:`GeometryEstimator` /
    :class:`FlowEstimator` (``[]`` when both are): the one protocol check of every entry point."""
    pairs = (("geometry", geometry, GeometryEstimator), ("flow", flow, FlowEstimator))
    return [name for name, estimator, protocol in pairs if not isinstance(estimator, protocol)]


#: The keyword arguments that once passed the two estimators one by one.
ESTIMATOR_KEYWORDS = ("geometry_estimator", "flow_estimator", "geometry", "flow")

_F = TypeVar("_F", bound=Callable[..., Any])


def refuses_earlier_keywords(where: str, **hints: str) -> Callable[[_F], _F]:
    """Decorate a public entry point so that a keyword it does not take is refused in one line
    (a TypeError) before the call: an earlier spelling of the estimator pair (``geometry=``,
    ``flow_estimator=``, ...) names ``estimators=Estimators(geometry, flow)``, a keyword of
    ``hints`` (earlier spelling -> where it went) names its new place, any other is refused as
    Python would, under ``where`` (e.g. ``"GeCoLoss"``). The signature stays the function's own.
    """
    def decorate(function: _F) -> _F:
        parameters = inspect.signature(function).parameters.values()
        named = {p.name for p in parameters}
        takes_any = any(p.kind is p.VAR_KEYWORD for p in parameters)  # then only the earlier spellings are refused
        earlier = {*hints, *ESTIMATOR_KEYWORDS}

        @functools.wraps(function)
        def call(*args: Any, **kwargs: Any) -> Any:
            unknown = sorted(key for key in kwargs if key not in named and (not takes_any or key in earlier))
            if unknown:
                hinted = [key for key in unknown if key in hints]
                old = [key for key in unknown if key in ESTIMATOR_KEYWORDS]
                if hinted:
                    raise TypeError(f"{where}({hinted[0]}=...) is the earlier spelling: {hints[hinted[0]]}")
                if old:
                    raise TypeError(f"{where}({old[0]}=...) is the earlier spelling: pass the models as one "
                                    "estimators=Estimators(geometry, flow) (geco_guide.Estimators)")
                raise TypeError(f"{where}() got an unexpected keyword argument {unknown[0]!r}")
            return function(*args, **kwargs)

        return call  # type: ignore[return-value]

    return decorate


def check_estimator_bundle(estimators: object, where: str, argument: str | None = None) -> Any:
    """``estimators`` if it is an estimator bundle (``.geometry`` a :class:`GeometryEstimator`,
    ``.flow`` a :class:`FlowEstimator`: :class:`geco_guide.estimators.Estimators`); refused
    otherwise in one line naming ``where`` (e.g. ``"GeCoLoss"``). Where guidance was passed its
    models by the keyword ``argument``, ``None`` is refused as models not given, naming how to pass
    them.

    Raises:
        TypeError: not a bundle (a tuple, a lone model, ``None`` without ``argument``).
        ValueError: a bundle whose geometry or flow estimator lacks its method, or ``None`` passed
            as ``argument``.
    """
    if estimators is None and argument is not None:
        raise ValueError(f"GeCo guidance needs its models: pass {argument}=Estimators(geometry, flow) to {where} "
                         "(geco_guide.Estimators; e.g. geco_guide.estimators.load_estimators)")
    if isinstance(estimators, tuple) or not (hasattr(estimators, "geometry") and hasattr(estimators, "flow")):
        raise TypeError(f"{where} takes the estimators as one Estimators(geometry, flow) (geco_guide.Estimators), "
                        f"got {type(estimators).__name__}")
    missing = missing_estimators(estimators.geometry, estimators.flow)
    if missing:
        methods = {"geometry": "estimate_geometry(frames)", "flow": "estimate_flow(source, target)"}
        name = missing[0]
        raise ValueError(f"{where}: estimators.{name} must implement {methods[name]}, got "
                         f"{type(getattr(estimators, name)).__name__}")
    return estimators


def check_frames(frames: Tensor, name: str = "frames") -> None:
    """Raise a ValueError naming ``name`` unless it is a floating ``[B, S, 3, H, W]`` tensor."""
    if not isinstance(frames, torch.Tensor):
        raise ValueError(f"{name} must be a torch.Tensor, got {type(frames).__name__}")
    if frames.ndim != 5 or frames.shape[2] != 3:
        raise ValueError(f"{name} must have shape [B, S, 3, H, W], got {list(frames.shape)}")
    if not frames.is_floating_point():
        raise ValueError(f"{name} must be a floating tensor in [0, 1], got dtype {frames.dtype}")


# Tolerated excursion outside [0, 1]: float rounding of resampled frames, while 0-255 or [-1, 1]
# frames are far outside it.
FRAME_RANGE_SLACK = 1e-3


class OptionError(ValueError):
    """An invalid value of a config dataclass's option ``key`` (a field name, dotted below the
    dataclass for nested ones): the message starts with the key, and ``key`` lets a caller that
    knows where the dataclass sits name the full config key without parsing the message."""

    def __init__(self, key: str, problem: str):
        super().__init__(f"{key} {problem}")
        self.key = key


class NonFiniteFramesError(ValueError):
    """Frames hold NaN or inf values (a corrupt input or a diverged decode)."""


def _frame_list(positions: list[int], indices: Sequence[int] | None) -> list[int]:
    return [int(indices[p]) if indices is not None else p for p in positions]


def check_frame_values(frames: Tensor, name: str = "frames", indices: Sequence[int] | None = None) -> None:
    """Raise a ValueError naming the frames unless ``frames`` are finite and in ``[0, 1]``.

    Args:
        frames: ``[S, 3, H, W]`` or ``[B, S, 3, H, W]`` (a frame is bad if it is in any video).
        name: what the message calls the tensor.
        indices: ``S`` frame numbers to report (e.g. in the source video); default ``0..S-1``.

    Raises:
        NonFiniteFramesError: a frame holds NaN or inf.
        ValueError: a frame has values outside ``[0, 1]`` (beyond :data:`FRAME_RANGE_SLACK`).

    One device-to-host copy (two numbers per frame); no copy of the frames.
    """
    if frames.numel() == 0:
        raise ValueError(f"{name} must not be empty, got shape {list(frames.shape)}")
    per_frame = frames.detach().flatten(-3)  # [..., S, 3*H*W]
    per_frame = per_frame.reshape(-1, *per_frame.shape[-2:])  # [B, S, N]
    # amin/amax propagate NaN, and an inf shows in one of them: no isfinite copy of the frames.
    low, high = torch.stack((per_frame.amin(dim=(0, 2)), per_frame.amax(dim=(0, 2)))).float().cpu()
    finite = torch.isfinite(low) & torch.isfinite(high)
    if not bool(finite.all()):
        bad = _frame_list((~finite).nonzero().flatten().tolist(), indices)
        raise NonFiniteFramesError(f"{name} must be finite: frame(s) {bad} hold NaN or inf values")
    outside = (low < -FRAME_RANGE_SLACK) | (high > 1.0 + FRAME_RANGE_SLACK)
    if bool(outside.any()):
        bad = _frame_list(outside.nonzero().flatten().tolist(), indices)
        raise ValueError(
            f"{name} must be float RGB in [0, 1]: frame(s) {bad} hold values in "
            f"[{float(low.min()):.4g}, {float(high.max()):.4g}] (divide 0-255 frames by 255, map [-1, 1] "
            "frames with x / 2 + 0.5, clamp resampled ones)"
        )


def non_finite_fields(obj: Any, prefix: str = "") -> list[tuple[str, float]]:
    """``(dotted key, value)`` of every NaN or infinite float of a dataclass, in nested dataclasses,
    lists and dicts too (``prefix`` starts the keys, e.g. ``"guidance."``)."""
    found: list[tuple[str, float]] = []
    for f in fields(obj):
        value, key = getattr(obj, f.name), f"{prefix}{f.name}"
        if is_dataclass(value):
            found.extend(non_finite_fields(value, f"{key}."))
        elif isinstance(value, dict):
            found.extend((f"{key}.{name}", v) for name, v in value.items() if _non_finite(v))
        elif isinstance(value, (list, tuple)):
            found.extend((f"{key}[{i}]", v) for i, v in enumerate(value) if _non_finite(v))
        elif _non_finite(value):
            found.append((key, value))
    return found


def _non_finite(value: Any) -> bool:
    return isinstance(value, float) and not math.isfinite(value)


T = TypeVar("T")


def merge_dataclass(obj: T, changes: Mapping[str, Any], path: str = "") -> T:
    """``obj`` (a dataclass instance) with ``changes`` (a nested mapping, e.g. parsed JSON/YAML)
    applied: a mapping merges into a dataclass field, a list takes the field's sequence type
    (tuple or list), a list of mappings becomes a list of the default elements' dataclass. An
    unknown key raises ValueError naming where it is (``path`` prefixes the names)."""
    if not hasattr(changes, "keys"):  # a dict or an omegaconf DictConfig
        raise ValueError(f"{path or 'config'} must be a mapping, got {type(changes).__name__}")
    known = {f.name for f in fields(obj)}
    unknown = sorted(set(changes) - known)
    for key in unknown:
        problem = renamed_option(type(obj), key, path)
        if problem is not None:
            raise ValueError(problem)
    if unknown:
        names = [f"{path}.{key}" if path else key for key in unknown]
        raise ValueError(f"{path or 'config'}: unknown key(s) {names}; known: {sorted(known)}")
    updates = {}
    for key, value in dict(changes).items():
        current, where = getattr(obj, key), f"{path}.{key}" if path else key
        if is_dataclass(current):
            value = merge_dataclass(current, value, where)
        elif isinstance(value, Sequence) and not isinstance(value, str):
            items = list(value)
            if isinstance(current, (list, tuple)) and current and is_dataclass(current[0]):
                element = type(current[0])
                items = [merge_dataclass(element(**{f.name: getattr(current[0], f.name) for f in fields(element)}),
                                         item, f"{where}[{k}]") for k, item in enumerate(items)]
            value = tuple(items) if isinstance(current, tuple) else items
        updates[key] = value
    try:
        return replace(obj, **updates)
    except (TypeError, ValueError) as err:
        raise ValueError(f"{path or 'config'}: {err}") from None


def renamed_option(cls: type, key: str, path: str = "", python: bool = False) -> str | None:
    """Why ``key`` is refused as an option of the dataclass ``cls`` (under ``path``, e.g.
    ``"guidance"``) when it is the earlier name of one: one line naming the new spelling, from the
    class's ``RENAMED`` table (old field -> ``(new config key, new Python spelling)``); with
    ``python``, as a keyword argument. ``None`` for a key that was never renamed."""
    new = getattr(cls, "RENAMED", {}).get(key)
    if new is None:
        return None
    config_key, python_spelling = new
    if python:
        return f"{cls.__name__}({key}=...) is the earlier spelling of {python_spelling}: use that instead"
    old = f"{path}.{key}" if path else key
    return f"{old} is the earlier name of {config_key}: use {config_key} instead"


def refuse_renamed_arguments(cls: type[T]) -> type[T]:
    """Make the dataclass ``cls`` refuse its ``RENAMED`` keyword arguments in one line naming the
    new spelling (a bare TypeError would name neither), e.g. ``GuidanceConfig(eta=3.0)``."""
    init = cls.__init__

    def __init__(self: Any, *args: Any, **kwargs: Any) -> None:
        for key in kwargs:
            problem = renamed_option(cls, key, python=True)
            if problem is not None:
                raise TypeError(problem)
        init(self, *args, **kwargs)

    __init__.__doc__, __init__.__wrapped__ = init.__doc__, init  # type: ignore[attr-defined]
    cls.__init__ = __init__  # type: ignore[method-assign]
    return cls


def is_number(value: Any) -> bool:
    """A real number of any numeric type (numpy's too), not a bool (an option's true/false is no number)."""
    return isinstance(value, numbers.Real) and not isinstance(value, bool)


def is_integer(value: Any) -> bool:
    """An integer of any numeric type (numpy's too), not a bool."""
    return isinstance(value, numbers.Integral) and not isinstance(value, bool)


def plural(count: int, noun: str) -> str:
    """``"1 window"``, ``"2 windows"``: a count and its noun (regular plurals only)."""
    return f"{count} {noun}" if count == 1 else f"{count} {noun}s"
