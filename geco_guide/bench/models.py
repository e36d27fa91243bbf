"""The video models GeCo-Eval runs: one registry (:data:`MODELS`) of checkpoints, pipelines and
default call settings, whose native frame rates are the metric's table
(:data:`geco_guide.metric.model_fps.PAPER_MODEL_FPS`: the metric floor times videos without
knowing about generation, so the registry reads its rates from there and never repeats them)."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

from ..metric.model_fps import PAPER_MODEL_FPS

__all__ = ["MODELS", "SCORED_ONLY", "VideoModel"]

#: Models of the paper's table that GeCo-Eval only scores (``--videos NAME=DIR``): no open weights.
SCORED_ONLY = ("sora-2", "veo-3.1")


@dataclass(frozen=True)
class VideoModel:
    """A text-to-video model as GeCo-Eval runs it.

    Attributes:
        name: the registry name (also the key of ``evaluation.model_fps``, its native rate).
        hub_id: the diffusers checkpoint (``--weights NAME=DIR`` replaces it with a folder).
        pipeline: the diffusers pipeline class.
        call: the documented default call settings (frames, size, steps, CFG, ...).
        temporal_compression: frames per latent of the VAE (anchors of guided runs).
        tiny: the tiny random family of ``--preset tiny`` (:mod:`geco_guide.tiny`).
    """

    name: str
    hub_id: str
    pipeline: str
    call: dict[str, Any] = field(hash=False)
    temporal_compression: int
    tiny: str

    @property
    def fps(self) -> float:
        """The native frame rate, from the paper's table (the default of ``evaluation.model_fps``)."""
        return PAPER_MODEL_FPS[self.name]


#: Defaults from each model card / diffusers' pipeline documentation. Guided runs use the
#: config's guidance schedule, written for 50 steps (other counts are scaled, see README).
MODELS: dict[str, VideoModel] = {
    m.name: m
    for m in (
        VideoModel("cogvideox-2b", "THUDM/CogVideoX-2b", "CogVideoXPipeline",
                   {"num_frames": 49, "height": 480, "width": 720, "num_inference_steps": 50, "guidance_scale": 6.0},
                   4, "cogvideox"),
        VideoModel("cogvideox-5b", "THUDM/CogVideoX-5b", "CogVideoXPipeline",
                   {"num_frames": 49, "height": 480, "width": 720, "num_inference_steps": 50, "guidance_scale": 6.0},
                   4, "cogvideox"),
        VideoModel("cogvideox1.5-5b", "THUDM/CogVideoX1.5-5B", "CogVideoXPipeline",
                   {"num_frames": 81, "height": 768, "width": 1360, "num_inference_steps": 50, "guidance_scale": 6.0},
                   4, "cogvideox1.5"),
        VideoModel("wan2.1-t2v-1.3b", "Wan-AI/Wan2.1-T2V-1.3B-Diffusers", "WanPipeline",
                   {"num_frames": 81, "height": 480, "width": 832, "num_inference_steps": 50, "guidance_scale": 5.0},
                   4, "wan"),
        VideoModel("wan2.1-t2v-14b", "Wan-AI/Wan2.1-T2V-14B-Diffusers", "WanPipeline",
                   {"num_frames": 81, "height": 720, "width": 1280, "num_inference_steps": 50, "guidance_scale": 5.0},
                   4, "wan"),
        VideoModel("wan2.2-t2v-a14b", "Wan-AI/Wan2.2-T2V-A14B-Diffusers", "WanPipeline",
                   {"num_frames": 81, "height": 720, "width": 1280, "num_inference_steps": 40, "guidance_scale": 4.0,
                    "guidance_scale_2": 3.0},
                   4, "wan"),
        VideoModel("hunyuanvideo", "hunyuanvideo-community/HunyuanVideo", "HunyuanVideoPipeline",
                   {"num_frames": 129, "height": 720, "width": 1280, "num_inference_steps": 50, "guidance_scale": 6.0},
                   4, "hunyuan"),
        VideoModel("ltx-video", "Lightricks/LTX-Video", "LTXPipeline",
                   {"num_frames": 161, "height": 480, "width": 704, "num_inference_steps": 50, "guidance_scale": 3.0},
                   8, "ltx"),
    )
}
