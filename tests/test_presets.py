"""The two CogVideoX-5b presets (the paper's experiment and the fused loss), whether the
update's gradient reaches the geometry estimator, and the structure cue without it."""

from __future__ import annotations

from dataclasses import replace

import pytest
import torch

from geco_guide.config import config_to_dict, load_config
from geco_guide.estimators import Estimators
from geco_guide.loss.geco import GeCoLoss, GeCoLossConfig
from geco_guide.sampler.algorithm.config import (
    GuidanceConfig,
    fused_guidance_config,
    paper_guidance_config,
)
from geco_guide.tiny import tiny_estimators
from geco_guide.types import SceneGeometry


def _flatten(d, prefix=""):
    out = {}
    for k, v in d.items():
        if isinstance(v, dict):
            out.update(_flatten(v, f"{prefix}{k}."))
        else:
            out[f"{prefix}{k}"] = v
    return out


def test_paper_preset_is_the_papers_experiment_and_fused_differs_only_in_the_loss():
    paper = load_config(preset="cogvideox-5b")
    fused = load_config(preset="cogvideox-5b-fused")
    p = paper.guidance.loss
    assert (p.cue, p.pairs, p.flow_downscale, p.geometry_grad) == ("motion", "adjacent", 0.5, False)
    assert paper.guidance.anchors == [12, 24, 36, 48] and paper.guidance.repeats == "0x3,3x17,2x30"
    assert paper.guidance.step_size == 3.0 and paper.guidance.time_travel == [15, 20] and paper.guidance.denoiser_grad
    assert paper.sampling.scheduler == "ddim" and fused.sampling.scheduler == "ddim"  # DDIM, chosen explicitly
    assert (fused.guidance.loss.cue, fused.guidance.loss.geometry_grad) == ("fused", True)
    a, b = _flatten(config_to_dict(paper)), _flatten(config_to_dict(fused))
    assert {k for k in a if a[k] != b[k]} == {"guidance.loss.cue", "guidance.loss.geometry_grad"}
    # the Python API: GuidanceConfig() (and paper_guidance_config()) is the CLI default, the paper's
    # experiment; fused_guidance_config() the fused preset's. Its anchors (None) are the paper's four
    # spread over the call's video, which the config names once it knows the model (CogVideoX-5b: 49 frames).
    assert paper_guidance_config() == GuidanceConfig() and GuidanceConfig().anchors is None
    assert GuidanceConfig().anchors_for(49, 4) == [12, 24, 36, 48]
    assert replace(GuidanceConfig(), anchors=[12, 24, 36, 48]) == paper.guidance == load_config().guidance
    assert replace(fused_guidance_config(), anchors=[12, 24, 36, 48]) == fused.guidance


class _GradProbe:
    """A geometry estimator that records every gradient reaching its outputs. ``leaky`` runs the
    estimator with gradients enabled whatever the caller asked (as an estimator with its own
    ``torch.enable_grad`` would): ``geometry_grad=False`` must still cut the gradient."""

    def __init__(self, inner, leaky=False):
        self.inner, self.leaky, self.seen = inner, leaky, []

    def estimate_geometry(self, frames):
        with torch.set_grad_enabled(self.leaky or torch.is_grad_enabled()):
            geometry = self.inner.estimate_geometry(frames)
        for name in ("depth", "intrinsics", "extrinsics"):
            tensor = getattr(geometry, name)
            if tensor.requires_grad:
                tensor.register_hook(lambda g, name=name: self.seen.append((name, float(g.abs().sum()))))
        return geometry


@pytest.mark.parametrize("leaky", [False, True])
def test_paper_preset_gradient_does_not_reach_the_geometry_estimator_and_fused_does(leaky):
    tiny = tiny_estimators(0)
    vggt, ufm = tiny.geometry, tiny.flow
    frames = torch.rand(1, 3, 3, 32, 48, generator=torch.Generator().manual_seed(0))
    grads = {}
    for preset in ("cogvideox-5b", "cogvideox-5b-fused"):
        probe = _GradProbe(vggt, leaky=leaky)
        loss_fn = GeCoLoss(Estimators(probe, ufm), load_config(preset=preset).guidance.loss)
        x = frames.clone().requires_grad_(True)
        loss_fn(x).loss.backward()
        grads[preset] = (probe.seen, x.grad)
    seen, grad = grads["cogvideox-5b"]
    assert seen == []  # depth and cameras are constants of the update ...
    assert grad is not None and float(grad.abs().sum()) > 0  # ... which reaches the frames through the flow
    seen, grad = grads["cogvideox-5b-fused"]
    assert {name for name, _ in seen} >= {"depth"} and any(value > 0 for _, value in seen)
    assert float(grad.abs().sum()) > 0


def test_rigid_flow_depends_on_the_frames_only_through_the_flow_estimator():
    # with geometry_grad=False, the motion cue's gradient equals the one with the geometry frozen
    # to constants computed beforehand
    tiny = tiny_estimators(0)
    vggt, ufm = tiny.geometry, tiny.flow
    frames = torch.rand(1, 3, 3, 32, 48, generator=torch.Generator().manual_seed(1))
    config = load_config(preset="cogvideox-5b").guidance.loss
    with torch.no_grad():
        fixed = vggt.estimate_geometry(frames)

    class Constant:
        def estimate_geometry(self, _frames):
            return SceneGeometry(fixed.depth, fixed.intrinsics, fixed.extrinsics, fixed.confidence)

    x1, x2 = frames.clone().requires_grad_(True), frames.clone().requires_grad_(True)
    GeCoLoss(Estimators(_GradProbe(vggt, leaky=True), ufm), config)(x1).loss.backward()
    GeCoLoss(Estimators(Constant(), ufm), config)(x2).loss.backward()
    torch.testing.assert_close(x1.grad, x2.grad)


def test_structure_cue_without_geometry_gradient_is_refused_up_front():
    with pytest.raises(ValueError) as err:
        load_config(preset="tiny", overrides=["guidance.loss.cue=structure"])  # the schema: geometry_grad=false
    message = str(err.value)
    assert "guidance.loss.geometry_grad" in message and "structure" in message and "\n" not in message
    load_config(preset="tiny", overrides=["guidance.loss.cue=structure", "guidance.loss.geometry_grad=true"])
    load_config(preset="tiny", overrides=["guidance.loss.cue=structure", "guidance.enabled=false"])
    with pytest.raises(ValueError, match="geometry_grad=true"):
        GuidanceConfig(loss=GeCoLossConfig(cue="structure", geometry_grad=False)).validate(50, 49, 4)
