"""Everything that knows about diffusion, in four rooms from the bottom up: ``algorithm`` (what
guidance computes: options and presets, the schedule, noise levels, anchor slicing, the guided
step), ``running`` (how a machine runs it: run options, memory plans, the anchor decode, devices,
context parallelism, the guidance context of one call), ``search`` (particle search with GeCo as
the verifier) and ``pipelines`` (the front doors: the CogVideoX pipeline, the hooks and adapters
that guide other diffusers video pipelines, the Modular blocks, loading; imported lazily: they
pull in diffusers)."""

from .algorithm.config import GuidanceConfig, fused_guidance_config, paper_guidance_config, resolve_guidance_config
from .algorithm.levels import FlowLevels, NoiseLevels, VPLevels, ddim_step, renoise, v_to_x0
from .algorithm.schedule import GuidanceSchedule, paper_schedule, parse_repeats, scale_schedule
from .algorithm.slicing import (
    AnchorChunk,
    anchor_latent_chunks,
    check_num_frames,
    decode_anchor_frames,
)
from .algorithm.step import GuidanceRecord, guided_step, normalized_update, score_anchor_frames
from .running.context import GuidanceContext, GuidanceObserver, GuidanceReport
from .running.run_options import RunOptions, resolve_call_options
from .search.particle_search import SearchConfig

_LAZY = {
    "GeCoCogVideoXPipeline": "pipelines.pipeline_cogvideox",
    "GeCoCogVideoXPipelineOutput": "pipelines.pipeline_cogvideox",
    "attach_geco_guidance": "pipelines.hooks",
    "GeCoGuidanceHandle": "pipelines.hooks",
    "PipelineAdapter": "pipelines.adapters",
    "register_adapter": "pipelines.adapters",
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
