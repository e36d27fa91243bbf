"""Named GeCo loss options: the one place where the paper's settings are written down.

``GeCoLossConfig()`` holds the metric's neutral defaults (fused map, adjacent pairs, full-size
flow input, depth-test occlusion). Each experiment of the paper changes a few of them:

- :func:`guidance_loss` — the paper's guidance experiment (supplement; the published code's
  ``--loss-fn residual_motion``): the residual motion cue on adjacent pairs of the anchor frames,
  flow input downscaled by 0.5, depth and cameras constants of the update (``geometry_grad=False``).
  ``GuidanceConfig()`` and the CLI default to it.
- :func:`fused_guidance_loss` — the method section's equation: the fused map ``M_geo`` with
  gradients through the geometry estimator too (the ``cogvideox-5b-fused`` preset).
- :func:`evaluation_loss` — the GeCo-Eval script: every ordered pair of a window, full-resolution
  flow input, the script's structure-cue occlusion rule (``evaluate_video`` defaults to it).

Guidance scores 4 anchor frames with a cheap differentiable loss, so it uses adjacent pairs; the
benchmark reproduces the published evaluation script, so it uses all pairs.
"""

from __future__ import annotations

from .geco import GeCoLossConfig

__all__ = ["evaluation_loss", "fused_guidance_loss", "guidance_loss"]


def guidance_loss() -> GeCoLossConfig:
    """The paper's guidance experiment: residual motion, adjacent pairs, flow x0.5, no VGGT gradient."""
    return GeCoLossConfig(cue="motion", pairs="adjacent", flow_downscale=0.5, geometry_grad=False)


def fused_guidance_loss() -> GeCoLossConfig:
    """The method section's loss: the fused ``M_geo`` on adjacent pairs, flow x0.5, gradients through VGGT."""
    return GeCoLossConfig(cue="fused", pairs="adjacent", flow_downscale=0.5, geometry_grad=True)


def evaluation_loss() -> GeCoLossConfig:
    """The GeCo-Eval script's metric: all ordered pairs, full-resolution flow, covisibility occlusion."""
    return GeCoLossConfig(pairs="all", flow_downscale=1.0, structure_occlusion="covisibility")

