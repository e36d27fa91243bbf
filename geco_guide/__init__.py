"""GeCo: geometric-consistency metric and training-free guidance for diffusers video models.

Public names are imported lazily, so ``import geco_guide`` stays light (no diffusers import)
until a name of the sampler that needs diffusers (``GeCoCogVideoXPipeline``,
``attach_geco_guidance``) is used.
"""

from importlib import import_module as _import_module
from typing import TYPE_CHECKING

__version__ = "0.1.0"

_EXPORTS = {
    "GeCoLoss": "geco_guide.loss.geco",
    "GeCoLossConfig": "geco_guide.loss.geco",
    "GeCoResult": "geco_guide.loss.geco",
    "geco_from_geometry": "geco_guide.loss.geco",
    "motion_statistics": "geco_guide.loss.motion_stats",
    "SceneGeometry": "geco_guide.types",
    "Correspondences": "geco_guide.types",
    "GeometryEstimator": "geco_guide.types",
    "FlowEstimator": "geco_guide.types",
    "Estimators": "geco_guide.estimators.bundle",
    "VGGT": "geco_guide.estimators.vggt",
    "VGGTConfig": "geco_guide.estimators.vggt",
    "UFM": "geco_guide.estimators.ufm",
    "UFMConfig": "geco_guide.estimators.ufm",
    "TinyDecoder": "geco_guide.estimators.tiny_decoder",
    "attach_geco_guidance": "geco_guide.sampler.pipelines.hooks",
    "GeCoCogVideoXPipeline": "geco_guide.sampler.pipelines.pipeline_cogvideox",
    "GuidanceConfig": "geco_guide.sampler.algorithm.config",
    "RunOptions": "geco_guide.sampler.running.run_options",
    "SearchConfig": "geco_guide.sampler.search.particle_search",
    "evaluate_video": "geco_guide.metric.evaluate",
    "GuidanceReport": "geco_guide.sampler.running.context",
    "generate": "geco_guide.generation",
    "MODELS": "geco_guide.families",
    "load_prompts": "geco_guide.bench.geco_eval",
}

__all__ = sorted(_EXPORTS)

if TYPE_CHECKING:  # pragma: no cover
    from .bench.geco_eval import load_prompts
    from .estimators.bundle import Estimators
    from .estimators.tiny_decoder import TinyDecoder
    from .estimators.ufm import UFM, UFMConfig
    from .estimators.vggt import VGGT, VGGTConfig
    from .loss.geco import GeCoLoss, GeCoLossConfig, GeCoResult, geco_from_geometry
    from .loss.motion_stats import motion_statistics
    from .metric.evaluate import evaluate_video
    from .families import MODELS
    from .generation import generate
    from .sampler.algorithm.config import GuidanceConfig
    from .sampler.running.context import GuidanceReport
    from .sampler.pipelines.hooks import attach_geco_guidance
    from .sampler.pipelines.pipeline_cogvideox import GeCoCogVideoXPipeline
    from .sampler.running.run_options import RunOptions
    from .sampler.search.particle_search import SearchConfig
    from .types import Correspondences, FlowEstimator, GeometryEstimator, SceneGeometry


def __getattr__(name: str):
    if name not in _EXPORTS:
        raise AttributeError(f"module 'geco_guide' has no attribute {name!r}")
    value = getattr(_import_module(_EXPORTS[name]), name)
    globals()[name] = value
    return value


def __dir__():
    # the public names and the subpackages already imported, not this file's own helpers
    loaded = {name for name, value in globals().items() if getattr(value, "__name__", "").startswith(f"{__name__}.")}
    return sorted(set(__all__) | loaded | {"__version__"})
