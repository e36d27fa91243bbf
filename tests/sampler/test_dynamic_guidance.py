"""Guidance with dynamic masks: the refresh rule, the pipeline and the hooks alike, the log and
the sidecar, ``--dynamic`` on generate, and the paper's default left exactly as it was."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
import torch

from geco_guide import tiny as T
from geco_guide.cli.generate import main
from geco_guide.generation import default_name, video_key
from geco_guide.config import config_to_dict, load_config
from geco_guide.sampler.algorithm.dynamic import RefreshedMasks
from geco_guide.sampler.pipelines.hooks import attach_geco_guidance

PROMPT = "a dog on a lawn"
#: Guided steps 1, 2 (two updates each) and 3 (one) of 4.
GUIDED_STEPS, UPDATES = 3, 5
#: The keys of a guidance-log record without masks (as before masks existed).
RECORD_KEYS = {"step", "repeat", "t", "loss", "motion", "structure", "fused", "grad_norm", "seconds", "time_travel",
               "skipped", "valid_fraction"}


class LeftHalf:
    """A mask source that masks the left half of every frame and notes what it was asked."""

    source_name = "left half"

    def __init__(self):
        self.calls = 0
        self.saw_grad = False

    def dynamic_masks(self, frames, geometry=None, flow=None, pairs=None):
        self.calls += 1
        self.saw_grad |= frames.requires_grad
        masks = torch.zeros(frames.shape[0], *frames.shape[-2:], dtype=torch.bool)
        masks[..., : frames.shape[-1] // 2] = True
        return masks


def test_masks_refresh_at_the_first_update_of_every_nth_step():
    source = LeftHalf()
    masks = RefreshedMasks(source, refresh=2, dilation=0)
    frames = torch.rand(2, 3, 8, 8)
    asked = []
    for step, updates in ((1, 2), (2, 2), (3, 1), (3, 1)):  # step 3 twice: the retry after a fallback
        masks.start_step(step)
        for _ in range(updates):
            masks.start_update()
            for _clip in range(2):
                masks.dynamic_masks(frames)
            asked.append(source.calls)
    # step 1 (the 1st guided step) computes both clips' masks once; step 2 reuses them; step 3
    # (the 3rd) computes again, and its retry computes again.
    assert asked == [2, 2, 2, 2, 4, 6]
    grown = RefreshedMasks(LeftHalf(), dilation=1).dynamic_masks(frames)
    assert grown[:, :, :5].all() and not grown[:, :, 5:].any()  # 4 columns grown by 1


def run_pipeline(pipe, seed: int = 1, **call):
    return pipe(PROMPT, generator=torch.Generator().manual_seed(seed), output_type="latent", **T.TINY_CALL_KWARGS, **call)


def run_tiny(pipe, estimators, seed: int = 1, **call):
    """A call of the tiny GeCo pipeline with ``estimators`` and the tiny run options."""
    return run_pipeline(pipe, seed, estimators=estimators, run_options=T.tiny_run_options(), **call)


@pytest.mark.slow
def test_pipeline_guidance_leaves_the_masked_pixels_out(estimators):
    pipe = T.tiny_pipeline(0)
    plain = run_tiny(pipe, estimators)
    source = LeftHalf()
    masked = run_tiny(pipe, estimators.with_segmenter(source), guidance={"dynamic": "the dog"})
    log = masked.report.log
    assert len(log) == UPDATES and source.calls == GUIDED_STEPS and not source.saw_grad
    assert all(r["mask_source"] == "left half" and r["masked_fraction"] == pytest.approx(0.5) for r in log)
    assert log[0]["loss"] != pytest.approx(plain.report.log[0]["loss"])  # half the frame is out
    assert masked.report.mask_source == "left half" and masked.report.masked_fraction == pytest.approx(0.5)
    assert plain.report.mask_source is None and plain.report.masked_fraction is None
    assert not torch.equal(masked.frames, plain.frames)
    every_other = LeftHalf()
    run_tiny(pipe, estimators.with_segmenter(every_other), guidance={"dynamic": "the dog", "dynamic_refresh": 2})
    assert every_other.calls == 2  # guided steps 1 and 3


@pytest.mark.slow
def test_hooks_guide_with_masks_as_the_pipeline_does(estimators):
    from diffusers import CogVideoXPipeline

    from geco_guide.sampler.pipelines.pipeline_cogvideox import GeCoCogVideoXPipeline

    config = T.tiny_guidance_config(dynamic="the dog", denoiser_grad=False)
    geco = GeCoCogVideoXPipeline(**T.tiny_cogvideox_components(0))
    geco.set_progress_bar_config(disable=True)
    ours = run_pipeline(geco, guidance=config, estimators=estimators.with_segmenter(LeftHalf()))
    stock = CogVideoXPipeline(**T.tiny_cogvideox_components(0))
    stock.set_progress_bar_config(disable=True)
    source = LeftHalf()
    with attach_geco_guidance(stock, config, estimators.with_segmenter(source)) as handle:
        hooked = run_pipeline(stock).frames
    assert source.calls == GUIDED_STEPS and len(handle.log) == UPDATES
    assert handle.last.mask_source == ours.report.mask_source == "left half"
    for a, b in zip(handle.log, ours.report.log):
        assert a["mask_source"] == b["mask_source"] == "left half"
        assert a["masked_fraction"] == b["masked_fraction"] and a["loss"] == pytest.approx(b["loss"], rel=1e-4)
    torch.testing.assert_close(hooked, ours.frames, rtol=1e-4, atol=1e-4)


def test_mask_options_that_cannot_work_fail_before_any_denoising(estimators):
    pipe = T.tiny_pipeline(0)
    steps = []
    pipe.transformer.register_forward_pre_hook(lambda *_: steps.append(1))
    with pytest.raises(ValueError, match="guidance.dynamic='a dog' needs a text segmenter"):
        run_tiny(pipe, estimators, guidance={"dynamic": "a dog"})
    not_a_source = torch.zeros(4, 32, 48, dtype=torch.bool)
    with pytest.raises(ValueError, match="the segmenter must be a DynamicMaskSource") as err:
        run_tiny(pipe, estimators.with_segmenter(not_a_source), guidance={"dynamic": "a dog"})
    assert "\n" not in str(err.value)
    with pytest.raises(ValueError, match="the segmenter must make a DynamicMaskSource"):
        run_tiny(pipe, estimators.with_segmenter(lambda subjects: not_a_source), guidance={"dynamic": "a dog"})
    # the masks come from the estimators' segmenter: the call has no argument of its own for them
    with pytest.raises(TypeError, match=r"^GeCoCogVideoXPipeline\(dynamic_masks=...\) is the earlier spelling: name "
                                        r"what moves in guidance="):
        run_tiny(pipe, estimators, guidance={"dynamic": "a dog"}, dynamic_masks=LeftHalf())
    with pytest.raises(TypeError, match=r"^GeCoCogVideoXPipeline\(geometry_estimator=...\) is the earlier spelling: "
                                        r"pass the models as one estimators=Estimators\(geometry, flow\)"):
        run_tiny(pipe, estimators, geometry_estimator=estimators.geometry)
    with pytest.raises(TypeError, match=r"^GeCoCogVideoXPipeline\(\) got an unexpected keyword argument 'num_frame'"):
        run_tiny(pipe, estimators, num_frame=9)
    assert steps == []
    with pytest.raises(TypeError, match=r"attach_geco_guidance\(dynamic_masks=...\) is the earlier spelling: the "
                                        r"segmenter is Estimators\(..., segmenter=...\)"):
        attach_geco_guidance(T.tiny_wan_pipeline(0), T.tiny_guidance_config(dynamic="a dog"), estimators,
                             dynamic_masks=LeftHalf())
    for changes, match in (({"dynamic": " , "}, "dynamic must be null, 'auto' or the subjects"),
                           ({"dynamic_dilation": -1}, "dynamic_dilation must be a whole number"),
                           ({"dynamic_refresh": 0}, "dynamic_refresh must be a whole number")):
        with pytest.raises(ValueError, match=match):
            T.tiny_guidance_config(**changes)


@pytest.mark.slow
def test_without_dynamic_the_video_its_name_and_log_stay_as_before(estimators):
    # The names the presets give without masks (since the model registry added model.name and
    # sampling.guidance_scale_2: before, 21df29c8 and e56702e3; before the run options left the key
    # and eta became step_size, 61238450 and 3e3f47ff).
    assert default_name(load_config(preset="tiny"), "a marble bust") == "a-marble-bust-37535cc1-seed0"
    assert default_name(load_config(preset="cogvideox-5b"), "a marble bust") == "a-marble-bust-940e6926-seed0"
    pipe = T.tiny_pipeline(0)
    before = run_tiny(pipe, estimators)
    unused = LeftHalf()
    after = run_tiny(pipe, estimators.with_segmenter(unused))  # loaded, but guidance.dynamic is null: not asked
    assert unused.calls == 0 and torch.equal(before.frames, after.frames)
    assert all(set(record) == RECORD_KEYS for record in after.report.log)
    assert after.report.mask_source is None and after.report.masked_fraction is None


def test_the_video_key_counts_what_masks_the_frames():
    base = config_to_dict(load_config(preset="tiny"))
    key = video_key(base, PROMPT)
    unused = json.loads(json.dumps(base))
    unused["guidance"].update(dynamic_dilation=4, dynamic_refresh=3)
    unused["estimators"]["segmenter"] = "/elsewhere/sam3"
    assert video_key(unused, PROMPT) == key  # nothing masked: nothing of it makes a frame
    unguided = json.loads(json.dumps(base))
    unguided["guidance"].update(enabled=False)
    masked_unguided = json.loads(json.dumps(unguided))
    masked_unguided["guidance"]["dynamic"] = "a dog"
    assert video_key(masked_unguided, PROMPT) == video_key(unguided, PROMPT)
    auto = json.loads(json.dumps(base))
    auto["guidance"]["dynamic"] = "auto"
    assert video_key(auto, PROMPT) != key
    auto["estimators"]["segmenter"] = "/elsewhere/sam3"
    assert video_key(auto, PROMPT) == video_key({**auto, "estimators": base["estimators"]}, PROMPT)
    text = json.loads(json.dumps(base))
    text["guidance"]["dynamic"] = "a dog"
    other = json.loads(json.dumps(text))
    other["estimators"]["segmenter"] = "/elsewhere/sam3"
    assert len({video_key(text, PROMPT), video_key(other, PROMPT), key}) == 3


@pytest.mark.parametrize("dynamic, source", [("a dog", "sam3: a dog"), ("auto", "auto")])
@pytest.mark.slow
def test_generate_with_dynamic_writes_masks_into_log_and_sidecar(dynamic, source, tmp_path: Path, capsys):
    out = tmp_path / "run.mp4"
    argv = ["--preset", "tiny", "--prompt", PROMPT, "--dynamic", dynamic, "estimators.segmenter=tiny-random",
            "--out", str(out)]
    assert main(argv) == 0
    out_text, err = capsys.readouterr()
    assert sum(line.startswith(f"dynamic masks: {source}, masked ") for line in out_text.splitlines()) == 1, out_text
    loading = [line for line in err.splitlines() if line.startswith("loading models:")]
    assert len(loading) == 1 and ("segmenter tiny-random for 'a dog'" in loading[0]) == (dynamic != "auto")
    sidecar = json.loads(out.with_suffix(".json").read_text())
    assert sidecar["config"]["guidance"]["dynamic"] == dynamic and sidecar["dynamic_masks"] == source
    assert all(r["mask_source"] == source and 0 <= r["masked_fraction"] <= 1 for r in sidecar["guidance_log"])
    assert 0 <= sidecar["geco_scores"]["masked_fraction"] <= 1


def test_generate_with_missing_segmenter_weights_fails_before_the_video_model(tmp_path: Path, capsys):
    argv = ["--preset", "tiny", "--prompt", PROMPT, "--dynamic", "a dog",
            "estimators.segmenter=/nonexistent/sam3", "--out", str(tmp_path / "run.mp4")]
    assert main(argv) == 2
    err = capsys.readouterr().err
    lines = [line for line in err.splitlines() if line.startswith("error:")]
    assert len(lines) == 1 and "'/nonexistent/sam3' does not exist" in lines[0]
    assert "estimators.segmenter=/path/to/sam3" in lines[0] and "loading models" not in err
    assert list(tmp_path.iterdir()) == []
