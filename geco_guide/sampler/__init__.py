"""Everything that knows about diffusion: anchor slicing, the guidance schedule, the
model-agnostic guided step and the CogVideoX pipeline (imported lazily: it pulls in diffusers)."""

from .guidance import (
    GuidanceConfig,
    GuidanceRecord,
    ddim_step,
    guided_step,
    normalized_update,
    renoise,
    resolve_guidance_config,
    score_anchor_frames,
    v_to_x0,
)
from .schedule import GuidanceSchedule, paper_schedule, parse_repeats
from .slicing import AnchorChunk, anchor_latent_chunks, check_num_frames, decode_anchor_frames

__all__ = [
    "AnchorChunk",
    "GeCoCogVideoXPipeline",
    "GeCoCogVideoXPipelineOutput",
    "GuidanceConfig",
    "GuidanceRecord",
    "GuidanceSchedule",
    "anchor_latent_chunks",
    "check_num_frames",
    "ddim_step",
    "decode_anchor_frames",
    "guided_step",
    "normalized_update",
    "paper_schedule",
    "parse_repeats",
    "renoise",
    "resolve_guidance_config",
    "score_anchor_frames",
    "v_to_x0",
]


def __getattr__(name: str):
    if name in ("GeCoCogVideoXPipeline", "GeCoCogVideoXPipelineOutput"):
        from . import pipeline_cogvideox

        return getattr(pipeline_cogvideox, name)
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
