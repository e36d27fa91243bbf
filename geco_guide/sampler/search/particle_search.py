"""Particle search with GeCo as the verifier (sequential Monte Carlo over denoising trajectories).

``K`` particles are the batch of one pipeline call, particle ``k`` seeded by the call's ``k``-th
generator. At each resampling step (:attr:`SearchConfig.resample_steps`), after that step's
guidance if any and before the scheduler steps:

1. every particle's clean estimate ``x0 = levels.to_x0(z_t, output)`` (the scheduler's own
   parametrisation, as guidance computes it) has its anchor chunks decoded, without gradients,
   and scored by the GeCo loss with the guidance loss' settings (``guidance.loss``: pairs,
   thresholds, flow scale; the anchors and decoder of ``guidance``; without what
   ``guidance.dynamic`` names): the potential ``G_k`` is the fused score of particle ``k``'s
   anchors (:class:`ParticleScorer`); ``potential="difference"`` takes its change since the
   particle's ancestor was last scored;
2. the weights ``w_k ~ exp(-G_k / temperature)`` (a particle of non-finite score weighs 0), and
   ``K`` ancestors drawn from them by systematic or multinomial resampling from the search's own
   seeded generator (:data:`RESAMPLERS`);
3. slot ``k`` takes ancestor ``a_k``'s latents, model output and every per-particle tensor of the
   scheduler's state (:func:`~.particles.reorder_scheduler_state`: UniPC's ``model_outputs`` and
   ``last_sample``, DPM-Solver's history, ...) and of the loop (CogVideoX-DPM's
   ``old_pred_original_sample``), and guidance's dynamic masks;
4. with ``renoise``, each copy of an ancestor but the first is moved off it: a deterministic step
   to the next level and the forward process back to ``t`` with noise from its slot's generator
   (what guidance's time travel does), and its model output computed there. The samplers of the
   families are deterministic, so copies would otherwise stay identical to the end.

The lineage of every slot is recorded; :func:`geco_guide.generation.sample` keeps the final
particle of least fused score under the evaluation protocol, as best-of-N does.
"""

from __future__ import annotations

import hashlib
import logging
import math
import time
from collections.abc import Callable, Mapping, Sequence
from dataclasses import asdict, dataclass
from typing import Any, Optional

import torch
from torch import Tensor

from ...loss.cues import masked_mean
from ...types import OptionError, is_integer, is_number, merge_dataclass
from ..algorithm.config import GuidanceConfig
from ..algorithm.dynamic import RefreshedMasks
from ..algorithm.levels import NoiseLevels, keep_update, randn_like
from ..running.memory_plan import (
    DEVICE_HEADROOM,
    GIB,
    PlanChoice,
    known_model,
    load_estimates,
    predicted_parts,
    search_parts,
)
from ..running.run_options import RunOptions
from .particles import particle_batches, reorder_scheduler_state

__all__ = ["MAX_PARTICLES", "POTENTIALS", "RESAMPLERS", "ParticleBatch", "ParticleScorer", "ParticleSearch",
           "SearchConfig", "SearchCounts", "check_search_before_loading", "check_search_call", "choose_particle_batch", "clip_scores",
           "default_resample_steps", "effective_sample_size", "log_weights",
           "multinomial_resample", "normalized_weights", "particle_gb", "resolve_search_config", "search_counts",
           "search_seed",
           "systematic_resample"]

logger = logging.getLogger(__name__)

#: The most particles of a search (best-of-N's bound: each is a whole video at the end).
MAX_PARTICLES = 1000
#: What a resampling weighs: the fused score of x0-hat's anchors, or its change since the last one.
POTENTIALS = ("score", "difference")
#: About the fused score's noise floor on real videos (the GeCo paper: 0.0223 on DL3DV): the default
#: temperature, so that a particle worse by the noise floor weighs e^-1 times as much.
DEFAULT_TEMPERATURE = 0.02
#: The default resampling steps: every tenth of the schedule through its first half.
RESAMPLE_EVERY, RESAMPLE_UNTIL = 0.1, 0.5
#: The cue a particle is scored by (the protocol's selection score of best-of-N too).
SEARCH_CUE = "fused"


def systematic_resample(weights: Tensor, generator: torch.Generator) -> Tensor:
    """Systematic resampling: ``K`` ancestors ``[K]`` (long, ascending) of normalised ``weights
    [K]`` (float64), from one uniform of ``generator``: positions ``(u + k) / K`` on the weights'
    cumulative sum. A particle of weight ``w`` gets ``floor(K w)`` or ``ceil(K w)`` copies."""
    count = weights.shape[0]
    u = torch.rand((), generator=generator, dtype=torch.float64)
    positions = (u + torch.arange(count, dtype=torch.float64)) / count
    cumulative = torch.cumsum(weights.double(), 0)
    return torch.searchsorted(cumulative, positions, right=True).clamp_max(count - 1)


def multinomial_resample(weights: Tensor, generator: torch.Generator) -> Tensor:
    """Multinomial resampling: ``K`` ancestors ``[K]`` (long, ascending) drawn independently from
    normalised ``weights [K]`` with ``generator``."""
    drawn = torch.multinomial(weights.double(), weights.shape[0], replacement=True, generator=generator)
    return drawn.sort().values


#: The resampling schemes by name (``search.scheme``): ``(weights [K] float64 summing to 1,
#: generator) -> ancestors [K] long``.
RESAMPLERS: dict[str, Callable[[Tensor, torch.Generator], Tensor]] = {
    "systematic": systematic_resample,
    "multinomial": multinomial_resample,
}


def default_resample_steps(num_steps: int) -> list[int]:
    """The resampling steps of a ``num_steps`` schedule when ``search.resample_steps`` is null:
    every ``max(1, round(num_steps / 10))``-th step from that step through the middle of the
    schedule (50 steps: 5, 10, 15, 20, 25), where x0-hat already shows the layout and the motion
    that GeCo scores, and later steps mostly refine texture."""
    every = max(1, round(num_steps * RESAMPLE_EVERY))
    return list(range(every, int(num_steps * RESAMPLE_UNTIL) + 1, every))


@dataclass
class SearchConfig:
    """The config's ``search`` section: particle search with GeCo as the verifier (module
    docstring). Off by default (``particles: null``): every video is made as without it.

    Attributes:
        particles: ``K``, the particles of the search (``--search K``), from 1 to
            :data:`MAX_PARTICLES`; ``None``: no search. Particle ``k`` is seeded with ``seed + k``.
        resample_steps: the 0-based denoising steps at which the particles are scored and
            resampled; ``None``: :func:`default_resample_steps`; ``[]``: never (the particles run to
            the end and the best is kept: best-of-K in one batched call).
        temperature: of the weights ``exp(-potential / temperature)``, in units of the fused
            score (> 0): small keeps the best few, large resamples nearly uniformly.
        potential: ``score`` (the fused GeCo score of x0-hat's anchors) or ``difference`` (its
            change since the particle's ancestor was last scored: the product of the weights along
            a lineage is then the weight of its last score alone).
        scheme: ``systematic`` (default: the least resampling noise) or ``multinomial``.
        renoise: move each copy of a resampled particle but the first off its ancestor (a step to
            the next noise level and the forward process back, with its own noise), so that the
            copies explore; without it the copies of a deterministic sampler stay identical.
    """

    particles: Optional[int] = None
    resample_steps: Optional[list[int]] = None
    temperature: float = DEFAULT_TEMPERATURE
    potential: str = "score"
    scheme: str = "systematic"
    renoise: bool = True

    def __post_init__(self) -> None:
        if self.particles is not None and (not is_integer(self.particles) or not 1 <= self.particles <= MAX_PARTICLES):
            raise OptionError("particles", f"must be a whole number of particles in [1, {MAX_PARTICLES}] (or null: no "
                                           f"search), got {self.particles!r}")
        steps = self.resample_steps
        if steps is not None and (isinstance(steps, (str, bytes)) or not isinstance(steps, Sequence)
                                  or not all(is_integer(s) and s >= 0 for s in steps)):
            raise OptionError("resample_steps", f"must be a list of 0-based denoising steps (or null: every tenth of "
                                                f"the schedule through its middle), got {steps!r}")
        if steps is not None and len(set(steps)) != len(steps):
            raise OptionError("resample_steps", f"lists a step twice: {list(steps)}")
        if not is_number(self.temperature) or not math.isfinite(self.temperature) or not self.temperature > 0:
            raise OptionError("temperature", f"must be a finite number > 0, got {self.temperature!r}")
        if self.potential not in POTENTIALS:
            raise OptionError("potential", f"must be one of {', '.join(POTENTIALS)}, got {self.potential!r}")
        if self.scheme not in RESAMPLERS:
            raise OptionError("scheme", f"must be one of {', '.join(RESAMPLERS)}, got {self.scheme!r}")
        if not isinstance(self.renoise, bool):
            raise OptionError("renoise", f"must be true or false, got {self.renoise!r}")

    @property
    def enabled(self) -> bool:
        """Whether there is a search (:attr:`particles` set)."""
        return self.particles is not None

    def steps(self, num_steps: int) -> list[int]:
        """The resampling steps of a ``num_steps`` schedule, ascending.

        Raises:
            ValueError: (one line) a step outside the schedule.
        """
        steps = default_resample_steps(num_steps) if self.resample_steps is None else sorted(self.resample_steps)
        outside = [s for s in steps if not 0 <= s < num_steps]
        if outside:
            raise ValueError(f"search.resample_steps {outside} are outside the {num_steps} denoising steps (0 to "
                             f"{num_steps - 1})")
        return steps


def resolve_search_config(search: SearchConfig | Mapping[str, Any] | None) -> SearchConfig | None:
    """The search of one call: a :class:`SearchConfig`, or a dict of its fields over the defaults;
    ``None`` (and a config of no ``particles``): no search. ValueError (one line) naming an
    unknown key or a bad value."""
    if search is None:
        return None
    if not isinstance(search, SearchConfig):
        if not hasattr(search, "keys"):
            raise ValueError(f"search must be a SearchConfig or a dict, got {type(search).__name__}")
        search = merge_dataclass(SearchConfig(), search, "search")
    return search if search.enabled else None


def check_search_call(search: SearchConfig, run: RunOptions, generator: Any, search_generator: Any, *,
                      num_steps: int | None = None, videos: int | None = None) -> None:
    """What a call of a search must get right, checked before any work; ValueError (one line):
    resampling steps outside the call's ``num_steps`` (where known), ``run.split_cfg`` (a search
    deals its particles over ``run.devices`` instead), a call of ``videos`` prompts or videos
    (where known) other than one (``GeCoCogVideoXPipeline``) or the particles (a stock
    pipeline's ``num_videos_per_prompt``), a ``generator`` list of another length than the
    particles, no generator where copies are re-noised, no ``search_generator``."""
    particles = search.particles
    if num_steps is not None:
        search.steps(num_steps)
    if run.split_cfg:
        raise ValueError("run.split_cfg splits one video's CFG batch over two devices; a search deals its particles over "
                         "run.devices instead: use run.split_cfg=false")
    if videos is not None and videos != 1:
        raise ValueError(f"a search makes search.particles={particles} videos of one prompt; this call makes {videos} "
                         "(call it with one prompt: the search makes the videos)")
    if isinstance(generator, list) and len(generator) != particles:
        raise ValueError(f"search.particles={particles} needs one generator per particle, got a list of "
                         f"{len(generator)}")
    if generator is None and search.renoise:
        raise ValueError("a search re-noises its copies with the particles' own noise: pass generator=[torch.Generator()"
                         ".manual_seed(seed + k) for k in range(K)] (or search.renoise=false)")
    if not isinstance(search_generator, torch.Generator):
        raise ValueError(f"a search draws its resamplings from a generator of its own: pass search_generator="
                         f"torch.Generator().manual_seed(...) (geco_guide.sampler.search.particle_search.search_seed), got "
                         f"{type(search_generator).__name__}")


def search_seed(seed: int) -> int:
    """The seed of a search's resampling generator for a run of seed ``seed`` (a 64-bit hash of
    it: a stream apart from every particle's own, seeds ``seed .. seed + K - 1``)."""
    digest = hashlib.sha256(f"geco search {int(seed)}".encode()).digest()
    return int.from_bytes(digest[:8], "little")


def log_weights(scores: Tensor, previous: Tensor | None, temperature: float) -> Tensor:
    """``-potential / temperature`` ``[K]`` (float64) of the particles' ``scores [K]``: the score
    itself, or with ``previous`` (the scores of their ancestors at the last resampling) its change
    where that was finite. Non-finite entries are ``-inf`` (weight 0)."""
    scores = scores.double()
    potential = scores if previous is None else scores - torch.where(torch.isfinite(previous), previous.double(),
                                                                     torch.zeros_like(scores))
    log_w = -potential / temperature
    return torch.where(torch.isfinite(log_w), log_w, torch.full_like(log_w, -math.inf))


def normalized_weights(log_w: Tensor) -> Tensor | None:
    """The weights ``[K]`` summing to 1 of ``log_w [K]``, or ``None`` where no entry is finite
    (nothing to prefer: no resampling)."""
    if not bool(torch.isfinite(log_w).any()):
        return None
    return torch.softmax(log_w, 0)


def effective_sample_size(weights: Tensor) -> float:
    """``1 / sum(w^2)`` of normalised ``weights``: ``K`` for equal weights, 1 for one particle."""
    return float(1.0 / (weights.double() ** 2).sum())


def clip_scores(result: Any, cue: str = SEARCH_CUE) -> Tensor:
    """Each clip's score ``[B]`` of cue ``cue`` of a :class:`~geco_guide.loss.geco.GeCoResult`:
    the mean over its frames that count (as the batch's scalar averages them), NaN for a clip
    without any."""
    values, valid = result.frame_scores[cue], result.frame_has_valid[cue]
    score = masked_mean(values, valid, dims=(1,))
    return torch.where(valid.any(1), score, torch.full_like(score, math.nan))


class ParticleScorer:
    """The potential of each particle: the fused GeCo score ``[K]`` of the anchors of its clean
    estimate, decoded and scored without gradients, ``batch`` particles at a time.

    Args:
        decode: the anchor decode ``latents [B, F, C, h, w] -> frames [B, S, 3, H, W]`` in
            ``[0, 1]`` (guidance's: :func:`~.anchor_decode.plan_anchor_decode`).
        latent_frames: ``x0 -> [B, F, C, h, w]``: the video's latents, frames first.
        loss: ``frames -> GeCoResult`` (a :class:`~geco_guide.loss.geco.GeCoLoss` with the guidance
            loss' settings, ``check_values=False``).
        masks: guidance's dynamic masks (:func:`~.dynamic.guidance_mask_source`), or ``None``:
            each scoring asks their source afresh for every particle.
        batch: particles decoded and scored at once.
    """

    def __init__(self, decode: Callable[[Tensor], Tensor], latent_frames: Callable[[Tensor], Tensor],
                 loss: Callable[..., Any], masks: RefreshedMasks | None = None, batch: int = 1):
        self.decode, self.latent_frames, self.loss, self.masks, self.batch = decode, latent_frames, loss, masks, batch

    def __call__(self, x0: Tensor) -> Tensor:
        """``x0 [K, ...]`` (the scheduler's layout) -> the particles' scores ``[K]`` float64 on the
        CPU (one device-to-host copy); NaN for a particle whose frames are not finite or that has
        no valid pixel."""
        scores = []
        with torch.no_grad():
            for rows in particle_batches(x0.shape[0], self.batch):
                frames = self.decode(self.latent_frames(x0[rows]))
                extra = {} if self.masks is None else {
                    "dynamic_masks": RefreshedMasks(self.masks.source, dilation=self.masks.dilation)}
                result = self.loss(frames, **extra)
                finite = torch.isfinite(frames).flatten(1).all(1)
                scored = clip_scores(result)
                scores.append(torch.where(finite.to(scored.device), scored, torch.full_like(scored, math.nan)))
        return torch.cat([s.to(scores[0].device) for s in scores]).double().cpu()


def _copies_beyond_first(ancestors: Sequence[int]) -> list[int]:
    """The slots whose ancestor an earlier slot already took."""
    seen, copies = set(), []
    for slot, ancestor in enumerate(ancestors):
        if ancestor in seen:
            copies.append(slot)
        seen.add(ancestor)
    return copies


def _finite_or_none(value: float) -> float | None:
    return value if math.isfinite(value) else None


PredictRows = Callable[[Tensor, Sequence[int], bool], Tensor]


class ParticleSearch:
    """The search of one pipeline call (see the module docstring): :meth:`step` at each denoising
    step, before the scheduler's step; :meth:`report` once the loop is done.

    Args:
        config: the call's :class:`SearchConfig`.
        num_steps: the call's denoising steps (the resampling steps are checked against them).
        scorer: the particles' potentials (:class:`ParticleScorer`).
        generator: the resampling draws' generator (:func:`search_seed` from a run's seed).
        noise: the call's generator(s), one per particle: the source of the re-noising.
        batch: the most particles one denoiser call holds (re-noised particles' model outputs).
        masks: guidance's dynamic masks, carried with their particles; ``None`` without.
    """

    def __init__(self, config: SearchConfig, num_steps: int, scorer: ParticleScorer, *, generator: torch.Generator,
                 noise: torch.Generator | list[torch.Generator] | None, batch: int,
                 masks: RefreshedMasks | None = None):
        self.config, self.scorer, self.generator, self.noise = config, scorer, generator, noise
        self.batch, self.masks = batch, masks
        self.steps = config.steps(num_steps)
        self.records: list[dict[str, Any]] = []
        self.ancestry: list[list[int]] = []
        self.carried: list[str] = []
        self._previous: Tensor | None = None

    def resamples_at(self, step: int) -> bool:
        """Whether the particles are scored and resampled at denoising step ``step``."""
        return step in self.steps

    def step(self, step: int, t: int, z: Tensor, output: Tensor, levels: NoiseLevels, predict_rows: PredictRows,
             scheduler: Any, carried: Sequence[Tensor | None] = ()) -> tuple[Tensor, Tensor, list[Tensor | None]]:
        """The search at denoising step ``step`` (timestep ``t``): nothing where it does not
        resample; else score, resample and carry.

        Args:
            z: the latents ``[K, ...]`` the scheduler is about to step (guided, if guidance ran).
            output: the model output at ``z`` ``[K, ...]``.
            levels: the step's noise levels.
            predict_rows: ``(z_rows, rows, differentiate) -> model output`` of particles ``rows``
                at ``z_rows``, a call of those particles alone (the re-noised particles').
            scheduler: the pipeline's scheduler; its per-particle state is carried.
            carried: other per-particle tensors ``[K, ...]`` of the loop (``None`` entries stay).

        Returns:
            ``(z, output, carried)`` of the slots after the resampling.
        """
        if not self.resamples_at(step):
            return z, output, list(carried)
        started = time.perf_counter()
        count = z.shape[0]
        with torch.no_grad():
            scores = self.scorer(levels.to_x0(z.float(), output.float()))
        previous = self._previous if self.config.potential == "difference" else None
        weights = normalized_weights(log_weights(scores, previous, self.config.temperature))
        if weights is None:  # no particle has a finite score: nothing to prefer
            ancestors = torch.arange(count)
            logger.warning("search: no particle has a finite GeCo score at step %d; not resampled", step)
        else:
            ancestors = RESAMPLERS[self.config.scheme](weights, self.generator)
        self._previous = scores[ancestors]
        z, output, carried = self._carry(ancestors, z, output, scheduler, carried)
        renoised = _copies_beyond_first(ancestors.tolist()) if self.config.renoise else []
        if renoised:
            z, output = self._renoise(renoised, z, output, levels, predict_rows, scheduler)
        self.ancestry.append(ancestors.tolist())
        self.records.append({
            "step": step, "t": int(t), "scores": [_finite_or_none(s) for s in scores.tolist()],
            "ancestors": ancestors.tolist(), "resampled": weights is not None,
            "effective_sample_size": effective_sample_size(weights) if weights is not None else None,
            "renoised": renoised, "seconds": time.perf_counter() - started,
        })
        return z, output, carried

    def _carry(self, ancestors: Tensor, z: Tensor, output: Tensor, scheduler: Any,
               carried: Sequence[Tensor | None]) -> tuple[Tensor, Tensor, list[Tensor | None]]:
        """Slot ``k`` takes particle ``ancestors[k]``'s latents, output, scheduler state, loop
        tensors and masks."""
        index = ancestors.to(z.device)
        names = reorder_scheduler_state(scheduler, ancestors, z.shape)
        self.carried = sorted(set(self.carried) | set(names))
        if self.masks is not None:
            self.masks.reorder(ancestors.tolist())
        moved = [None if c is None else c[index.to(c.device)] for c in carried]
        return z[index], output[index.to(output.device)], moved

    def _renoise(self, slots: list[int], z: Tensor, output: Tensor, levels: NoiseLevels, predict_rows: PredictRows,
                 scheduler: Any) -> tuple[Tensor, Tensor]:
        """The copies ``slots`` moved off their ancestors (a step to the next level, then the
        forward process back to ``t`` with their own noise) and their model outputs there; the
        scheduler's history told to keep the move (:func:`~geco_guide.sampler.algorithm.levels.keep_update`)."""
        rows = torch.as_tensor(slots, device=z.device)
        start = z[rows].float()
        noise = randn_like(start, [self.noise[s] for s in slots] if isinstance(self.noise, list) else self.noise)
        moved = levels.renoise(levels.step(start, levels.to_x0(start, output[rows.to(output.device)].float())), noise)
        new_z = z.clone()
        new_z[rows] = moved.to(z.dtype)
        new_output = output.clone()
        with torch.no_grad():
            for chunk in particle_batches(len(slots), self.batch):
                chosen = [slots[c] for c in chunk]
                out = predict_rows(new_z[torch.as_tensor(chosen, device=z.device)], chosen, False)
                new_output[torch.as_tensor(chosen, device=output.device)] = out.to(output.dtype)
        keep_update(scheduler, z, new_z)
        return new_z, new_output

    def lineage(self, particle: int) -> list[int]:
        """The slots of particle ``particle``'s ancestors just before each resampling, in order
        (the first: the particle it started as, of seed ``seed + that``), then ``particle``."""
        slots = [particle]
        for ancestors in reversed(self.ancestry):
            slots.insert(0, ancestors[slots[0]])
        return slots

    def report(self, particles: int) -> dict[str, Any]:
        """What the search of a call of ``particles`` particles did: its options (the resampling
        steps resolved), each resampling's record (``step, t, scores, ancestors, resampled,
        effective_sample_size, renoised, seconds``), the scheduler state carried, and each final
        particle's lineage."""
        return {
            **asdict(self.config), "resample_steps": self.steps,
            "resamplings": self.records, "carried_state": self.carried,
            "lineages": [self.lineage(k) for k in range(particles)],
        }


@dataclass(frozen=True)
class ParticleBatch:
    """How many particles one call holds (:func:`choose_particle_batch`), and why.

    Attributes:
        size: the most particles of one denoiser call, guided update, scoring or final decode.
        reason: one line for the sidecar.
        predicted_peak_gb: the predicted peak of a sub-batch of :attr:`size` beside every
            particle's latents and video (GiB), ``None`` where the estimates do not know the model.
    """

    size: int
    reason: str
    predicted_peak_gb: float | None = None

    def to_dict(self) -> dict[str, Any]:
        return asdict(self)


#: fp32 copies of its video's size a search holds for each particle beside the work of one
#: sub-batch: its latents and model output (with the scheduler's history, a fraction of a video
#: each), and its decoded video until the selection.
PARTICLE_VIDEO_COPIES = 3


def particle_gb(frames: int, height: int, width: int) -> float:
    """What a search holds for each particle (GiB): :data:`PARTICLE_VIDEO_COPIES` fp32 videos."""
    return PARTICLE_VIDEO_COPIES * frames * 3 * height * width * 4 / GIB


#: the name of an unguided search's work among the parts :func:`choose_particle_batch` weighs
SEARCH_WORK = "search"


def choose_particle_batch(guidance: GuidanceConfig, run: RunOptions, particles: int, plan: PlanChoice | None, *,
                          signature: Mapping[str, Any] | None = None, model_id: str | None = None, frames: int,
                          height: int, width: int, device_gb: float | None, offload: bool = False, devices: int = 1,
                          estimates: Mapping[str, Any] | None = None) -> ParticleBatch:
    """The particle batch of a search of ``particles`` particles: ``run.particle_batch`` where set;
    else, for a model the estimates know (:mod:`.memory_plan`) and a known budget, the most
    particles whose work fits beside every particle's latents and video: ``weights + K x``
    :func:`particle_gb` ``+ m x activations <= budget``, the activations of one video under the
    guidance's ``plan`` (without guidance, a work that runs no backward: the unguided call's,
    :func:`~.memory_plan.search_parts`), and no more than a ``devices``-th of them (each of
    the ``devices`` of ``run.devices`` then gets a sub-batch); else one particle per call (as an
    unknown model gets the most memory-saving plan).

    Raises:
        ValueError: (one line) where even one particle's work does not fit beside the
            ``particles`` particles' latents and videos, naming how many would.
    """
    if run.particle_batch is not None:
        return ParticleBatch(min(run.particle_batch, particles), f"run.particle_batch={run.particle_batch}")
    estimates = load_estimates() if estimates is None else estimates
    key = known_model(estimates, signature=signature, model_id=model_id)
    guided = guidance.enabled
    mode = "faithful" if guided and guidance.denoiser_grad else "fast"
    entry = estimates["models"][key] if key is not None else None
    if entry is None:
        parts = None
    elif guided:
        parts = predicted_parts(entry, mode, guidance.decoder, frames, height, width, offload)
    else:  # a search's particles run no backward
        parts = {SEARCH_WORK: search_parts(entry, frames, height, width, offload)} if "unguided" in entry else None
    budget = run.memory_budget_gb
    if budget is None and device_gb is not None:
        budget = DEVICE_HEADROOM * device_gb
    if parts is None or budget is None:
        why = "no memory budget known" if parts is not None else "no estimates for this model"
        return ParticleBatch(1, f"{why}: one particle per call (run.particle_batch sets more)")
    name = plan.plan.name if guided and plan is not None and plan.plan.name in parts else (
        "fastest" if guided else SEARCH_WORK)  # an explicit plan: the one that keeps everything
    weights, activations = parts[name]
    work = f"{mode} mode, plan {name}" if guided else "unguided, no backward: bounded by the unguided call's activations"
    held = particles * particle_gb(frames, height, width)
    free = budget - weights - held
    if free < activations:
        most = int((budget - weights - activations) // particle_gb(frames, height, width))
        raise ValueError(
            f"search.particles={particles} does not fit {budget:.1f} GiB: the particles' latents and videos take "
            f"{held:.1f} GiB beside the weights ({weights:.1f} GiB) and one particle's work ({activations:.1f} GiB, "
            f"{key}, {work}); at most {max(most, 0)} particles fit (or set run.memory_budget_gb)")
    size = min(-(-particles // devices), particles if activations <= 0 else int(free // activations))
    peak = weights + held + size * activations
    return ParticleBatch(size, f"auto: the most particles predicted to fit {budget:.1f} GiB ({key}, {work})",
                         predicted_peak_gb=peak)


def check_search_before_loading(search: SearchConfig, guidance: GuidanceConfig, run: RunOptions,
                                plan: PlanChoice | None, *, model_id: str, frames: int, height: int, width: int,
                                device_gb: float | None, devices: int = 1) -> ParticleBatch:
    """The particle batch a search of a ``frames x height x width`` video of the pipeline
    ``model_id`` is predicted to get (:func:`choose_particle_batch`, the model known by its stored
    denoiser config or its id) beside the guidance's ``plan``, on ``devices`` devices of
    ``device_gb`` GiB, for a command to check before any model loads.

    Raises:
        ValueError: (one line) the particles do not fit the memory plan's budget.
    """
    from ..running.memory_plan import stored_signature

    return choose_particle_batch(guidance, run, search.particles, plan, signature=stored_signature(model_id),
                                 model_id=model_id, frames=frames, height=height, width=width, device_gb=device_gb,
                                 devices=devices)


@dataclass(frozen=True)
class SearchCounts:
    """The work of a search of ``K`` particles over ``num_steps`` steps, in one particle's units,
    beside guidance's (each particle guided as one video is): what the cost model prices.

    Attributes:
        denoiser_forwards: CFG-combined model outputs of the sampling, ``K x num_steps`` (as ``K``
            unguided videos), made as ``ceil(K / batch)`` denoiser calls per step.
        renoise_forwards_max: model outputs of re-noised copies: at most ``K - 1`` per resampling
            (the copies of a resampling; 0 without ``renoise``); the exact count is in the
            sidecar's ``renoised`` lists.
        scorings: ``K x`` resamplings: each a no-gradient decode of one particle's anchor chunks
            and the estimators' forward on its anchors (guidance's loss without its backward).
        final_decodes: ``K`` VAE decodes of a whole video (one particle at a time).
        final_evaluations: ``K`` GeCo-protocol scorings of a whole video (the selection).
    """

    denoiser_forwards: int
    renoise_forwards_max: int
    scorings: int
    final_decodes: int
    final_evaluations: int


def search_counts(config: SearchConfig, num_steps: int) -> SearchCounts:
    """The :class:`SearchCounts` of ``config`` (its ``particles`` set) over ``num_steps`` steps."""
    if not config.enabled:
        raise ValueError("search_counts needs a search: set search.particles")
    particles, resamplings = config.particles, len(config.steps(num_steps))
    return SearchCounts(
        denoiser_forwards=particles * num_steps,
        renoise_forwards_max=(particles - 1) * resamplings if config.renoise else 0,
        scorings=particles * resamplings,
        final_decodes=particles,
        final_evaluations=particles,
    )
