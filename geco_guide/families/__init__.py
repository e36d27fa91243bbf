"""The video models GeCo guides and scores: ONE registry (:data:`MODELS`) of their facts.

Each :class:`VideoModel` holds what every other part of the package needs to know about one
checkpoint: its hub id and diffusers pipeline class, the call defaults of its model card (frames,
size, steps, CFG, the second expert's CFG, the frame rate its videos are written at), its VAE's
spatial and temporal compression and frame-count rule, the latent channels, the default anchors
(the paper's four, spread over the model's frame count as the paper spreads them over 49), the
tiny-decoder variant, the tiny random stand-in of its family, the native frame rate GeCo-Eval
times it with, and how guidance reaches its pipeline. The sampler, the commands, the benchmarks
and the cost model read this table and repeat none of it.

This module imports nothing of the package and nothing heavy: the metric, the config and the
commands' parsers read it without torch. The published full-size configs the cost model traces
are :mod:`geco_guide.families.published`.
"""

from __future__ import annotations

import difflib
from collections.abc import Iterable
from dataclasses import dataclass, field
from typing import Any

__all__ = ["DEFAULT_MODEL", "FAMILIES", "MODELS", "PAPER_ANCHOR_COUNT", "SCORED_ONLY", "TINY_DECODERS",
           "TINY_DECODER_ALIASES", "UNSUPPORTED_TINY_DECODERS", "TinyDecoderVariant", "VideoModel",
           "default_anchors", "did_you_mean", "frames_problem", "generating_model", "model_named", "models_of_pipeline",
           "paper_fps", "scheduler_names", "video_models"]

#: The model the config's defaults are: the paper's guidance experiment.
DEFAULT_MODEL = "cogvideox-5b"
#: Anchors the paper spreads over its 49 frames (12, 24, 36, 48): a quarter of the latents apart.
PAPER_ANCHOR_COUNT = 4
#: How guidance reaches a family's pipeline: ``pipeline`` (the GeCoCogVideoXPipeline subclass, the
#: paper's loop) or ``hooks`` (attach_geco_guidance on the stock pipeline).
GUIDED_BY = ("pipeline", "hooks")
#: The families: what decodes their latents and which tiny random stand-in they have.
FAMILIES = ("cogvideox", "cogvideox1.5", "wan", "wan2.2", "wan2.2-ti2v", "hunyuan", "hunyuan1.5", "ltx", "ltx2", "")


@dataclass(frozen=True)
class VideoModel:
    """One text-to-video (or image-to-video) checkpoint, as the package runs it.

    Attributes:
        name: the registry name (``--model NAME``, ``evaluation.model_fps.<name>``).
        family: the family its pipeline, latents and tiny stand-in belong to (:data:`FAMILIES`).
        hub_id: the diffusers checkpoint (``model.id`` replaces it with a folder); ``None`` for a
            model GeCo-Eval only scores (no open weights).
        hub_aliases: the other hub ids of the same checkpoint (an organisation's new name), which
            the memory plans' estimates answer to as well.
        pipeline: the diffusers pipeline class's name.
        call: the model card's default call: ``num_frames``, ``height``, ``width``,
            ``num_inference_steps``, ``guidance_scale`` and, for a two-expert model,
            ``guidance_scale_2``.
        fps: the frame rate its videos are written at (the model card's export).
        eval_fps: the native frame rate GeCo-Eval times its windows with (the paper's table).
        spatial_compression: pixels per latent, each way.
        temporal_compression: ``r``: latent 0 is pixel frame 0, latent ``k >= 1`` pixels
            ``r(k-1)+1 .. rk``.
        frame_multiple: valid frame counts are ``frame_multiple * k + 1`` (``2r`` for VAEs that
            decode latents in pairs, CogVideoX 1.0).
        size_multiple: height and width must be multiples of it (the VAE's compression times the
            transformer's patch).
        latent_channels: channels of the latents the denoiser and the VAE share.
        tiny_decoder: the tiny decoder variant that decodes its latents
            (:mod:`geco_guide.estimators.tiny_decoder`), ``None`` where there is none.
        tiny: the builder of its family's tiny random stand-in in :mod:`geco_guide.tiny.pipelines`
            (the real diffusers classes at a few pixels: tests, ``model.id=tiny-random``).
        tiny_call: what the calls of its tiny stand-in need beyond the config's sampling
            (HunyuanVideo's bare prompt template: the tiny tokenizer cannot crop the real one's
            system text).
        adapter: the name of the :class:`~geco_guide.sampler.pipelines.adapters.PipelineAdapter` that knows
            its pipeline's latents (:data:`geco_guide.sampler.pipelines.adapters.ADAPTERS`).
        guided_by: ``pipeline`` or ``hooks`` (:data:`GUIDED_BY`).
        schedulers: the ``sampling.scheduler`` names it can sample with besides its checkpoint's
            own, each with the diffusers scheduler class it builds from the checkpoint's
            scheduler config.
        scheduler: the ``sampling.scheduler`` it samples with by default (``ddim``: the paper's
            DDIM for CogVideoX), ``None``: the checkpoint's own.
        image_to_video: the pipeline conditions on an image (``--image``).
        text_length: its pipeline's call takes ``max_sequence_length`` (HunyuanVideo 1.5's pads
            its prompts to lengths of its own).
        source: where the call defaults and compressions come from.
    """

    name: str
    family: str
    hub_id: str | None
    pipeline: str | None
    call: dict[str, Any] = field(hash=False, compare=False)
    fps: int
    eval_fps: float
    spatial_compression: int = 8
    temporal_compression: int = 4
    frame_multiple: int = 4
    size_multiple: int = 16
    latent_channels: int = 16
    tiny_decoder: str | None = None
    tiny: str | None = None
    tiny_call: dict[str, Any] = field(default_factory=dict, hash=False, compare=False)
    adapter: str | None = None
    guided_by: str = "hooks"
    schedulers: dict[str, str] = field(default_factory=dict, hash=False, compare=False)
    scheduler: str | None = None
    image_to_video: bool = False
    text_length: bool = True
    source: str = ""
    hub_aliases: tuple[str, ...] = ()

    @property
    def generates(self) -> bool:
        """Whether the package can load and run it (it has open weights and a pipeline)."""
        return self.hub_id is not None and self.pipeline is not None

    @property
    def cogvideox_vae(self) -> bool:
        """Whether it decodes with the CogVideoX VAE: CogVideoX's DDIM / DPM schedulers
        (``sampling.scheduler``) and the channels-last guidance decode (``run.decode_layout``) are
        written for its family."""
        return self.family.startswith("cogvideox")

    @property
    def anchors(self) -> list[int]:
        """The default anchors of its default video (:func:`default_anchors`)."""
        return default_anchors(self.call["num_frames"], self.temporal_compression)


def frames_problem(num_frames: Any, multiple: int) -> str | None:
    """Why ``num_frames`` is no frame count a VAE of ``multiple * k + 1`` frames makes, or ``None``."""
    if isinstance(num_frames, bool) or not isinstance(num_frames, int) or num_frames < 1:
        return f"must be a whole number of frames >= 1, got {num_frames!r}"
    if (num_frames - 1) % multiple:
        below = num_frames - (num_frames - 1) % multiple
        return (f"must be {multiple}k+1 frames for this model's VAE, got {num_frames} "
                f"(e.g. {below} or {below + multiple})")
    return None


def default_anchors(num_frames: int, temporal_compression: int) -> list[int]:
    """The paper's anchors spread over a ``num_frames`` video: the last pixel frame of latents
    ``round(L * j / 4)``, ``j = 1..4`` (``L``: the last latent's index). (12, 24, 36, 48) at 49
    frames with ``r = 4``; (20, 40, 60, 80) at 81; a short video gets fewer, distinct, anchors.

    Raises:
        ValueError: ``num_frames`` is no ``r k + 1`` frame count.
    """
    problem = frames_problem(num_frames, temporal_compression)
    if problem is not None:
        raise ValueError(f"num_frames {problem}")
    last = (num_frames - 1) // temporal_compression
    return sorted({temporal_compression * max(1, round(last * j / PAPER_ANCHOR_COUNT))
                   for j in range(1, PAPER_ANCHOR_COUNT + 1)})


@dataclass(frozen=True)
class TinyDecoderVariant:
    """One published tiny decoder (a TAEHV checkpoint) of a family's latents.

    Attributes:
        name: our variant name (a registry entry's ``tiny_decoder``, ``TinyDecoder(variant=name)``).
        checkpoint: the published file stem (``<checkpoint>.pth``,
            ``safetensors/<checkpoint>.safetensors``).
        latent_channels: channels ``C`` of the latents.
        patch_size: pixel-(un)shuffle factor of the frames.
        even_count_untrimmed: keep all ``4 T`` frames when the latent count ``T`` is even (the
            published CogVideoX rule).
        scale_by_vae_scaling_factor: the decoder takes the pipeline's latents divided by
            ``vae.config.scaling_factor`` (CogVideoX), else the pipeline's latents as they are.
        pipeline_layout: how the variant's diffusers pipeline holds its latents.
        models: the video models whose latents it decodes.
    """

    name: str
    checkpoint: str
    latent_channels: int
    patch_size: int
    even_count_untrimmed: bool
    scale_by_vae_scaling_factor: bool
    pipeline_layout: str
    models: str


#: The published tiny decoders (github.com/madebyollin/taehv) by variant name.
TINY_DECODERS: dict[str, TinyDecoderVariant] = {v.name: v for v in (
    TinyDecoderVariant("cogvideox", "taecvx", 16, 1, True, True, "NTCHW", "CogVideoX 2b / 5b / 1.5"),
    TinyDecoderVariant("wan2.1", "taew2_1", 16, 1, False, False, "NCTHW", "Wan 2.1, Wan 2.2 14B"),
    TinyDecoderVariant("hunyuanvideo", "taehv", 16, 1, False, False, "NCTHW", "HunyuanVideo"),
    TinyDecoderVariant("wan2.2-5b", "taew2_2", 48, 2, False, False, "NCTHW", "Wan 2.2 TI2V 5B"),
    TinyDecoderVariant("hunyuanvideo1.5", "taehv1_5", 32, 2, False, False, "NCTHW", "HunyuanVideo 1.5"),
)}
#: Other spellings of the variants users reach for (the checkpoint stems are accepted too).
TINY_DECODER_ALIASES = {"wan2.2-14b": "wan2.1", "wan2.2-ti2v-5b": "wan2.2-5b", "hunyuan": "hunyuanvideo",
                        "hunyuanvideo-1.5": "hunyuanvideo1.5"}
#: Published tiny decoders the package cannot load, by a word of their names, and why.
UNSUPPORTED_TINY_DECODERS = {"ltx": "taeltx checkpoints (LTX-Video: 128 latent channels, patch 4, time strides "
                                    "(2, 2, 2)) are not supported"}


def _call(frames: int, height: int, width: int, steps: int, cfg: float, **more: Any) -> dict[str, Any]:
    return {"num_frames": frames, "height": height, "width": width, "num_inference_steps": steps,
            "guidance_scale": cfg, **more}


#: CogVideoX's schedulers: the paper samples with deterministic DDIM, and CogVideoX-5B ships DPM.
_COGVIDEOX_SCHEDULERS = {"ddim": "CogVideoXDDIMScheduler", "dpm": "CogVideoXDPMScheduler"}
_COGVIDEOX = dict(family="cogvideox", pipeline="CogVideoXPipeline", frame_multiple=8, tiny_decoder="cogvideox",
                  guided_by="pipeline", scheduler="ddim", fps=8, eval_fps=16.0, tiny="tiny_cogvideox_pipeline",
                  adapter="CogVideoXAdapter", schedulers=_COGVIDEOX_SCHEDULERS)
_WAN21 = dict(family="wan", pipeline="WanPipeline", tiny_decoder="wan2.1", fps=16, eval_fps=16.0,
              tiny="tiny_wan_pipeline", adapter="WanAdapter")

#: Every model, by name. Call defaults: each model card / diffusers' pipeline documentation (the
#: ``source`` of each); native rates: the GeCo paper's supplement ("Frame rate of evaluated
#: models"), the models it has no row for at their card's export rate.
MODELS: dict[str, VideoModel] = {m.name: m for m in (
    VideoModel("cogvideox-2b", hub_id="THUDM/CogVideoX-2b", hub_aliases=("zai-org/CogVideoX-2b",),
               call=_call(49, 480, 720, 50, 6.0),
               source="CogVideoX-2b model card; diffusers CogVideoXPipeline docs", **_COGVIDEOX),
    VideoModel("cogvideox-5b", hub_id="THUDM/CogVideoX-5b", hub_aliases=("zai-org/CogVideoX-5b",),
               call=_call(49, 480, 720, 50, 6.0),
               source="CogVideoX-5b model card; the GeCo paper's guidance experiment", **_COGVIDEOX),
    VideoModel("cogvideox1.5-5b", family="cogvideox1.5", hub_id="THUDM/CogVideoX1.5-5B",
               hub_aliases=("zai-org/CogVideoX1.5-5B",), pipeline="CogVideoXPipeline",
               call=_call(81, 768, 1360, 50, 6.0), fps=16, eval_fps=16.0, frame_multiple=8,
               tiny_decoder="cogvideox", tiny="tiny_cogvideox15_pipeline", guided_by="pipeline", scheduler="ddim",
               adapter="CogVideoXAdapter", schedulers=_COGVIDEOX_SCHEDULERS,
               source="CogVideoX1.5-5B model card"),
    VideoModel("wan2.1-t2v-1.3b", hub_id="Wan-AI/Wan2.1-T2V-1.3B-Diffusers", call=_call(81, 480, 832, 50, 5.0),
               source="Wan2.1-T2V-1.3B-Diffusers model card", **_WAN21),
    VideoModel("wan2.1-t2v-14b", hub_id="Wan-AI/Wan2.1-T2V-14B-Diffusers", call=_call(81, 720, 1280, 50, 5.0),
               source="Wan2.1-T2V-14B-Diffusers model card", **_WAN21),
    VideoModel("wan2.2-t2v-a14b", family="wan2.2", hub_id="Wan-AI/Wan2.2-T2V-A14B-Diffusers", pipeline="WanPipeline",
               call=_call(81, 720, 1280, 40, 4.0, guidance_scale_2=3.0), fps=16, eval_fps=16.0,
               tiny_decoder="wan2.1", tiny="tiny_wan22_a14b_pipeline", adapter="WanAdapter",
               source="Wan2.2-T2V-A14B-Diffusers model card (two experts)"),
    VideoModel("cogvideox-5b-i2v", family="cogvideox", hub_id="THUDM/CogVideoX-5b-I2V",
               hub_aliases=("zai-org/CogVideoX-5b-I2V",),
               pipeline="CogVideoXImageToVideoPipeline", call=_call(49, 480, 720, 50, 6.0), fps=8, eval_fps=16.0,
               frame_multiple=8, tiny_decoder="cogvideox", tiny="tiny_cogvideox_i2v_pipeline", scheduler="ddim",
               adapter="CogVideoXAdapter", schedulers=_COGVIDEOX_SCHEDULERS,
               image_to_video=True, source="CogVideoX-5b-I2V model card (guided by the hooks: the paper's loop is "
               "text-to-video)"),
    VideoModel("wan2.2-ti2v-5b", family="wan2.2-ti2v", hub_id="Wan-AI/Wan2.2-TI2V-5B-Diffusers", pipeline="WanPipeline",
               call=_call(121, 704, 1280, 50, 5.0), fps=24, eval_fps=24.0, spatial_compression=16,
               size_multiple=32, latent_channels=48, tiny_decoder="wan2.2-5b", tiny="tiny_wan22_ti2v_pipeline", adapter="WanAdapter",
               source="Wan2.2 TI2V-5B configs of the official repository (wan_ti2v_5B.py); text-to-video here: "
               "its image-to-video mode runs through WanImageToVideoPipeline, which the hooks cannot guide yet"),
    VideoModel("hunyuanvideo", family="hunyuan", hub_id="hunyuanvideo-community/HunyuanVideo",
               pipeline="HunyuanVideoPipeline", call=_call(129, 720, 1280, 50, 6.0), fps=15, eval_fps=24.0,
               tiny_decoder="hunyuanvideo", tiny="tiny_hunyuan_pipeline", adapter="HunyuanVideoAdapter",
               tiny_call={"prompt_template": {"template": "{}", "crop_start": 0}},
               source="diffusers HunyuanVideoPipeline docs"),
    VideoModel("hunyuanvideo-1.5", family="hunyuan1.5", hub_id="hunyuanvideo-community/HunyuanVideo-1.5-480p_t2v",
               pipeline="HunyuanVideo15Pipeline", call=_call(121, 480, 848, 50, 6.0), fps=24, eval_fps=24.0,
               spatial_compression=16, latent_channels=32, tiny_decoder="hunyuanvideo1.5",
               tiny="tiny_hunyuan15_pipeline", adapter="HunyuanVideo15Adapter", text_length=False,
               source="diffusers HunyuanVideo15Pipeline docs and conversion script (480p)"),
    VideoModel("hunyuanvideo-1.5-i2v", family="hunyuan1.5", hub_id="hunyuanvideo-community/HunyuanVideo-1.5-480p_i2v",
               pipeline="HunyuanVideo15ImageToVideoPipeline", call=_call(121, 480, 848, 50, 6.0), fps=24,
               eval_fps=24.0, spatial_compression=16, latent_channels=32, tiny_decoder="hunyuanvideo1.5",
               tiny="tiny_hunyuan15_i2v_pipeline", adapter="HunyuanVideo15Adapter", image_to_video=True,
               text_length=False,
               source="diffusers HunyuanVideo15ImageToVideoPipeline docs and conversion script (480p)"),
    VideoModel("ltx-video", family="ltx", hub_id="Lightricks/LTX-Video", pipeline="LTXPipeline",
               call=_call(161, 480, 704, 50, 3.0), fps=24, eval_fps=30.0, spatial_compression=32,
               temporal_compression=8, frame_multiple=8, size_multiple=32, latent_channels=128, tiny="tiny_ltx_pipeline",
               adapter="LTXAdapter", source="diffusers LTXPipeline docs"),
    VideoModel("ltx-2", family="ltx2", hub_id="Lightricks/LTX-2", pipeline="LTX2Pipeline",
               call=_call(121, 512, 768, 30, 3.0), fps=24, eval_fps=24.0, spatial_compression=32,
               temporal_compression=8, frame_multiple=8, size_multiple=32, latent_channels=128, tiny="tiny_ltx2_pipeline",
               adapter="LTX2Adapter",
               source="diffusers LTX2Pipeline docs and call defaults (video only: the audio stream passes through)"),
    VideoModel("sora-2", family="", hub_id=None, pipeline=None, call=_call(1, 0, 0, 0, 0.0), fps=30, eval_fps=30.0,
               source="the GeCo paper (scored only: no open weights)"),
    VideoModel("veo-3.1", family="", hub_id=None, pipeline=None, call=_call(1, 0, 0, 0, 0.0), fps=24, eval_fps=24.0,
               source="the GeCo paper (scored only: no open weights)"),
)}

#: Models of the paper's table that GeCo-Eval only scores (``--videos NAME=DIR``): no open weights.
SCORED_ONLY = tuple(name for name, model in MODELS.items() if not model.generates)


def video_models() -> list[str]:
    """The names of the models the package can generate with."""
    return [name for name, model in MODELS.items() if model.generates]


def did_you_mean(word: Any, names: Iterable[str], prefix: str = "") -> str:
    """`` (did you mean 'a' or 'b'?)`` naming at most three of ``names`` close to the misspelt
    ``word``: those it begins (``wan2.2`` for ``wan2.2-t2v-a14b``), else difflib's close matches
    (``stepsize`` for ``step_size``), each written after ``prefix`` (a config key's section:
    ``guidance.``); ``''`` where none is close."""
    names = list(names)
    typed = str(word).lower()
    close = [name for name in names if typed and name.lower().startswith(typed)][:3]
    close = close or difflib.get_close_matches(typed, names, n=3)
    return f" (did you mean {' or '.join(repr(prefix + name) for name in close)}?)" if close else ""


def model_named(name: str) -> VideoModel:
    """The :class:`VideoModel` of ``name``; ValueError (one line) listing the names otherwise,
    the closest first."""
    try:
        return MODELS[name]
    except (KeyError, TypeError):
        raise ValueError(f"unknown model {name!r}{did_you_mean(name, MODELS)}; one of {', '.join(video_models())} "
                         f"(scored only: {', '.join(SCORED_ONLY)})") from None


def generating_model(name: str) -> VideoModel:
    """The :class:`VideoModel` of ``name``, one the package generates with; ValueError (one line)
    for a name the registry does not know (:func:`model_named`) or a model it only scores, saying
    how to score its videos."""
    model = model_named(name)
    if not model.generates:
        raise ValueError(f"{name} has no open weights to generate with: its videos can only be scored (geco evaluate; "
                         f"geco geco-eval --videos {name}=DIR)")
    return model


def models_of_pipeline(pipeline_classes: Iterable[str]) -> list[VideoModel]:
    """The models whose pipeline class is one of ``pipeline_classes`` (names: a pipeline's class
    and its bases), in the registry's order."""
    names = set(pipeline_classes)
    return [model for model in MODELS.values() if model.pipeline in names]


def scheduler_names() -> tuple[str, ...]:
    """Every ``sampling.scheduler`` name some model can sample with besides its checkpoint's own."""
    return tuple(dict.fromkeys(name for model in MODELS.values() for name in model.schedulers))


def paper_fps() -> dict[str, float]:
    """Every model's native frame rate for GeCo-Eval, by name (``evaluation.model_fps``)."""
    return {name: model.eval_fps for name, model in MODELS.items()}
