"""GeCoCogVideoXPipeline: diffusers' CogVideoXPipeline with GeCo geometric-consistency guidance.

The denoising loop below is the stock ``CogVideoXPipeline`` loop, readable top to bottom, with one
addition: at a step with ``R_t > 0`` the latents get ``R_t`` GeCo updates before the step
(:meth:`GuidanceContext.guide <geco_guide.sampler.running.context.GuidanceContext.guide>`, the same
guidance the pipeline hooks use), and the pipeline's own scheduler then takes the step from the
guided latents with the model output there, exactly as the hooks hand it to ``scheduler.step``. Noise levels come
from the scheduler's ``alphas_cumprod`` with the scheduler's own rule (``t`` and
``t - num_train_timesteps // num_inference_steps``, :func:`.adapters.noise_levels`).

A drop-in ``CogVideoXPipeline``: with guidance off the call is the stock call in every respect
(any scheduler, any frame count the stock pipeline accepts, latents rounded to the model dtype
after each step as stock does), so the output is the stock output bit for bit; only ``latents``
passed by the caller are checked in both modes (their shape, finite values), before any work, where
the stock pipeline fails in the denoiser's first layer or returns an all-NaN video. With guidance on,
what guidance needs is checked up front (``4k+1`` frames, a v-prediction VP scheduler, the
estimators, no denoiser cache), and the latents are kept in fp32 between steps whatever the model
dtype (the stock pipeline rounds them to the model dtype, which adds rounding noise to an update:
measured in docs/guidance.md, "Latent precision").

The estimators enter at the call, as a guider would (``estimators=Estimators(...)``), and are no
components: ``to``, offloading, ``save_pretrained`` and ``from_pretrained`` are diffusers' own,
untouched (docs/architecture.md says why). What a call decided (the guidance log, the memory plan,
the devices, the decoder, the masks) comes back in its output, ``output.report``.
"""

from __future__ import annotations

import contextlib
import math
import os
from collections.abc import Callable, Mapping
from dataclasses import asdict, dataclass, field
from functools import partial
from typing import Any

import torch
from diffusers import CogVideoXDPMScheduler, CogVideoXPipeline
from diffusers.callbacks import MultiPipelineCallbacks, PipelineCallback
from diffusers.pipelines.cogvideo.pipeline_cogvideox import retrieve_timesteps
from diffusers.pipelines.cogvideo.pipeline_output import CogVideoXPipelineOutput
from diffusers.utils import logging
from torch import Tensor

from ...estimators.bundle import Estimators
from ...io.devices import planning_memory_gb, resolve_devices
from ...loss.geco import GeCoLoss
from ...types import check_estimator_bundle, refuses_earlier_keywords
from ..algorithm.config import GuidanceConfig, resolve_guidance_config
from ..algorithm.dynamic import guidance_mask_source
from ..algorithm.slicing import (
    check_latents,
    check_num_frames,
    check_paired_latent_frames,
    decode_chunk,
)
from ..algorithm.step import LatentsWatch
from ..diffusers_private import execution_device, offloads_models, rotary_embeddings
from ..running.anchor_decode import anchor_decoder, plan_anchor_decode
from ..running.context import GuidanceContext, GuidanceObserver, GuidanceReport
from ..running.context_parallel import start_context_parallel
from ..running.memory_plan import SAFE_PLAN, PlanChoice, choose_plan, model_signature
from ..running.multi_device import CfgHalves
from ..running.run_options import RunOptions, resolve_call_options
from ..search.particle_search import (
    ParticleBatch,
    ParticleScorer,
    ParticleSearch,
    SearchConfig,
    check_search_call,
    choose_particle_batch,
    resolve_search_config,
)
from ..search.particles import ParticleBatches, deal_final_decode, denoiser_places, output_tensor, particle_batches, particle_rows
from .adapters import adapter_for, check_no_denoiser_cache, check_scheduler, noise_levels

from diffusers.utils import is_torch_xla_available

__all__ = ["GeCoCogVideoXPipeline", "GeCoCogVideoXPipelineOutput"]

if is_torch_xla_available():  # pragma: no cover (as the stock pipeline: an XLA graph per step)
    import torch_xla.core.xla_model as xm

    XLA_AVAILABLE = True
else:
    XLA_AVAILABLE = False

logger = logging.get_logger(__name__)


@dataclass
class GeCoCogVideoXPipelineOutput(CogVideoXPipelineOutput):
    """Frames as the stock output, plus what the call decided.

    Attributes:
        frames: as :class:`CogVideoXPipelineOutput`.
        report: the call's :class:`~geco_guide.sampler.running.context.GuidanceReport`: the guidance log
            (``report.log``, one dict per guided update), the resolved guidance config, the
            memory plan, the devices, the scheduler, the decoder, the masks. Without guidance
            only ``scheduler`` is set.
    """

    report: GuidanceReport | None = None


#: The components the estimators once were, and where each went: the pipeline's constructor and
#: ``from_pretrained`` refuse them in one line.
EARLIER_COMPONENTS = {
    name: "the estimators are no components: pass estimators=Estimators(geometry, flow) (geco_guide.Estimators) "
          "to each call" for name in ("geometry_estimator", "flow_estimator")
} | {"guidance_decoder": "the tiny decoder is no component: pass estimators=Estimators(geometry, flow, "
                        "tiny_decoder=...) to each call"}

#: What ``output_type`` may be: the video processor's kinds, or the latents themselves.
OUTPUT_TYPES = ("pil", "np", "pt", "latent")


@dataclass
class _GeCoCall:
    """What one call guides and searches with, as its stages set it up
    (:meth:`GeCoCogVideoXPipeline.__call__`).

    Attributes:
        config, run, search: the call's guidance, run options and search (``None``: none),
            resolved; estimators: its models.
        schedule, chunks, decode: the guidance schedule (``None`` unguided), the anchor chunks
            and their decode (``None`` without guidance and search).
        devices, memory_plan, masks, particle_batch: the devices guidance runs on, its memory
            plan, the dynamic masks' source and a search's particle batch (each ``None`` where unused).
        denoisers: the transformer and its replicas (stage 1); geco, searcher, batches: the
            guidance, the search and its sub-batches of particles (stage 8).
    """

    config: GuidanceConfig
    run: RunOptions
    search: SearchConfig | None
    estimators: Estimators | None
    schedule: Any
    chunks: Any
    decode: Any
    devices: list[torch.device] | None
    memory_plan: PlanChoice | None
    masks: Any
    particle_batch: ParticleBatch | None
    denoisers: list[Any] = field(default_factory=list)
    geco: GuidanceContext | None = None
    searcher: ParticleSearch | None = None
    batches: Any = None

    @property
    def particles(self) -> int | None:
        """A search's ``K`` particles, ``None`` without a search."""
        return self.search.particles if self.search is not None else None


@dataclass
class _LoopInputs:
    """The denoising loop's inputs as stages 2 to 7 make them (the stock pipeline's), and its
    latents and text states after it.

    Attributes:
        latents: ``[B, F, C, h, w]`` (fp32 where ``keep_fp32``: a guided call), ``F`` with the
            ``additional_frames`` latent frames CogVideoX 1.5 pads in front.
        prompt_embeds: ``[2B, L, D]`` with CFG (the negative states first), ``[B, L, D]``
            without; negative_prompt_embeds: ``[B, L, D]`` or ``None``.
        timesteps, num_inference_steps: the scheduler's; extra_step_kwargs: its step's (eta,
            generator); image_rotary_emb: the rotary embeddings, or ``None``.
        do_classifier_free_guidance: ``guidance_scale > 1``.
    """

    latents: Tensor
    prompt_embeds: Tensor
    negative_prompt_embeds: Tensor | None
    timesteps: Tensor
    num_inference_steps: int
    extra_step_kwargs: dict[str, Any]
    image_rotary_emb: Any
    do_classifier_free_guidance: bool
    keep_fp32: bool
    additional_frames: int


class GeCoCogVideoXPipeline(CogVideoXPipeline):
    r"""Text-to-video CogVideoX with training-free GeCo geometric-consistency guidance.

    Components: the stock ``tokenizer``, ``text_encoder``, ``vae``, ``transformer``, ``scheduler``
    (any of them may be ``None``, as in the stock pipeline), and ``guidance_config``: the default
    :class:`GuidanceConfig` of its calls (a dict of its fields works too), kept in the pipeline's
    config so that ``save_pretrained`` / ``from_pretrained`` round-trip it; read it as
    ``pipe.guidance_config`` and change it per call (``guidance=``).

    The models GeCo runs with are no components: each guided call takes them, as one
    :class:`~geco_guide.estimators.Estimators` (``estimators=``: the geometry and flow estimators,
    and the text segmenter and the tiny decoder where the guidance uses them), like a guider. How
    guidance runs on this machine (memory plan, decode layout, devices) is the call's
    ``run_options`` (a :class:`~geco_guide.sampler.running.run_options.RunOptions`, or a dict of its
    fields), never saved with the pipeline: a folder saved on one card plans for the card that
    loads it.

    The scheduler is the one given, kept as is: the paper samples with deterministic DDIM, so
    choose ``CogVideoXDDIMScheduler.from_config(pipe.scheduler.config)`` for its setting (the
    ``cogvideox-5b`` preset of ``geco_guide.generate`` does, and logs it). Guidance works with
    any variance-preserving v-prediction scheduler (CogVideoX's DDIM and DPM, diffusers' DDIM).

    Example::

        pipe = GeCoCogVideoXPipeline.from_pretrained(MODELS["cogvideox-5b"].hub_id, torch_dtype=torch.bfloat16)
        pipe.scheduler = CogVideoXDDIMScheduler.from_config(pipe.scheduler.config)  # the paper's sampler
        estimators = Estimators(VGGT.from_pretrained("facebook/VGGT-1B"), UFM.from_pretrained(...))
        out = pipe("a marble bust on a turntable", estimators=estimators,  # MODELS: geco_guide.families
                   generator=torch.Generator().manual_seed(0))
        out.frames, out.report.log
    """

    @refuses_earlier_keywords("GeCoCogVideoXPipeline", **EARLIER_COMPONENTS)
    def __init__(
        self,
        tokenizer,
        text_encoder,
        vae,
        transformer,
        scheduler,
        guidance_config: GuidanceConfig | Mapping[str, Any] | None = None,
    ):
        super().__init__(tokenizer=tokenizer, text_encoder=text_encoder, vae=vae, transformer=transformer, scheduler=scheduler)
        # The pipeline's config keeps the plain dict, for model_index.json and repr().
        self.register_to_config(guidance_config=asdict(resolve_guidance_config(None, guidance_config)))
        self._cfg_halves: CfgHalves | None = None  # a guided call's run.split_cfg
        self._particle_batches: ParticleBatches | None = None  # a search's denoiser calls

    @classmethod
    def from_pretrained(cls, pretrained_model_name_or_path: str | os.PathLike, **kwargs: Any) -> GeCoCogVideoXPipeline:
        """:meth:`DiffusionPipeline.from_pretrained`, which would only warn about an earlier
        component (``geometry_estimator=``, ``flow_estimator=``, ``guidance_decoder=``) and drop
        it: refused in one line naming the call's ``estimators=`` instead."""
        earlier = sorted(set(kwargs) & set(EARLIER_COMPONENTS))
        if earlier:
            raise TypeError(f"GeCoCogVideoXPipeline.from_pretrained({earlier[0]}=...) is the earlier spelling: "
                            f"{EARLIER_COMPONENTS[earlier[0]]}")
        return super().from_pretrained(pretrained_model_name_or_path, **kwargs)

    @property
    def guidance_config(self) -> GuidanceConfig:
        """The default :class:`GuidanceConfig` of the calls, as saved in the pipeline's config."""
        return resolve_guidance_config(None, self.config.guidance_config)

    # ------------------------------------------------------------------------------------------
    # checks

    def check_geco_inputs(
        self,
        height: int,
        width: int,
        num_frames: int,
        num_steps: int,
        guidance: GuidanceConfig,
        run: RunOptions,
        estimators: Estimators | None,
        searching: bool = False,
    ):
        """Validate what guidance (or a search, ``searching``: it decodes and scores the same
        anchors) needs, before any denoising step; ValueError naming the problem.

        Nothing is checked without either (the stock pipeline's own checks apply). Returns the
        guidance schedule (``None`` without guidance), the anchor chunks and their decode
        (``(None, None, None)`` without either).
        """
        if not guidance.enabled and not searching:
            return None, None, None
        guidance.check_loss()
        multiple = self.vae_scale_factor_spatial * self.transformer.config.patch_size
        if height % multiple or width % multiple:
            raise ValueError(
                f"height and width must be multiples of {multiple} (VAE factor {self.vae_scale_factor_spatial} x "
                f"patch size {self.transformer.config.patch_size}), got height={height}, width={width}"
            )
        if getattr(self.vae, "num_latent_frames_batch_size", None) == 2:
            check_paired_latent_frames(num_frames, self.vae_scale_factor_temporal)
        else:
            check_num_frames(num_frames, self.vae_scale_factor_temporal)
        check_scheduler(self.scheduler)
        check_no_denoiser_cache([self.transformer])
        chunks = guidance.anchor_chunks(num_frames, self.vae_scale_factor_temporal)
        schedule = guidance.validate(num_steps, num_frames, self.vae_scale_factor_temporal)[0] if guidance.enabled else None
        if estimators is None and not guidance.enabled:
            raise ValueError("a search scores its particles with GeCo: pass estimators=Estimators(geometry, flow) to "
                             "the call (geco_guide.Estimators), or call without search")
        if estimators is None:
            raise ValueError("GeCo guidance needs its models: pass estimators=Estimators(geometry, flow) to the call "
                             "(geco_guide.Estimators), or call with guidance=False")
        check_estimator_bundle(estimators, "GeCo guidance")
        decode = anchor_decoder(guidance, run, lambda vae: partial(decode_chunk, vae, scaling_factor=self.vae_scaling_factor_image),
                                estimators.tiny_decoder, self.vae)
        return schedule, chunks, decode

    def choose_memory_plan(self, guidance: GuidanceConfig, run: RunOptions, num_frames: int, height: int,
                           width: int, devices: list[torch.device] | None = None) -> PlanChoice:
        """The memory plan of a guided call (:func:`~geco_guide.sampler.running.memory_plan.choose_plan`) for
        this transformer, video size and execution device, or the smallest of it and ``devices``
        (model CPU offload counted); ValueError (one line) where ``auto`` finds no plan that fits."""
        return choose_plan(guidance, run, signature=model_signature(self.transformer.config), frames=num_frames,
                           height=height, width=width, device_gb=planning_memory_gb(execution_device(self), devices),
                           offload=offloads_models(self))

    def latents_shape(self, batch_size: int, num_frames: int, height: int, width: int) -> tuple[tuple[int, ...], int]:
        """The shape ``[B, F, C, h, w]`` of the latents a call makes, and the latent frames
        CogVideoX 1.5 pads in front (to a multiple of ``patch_size_t``; 0 otherwise)."""
        latent_frames = (num_frames - 1) // self.vae_scale_factor_temporal + 1
        patch_size_t = self.transformer.config.patch_size_t
        padding = (patch_size_t - latent_frames % patch_size_t) % patch_size_t if patch_size_t is not None else 0
        scale = self.vae_scale_factor_spatial
        shape = (batch_size, latent_frames + padding, self.transformer.config.in_channels, height // scale, width // scale)
        return shape, padding

    # ------------------------------------------------------------------------------------------
    # the model, as the stock loop and the guided step see it

    def model_output(
        self,
        z: Tensor,
        *,
        t: Tensor,
        prompt_embeds: Tensor,
        image_rotary_emb: Any,
        attention_kwargs: dict | None,
        do_classifier_free_guidance: bool,
    ) -> Tensor:
        """The CFG-combined model output (fp32) at latents ``z``: the stock loop's ``noise_pred``."""
        latent_model_input = z.to(prompt_embeds.dtype)
        latent_model_input = torch.cat([latent_model_input] * 2) if do_classifier_free_guidance else latent_model_input
        latent_model_input = self.scheduler.scale_model_input(latent_model_input, t)
        timestep = t.expand(latent_model_input.shape[0])
        inputs = dict(hidden_states=latent_model_input, encoder_hidden_states=prompt_embeds, timestep=timestep,
                      image_rotary_emb=image_rotary_emb, attention_kwargs=attention_kwargs, return_dict=False)
        with self.transformer.cache_context("cond_uncond"):
            if do_classifier_free_guidance and self._cfg_halves is not None:
                noise_pred = self._cfg_halves(**inputs)
            elif self._particle_batches is not None and z.shape[0] == self._particle_batches.particles > 1:
                noise_pred = output_tensor(self._particle_batches(**inputs))
            else:
                noise_pred = self.transformer(**inputs)[0]
        noise_pred = noise_pred.float()
        if do_classifier_free_guidance:
            noise_pred_uncond, noise_pred_text = noise_pred.chunk(2)
            noise_pred = noise_pred_uncond + self.guidance_scale * (noise_pred_text - noise_pred_uncond)
        return noise_pred

    def predict(self, z: Tensor, differentiate: bool, **model_kwargs) -> Tensor:
        """The model output at ``z`` for the guided step: through the transformer's graph when
        ``differentiate`` (faithful mode), else without gradients."""
        with torch.set_grad_enabled(differentiate and torch.is_grad_enabled()):
            return self.model_output(z, **model_kwargs)

    def predict_particles(self, z: Tensor, rows: list[int], differentiate: bool, *, particles: int,
                          **model_kwargs) -> Tensor:
        """:meth:`predict` for particles ``rows`` of a search of ``particles``: ``z [len(rows), ...]``
        with their rows of the text states, a call of those particles alone."""
        embeds = model_kwargs["prompt_embeds"]
        embeds = embeds[particle_rows(particles, embeds.shape[0], rows)]
        return self.predict(z, differentiate, **{**model_kwargs, "prompt_embeds": embeds})

    # ------------------------------------------------------------------------------------------

    @refuses_earlier_keywords(
        "GeCoCogVideoXPipeline",
        dynamic_masks="name what moves in guidance={'dynamic': 'auto' or the subjects} and pass the text segmenter "
                      "in estimators=Estimators(geometry, flow, segmenter=...)")
    @torch.no_grad()
    def __call__(
        self,
        prompt: str | list[str] | None = None,
        negative_prompt: str | list[str] | None = None,
        height: int | None = None,
        width: int | None = None,
        num_frames: int | None = None,
        num_inference_steps: int = 50,
        timesteps: list[int] | None = None,
        guidance_scale: float = 6,
        use_dynamic_cfg: bool = False,
        num_videos_per_prompt: int = 1,
        eta: float = 0.0,
        generator: torch.Generator | list[torch.Generator] | None = None,
        latents: torch.FloatTensor | None = None,
        prompt_embeds: torch.FloatTensor | None = None,
        negative_prompt_embeds: torch.FloatTensor | None = None,
        output_type: str = "pil",
        return_dict: bool = True,
        attention_kwargs: dict[str, Any] | None = None,
        callback_on_step_end: Callable[[int, int], None] | PipelineCallback | MultiPipelineCallbacks | None = None,
        callback_on_step_end_tensor_inputs: list[str] = ["latents"],
        max_sequence_length: int = 226,
        guidance: GuidanceConfig | Mapping[str, Any] | bool | None = None,
        run_options: RunOptions | Mapping[str, Any] | None = None,
        estimators: Estimators | None = None,
        observer: GuidanceObserver | None = None,
        search: SearchConfig | Mapping[str, Any] | None = None,
        search_generator: torch.Generator | None = None,
    ) -> GeCoCogVideoXPipelineOutput | tuple:
        """Generate a video; arguments as :meth:`CogVideoXPipeline.__call__`, plus:

        Args:
            guidance: a :class:`GuidanceConfig`, a dict of fields overriding
                ``self.guidance_config`` (e.g. ``{"step_size": 2.0, "loss": {"cue": "motion"}}``),
                ``False`` to sample without guidance, or ``None`` for the default.
            run_options: how this call's guidance runs: a :class:`~geco_guide.sampler.running.run_options.RunOptions`
                or a dict of fields over the defaults (e.g. ``{"memory_plan": "chunked", "devices": ["cuda:0", "cuda:1"]}``).
            estimators: the models GeCo runs with, one :class:`~geco_guide.estimators.Estimators`
                (required with guidance): the geometry and flow estimators, the text segmenter
                of the subjects ``guidance.dynamic`` names (``"auto"`` needs none; see
                docs/guidance.md, Moving subjects) and the tiny decoder of ``guidance.decoder="tiny"``.
            observer: a :class:`~geco_guide.sampler.running.context.GuidanceObserver` that watches the
                updates (profilers, measurements); ``None``: nothing watches.
            eta: the scheduler's eta, passed to its ``step`` as in the stock pipeline (DDIM noise;
                ``CogVideoXDDIMScheduler`` ignores it). The GeCo step size is ``guidance.step_size``.
            search: a particle search (:class:`~geco_guide.sampler.search.particle_search.SearchConfig`, or a dict
                of its fields; ``None`` or ``particles=None``: none): ``K = search.particles``
                videos of the one prompt as one batch, scored by GeCo and resampled at its
                resampling steps (needs ``estimators``). ``generator``: a list of ``K``
                generators, one per particle (particle ``k``'s noise); the output holds the ``K``
                final videos, ``report.search`` what the search did (scores, ancestors, lineages).
            search_generator: the generator of the search's resampling draws (required with
                ``search``), apart from the particles' own.

        An earlier spelling (``geometry_estimator=``, ``dynamic_masks=``, ...) is refused in one
        line naming the new one.

        Returns:
            :class:`GeCoCogVideoXPipelineOutput` (``frames``, ``report``) or ``(frames,)`` when
            ``return_dict=False``.
        """
        if isinstance(callback_on_step_end, (PipelineCallback, MultiPipelineCallbacks)):
            callback_on_step_end_tensor_inputs = callback_on_step_end.tensor_inputs
        height = height or self.transformer.config.sample_height * self.vae_scale_factor_spatial
        width = width or self.transformer.config.sample_width * self.vae_scale_factor_spatial
        num_frames = num_frames or self.transformer.config.sample_frames
        size = (num_frames, height, width)

        # 1. Check inputs, all of them, before any work; set up what guidance and a search run with
        self.check_inputs(prompt, height, width, negative_prompt, callback_on_step_end_tensor_inputs, prompt_embeds,
                          negative_prompt_embeds)
        if output_type not in OUTPUT_TYPES:  # the stock pipeline finds out after the whole denoising
            raise ValueError(f"output_type must be one of {list(OUTPUT_TYPES)}, got {output_type!r}")
        batch_size = len(prompt) if isinstance(prompt, list) else 1 if prompt is not None else prompt_embeds.shape[0]
        call = self.set_up_geco(guidance, run_options, estimators, search, batch_size=batch_size, size=size,
                                num_steps=len(timesteps) if timesteps is not None else num_inference_steps,
                                generators=(generator, search_generator))
        self.start_call(call, guidance_scale, attention_kwargs)

        # 2.-7. The loop's inputs, as the stock pipeline makes them
        loop = self.prepare_denoising(
            call, prompt, negative_prompt, prompt_embeds, negative_prompt_embeds, batch_size=batch_size, size=size,
            latents=latents, generator=generator, eta=eta, timesteps=timesteps, num_inference_steps=num_inference_steps,
            guidance_scale=guidance_scale, max_sequence_length=max_sequence_length)

        # 8. Guidance (anchors decoded from short causal chunks, the GeCo loss, the log) and the search
        self.set_up_guidance(call, loop, generator, search_generator, observer)

        # 9. Denoising loop
        self.denoise(call, loop, callback_on_step_end, callback_on_step_end_tensor_inputs, use_dynamic_cfg=use_dynamic_cfg,
                     guidance_scale=guidance_scale, attention_kwargs=attention_kwargs)
        report = self.call_report(call)

        # 10. Decode the video
        video = self.decode_video(call, loop, output_type, report)
        self.maybe_free_model_hooks()
        if not return_dict:
            return (video,)
        return GeCoCogVideoXPipelineOutput(frames=video, report=report)

    # ------------------------------------------------------------------------------------------
    # the stages of a call

    def set_up_geco(self, guidance: GuidanceConfig | Mapping[str, Any] | bool | None,
                    run_options: RunOptions | Mapping[str, Any] | None, estimators: Estimators | None,
                    search: SearchConfig | Mapping[str, Any] | None, *, batch_size: int, size: tuple[int, int, int],
                    num_steps: int, generators: tuple[Any, torch.Generator | None]) -> _GeCoCall:
        """Stage 1 of a call, before any work: the call's guidance, run options and search resolved
        and checked (the search against the ``generators``, the particles' and its own, and the
        ``batch_size`` prompts; what guidance needs: :meth:`check_geco_inputs`), the denoiser split
        over the launch's processes (``run.context_parallel``, once), and what guidance and a
        search run with: the devices, the memory plan, the dynamic masks' source and a search's
        particle batch. ``size``: ``(num_frames, height, width)`` of the video."""
        num_frames, height, width = size
        config, run = resolve_call_options(self.guidance_config, guidance, None, run_options)
        search = resolve_search_config(search)
        if search is not None:
            check_search_call(search, run, *generators, num_steps=num_steps, videos=batch_size)
        schedule, chunks, decode = self.check_geco_inputs(height, width, num_frames, num_steps, config, run, estimators,
                                                          searching=search is not None)
        start_context_parallel(self, adapter_for(self), run, differentiates=config.enabled and config.denoiser_grad)
        working = config.enabled or search is not None
        devices = resolve_devices(run.devices) if working else None
        memory_plan = self.choose_memory_plan(config, run, num_frames, height, width, devices) if config.enabled else None
        masks = guidance_mask_source(config, estimators, execution_device(self)) if working else None
        particle_batch = choose_particle_batch(
            config, run, search.particles, memory_plan, signature=model_signature(self.transformer.config),
            frames=num_frames, height=height, width=width, device_gb=planning_memory_gb(execution_device(self), devices),
            offload=offloads_models(self), devices=len(devices) if devices else 1,
        ) if search is not None else None
        return _GeCoCall(config, run, search, estimators, schedule, chunks, decode, devices, memory_plan, masks,
                         particle_batch)

    def start_call(self, call: _GeCoCall, guidance_scale: float, attention_kwargs: dict[str, Any] | None) -> None:
        """The call's state on the pipeline, as the stock pipeline keeps it (guidance scale,
        attention kwargs, current timestep, interrupt), and its denoisers (``call.denoisers``): the
        transformer, with its replicas of ``run.split_cfg`` on a guided call with CFG (made before
        any checkpointing switch or hook of the memory plan, which then covers them too); a
        search's denoiser calls in sub-batches of particles, dealt over the devices."""
        self._guidance_scale = guidance_scale
        self._attention_kwargs = attention_kwargs
        self._current_timestep = None
        self._interrupt = False
        config, devices = call.config, call.devices
        self._cfg_halves = (CfgHalves(self.transformer, devices, execution_device(self))
                            if config.enabled and call.run.split_cfg and guidance_scale > 1.0 else None)
        replicas = [m for m in self._cfg_halves.replicas if m is not self.transformer] if self._cfg_halves else []
        call.denoisers = [self.transformer, *replicas]
        self._particle_batches = (ParticleBatches(call.particles, call.particle_batch.size,
                                                  denoiser_places(self.transformer, devices, self.transformer))
                                  if call.search is not None else None)

    def prepare_denoising(self, call: _GeCoCall, prompt: str | list[str] | None, negative_prompt: str | list[str] | None,
                          prompt_embeds: Tensor | None, negative_prompt_embeds: Tensor | None, *, batch_size: int,
                          size: tuple[int, int, int], latents: Tensor | None, generator: Any, eta: float,
                          timesteps: list[int] | None, num_inference_steps: int, guidance_scale: float,
                          max_sequence_length: int) -> _LoopInputs:
        """Stages 2 to 7 of a call, the stock pipeline's: the latents' shape (a search: ``K``
        videos of the one prompt; the caller's ``latents`` checked against it), the text states
        (repeated for each particle), the timesteps, the initial latents (fp32 with guidance),
        the scheduler's extra step kwargs and the rotary embeddings. ``size``: ``(num_frames,
        height, width)``."""
        num_frames, height, width = size
        num_videos_per_prompt = 1  # as the stock pipeline
        particles = call.particles

        # 2. Default call parameters
        videos = particles or batch_size  # a search: K videos of the one prompt
        latents_shape, additional_frames = self.latents_shape(videos, num_frames, height, width)
        check_latents(latents, latents_shape, f"a call with num_frames={num_frames}, height={height}, width={width}, "
                                               "as [batch, frames, channels, height, width]")
        device = execution_device(self)
        do_classifier_free_guidance = guidance_scale > 1.0

        # 3. Encode input prompt
        prompt_embeds, negative_prompt_embeds = self.encode_prompt(
            prompt,
            negative_prompt,
            do_classifier_free_guidance,
            num_videos_per_prompt=num_videos_per_prompt,
            prompt_embeds=prompt_embeds,
            negative_prompt_embeds=negative_prompt_embeds,
            max_sequence_length=max_sequence_length,
            device=device,
        )
        if particles is not None:  # one prompt's states for every particle, row for row the same
            prompt_embeds = prompt_embeds.repeat(particles, 1, 1)
            negative_prompt_embeds = negative_prompt_embeds.repeat(particles, 1, 1) if do_classifier_free_guidance else None
        if do_classifier_free_guidance:
            prompt_embeds = torch.cat([negative_prompt_embeds, prompt_embeds], dim=0)

        # 4. Timesteps
        timestep_device = "cpu" if XLA_AVAILABLE else device
        timesteps, num_inference_steps = retrieve_timesteps(self.scheduler, num_inference_steps, timestep_device, timesteps)
        self._num_timesteps = len(timesteps)

        # 5. Latents (CogVideoX 1.5 pads latent frames to a multiple of patch_size_t)
        latents = self.prepare_latents(
            videos * num_videos_per_prompt,
            self.transformer.config.in_channels,
            num_frames + additional_frames * self.vae_scale_factor_temporal,
            height,
            width,
            prompt_embeds.dtype,
            device,
            generator,
            latents,
        )
        # With guidance the latents stay fp32 between steps (an update is far below bf16 resolution);
        # without, they are rounded to the model dtype after each step, as the stock pipeline does.
        keep_fp32 = call.config.enabled
        if keep_fp32:
            latents = latents.float()

        # 6. Extra step kwargs (eta, generator), as the stock pipeline
        extra_step_kwargs = self.prepare_extra_step_kwargs(generator, eta)

        # 7. Rotary embeddings
        image_rotary_emb = (
            rotary_embeddings(self, height, width, latents.size(1), device)
            if self.transformer.config.use_rotary_positional_embeddings
            else None
        )
        return _LoopInputs(latents, prompt_embeds, negative_prompt_embeds, timesteps, num_inference_steps,
                           extra_step_kwargs, image_rotary_emb, do_classifier_free_guidance, keep_fp32, additional_frames)

    def set_up_guidance(self, call: _GeCoCall, loop: _LoopInputs, generator: Any, search_generator: torch.Generator | None,
                        observer: GuidanceObserver | None) -> None:
        """Stage 8 of a call: the guidance of ``call.config`` (``call.geco``: anchors decoded from
        short causal chunks, the GeCo loss, the log, watched by ``observer``) and the search of
        ``call.search`` (``call.searcher``, scoring the particles with the guidance's decode or,
        unguided, its own, and ``call.batches``, their sub-batches)."""
        config, run, devices, masks = call.config, call.run, call.devices, call.masks
        if config.enabled:
            call.geco = GuidanceContext(
                config, call.schedule, call.chunks,
                decode_chunk=call.decode,
                latent_frames=lambda x0: x0[:, loop.additional_frames:],
                estimators=call.estimators, generator=generator,
                run=run, memory_plan=call.memory_plan, dynamic_masks=masks, devices=devices, observer=observer,
            )
            if devices:
                logger.info("guidance: anchor chunks dealt over %s", ", ".join(map(str, devices)))
        if call.search is not None:
            geco, size = call.geco, call.particle_batch.size
            scorer = ParticleScorer(
                geco.anchor_objective.decode if geco else plan_anchor_decode(
                    SAFE_PLAN, call.decode, call.chunks, devices, processes=run.context_parallel or 1),
                lambda x0: x0[:, loop.additional_frames:], GeCoLoss(call.estimators, config.loss, check_values=False),
                masks, size)
            call.searcher = ParticleSearch(call.search, len(loop.timesteps), scorer, generator=search_generator,
                                           noise=generator, batch=size, masks=masks if geco else None)
            call.batches = particle_batches(call.particles, size)

    def denoise(self, call: _GeCoCall, loop: _LoopInputs, callback_on_step_end: Any,
                callback_on_step_end_tensor_inputs: list[str], *, use_dynamic_cfg: bool, guidance_scale: float,
                attention_kwargs: dict[str, Any] | None) -> None:
        """Stage 9 of a call: the stock denoising loop over ``loop.timesteps``, from and into
        ``loop.latents`` (``[B, F, C, h, w]``), with ``R_t`` GeCo updates of the latents before
        each guided step (``call.geco``) and a search's resampling at its steps (``call.searcher``);
        NaN latents are refused after the loop, not decoded."""
        geco, searcher, batches, schedule, particles = call.geco, call.searcher, call.batches, call.schedule, call.particles
        latents, prompt_embeds, negative_prompt_embeds = loop.latents, loop.prompt_embeds, loop.negative_prompt_embeds
        timesteps, num_inference_steps, keep_fp32 = loop.timesteps, loop.num_inference_steps, loop.keep_fp32
        num_warmup_steps = max(len(timesteps) - num_inference_steps * self.scheduler.order, 0)
        step_values = [int(v) for v in timesteps.tolist()]  # host copies: the guided steps add no device sync
        watch = LatentsWatch(len(timesteps))  # read once, after the loop: NaN latents are refused, not decoded
        with (
            geco.models(call.denoisers, self.vae, [self.text_encoder]) if geco else contextlib.nullcontext(),
            self.progress_bar(total=num_inference_steps) as progress_bar,
        ):
            if geco:
                geco.on_record = lambda record: progress_bar.set_postfix(loss=f"{record.loss:.4f}", refresh=False)
                # what the bar counts and how guidance keeps to memory (docs/performance.md: memory plans)
                progress_bar.set_description(f"GeCo-guided denoising steps (memory plan: {geco.memory_plan.plan.name})",
                                             refresh=False)
            old_pred_original_sample = None  # for DPM-solver++
            for i, t in enumerate(timesteps):
                if self.interrupt:
                    continue
                self._current_timestep = t
                if use_dynamic_cfg:
                    self._guidance_scale = 1 + guidance_scale * (
                        (1 - math.cos(math.pi * ((num_inference_steps - t.item()) / num_inference_steps) ** 5.0)) / 2
                    )
                model_kwargs = dict(
                    t=t,
                    prompt_embeds=prompt_embeds,
                    image_rotary_emb=loop.image_rotary_emb,
                    attention_kwargs=attention_kwargs,
                    do_classifier_free_guidance=loop.do_classifier_free_guidance,
                )
                predict_rows = partial(self.predict_particles, particles=particles, **model_kwargs) if particles else None
                if geco is None or schedule.repeats_at(i) == 0:
                    noise_pred = self.model_output(latents, **model_kwargs)
                    sample = latents
                else:
                    # R_t GeCo updates of z_t; the scheduler then steps from the guided z_t with the
                    # model output there (the hooks' path: one guidance for both)
                    levels = noise_levels(self.scheduler, step_values[i], i)
                    sample, noise_pred = geco.guide(latents, partial(self.predict, **model_kwargs), levels, i,
                                                    step_values[i], batches=batches, predict_rows=predict_rows)
                if searcher is not None and searcher.resamples_at(i):
                    # the particles scored and resampled, their scheduler state and loop state carried
                    sample, noise_pred, (old_pred_original_sample,) = searcher.step(
                        i, step_values[i], sample, noise_pred, noise_levels(self.scheduler, step_values[i], i),
                        predict_rows, self.scheduler, (old_pred_original_sample,))

                # compute the previous noisy sample x_t -> x_t-1, with the pipeline's own scheduler
                if not isinstance(self.scheduler, CogVideoXDPMScheduler):
                    latents = self.scheduler.step(noise_pred, t, sample, **loop.extra_step_kwargs, return_dict=False)[0]
                else:
                    latents, old_pred_original_sample = self.scheduler.step(
                        noise_pred,
                        old_pred_original_sample,
                        t,
                        timesteps[i - 1] if i > 0 else None,
                        sample,
                        **loop.extra_step_kwargs,
                        return_dict=False,
                    )
                latents = latents.float() if keep_fp32 else latents.to(prompt_embeds.dtype)

                if callback_on_step_end is not None:
                    callback_kwargs = {}
                    for k in callback_on_step_end_tensor_inputs:
                        callback_kwargs[k] = {
                            "latents": latents,
                            "prompt_embeds": prompt_embeds,
                            "negative_prompt_embeds": negative_prompt_embeds,
                        }[k]
                    callback_outputs = callback_on_step_end(self, i, t, callback_kwargs)
                    latents = callback_outputs.pop("latents", latents)
                    latents = latents.float() if keep_fp32 else latents
                    prompt_embeds = callback_outputs.pop("prompt_embeds", prompt_embeds)
                    negative_prompt_embeds = callback_outputs.pop("negative_prompt_embeds", negative_prompt_embeds)
                watch.see(latents, i)

                if i == len(timesteps) - 1 or ((i + 1) > num_warmup_steps and (i + 1) % self.scheduler.order == 0):
                    progress_bar.update()

                if XLA_AVAILABLE:
                    xm.mark_step()

        self._current_timestep = None
        self._cfg_halves = self._particle_batches = None
        loop.latents, loop.prompt_embeds = latents, prompt_embeds
        watch.check()

    def call_report(self, call: _GeCoCall) -> GuidanceReport:
        """What the call decided: the guidance's report (only the scheduler without guidance), with a
        search's record and the masks its scores left out."""
        geco, searcher = call.geco, call.searcher
        report = geco.report(self.scheduler) if geco else GuidanceReport(scheduler=type(self.scheduler).__name__)
        if searcher is not None:
            report.mask_source = None if call.masks is None else call.masks.source_name  # what its scores left out
            report.search = {**searcher.report(call.particles), "particle_batch": call.particle_batch.to_dict()}
        return report

    def decode_video(self, call: _GeCoCall, loop: _LoopInputs, output_type: str, report: GuidanceReport) -> Any:
        """Stage 10 of a call: the final latents decoded to ``output_type`` (the latents themselves
        for ``"latent"``, in the model dtype), the padded latent frames left out; a search's
        particles each decoded on its own or, over ``run.devices``, dealt over them (said in
        ``report.search``)."""
        latents, particles, devices = loop.latents, call.particles, call.devices
        if output_type == "latent":
            return latents.to(loop.prompt_embeds.dtype) if loop.keep_fp32 else latents
        latents = latents[:, loop.additional_frames:]
        latents = latents.to(self.vae.dtype) if loop.keep_fp32 else latents
        if particles and devices:  # each device decodes its share of the particles
            restore = deal_final_decode(self.vae, devices)
            report.search["final_decode_devices"] = [str(device) for device in devices]
            try:
                video = self.decode_latents(latents)
            finally:
                restore()
        elif particles:  # a search's videos one at a time: each particle's frames as its own decode makes them
            video = torch.cat([self.decode_latents(latents[k:k + 1]) for k in range(particles)])
        else:
            video = self.decode_latents(latents)
        return self.video_processor.postprocess_video(video=video, output_type=output_type)
