"""Everything that knows about diffusion: anchor slicing, the guidance schedule, the
model-agnostic guided step, the CogVideoX pipeline and the hooks that guide other diffusers video
pipelines (both imported lazily: they pull in diffusers)."""

from .guidance import (
    FlowLevels,
    GuidanceConfig,
    GuidanceRecord,
    NoiseLevels,
    VPLevels,
    ddim_step,
    guided_step,
    normalized_update,
    paper_guidance_config,
    renoise,
    resolve_guidance_config,
    score_anchor_frames,
    v_to_x0,
)
from .schedule import GuidanceSchedule, paper_schedule, parse_repeats, scale_schedule
from .slicing import (
    AnchorChunk,
    anchor_latent_chunks,
    check_num_frames,
    decode_anchor_frames,
)

_LAZY = {
    "GeCoCogVideoXPipeline": "pipeline_cogvideox",
    "GeCoCogVideoXPipelineOutput": "pipeline_cogvideox",
    "attach_geco_guidance": "hooks",
    "GeCoGuidanceHandle": "hooks",
    "PipelineAdapter": "adapters",
    "register_adapter": "adapters",
}

__all__ = [
    "AnchorChunk",
    "FlowLevels",
    "GeCoGuidanceHandle",
    "NoiseLevels",
    "PipelineAdapter",
    "VPLevels",
    "attach_geco_guidance",
    "register_adapter",
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
    "paper_guidance_config",
    "paper_schedule",
    "parse_repeats",
    "renoise",
    "resolve_guidance_config",
    "scale_schedule",
    "score_anchor_frames",
    "v_to_x0",
]


def __getattr__(name: str):
    if name in _LAZY:
        from importlib import import_module

        return getattr(import_module(f"{__name__}.{_LAZY[name]}"), name)
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
