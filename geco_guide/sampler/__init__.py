"""Everything that knows about diffusion: guidance options and presets, the guidance schedule,
anchor slicing, noise-level arithmetic, the model-agnostic guided step and the guidance context,
particle search with GeCo as the verifier, the CogVideoX pipeline and the hooks that guide other
diffusers video pipelines (both imported lazily: they pull in diffusers)."""

from .config import GuidanceConfig, fused_guidance_config, paper_guidance_config, resolve_guidance_config
from .run_options import RunOptions, resolve_call_options
from .context import GuidanceContext, GuidanceObserver, GuidanceReport
from .levels import FlowLevels, NoiseLevels, VPLevels, ddim_step, renoise, v_to_x0
from .schedule import GuidanceSchedule, paper_schedule, parse_repeats, scale_schedule
from .slicing import (
    AnchorChunk,
    anchor_latent_chunks,
    check_num_frames,
    decode_anchor_frames,
)
from .step import GuidanceRecord, guided_step, normalized_update, score_anchor_frames
from .search import SearchConfig

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
    "GuidanceContext",
    "GuidanceObserver",
    "GuidanceRecord",
    "GuidanceReport",
    "GuidanceSchedule",
    "anchor_latent_chunks",
    "check_num_frames",
    "ddim_step",
    "decode_anchor_frames",
    "guided_step",
    "fused_guidance_config",
    "normalized_update",
    "paper_guidance_config",
    "paper_schedule",
    "parse_repeats",
    "renoise",
    "resolve_call_options",
    "resolve_guidance_config",
    "RunOptions",
    "scale_schedule",
    "SearchConfig",
    "score_anchor_frames",
    "v_to_x0",
]


def __getattr__(name: str):
    if name in _LAZY:
        from importlib import import_module

        return getattr(import_module(f"{__name__}.{_LAZY[name]}"), name)
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
