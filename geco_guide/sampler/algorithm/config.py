"""Guidance options (:class:`GuidanceConfig`) and the paper's two presets.

``GuidanceConfig()`` is the paper's guidance experiment, what the CLI runs by default (the
``cogvideox-5b`` preset): the residual motion cue without gradients through the geometry
estimator (:func:`~geco_guide.loss.presets.guidance_loss`). :func:`fused_guidance_config` is the
method section's fused loss (the ``cogvideox-5b-fused`` preset). See docs/guidance.md.
"""

from __future__ import annotations

import re
from collections.abc import Mapping
from dataclasses import dataclass, field, replace
from typing import Any, ClassVar, Optional

from ...estimators.tiny_decoder import CONTEXT_LATENTS
from ...families import default_anchors
from ...loss.cues import CUES, MAP_ORDER
from ...loss.geco import GeCoLossConfig, movers_problem
from ...loss.presets import fused_guidance_loss, guidance_loss
from ...types import OptionError, is_integer, is_number, merge_dataclass, non_finite_fields, refuse_renamed_arguments
from .schedule import (
    PAPER_STEP_SIZE,
    PAPER_REPEATS,
    PAPER_TIME_TRAVEL,
    GuidanceSchedule,
    scale_schedule,
)
from .slicing import AnchorChunk, anchor_latent_chunks

__all__ = ["DECODERS", "MAX_STEP_SIZE", "PAPER_ANCHORS", "GuidanceConfig", "fused_guidance_config",
           "paper_guidance_config", "resolve_guidance_config"]

PAPER_ANCHORS = (12, 24, 36, 48)
# An update moves the latents by step_size in L2 norm; 1000 is about the norm of the whole latent
# video at 480x720 (the paper: 3). Larger values only overflow the latents to NaN/inf after
# minutes of sampling (a black video), so they are refused at once.
MAX_STEP_SIZE = 1000.0
DECODERS = ("vae", "tiny")


@refuse_renamed_arguments
@dataclass
class GuidanceConfig:
    """GeCo guidance options: what guidance computes (defaults: the paper's guidance experiment,
    for 50 DDIM steps of a 49-frame video; :func:`fused_guidance_config` is the method section's
    fused loss). How one machine runs it (memory plan, decode layout, devices) is
    :class:`~geco_guide.sampler.running.run_options.RunOptions`.

    Attributes:
        enabled: ``False`` samples without guidance (plain deterministic DDIM).
        anchors: 0-based pixel frames decoded and scored during guidance; ``None``: the paper's
            four spread over the call's video (:func:`~geco_guide.families.default_anchors`:
            (12, 24, 36, 48) of 49 frames, as the paper).
        chunk_latents: latents per causal chunk decoded for each anchor (ending at its latent).
        repeats: ``R_t`` per step, as runs ``"RxN,..."`` (see :mod:`.schedule`). Runs written for
            another step count are scaled to the sampler's, phases in proportion (with a
            warning); an explicit per-step list must match exactly.
        step_size: normalised step size of each update (>= 0; the paper's eta, renamed apart from the
            scheduler's ``eta``).
        time_travel: inclusive ``[first, last]`` step window of time travel; empty/None disables.
            Scaled with the runs of ``repeats``.
        denoiser_grad: ``True`` backpropagates through the denoiser at every update (paper);
            ``False`` is the fast mode that holds the model output constant through the step
            (``dx0/dz_t = sqrt(a_t)``), so the denoiser runs once per step as without guidance
            (plus once after each time-travel re-noising).
        grad_eps: ``eps`` of the normalised update.
        decoder: what decodes the anchor frames for the loss: ``vae`` (the model's own VAE,
            exact) or ``tiny`` (an approximation: a :class:`~geco_guide.estimators.tiny_decoder.TinyDecoder`
            trained on the model's latents, a small fraction of the VAE's cost (docs/performance.md);
            its chunks are :data:`~geco_guide.estimators.tiny_decoder.CONTEXT_LATENTS` long),
            whose weights a config names in ``estimators.tiny_decoder``. The final video always
            comes from the VAE. See docs/performance.md for what it saves (predicted) and how
            to measure what it costs in fidelity (``geco bench decoder-agreement``).
        loss: the GeCo loss options (default :func:`~geco_guide.loss.presets.guidance_loss`); the
            structure cue only gives gradients with ``loss.geometry_grad=True``, since it depends
            on the frames only through the geometry estimator: ``cue="structure"`` with
            ``geometry_grad=False`` is refused before any denoising step.
        dynamic: what moves on its own and stays out of the loss (docs/guidance.md, Moving
            subjects): ``None`` (default, the paper: nothing), ``"auto"`` (the training-free
            detector on GeCo's own depth and flow) or subjects to segment, ``"a dog, a person"``
            (the text segmenter of ``estimators.segmenter``). The masks are computed on the anchor
            frames decoded from x0-hat, without gradients.
        dynamic_dilation: pixels by which the masks grow (0: as found), to cover the subjects'
            blurred edges.
        dynamic_refresh: the masks are computed at the first update of every
            ``dynamic_refresh``-th guided step and reused until then (1: each step's own, shared
            by its repeats). With ``loss.movers="rigid"`` a mover that one rigid motion of its
            own explains is scored against that motion instead (so guidance steadies its shape;
            :mod:`geco_guide.loss.movers`), its motion fitted without gradients at each refresh.
    """

    #: Earlier spellings, refused in one line naming the new one: ``eta`` was also the scheduler's
    #: name, how one machine runs guidance moved to :class:`~.run_options.RunOptions`, and
    #: ``movers`` is the loss' own option, spelt once (``guidance.loss.movers``).
    RENAMED: ClassVar[dict[str, tuple[str, str]]] = {
        "eta": ("guidance.step_size", "GuidanceConfig(step_size=...)"),
        "movers": ("guidance.loss.movers", "GuidanceConfig(loss=GeCoLossConfig(movers=...))"),
        **{key: (f"run.{key}", f"RunOptions({key}=...)") for key in (
            "memory_plan", "memory_budget_gb", "gradient_checkpointing", "vae_checkpointing",
            "vae_block_checkpointing", "decode_layout", "compile", "devices")},
    }

    enabled: bool = True
    anchors: Optional[list[int]] = None
    chunk_latents: int = 3
    repeats: str = PAPER_REPEATS
    step_size: float = PAPER_STEP_SIZE
    time_travel: Optional[list[int]] = field(default_factory=lambda: list(PAPER_TIME_TRAVEL))
    denoiser_grad: bool = True
    grad_eps: float = 1e-8
    decoder: str = "vae"
    loss: GeCoLossConfig = field(default_factory=guidance_loss)
    dynamic: Optional[str] = None
    dynamic_dilation: int = 0
    dynamic_refresh: int = 1

    def __post_init__(self) -> None:
        check_option_types(self)
        for key, value in non_finite_fields(self):  # the first one
            raise OptionError(key, f"must be a finite number, got {value}")
        if not 0 <= self.step_size <= MAX_STEP_SIZE:
            raise OptionError("step_size", f"must be in [0, {MAX_STEP_SIZE:g}], got {self.step_size}")
        if not self.grad_eps > 0:
            raise OptionError("grad_eps", f"must be > 0, got {self.grad_eps}")
        if self.chunk_latents < 2:
            raise OptionError("chunk_latents", f"must be >= 2, got {self.chunk_latents}")
        if self.decoder not in DECODERS:
            raise OptionError("decoder", f"must be one of {DECODERS}, got {self.decoder!r}")
        check_dynamic_options(self)

    @property
    def subjects(self) -> str | None:
        """The subjects :attr:`dynamic` names for a text segmenter (``None`` for ``"auto"`` or no masks)."""
        return None if self.dynamic in (None, "auto") else self.dynamic

    def schedule(self, num_steps: int) -> GuidanceSchedule:
        """The validated :class:`GuidanceSchedule` for ``num_steps`` steps (runs scaled, see
        :func:`~geco_guide.sampler.algorithm.schedule.scale_schedule`)."""
        repeats, time_travel = scale_schedule(self.repeats, self.time_travel, num_steps)
        return GuidanceSchedule.build(repeats, num_steps, self.step_size, time_travel)

    def check_loss(self) -> None:
        """ValueError (one line) for a loss that cannot give an update."""
        loss = self.loss
        if self.enabled and CUES[loss.cue].geometry_only and not loss.geometry_grad:
            others = " or ".join(name for name in MAP_ORDER if not CUES[name].geometry_only)
            raise ValueError(
                f"guidance.loss.cue={loss.cue!r} needs guidance.loss.geometry_grad=true: the {loss.cue} cue reaches the "
                "frames only through the geometry estimator, so without its gradient there is no update "
                f"(use cue={others}, or geometry_grad=true)"
            )

    def anchor_chunks(self, num_frames: int, temporal_compression: int) -> list[AnchorChunk]:
        """The causal latent chunk of each anchor of a ``num_frames`` video (ValueError for anchors
        the video cannot contain): ``chunk_latents`` long for the VAE, the tiny decoder's context
        for it."""
        length = self.chunk_latents if self.decoder == "vae" else CONTEXT_LATENTS
        return anchor_latent_chunks(self.anchors_for(num_frames, temporal_compression), num_frames,
                                    temporal_compression, length)

    def anchors_for(self, num_frames: int, temporal_compression: int) -> list[int]:
        """The anchors of a ``num_frames`` video: :attr:`anchors`, or the paper's spread over it."""
        if self.anchors is not None:
            return list(self.anchors)
        return default_anchors(num_frames, temporal_compression)

    def validate(self, num_steps: int, num_frames: int,
                 temporal_compression: int) -> tuple[GuidanceSchedule, list[AnchorChunk]]:
        """Check everything against a run; ValueError naming the problem. Returns the schedule
        and the anchors' chunks."""
        self.check_loss()
        chunks = self.anchor_chunks(num_frames, temporal_compression)
        return self.schedule(num_steps), chunks


def check_dynamic_options(config: GuidanceConfig) -> None:
    """OptionError (one line naming the key) for moving-subject options that cannot work."""
    problem = dynamic_spec_problem(config.dynamic)
    if problem is not None:
        raise OptionError("dynamic", problem)
    if not is_integer(config.dynamic_dilation) or config.dynamic_dilation < 0:
        raise OptionError("dynamic_dilation", f"must be a whole number of pixels >= 0, got {config.dynamic_dilation!r}")
    if not is_integer(config.dynamic_refresh) or config.dynamic_refresh < 1:
        raise OptionError("dynamic_refresh", f"must be a whole number of steps >= 1, got {config.dynamic_refresh!r}")
    problem = movers_problem(config.loss.movers, config.dynamic is not None, "guidance.dynamic ('auto' or the subjects "
                             "that move)")
    if problem is not None:
        raise OptionError("loss.movers", problem)


def dynamic_spec_problem(spec: Any) -> str | None:
    """Why ``spec`` is not what ``guidance.dynamic`` (``--dynamic``) takes: null, ``auto`` or the
    text of the subjects that move; ``None`` when it is. A mask file is given masks (``evaluate
    --dynamic-masks``), which guidance cannot use: the anchors' frames change at every update."""
    from ...estimators.dynamic_masks import AUTO, looks_like_path

    expected = "must be null, 'auto' or the subjects that move, e.g. 'a dog, a person'"
    if spec is None:
        return None
    if not isinstance(spec, str) or not spec.strip(" ,"):
        return f"{expected}; got {spec!r}"
    if spec.strip().lower() == AUTO and spec != AUTO:
        return f"{expected}; got {spec!r} (write auto in lower case for the automatic masks)"
    if spec == AUTO:
        return None
    if re.fullmatch(r"[\s,]*[-+]?[\d.eE]+[\s,]*", spec):
        return f"{expected}; got the number {spec!r}"
    if looks_like_path(spec):
        return (f"{expected}; got {spec!r}, which names a file: guidance computes its masks on the anchor frames "
                "of every update, so it takes no mask file")
    return None


#: The options of :class:`GuidanceConfig` that take true or false.
FLAGS = ("enabled", "denoiser_grad")


def _frame_list_problem(value: Any, example: list[int]) -> str | None:
    """Why ``value`` is not a list of integer frame or step indices, or None."""
    if not isinstance(value, (list, tuple)):
        return f"must be a list of integers, e.g. {example}, got {value!r}"
    bad = [v for v in value if not is_integer(v)]
    return f"must hold integers only, e.g. {example}, got {bad[0]!r} in {list(value)!r}" if bad else None


def check_option_types(config: GuidanceConfig) -> None:
    """OptionError (one line naming the key) for an option of the wrong type, before any value
    check: a float anchor would be truncated to another frame, a string step size would fail deep
    inside a call."""
    for key in FLAGS:
        value = getattr(config, key)
        if not isinstance(value, bool):
            raise OptionError(key, f"must be true or false, got {value!r}")
    for key in ("step_size", "grad_eps"):
        if not is_number(getattr(config, key)):
            raise OptionError(key, f"must be a number, got {getattr(config, key)!r}")
    if not is_integer(config.chunk_latents):
        raise OptionError("chunk_latents", f"must be an integer, got {config.chunk_latents!r}")
    problem = None if config.anchors is None else _frame_list_problem(config.anchors, list(PAPER_ANCHORS))
    if problem is not None:
        raise OptionError("anchors", problem)
    if config.time_travel is not None:
        problem = _frame_list_problem(config.time_travel, list(PAPER_TIME_TRAVEL))
        if problem is not None:
            raise OptionError("time_travel", problem)
    if not isinstance(config.repeats, str):
        problem = _frame_list_problem(config.repeats, [0, 0, 3])
        if problem is not None:
            raise OptionError("repeats", f"must be runs 'RxN,...' (e.g. {PAPER_REPEATS!r}) or a list of integers per "
                                         f"step; {problem.removeprefix('must be a list of integers, e.g. [0, 0, 3], ')}")
    if not isinstance(config.decoder, str):
        raise OptionError("decoder", f"must be one of {DECODERS}, got {config.decoder!r}")
    if not isinstance(config.loss, GeCoLossConfig):
        raise OptionError("loss", f"must be a GeCoLossConfig (or a mapping of its options in a config), got "
                                  f"{type(config.loss).__name__}")


def paper_guidance_config() -> GuidanceConfig:
    """The paper's guidance experiment (supplement; the published code's ``residual_motion`` loss):
    ``GuidanceConfig()``, named for the code that says so."""
    return GuidanceConfig()


def fused_guidance_config() -> GuidanceConfig:
    """The method section's equation: the fused ``M_geo`` with gradients through the geometry
    estimator too (:func:`~geco_guide.loss.presets.fused_guidance_loss`); the rest as the paper."""
    return GuidanceConfig(loss=fused_guidance_loss())


def resolve_guidance_config(
    base: GuidanceConfig | None, override: GuidanceConfig | Mapping[str, Any] | bool | None
) -> GuidanceConfig:
    """The guidance config of one call: ``override`` (config, dict of changes, or bool) over ``base``.

    ``False`` disables guidance, ``True``/``None`` keeps ``base``; a dict changes only the keys it
    names (``{"loss": {"cue": "motion"}}`` works). Unknown keys raise ValueError naming them.
    """
    base = base if base is not None else GuidanceConfig()
    if override is None or override is True:
        return base
    if override is False:
        return replace(base, enabled=False)
    if isinstance(override, GuidanceConfig):
        return override
    if hasattr(override, "keys"):  # dict or omegaconf DictConfig
        return merge_dataclass(base, override, "guidance")
    raise ValueError(f"guidance must be a GuidanceConfig, a dict, True/False or None, got {type(override).__name__}")
