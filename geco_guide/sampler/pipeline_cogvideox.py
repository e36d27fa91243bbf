"""GeCoCogVideoXPipeline: diffusers' CogVideoXPipeline with GeCo geometric-consistency guidance.

The denoising loop below is the whole sampler, readable top to bottom: classifier-free guided
v-prediction, its clean estimate ``x0 = sqrt(a_t) z_t - sqrt(1 - a_t) v``, and a deterministic
DDIM step ``z_prev = A z_t + B x0``, with ``R_t`` GeCo updates of ``z_t`` before the step
(:func:`geco_guide.sampler.guidance.guided_step`). Noise levels come from the scheduler's
``alphas_cumprod`` at the entries of its timestep table. With guidance off the loop reproduces
the stock ``CogVideoXPipeline`` with ``CogVideoXDDIMScheduler`` bit for bit (fp32 models).

Latents are kept in fp32 between steps whatever the model dtype (the stock pipeline rounds them
to the model dtype after every step; guidance updates are far below bf16 resolution).
"""

from __future__ import annotations

import contextlib
import math
from collections.abc import Callable, Mapping
from dataclasses import asdict, dataclass
from functools import partial
from typing import Any

import torch
from diffusers import CogVideoXPipeline
from diffusers.callbacks import MultiPipelineCallbacks, PipelineCallback
from diffusers.pipelines.cogvideo.pipeline_cogvideox import retrieve_timesteps
from diffusers.pipelines.cogvideo.pipeline_output import CogVideoXPipelineOutput
from diffusers.schedulers import CogVideoXDDIMScheduler
from diffusers.utils import logging
from torch import Tensor, nn

from ..estimators.base import FlowEstimator, GeometryEstimator
from ..loss.geco import GeCoLoss
from .guidance import (
    GuidanceConfig,
    GuidanceRecord,
    VPLevels,
    frozen,
    gradient_checkpointing,
    guided_step,
    resolve_guidance_config,
    v_to_x0,
)
from .slicing import anchor_latent_chunks, check_num_frames, decode_anchor_frames

logger = logging.get_logger(__name__)


@dataclass
class GeCoCogVideoXPipelineOutput(CogVideoXPipelineOutput):
    """Frames as the stock output, plus the guidance log.

    Attributes:
        frames: as :class:`CogVideoXPipelineOutput`.
        guidance_log: one dict per guided update (``step, repeat, t, loss, motion, structure,
            fused, grad_norm, seconds, time_travel, skipped``); empty without guidance.
        guidance: the resolved guidance config of the call (a dict), ``None`` when off.
    """

    guidance_log: list[dict[str, Any]] | None = None
    guidance: dict[str, Any] | None = None


class GeCoCogVideoXPipeline(CogVideoXPipeline):
    r"""Text-to-video CogVideoX with training-free GeCo geometric-consistency guidance.

    Components: the stock ``tokenizer``, ``text_encoder``, ``vae``, ``transformer``, ``scheduler``,
    plus the optional ``geometry_estimator`` (e.g. VGGT) and ``flow_estimator`` (e.g. UFM), and
    ``guidance_config``: the default :class:`GuidanceConfig` (a dict of its fields works too).

    The sampler is deterministic DDIM (as in the paper). CogVideoX checkpoints may ship
    ``CogVideoXDPMScheduler``; any other scheduler is replaced at construction by a
    ``CogVideoXDDIMScheduler`` built from the same scheduler config (``self.scheduler_note``).

    Example::

        pipe = GeCoCogVideoXPipeline.from_pretrained(
            "THUDM/CogVideoX-5b", torch_dtype=torch.bfloat16,
            geometry_estimator=VGGT.from_pretrained("facebook/VGGT-1B"),
            flow_estimator=UFM.from_pretrained(...))
        out = pipe("a marble bust on a turntable", generator=torch.Generator().manual_seed(0))
        out.frames, out.guidance_log
    """

    def __init__(
        self,
        tokenizer,
        text_encoder,
        vae,
        transformer,
        scheduler,
        geometry_estimator: GeometryEstimator | None = None,
        flow_estimator: FlowEstimator | None = None,
        guidance_config: GuidanceConfig | Mapping[str, Any] | None = None,
    ):
        note = "CogVideoXDDIMScheduler"
        if not isinstance(scheduler, CogVideoXDDIMScheduler):
            note = f"CogVideoXDDIMScheduler built from the {type(scheduler).__name__} config (the paper samples with DDIM)"
            logger.info("GeCoCogVideoXPipeline: using %s", note)
            scheduler = CogVideoXDDIMScheduler.from_config(scheduler.config)
        super().__init__(tokenizer=tokenizer, text_encoder=text_encoder, vae=vae, transformer=transformer, scheduler=scheduler)
        # Plain attributes, not diffusers components: they are not diffusers/transformers models
        # (save_pretrained/offloading leave them alone); from_pretrained passes them through.
        self.geometry_estimator = geometry_estimator
        self.flow_estimator = flow_estimator
        self.scheduler_note = note
        self.guidance_config = resolve_guidance_config(None, guidance_config)

    def to(self, *args, **kwargs):
        """As :meth:`DiffusionPipeline.to`; the estimators follow the device (they keep their dtype)."""
        pipe = super().to(*args, **kwargs)
        device = kwargs.get("device")
        if device is None:
            device = next((a for a in args if isinstance(a, (str, torch.device))), None)
        if device is not None:
            for estimator in (self.geometry_estimator, self.flow_estimator):
                if isinstance(estimator, nn.Module):
                    estimator.to(device)
        return pipe

    # ------------------------------------------------------------------------------------------
    # checks

    def check_geco_inputs(
        self,
        height: int,
        width: int,
        num_frames: int,
        num_steps: int,
        guidance: GuidanceConfig,
        geometry_estimator: Any,
        flow_estimator: Any,
    ):
        """Validate a call before any denoising step; ValueError naming the problem.

        Returns the guidance schedule and anchor chunks (``(None, None)`` without guidance).
        """
        multiple = self.vae_scale_factor_spatial * self.transformer.config.patch_size
        if height % multiple or width % multiple:
            raise ValueError(
                f"height and width must be multiples of {multiple} (VAE factor {self.vae_scale_factor_spatial} x "
                f"patch size {self.transformer.config.patch_size}), got height={height}, width={width}"
            )
        num_latents = check_num_frames(num_frames, self.vae_scale_factor_temporal)
        if num_latents % 2 == 0 and getattr(self.vae, "num_latent_frames_batch_size", None) == 2:
            # The CogVideoX VAE decodes latents in pairs and keeps the causal first frame only when
            # the count is odd: an even count decodes to 4*n frames instead of 1 + 4*(n-1).
            r = self.vae_scale_factor_temporal
            raise ValueError(
                f"num_frames={num_frames} gives {num_latents} latent frames; the CogVideoX VAE cannot make a "
                f"{num_frames}-frame video from an even number of latents (it decodes them to {r * num_latents} "
                f"frames). Use {2 * r}k+1 frames, e.g. {num_frames + r} or 49."
            )
        if not isinstance(self.scheduler, CogVideoXDDIMScheduler):
            raise ValueError(
                f"GeCoCogVideoXPipeline samples with DDIM; got scheduler {type(self.scheduler).__name__}. Use "
                "pipe.scheduler = CogVideoXDDIMScheduler.from_config(pipe.scheduler.config)"
            )
        if self.scheduler.config.prediction_type != "v_prediction":
            raise ValueError(
                f"GeCoCogVideoXPipeline expects a v-prediction model, scheduler has prediction_type="
                f"{self.scheduler.config.prediction_type!r}"
            )
        if not guidance.enabled:
            return None, None
        schedule = guidance.validate(num_steps, num_frames, self.vae_scale_factor_temporal)
        chunks = anchor_latent_chunks(
            guidance.anchors, num_frames, self.vae_scale_factor_temporal, guidance.chunk_latents
        )
        missing = [
            name
            for name, est, proto in (
                ("geometry_estimator", geometry_estimator, GeometryEstimator),
                ("flow_estimator", flow_estimator, FlowEstimator),
            )
            if not isinstance(est, proto)
        ]
        if missing:
            raise ValueError(
                f"GeCo guidance needs {' and '.join(missing)}: pass them to from_pretrained(..., "
                "geometry_estimator=..., flow_estimator=...) or to the call, or call with guidance=False"
            )
        return schedule, chunks

    # ------------------------------------------------------------------------------------------
    # the model, as the guided step sees it

    def predict_x0(
        self,
        z: Tensor,
        differentiate: bool,
        *,
        t: Tensor,
        alpha_t: Tensor,
        prompt_embeds: Tensor,
        image_rotary_emb: Any,
        attention_kwargs: dict | None,
        do_classifier_free_guidance: bool,
    ) -> Tensor:
        """CFG-combined v-prediction of the transformer at ``t`` -> fp32 clean estimate ``x0``.

        With ``differentiate=False`` the transformer runs without gradients, so ``x0`` depends
        on ``z`` only through ``sqrt(a_t) z`` (the fast mode).
        """
        with torch.set_grad_enabled(differentiate and torch.is_grad_enabled()):
            latent_model_input = z.to(prompt_embeds.dtype)
            latent_model_input = torch.cat([latent_model_input] * 2) if do_classifier_free_guidance else latent_model_input
            latent_model_input = self.scheduler.scale_model_input(latent_model_input, t)
            timestep = t.expand(latent_model_input.shape[0])
            cache = getattr(self.transformer, "cache_context", None)
            with cache("cond_uncond") if cache is not None else contextlib.nullcontext():
                v = self.transformer(
                    hidden_states=latent_model_input,
                    encoder_hidden_states=prompt_embeds,
                    timestep=timestep,
                    image_rotary_emb=image_rotary_emb,
                    attention_kwargs=attention_kwargs,
                    return_dict=False,
                )[0]
            v = v.float()
            if do_classifier_free_guidance:
                v_uncond, v_text = v.chunk(2)
                v = v_uncond + self.guidance_scale * (v_text - v_uncond)
        return v_to_x0(z, v, alpha_t)

    # ------------------------------------------------------------------------------------------

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
        geometry_estimator: GeometryEstimator | None = None,
        flow_estimator: FlowEstimator | None = None,
    ) -> GeCoCogVideoXPipelineOutput | tuple:
        """Generate a video; arguments as :meth:`CogVideoXPipeline.__call__`, plus:

        Args:
            guidance: a :class:`GuidanceConfig`, a dict of fields overriding
                ``self.guidance_config`` (e.g. ``{"eta": 2.0, "loss": {"cue": "motion"}}``),
                ``False`` to sample without guidance, or ``None`` for the default.
            geometry_estimator, flow_estimator: override the pipeline's estimators for this call.
            eta: the DDIM eta of the stock signature; the sampler is deterministic DDIM
                (``CogVideoXDDIMScheduler.step`` ignores it too). The GeCo step size is
                ``guidance.eta``.

        Returns:
            :class:`GeCoCogVideoXPipelineOutput` (``frames``, ``guidance_log``, ``guidance``) or
            ``(frames,)`` when ``return_dict=False``.
        """
        if isinstance(callback_on_step_end, (PipelineCallback, MultiPipelineCallbacks)):
            callback_on_step_end_tensor_inputs = callback_on_step_end.tensor_inputs

        height = height or self.transformer.config.sample_height * self.vae_scale_factor_spatial
        width = width or self.transformer.config.sample_width * self.vae_scale_factor_spatial
        num_frames = num_frames or self.transformer.config.sample_frames
        num_videos_per_prompt = 1  # as the stock pipeline

        # 1. Check inputs, all of them, before any work
        self.check_inputs(
            prompt, height, width, negative_prompt, callback_on_step_end_tensor_inputs, prompt_embeds, negative_prompt_embeds
        )
        config = resolve_guidance_config(self.guidance_config, guidance)
        geometry_estimator = geometry_estimator if geometry_estimator is not None else self.geometry_estimator
        flow_estimator = flow_estimator if flow_estimator is not None else self.flow_estimator
        num_steps = len(timesteps) if timesteps is not None else num_inference_steps
        schedule, chunks = self.check_geco_inputs(
            height, width, num_frames, num_steps, config, geometry_estimator, flow_estimator
        )
        self._guidance_scale = guidance_scale
        self._attention_kwargs = attention_kwargs
        self._current_timestep = None
        self._interrupt = False

        # 2. Default call parameters
        if prompt is not None and isinstance(prompt, str):
            batch_size = 1
        elif prompt is not None and isinstance(prompt, list):
            batch_size = len(prompt)
        else:
            batch_size = prompt_embeds.shape[0]
        device = self._execution_device
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
        if do_classifier_free_guidance:
            prompt_embeds = torch.cat([negative_prompt_embeds, prompt_embeds], dim=0)

        # 4. Timestep table: noise levels are always looked up at its entries
        timesteps, num_inference_steps = retrieve_timesteps(self.scheduler, num_inference_steps, device, timesteps)
        self._num_timesteps = len(timesteps)
        alphas_cumprod = self.scheduler.alphas_cumprod
        final_alpha_cumprod = self.scheduler.final_alpha_cumprod

        # 5. Latents (CogVideoX 1.5 pads latent frames to a multiple of patch_size_t)
        latent_frames = (num_frames - 1) // self.vae_scale_factor_temporal + 1
        patch_size_t = self.transformer.config.patch_size_t
        additional_frames = 0
        if patch_size_t is not None and latent_frames % patch_size_t != 0:
            additional_frames = patch_size_t - latent_frames % patch_size_t
            num_frames += additional_frames * self.vae_scale_factor_temporal
        latents = self.prepare_latents(
            batch_size * num_videos_per_prompt,
            self.transformer.config.in_channels,
            num_frames,
            height,
            width,
            prompt_embeds.dtype,
            device,
            generator,
            latents,
        )
        latents = latents.float()  # fp32 master copy of z_t

        # 6. Rotary embeddings
        image_rotary_emb = (
            self._prepare_rotary_positional_embeddings(height, width, latents.size(1), device)
            if self.transformer.config.use_rotary_positional_embeddings
            else None
        )

        # 7. Guidance parts: anchors decoded from short causal chunks, the GeCo loss
        loss_fn = decode_anchors = None
        if config.enabled:
            # No frame check: it would make each update wait for the device; a NaN decode gives
            # NaN scalars and no update instead (GeCoLoss check_values).
            loss_fn = GeCoLoss(geometry_estimator, flow_estimator, config.loss, check_values=False)

            def decode_anchors(x0: Tensor) -> Tensor:
                return decode_anchor_frames(self.vae, x0[:, additional_frames:], chunks, self.vae_scaling_factor_image,
                                            checkpoint_chunks=config.vae_checkpointing)

        guidance_log: list[dict[str, Any]] = []

        # 8. Denoising loop
        models = (self.text_encoder, self.transformer, self.vae, geometry_estimator, flow_estimator)
        checkpointing = config.enabled and config.denoiser_grad and config.gradient_checkpointing
        with (
            frozen(*models),
            gradient_checkpointing(self.transformer, checkpointing),
            gradient_checkpointing(self.vae, config.enabled and config.vae_checkpointing),
            self.progress_bar(total=num_inference_steps) as progress_bar,
        ):
            for i, t in enumerate(timesteps):
                if self.interrupt:
                    continue
                self._current_timestep = t
                alpha_t = alphas_cumprod[int(t)]
                alpha_prev = alphas_cumprod[int(timesteps[i + 1])] if i + 1 < len(timesteps) else final_alpha_cumprod
                if use_dynamic_cfg:
                    self._guidance_scale = 1 + guidance_scale * (
                        (1 - math.cos(math.pi * ((num_inference_steps - t.item()) / num_inference_steps) ** 5.0)) / 2
                    )
                predict = partial(
                    self.predict_x0,
                    t=t,
                    alpha_t=alpha_t,
                    prompt_embeds=prompt_embeds,
                    image_rotary_emb=image_rotary_emb,
                    attention_kwargs=attention_kwargs,
                    do_classifier_free_guidance=do_classifier_free_guidance,
                )

                def on_record(record: GuidanceRecord) -> None:
                    guidance_log.append(record.to_dict())
                    progress_bar.set_postfix(loss=f"{record.loss:.4f}", refresh=False)

                latents, _, _ = guided_step(
                    latents,
                    predict_x0=predict,
                    decode_anchors=decode_anchors,
                    loss_fn=loss_fn,
                    levels=VPLevels(alpha_t, alpha_prev),
                    repeats=schedule.repeats_at(i) if config.enabled else 0,
                    eta=config.eta,
                    time_travel=config.enabled and schedule.time_travel_at(i),
                    denoiser_grad=config.denoiser_grad,
                    generator=generator,
                    eps=config.grad_eps,
                    step=i,
                    t=int(t),
                    on_record=on_record,
                )

                if callback_on_step_end is not None:
                    callback_kwargs = {}
                    for k in callback_on_step_end_tensor_inputs:
                        callback_kwargs[k] = {
                            "latents": latents,
                            "prompt_embeds": prompt_embeds,
                            "negative_prompt_embeds": negative_prompt_embeds,
                        }[k]
                    callback_outputs = callback_on_step_end(self, i, t, callback_kwargs)
                    latents = callback_outputs.pop("latents", latents).float()
                    prompt_embeds = callback_outputs.pop("prompt_embeds", prompt_embeds)
                    negative_prompt_embeds = callback_outputs.pop("negative_prompt_embeds", negative_prompt_embeds)

                progress_bar.update()

        self._current_timestep = None

        if not output_type == "latent":
            latents = latents[:, additional_frames:]
            video = self.decode_latents(latents.to(self.vae.dtype))
            video = self.video_processor.postprocess_video(video=video, output_type=output_type)
        else:
            video = latents.to(prompt_embeds.dtype)

        self.maybe_free_model_hooks()

        if not return_dict:
            return (video,)
        return GeCoCogVideoXPipelineOutput(
            frames=video,
            guidance_log=guidance_log,
            guidance=asdict(config) if config.enabled else None,
        )
