"""guidance.loss.movers=rigid: the movers' rigidity residual in the guidance loss, fitted without
gradients at each refresh of the masks, the gradient through the frames (pipeline and hooks)."""

from __future__ import annotations

from dataclasses import replace

import pytest
import torch

from geco_guide import tiny as T
from geco_guide.bench.synthetic import moving_clip
from geco_guide.config import load_config
from geco_guide.estimators.bundle import Estimators
from geco_guide.estimators.dynamic_masks import GivenMasks
from geco_guide.estimators.oracle import OracleGeometry
from geco_guide.loss.geco import GeCoLoss, GeCoLossConfig
from geco_guide.loss.movers import RefreshedMovers
from geco_guide.loss.presets import guidance_loss
from geco_guide.sampler.algorithm.config import GuidanceConfig
from geco_guide.sampler.algorithm.dynamic import RefreshedMasks
from geco_guide.sampler.pipelines.hooks import attach_geco_guidance
from geco_guide.sampler.algorithm.levels import FlowLevels
from geco_guide.sampler.algorithm.objective import AnchorObjective
from geco_guide.sampler.algorithm.step import guided_step
from geco_guide.types import OptionError

from loss.test_movers import CarriedFlow

PROMPT = "a red car drives along a street"


def test_guided_updates_with_rigid_movers_lower_a_deforming_movers_residual():
    # the latents are the frames (x0 = z at sigma 0, the decode is the identity), the anchors a
    # moving box whose middle band drifts on its own: guidance's own objective, masks and movers
    clip = moving_clip(5, 48, 64)
    on_box = (clip.objects == 0)[:, None].float()
    rows = torch.arange(48, dtype=torch.float32)[:, None]
    middle = float((clip.objects == 0).nonzero()[:, 1].float().mean())
    drift = 0.006 * torch.exp(-((rows - middle) / 2.0) ** 2) * on_box * torch.arange(5.0)[:, None, None, None]
    frames = (clip.frames.float() + drift.expand(-1, 3, -1, -1)).clamp(0, 1)[None]
    config = replace(guidance_loss(), flow_downscale=1.0, movers="rigid")
    estimators = Estimators(OracleGeometry(clip), CarriedFlow(clip, scale=100.0))
    movers = RefreshedMovers()
    masks = RefreshedMasks(GivenMasks(clip.dynamic_mask), movers=movers)
    objective = AnchorObjective(lambda latents: latents, lambda x0: x0,
                                GeCoLoss(estimators, config, check_values=False), masks)
    levels = FlowLevels(torch.tensor(0.0), torch.tensor(0.0))

    def residual(z):
        with torch.no_grad():
            return float(objective.loss_fn(z, dynamic_masks=masks, movers=movers).movers.contribution.sum())

    updates = []
    z, _ = guided_step(frames, lambda z, grad: torch.zeros_like(z), levels, objective, 15, step_size=0.03,
                       denoiser_grad=False, on_update=updates.append)
    assert len(updates) == 15 and all(bool(u.terms["finite"]) for u in updates)
    assert residual(z) < 0.5 * residual(frames)
    assert movers.last is not None  # fitted once, at the masks' first (and only) refresh


@pytest.mark.parametrize("front_door", ["pipeline", "hooks"])
@pytest.mark.slow
def test_rigid_movers_guide_in_the_pipeline_and_under_the_hooks(front_door, estimators):
    loss = replace(T.tiny_guidance_config().loss, movers="rigid")
    config = T.tiny_guidance_config(repeats="0x2,1x2", time_travel=[], dynamic="auto", loss=loss)
    if front_door == "pipeline":
        pipe = T.tiny_pipeline(0)
        out = pipe(PROMPT, generator=torch.Generator().manual_seed(0), guidance=config, estimators=estimators,
                   run_options=T.tiny_run_options(), output_type="latent", **T.TINY_CALL_KWARGS)
        report = out.report
    else:
        pipe = T.tiny_wan_pipeline(0)
        with attach_geco_guidance(pipe, config, estimators) as handle:
            pipe(PROMPT, generator=torch.Generator().manual_seed(0), output_type="latent", **T.tiny_call_kwargs(pipe))
        report = handle.last
    assert len(report.log) == 2 and report.mask_source == "auto"
    assert report.guidance["loss"]["movers"] == "rigid" and all(r["mask_source"] == "auto" for r in report.log)


def test_movers_options_are_one_line_before_any_work():
    rigid = replace(guidance_loss(), movers="rigid")
    with pytest.raises(OptionError, match=r"^loss.movers 'rigid' scores the movers of dynamic masks: give "
                                          r"guidance.dynamic \('auto' or the subjects that move\)"):
        GuidanceConfig(loss=rigid)
    with pytest.raises(OptionError, match="movers must be one of"):
        GuidanceConfig(dynamic="auto", loss=GeCoLossConfig(movers="melt"))
    assert GuidanceConfig(dynamic="auto", loss=rigid).loss.movers == "rigid"
    # one spelling, the loss' own: the earlier one is refused in one line naming it
    with pytest.raises(TypeError, match=r"^GuidanceConfig\(movers=...\) is the earlier spelling of "
                                        r"GuidanceConfig\(loss=GeCoLossConfig\(movers=...\)\): use that instead$"):
        GuidanceConfig(movers="rigid")
    with pytest.raises(ValueError, match=r"^guidance.movers is the earlier name of guidance.loss.movers: use "
                                         r"guidance.loss.movers instead \(command line\)$"):
        load_config(preset="tiny", overrides=["guidance.movers=rigid"])
