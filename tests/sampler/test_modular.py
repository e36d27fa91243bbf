"""The GeCo block of diffusers' Modular Wan loops (geco_guide.sampler.pipelines.modular), on tiny random
Wan 2.1 / 2.2 built from the real diffusers classes: the hooked ``WanPipeline``'s video, stock
output with guidance off, what a call decided in the pipeline state, and the block shared as
diffusers shares custom blocks."""

from __future__ import annotations

import json
import re
import sys

import pytest
import torch

from geco_guide import tiny as T
from geco_guide.sampler.algorithm.config import GuidanceConfig
from geco_guide.sampler.pipelines.hooks import attach_geco_guidance
from geco_guide.sampler.pipelines.modular import GeCoWan22DenoiseStep, GeCoWanDenoiseStep, save_geco_block

NUM_FRAMES = 9  # 3 latents
# guided at steps 1 and 3 of 4: Wan 2.2's first expert (t >= 875) guides step 1, its second step 3
SCHEDULE = dict(anchors=[5, 8], chunk_latents=3, repeats="0x1,1x1,0x1,2x1", step_size=1.0)
OUTPUTS = ["videos", "geco_report"]
LOOPS = {"2.1": GeCoWanDenoiseStep, "2.2": GeCoWan22DenoiseStep}
# The hooks rebuild the CFG output as w_u * uncond + w_c * cond, weights fitted to the captured
# calls (float64 least squares, used in float32); diffusers' guider computes uncond + s * (cond -
# uncond). The two round differently in float32, so where an update re-runs the denoiser with CFG
# (faithful mode, or the prediction after a time-travel re-noising) the two front doors differ by
# rounding, carried through the later steps. Measured on frames in [0, 1]: at most 7e-7 in this
# test's runs, 3.4e-5 in a Wan 2.2 faithful run without time travel, against a guidance effect of
# 0.17 to 0.29. Without CFG, or where the loop's own prediction serves every update (fast mode
# without time travel), nothing is rebuilt and the frames agree bit for bit.
CFG_REBUILD_ATOL = 1e-4


def call_kwargs() -> dict:
    return dict(num_frames=NUM_FRAMES, height=T.TINY_HEIGHT, width=T.TINY_WIDTH, num_inference_steps=4,
                output_type="pt")


def prompt_embeds(stock) -> dict:
    positive, negative = stock.encode_prompt("a marble bust on a table", "blurry",
                                             max_sequence_length=T.TINY_MAX_SEQUENCE_LENGTH, device="cpu")
    return dict(prompt_embeds=positive, negative_prompt_embeds=negative)


def scales(version: str, cfg: bool) -> dict:
    """The CFG scales of a ``WanPipeline`` call, as :func:`tiny_wan_modular_pipeline` gets them:
    Wan's 5 (3 for Wan 2.2's second expert), or 1, no CFG (one denoiser call per step)."""
    second = (3.0 if cfg else 1.0) if version == "2.2" else None
    return dict(guidance_scale=5.0 if cfg else 1.0, guidance_scale_2=second)


def wan_call(stock, version: str, cfg: bool) -> torch.Tensor:
    guidance = scales(version, cfg)
    if guidance["guidance_scale_2"] is None:
        del guidance["guidance_scale_2"]
    return stock(**prompt_embeds(stock), generator=torch.Generator().manual_seed(0), **guidance, **call_kwargs()).frames


def modular_call(pipe, embeds: dict, output=OUTPUTS, **inputs):
    return pipe(**embeds, generator=torch.Generator().manual_seed(0), output=output, **call_kwargs(), **inputs)


def without_seconds(log: list[dict]) -> list[dict]:
    return [{key: value for key, value in record.items() if key != "seconds"} for record in log]


@pytest.mark.parametrize("version", ["2.1", "2.2"])
@pytest.mark.parametrize(
    "faithful, cfg, time_travel, bitwise",
    [
        pytest.param(False, True, [], True, id="fast"),
        pytest.param(True, False, [1, 1], True, id="faithful-no-cfg"),
        pytest.param(True, True, [1, 1], False, id="faithful-cfg"),
    ],
)
@pytest.mark.slow
def test_the_block_gives_the_hooked_wan_pipelines_frames(version, faithful, cfg, time_travel, bitwise, estimators):
    bundle = estimators
    config = T.tiny_guidance_config(**SCHEDULE, time_travel=time_travel, denoiser_grad=faithful)
    stock = T.tiny_wan_pipeline(0, version=version)
    unguided = wan_call(stock, version, cfg)
    with attach_geco_guidance(stock, config, estimators=bundle) as handle:
        hooked = wan_call(stock, version, cfg)
        hooked_plan, hooked_log = handle.last.memory_plan, handle.log
    pipe = T.tiny_wan_modular_pipeline(0, version=version, denoise_loop=LOOPS[version](), **scales(version, cfg))
    out = modular_call(pipe, prompt_embeds(stock), geco_guidance=config, geco_estimators=bundle)

    assert (out["videos"] - unguided).abs().max() > 100 * CFG_REBUILD_ATOL  # guidance did change the video
    report = out["geco_report"]
    assert [(r["step"], r["time_travel"]) for r in report.log] == [(1, bool(time_travel)), (3, False), (3, False)]
    assert report.memory_plan == hooked_plan and report.devices is None
    if bitwise:
        assert torch.equal(out["videos"], hooked)
        assert without_seconds(report.log) == without_seconds(hooked_log)
    else:
        torch.testing.assert_close(out["videos"], hooked, rtol=0, atol=CFG_REBUILD_ATOL)
        for ours, theirs in zip(report.log, hooked_log, strict=True):
            assert ours["loss"] == pytest.approx(theirs["loss"], rel=1e-4)
            assert ours["grad_norm"] == pytest.approx(theirs["grad_norm"], rel=1e-4)


@pytest.mark.parametrize("version", ["2.1", "2.2"])
def test_guidance_off_is_the_stock_modular_output_bit_for_bit(version, estimators):
    stock = T.tiny_wan_pipeline(0, version=version)
    embeds = prompt_embeds(stock)
    wan = wan_call(stock, version, True)
    plain = modular_call(T.tiny_wan_modular_pipeline(0, version=version, **scales(version, True)), embeds, "videos")
    pipe = T.tiny_wan_modular_pipeline(0, version=version, denoise_loop=LOOPS[version](), **scales(version, True))
    absent = modular_call(pipe, embeds)
    disabled = modular_call(pipe, embeds, geco_guidance=GuidanceConfig(enabled=False),
                            geco_estimators=estimators)

    assert torch.equal(plain, wan)  # diffusers' two Wan front doors agree: the reference holds
    for out in (absent, disabled):
        assert torch.equal(out["videos"], plain)
        report = out["geco_report"]
        assert report.log == [] and report.memory_plan is None and report.guidance is None


def test_what_the_call_decided_is_in_the_pipeline_state(estimators):
    stock = T.tiny_wan_pipeline(0)
    pipe = T.tiny_wan_modular_pipeline(0, denoise_loop=GeCoWanDenoiseStep())
    config = T.tiny_guidance_config(**SCHEDULE, time_travel=[], denoiser_grad=False)
    state = modular_call(pipe, prompt_embeds(stock), output=None, geco_guidance=config,
                         geco_estimators=estimators, geco_run_options={"memory_plan": "fastest"})

    report = state.get("geco_report")
    log, plan = report.log, report.memory_plan
    assert [r["step"] for r in log] == [1, 3, 3] and all(r["grad_norm"] > 0 and not r["skipped"] for r in log)
    assert plan["name"] == "fastest" and plan["reason"] == "run.memory_plan=fastest"
    assert report.devices is None and report.decoder.startswith("vae") and report.scheduler


@pytest.fixture
def modules_cache(tmp_path, monkeypatch):
    """diffusers' cache of loaded code files in ``tmp_path``: a loaded block's code file is copied
    there and imported from there (``sys.path``, ``sys.modules``), all undone after the test."""
    import diffusers.utils.dynamic_modules_utils as dynamic_modules

    monkeypatch.setattr(dynamic_modules, "HF_MODULES_CACHE", str(tmp_path / "modules"))
    monkeypatch.setattr(sys, "path", list(sys.path))
    before = set(sys.modules)
    yield
    for name in set(sys.modules) - before:
        if name.startswith(dynamic_modules.DIFFUSERS_DYNAMIC_MODULE_NAME):
            del sys.modules[name]


@pytest.mark.slow
def test_the_block_saves_and_loads_as_a_diffusers_custom_block(tmp_path, modules_cache, estimators):
    from diffusers.modular_pipelines import ModularPipelineBlocks

    folder = tmp_path / "geco-wan22"
    config_file = save_geco_block(GeCoWan22DenoiseStep(), folder)

    assert json.loads(config_file.read_text())["auto_map"] == {"ModularPipelineBlocks": "modular.GeCoWan22DenoiseStep"}
    assert sorted(p.name for p in folder.iterdir()) == ["modular.py", "modular_config.json"]
    with pytest.raises(ValueError, match="trust_remote_code=True"):
        ModularPipelineBlocks.from_pretrained(str(folder))
    loaded = ModularPipelineBlocks.from_pretrained(str(folder), trust_remote_code=True)
    assert type(loaded) is GeCoWan22DenoiseStep

    stock = T.tiny_wan_pipeline(0, version="2.2")
    embeds, bundle = prompt_embeds(stock), estimators
    config = T.tiny_guidance_config(**SCHEDULE, time_travel=[], denoiser_grad=False)
    frames = [modular_call(T.tiny_wan_modular_pipeline(0, version="2.2", denoise_loop=loop), embeds, "videos",
                           geco_guidance=config, geco_estimators=bundle)
              for loop in (GeCoWan22DenoiseStep(), loaded)]
    assert torch.equal(frames[1], frames[0])


@pytest.mark.slow
def test_a_loop_block_under_no_grad_is_differentiated_all_the_same(estimators):
    from diffusers.modular_pipelines.wan.denoise import WanLoopDenoiser

    class NoGradDenoiser(WanLoopDenoiser):
        def __call__(self, components, block_state, i, t):
            with torch.no_grad():
                return super().__call__(components, block_state, i, t)

    stock = T.tiny_wan_pipeline(0)
    config = T.tiny_guidance_config(**SCHEDULE, time_travel=[], denoiser_grad=True)
    frames = []
    for denoiser in (None, NoGradDenoiser()):
        loop = GeCoWanDenoiseStep()
        if denoiser is not None:
            loop.sub_blocks["denoiser"] = denoiser  # the guidance reads the loop's sub-blocks as they are now
        pipe = T.tiny_wan_modular_pipeline(0, denoise_loop=loop)
        frames.append(modular_call(pipe, prompt_embeds(stock), "videos", geco_guidance=config,
                                   geco_estimators=estimators))
    assert torch.equal(frames[1], frames[0])


def test_a_loop_block_predicting_without_a_denoiser_is_refused_in_faithful_mode(estimators):
    from diffusers.modular_pipelines.wan.denoise import WanLoopDenoiser

    class ZeroDenoiser(WanLoopDenoiser):
        def __call__(self, components, block_state, i, t):
            block_state.noise_pred = torch.zeros_like(block_state.latents)
            return components, block_state

    loop = GeCoWanDenoiseStep()
    loop.sub_blocks["denoiser"] = ZeroDenoiser()
    stock = T.tiny_wan_pipeline(0)
    pipe = T.tiny_wan_modular_pipeline(0, denoise_loop=loop)
    config = T.tiny_guidance_config(**SCHEDULE, time_travel=[], denoiser_grad=True)
    with pytest.raises(RuntimeError, match="no gradient through the loop's sub-blocks .*ZeroDenoiser.*ran a denoiser"):
        modular_call(pipe, prompt_embeds(stock), geco_guidance=config, geco_estimators=estimators)


def test_guidance_is_a_pair_of_sub_blocks_in_diffusers_loop(estimators):
    from diffusers.modular_pipelines.wan.denoise import WanDenoiseStep

    from geco_guide.sampler.running.context import GuidanceObserver
    from geco_guide.sampler.pipelines.modular import GeCoGuidanceStep, GeCoStartStep

    loop = GeCoWanDenoiseStep()
    assert list(loop.sub_blocks) == ["geco_start", "before_denoiser", "denoiser", "geco_guidance", "after_denoiser"]
    assert isinstance(loop.sub_blocks["geco_start"], GeCoStartStep)
    assert isinstance(loop.sub_blocks["geco_guidance"], GeCoGuidanceStep)
    assert type(loop).loop_step is WanDenoiseStep.loop_step  # diffusers' own loop runs the sub-blocks

    class Counting(GuidanceObserver):
        updates: list = []

        def on_update(self, record):
            self.updates.append(record.step)

    observer = Counting()
    stock = T.tiny_wan_pipeline(0)
    pipe = T.tiny_wan_modular_pipeline(0, denoise_loop=loop)
    config = T.tiny_guidance_config(**SCHEDULE, time_travel=[], denoiser_grad=False)
    report = modular_call(pipe, prompt_embeds(stock), output="geco_report", geco_guidance=config,
                          geco_estimators=estimators, geco_observer=observer)
    assert observer.updates == [r["step"] for r in report.log] == [1, 3, 3]


def test_save_geco_block_refuses_other_blocks(tmp_path):
    from diffusers.modular_pipelines.wan.denoise import WanDenoiseStep

    with pytest.raises(TypeError, match="GeCoWanDenoiseStep or GeCoWan22DenoiseStep, got WanDenoiseStep"):
        save_geco_block(WanDenoiseStep(), tmp_path)
    assert list(tmp_path.iterdir()) == []


TINY = object()  # the tiny estimators, as one Estimators


@pytest.mark.parametrize(
    "given, changes, run_options, error, message",
    [
        (None, {}, None, ValueError, "pass geco_estimators=Estimators"),
        (("geometry", "flow"), {}, None, TypeError, "takes the estimators as one Estimators.*got tuple"),
        (TINY, dict(decoder="tiny"), None, ValueError, "guidance.decoder='tiny' needs a tiny decoder"),
        (TINY, dict(anchors=[5, 12]), None, ValueError, "out of range for a 9-frame video"),
        (TINY, {}, {"memory_plan": "nonsense"}, ValueError, "memory_plan"),
    ],
)
def test_bad_guidance_inputs_fail_in_one_line_before_the_first_step(given, changes, run_options, error, message,
                                                                    estimators):
    config = T.tiny_guidance_config(**{**SCHEDULE, **changes})
    stock = T.tiny_wan_pipeline(0)
    pipe = T.tiny_wan_modular_pipeline(0, denoise_loop=GeCoWanDenoiseStep())
    calls = []
    pipe.transformer.register_forward_pre_hook(lambda module, args: calls.append(1))
    with pytest.raises(error, match=message) as raised:
        modular_call(pipe, prompt_embeds(stock), geco_guidance=config, geco_run_options=run_options,
                     geco_estimators=estimators if given is TINY else given)
    assert "\n" not in str(raised.value) and calls == []


def test_wan_22s_loop_in_a_wan_21_pipeline_is_one_line_before_the_first_step():
    stock = T.tiny_wan_pipeline(0, version="2.1")
    pipe = T.tiny_wan_modular_pipeline(0, version="2.1", denoise_loop=GeCoWan22DenoiseStep())
    calls = []
    pipe.transformer.register_forward_pre_hook(lambda module, args: calls.append(1))
    message = ("GeCoWan22DenoiseStep is Wan 2.2's denoise loop, calling transformer and transformer_2; the pipeline it "
               "is in has no transformer_2: insert GeCoWanDenoiseStep (Wan 2.1's loop) instead")
    with pytest.raises(ValueError, match="^" + re.escape(message)) as raised:  # guided or not, the loop is wrong
        modular_call(pipe, prompt_embeds(stock), output="videos")
    assert "\n" not in str(raised.value) and calls == []
