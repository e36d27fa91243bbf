"""GeCo guidance on the video families diffusers ships now, through the stock pipelines and their
adapters: Wan 2.2 TI2V-5B (the Wan 2.2 VAE, per-token timesteps), Wan 2.2 T2V-A14B (two experts),
HunyuanVideo 1.5 (text- and image-to-video) and LTX-2 (video guided, audio passed through), on
tiny random instances of the real diffusers classes (CPU)."""

from __future__ import annotations

import copy
import functools
import re
from dataclasses import replace

import pytest
import torch
from counting import CountingForward

from geco_guide import tiny as T
from geco_guide.loss.geco import GeCoLoss
from geco_guide.sampler.pipelines.adapters import LTX2Adapter, PipelineAdapter, adapter_for, fit_combination, supported_pipelines
from geco_guide.sampler.pipelines.hooks import attach_geco_guidance
from geco_guide.sampler.algorithm.slicing import decode_anchor_frames
from geco_guide.sampler.algorithm.step import score_anchor_frames

PROMPT = "a marble bust on a table"
NUM_FRAMES = 9  # 3 latents at r=4, 2 at r=8 (LTX-2)
ANCHORS = [5, 8]  # both in the last latent: one chunk from latent 0, the whole video
# guidance on the last of 4 steps only: what it changes is what comes out
LAST_STEP = dict(anchors=ANCHORS, chunk_latents=3, repeats="0x3,2x1", time_travel=[], step_size=1.0)

BUILDERS = {
    "wan2.2-ti2v-5b": T.tiny_wan22_ti2v_pipeline,
    "wan2.2-t2v-a14b": T.tiny_wan22_a14b_pipeline,
    "hunyuanvideo1.5": T.tiny_hunyuan15_pipeline,
    "hunyuanvideo1.5-i2v": T.tiny_hunyuan15_i2v_pipeline,
    "ltx-2": T.tiny_ltx2_pipeline,
}
FAMILIES = list(BUILDERS)


def call(pipe, seed=0, **changes):
    """The pipeline's output (``output_type="pt"``: frames ``[B, T, 3, H, W]`` in ``[0, 1]``)."""
    kwargs = T.tiny_call_kwargs(pipe, **{"num_frames": NUM_FRAMES, "output_type": "pt", **changes})
    return pipe(prompt=PROMPT, negative_prompt="blurry", generator=torch.Generator().manual_seed(seed), **kwargs)


def attach(pipe, estimators, config):
    return attach_geco_guidance(pipe, config, estimators)


def score(frames, estimators, config):
    return score_anchor_frames(frames, config.anchors, GeCoLoss(estimators, config.loss))["loss"]


def final_latents(pipe, seed=0, **changes):
    """The latents the scheduler made last (scheduler layout), from a second call with the same seed:
    ``output_type="latent"`` where the pipeline returns them as they are, the step-end callback
    where it returns them unpacked and de-normalised (LTX-2)."""
    if type(pipe).__name__.startswith("LTX2"):
        seen = {}

        def keep(p, i, t, tensors):
            seen["latents"] = tensors["latents"]
            return tensors

        call(pipe, seed, output_type="latent", callback_on_step_end=keep, **changes)
        return seen["latents"]
    return call(pipe, seed, output_type="latent", **changes).frames


# ---- every new family: guidance end to end, off bit for bit -------------------------------------


@pytest.mark.parametrize("family, faithful", [
    ("wan2.2-ti2v-5b", True),
    ("wan2.2-t2v-a14b", False),
    ("hunyuanvideo1.5", True),
    ("hunyuanvideo1.5-i2v", False),
    ("ltx-2", True),
])
@pytest.mark.slow
def test_guidance_runs_end_to_end_and_detach_restores_bitwise(family, faithful, estimators):
    config = T.tiny_guidance_config(**LAST_STEP, denoiser_grad=faithful)
    reference = call(BUILDERS[family](0)).frames
    pipe = BUILDERS[family](0)
    with attach(pipe, estimators, config) as handle:
        guided = call(pipe).frames
    after = call(pipe).frames

    assert torch.equal(after, reference), "detach() must restore the pipeline bit for bit"
    assert [e["step"] for e in handle.log] == [3, 3] and all(e["grad_norm"] > 0 for e in handle.log)
    assert not torch.equal(guided, reference)
    # the first update scores x0 of the unguided last step (flow matching: the final latents),
    # decoded by the adapter from the anchors' chunk: what the pipeline itself decodes
    base = score(reference, estimators, config)
    assert handle.log[0]["loss"] == pytest.approx(base, rel=1e-4)
    assert score(guided, estimators, config) < base


@pytest.mark.parametrize("family", FAMILIES)
def test_guidance_off_gives_the_stock_output_bit_for_bit(family, estimators):
    reference = call(BUILDERS[family](0))
    pipe = BUILDERS[family](0)
    with attach(pipe, estimators, {**LAST_STEP, "enabled": False}) as handle:
        off = call(pipe)
    assert handle.log == []
    assert torch.equal(off.frames, reference.frames)
    if hasattr(reference, "audio"):
        assert torch.equal(off.audio, reference.audio)


# ---- the frame scored at anchor f is frame f of the output --------------------------------------


@pytest.mark.parametrize("family", FAMILIES)
@pytest.mark.slow
def test_the_frame_scored_at_anchor_f_is_frame_f_of_the_output(family, estimators):
    """Every frame 1..16 of a guided 17-frame video as an anchor, each decoded from its chunk as
    guidance decodes it (the adapter's layout, de-normalisation and decode, on the final latents).

    Causal VAEs (Wan 2.2, HunyuanVideo 1.5): a chunk that starts at latent 0 decodes exactly the
    frames the whole video's decode makes there, so with ``chunk_latents`` = all latents every
    scored frame is the output's frame, up to float32 rounding (measured below 1e-6: the
    de-normalisation is written differently, ``z * std + mean`` against the pipeline's
    ``z / (1 / std) + mean``, and the convolutions see different frame counts). The LTX-2 decoder
    is not causal: only the chunk that holds every latent (the anchors of the last latent) is the
    whole video's decode; an earlier anchor's chunk lacks the later latents the whole decode sees,
    and its frame differs (by as much as two random frames of the tiny VAE do).

    With the default ``chunk_latents=3`` a later chunk starts past latent 0 and decodes its first
    latent as a first frame: the paper's approximation, which trained VAEs make close and random
    tiny VAEs do not (errors as large as between two frames): not tested here.
    """
    pipe = BUILDERS[family](0)
    frames = 17
    config = T.tiny_guidance_config(**{**LAST_STEP, "repeats": "0x3,1x1"}, denoiser_grad=False)
    with attach(pipe, estimators, config) as handle:
        video = call(pipe, num_frames=frames).frames
        latents = final_latents(pipe, num_frames=frames)
    assert len(handle.log) == 1  # the latents are a guided call's
    geometry, adapter = handle.geometry, adapter_for(pipe)
    every_frame = replace(config, anchors=list(range(1, frames)), chunk_latents=5)
    chunks = every_frame.anchor_chunks(geometry.num_frames, geometry.temporal_compression)
    with torch.no_grad():
        scored = decode_anchor_frames(functools.partial(adapter.decode, pipe),
                                      adapter.frames_first(pipe, latents, geometry), chunks)
    assert video.shape[1] == geometry.num_frames == frames
    exact = [k for k, chunk in enumerate(chunks) if chunk.start == 0
             and (chunk.stop == geometry.num_latents or family != "ltx-2")]
    assert len(exact) == (frames - 1 if family != "ltx-2" else 8)  # LTX-2: the 8 frames of the last latent
    for k in exact:
        f = chunks[k].anchor
        torch.testing.assert_close(scored[0, k], video[0, f], rtol=0, atol=1e-5)
        # and not a neighbour: the frames of the tiny video differ by far more than the tolerance
        assert (scored[0, k] - video[0, f - 1]).abs().max() > 1e-2
    if family == "ltx-2":
        earlier = [k for k in range(len(chunks)) if k not in exact]
        assert all((scored[0, k] - video[0, chunks[k].anchor]).abs().max() > 1e-2 for k in earlier)


# ---- frame counts the VAE cannot make ------------------------------------------------------------


@pytest.mark.parametrize("family, num_frames, message", [
    ("hunyuanvideo1.5", 10, "num_frames=10 cannot be made by the HunyuanVideo 1.5 VAE: it makes 4k+1 frames "
                            "(temporal compression 4), so this call would make 9. Ask for num_frames=9 or 13"),
    ("ltx-2", 12, "num_frames=12 cannot be made by the LTX-2 VAE: it makes 8k+1 frames (temporal compression 8), "
                  "so this call would make 9. Ask for num_frames=9 or 17"),
    # Wan rounds num_frames to 4k+1 itself (with a warning) before it makes the latents: guidance
    # checks the anchors against the video it will make
    ("wan2.2-ti2v-5b", 7, "anchors [5, 8] are out of range for a 5-frame video"),
])
def test_frame_counts_the_vae_cannot_make_are_refused_before_any_denoising_step(family, num_frames, message,
                                                                               estimators):
    pipe = BUILDERS[family](0)
    with attach(pipe, estimators, T.tiny_guidance_config(**LAST_STEP)):
        counter = CountingForward(pipe.transformer)
        try:
            with pytest.raises(ValueError) as err:
                call(pipe, num_frames=num_frames)
        finally:
            counter.handle.remove()
    assert counter.n == 0 and "\n" not in str(err.value)
    assert str(err.value).startswith(message)
    # guidance off: the stock pipeline's behaviour (it makes the frames it can)
    with attach(pipe, estimators, {**LAST_STEP, "enabled": False}):
        assert call(pipe, num_frames=num_frames).frames.shape[1] < num_frames


@pytest.mark.parametrize("family, variant, channels", [
    ("wan2.2-ti2v-5b", "wan2.2-5b", T.WAN22_LATENT_CHANNELS),  # taew2_2
    ("hunyuanvideo1.5", "hunyuanvideo1.5", T.HUNYUAN15_LATENT_CHANNELS),  # taehv1_5
])
@pytest.mark.slow
def test_the_tiny_decoder_of_the_family_decodes_the_anchors(family, variant, channels, estimators):
    """The published tiny decoders of these families take their real latent channels (48, 32) and
    the pipelines' latents as they are, at the VAEs' 16x spatial scale (pixel patches of 2)."""
    pipe = BUILDERS[family](0)
    config = T.tiny_guidance_config(**LAST_STEP, denoiser_grad=False, decoder="tiny")
    decoder = T.tiny_guidance_decoder(variant, latent_channels=channels)
    with attach_geco_guidance(pipe, config, estimators.with_tiny_decoder(decoder)) as handle:
        call(pipe)
    assert [e["step"] for e in handle.log] == [3, 3] and all(e["grad_norm"] > 0 for e in handle.log)
    wrong = T.tiny_guidance_decoder(variant, latent_channels=16)
    with attach_geco_guidance(pipe, config, estimators.with_tiny_decoder(wrong)):
        with pytest.raises(ValueError, match=f"takes 16 latent channels but this VAE makes {channels}"):
            call(pipe)


@pytest.mark.parametrize("family", ["wan2.2-ti2v-5b", "hunyuanvideo1.5", "ltx-2"])
@pytest.mark.slow
def test_the_callers_latents_are_checked_before_any_denoising_step(family, estimators):
    """The latents a caller passes: ``[B, C, F, h, w]`` for all three (LTX-2 packs them itself), of
    the call's size, finite."""
    pipe = BUILDERS[family](0)
    shape = list(call(pipe, output_type="latent").frames.shape)
    with attach(pipe, estimators, T.tiny_guidance_config(**LAST_STEP)) as handle:
        counter = CountingForward(pipe.transformer)
        try:
            nan = torch.randn(shape)
            nan.view(-1)[7] = float("nan")
            with pytest.raises(ValueError, match=r"^latents hold 1 NaN or infinite value\(s\)"):
                call(pipe, latents=nan)
            with pytest.raises(ValueError, match=re.escape(f"latents must have shape {shape} (those of this ")):
                call(pipe, latents=torch.randn([*shape[:2], shape[2] + 1, *shape[3:]]))
            assert counter.n == 0
            call(pipe, latents=torch.randn(shape, generator=torch.Generator().manual_seed(1)))
        finally:
            counter.handle.remove()
    assert len(handle.log) == 2


# ---- Wan 2.2: both experts -----------------------------------------------------------------------


def test_both_wan22_experts_are_guided_each_with_its_own_cfg_scale(estimators):
    """Steps 0-1 are ``transformer``'s (t >= 900), steps 2-3 ``transformer_2``'s; one faithful
    update at step 1 and one at step 2 re-run the expert of their step, each combined with its own
    CFG scale (a wrong one would not rebuild the step's output, and the hook would refuse it)."""
    pipe = T.tiny_wan22_a14b_pipeline(0)
    config = T.tiny_guidance_config(anchors=ANCHORS, repeats="0x1,1x2,0x1", time_travel=[], step_size=1.0,
                                    denoiser_grad=True)
    counters = [CountingForward(pipe.transformer), CountingForward(pipe.transformer_2)]
    call(pipe, guidance_scale=5.0, guidance_scale_2=2.0)
    unguided = [c.n for c in counters]
    assert unguided == [4, 4]  # 2 steps x 2 CFG calls each
    with attach(pipe, estimators, config) as handle:
        call(pipe, guidance_scale=5.0, guidance_scale_2=2.0)
    extra = [c.n - 2 * n for c, n in zip(counters, unguided)]
    for c in counters:
        c.handle.remove()
    assert [e["step"] for e in handle.log] == [1, 2] and all(e["grad_norm"] > 0 for e in handle.log)
    # per guided step, its expert's two CFG calls twice: differentiated at the sample, then at the
    # guided sample for the model output the scheduler steps with
    assert extra == [4, 4]


# ---- HunyuanVideo 1.5: the guider ---------------------------------------------------------------


def test_hunyuan15_guider_rescale_is_followed_at_every_sample(estimators):
    """With the guider's ``guidance_rescale`` the step's output is a rescaled CFG whose factor
    depends on the outputs: at the captured sample a linear fit reproduces it, at the samples a
    faithful update re-runs the denoiser at it does not. The adapter combines with the guider
    itself: the pipeline's output at the captured sample (the hook checks it, which also fixes the
    guider's order: conditional first) and the guider's rescale at any other."""
    pipe = T.tiny_hunyuan15_pipeline(0, guidance_rescale=0.7)
    config = T.tiny_guidance_config(**LAST_STEP, denoiser_grad=True)
    with attach(pipe, estimators, config) as handle:
        call(pipe)
    assert len(handle.log) == 2 and all(e["grad_norm"] > 0 for e in handle.log)

    g = torch.Generator().manual_seed(0)
    captured, moved = ([torch.randn(1, 32, 3, 2, 3, generator=g) for _ in range(2)] for _ in range(2))
    weights, residual = fit_combination(captured, pipe.guider.forward(*captured).pred)
    assert residual < 1e-5  # one rescale factor: linear at the captured sample
    combine = functools.partial(handle.adapter.combine, pipe, sample=None, step=0)
    assert torch.equal(combine(moved, weights), pipe.guider.forward(*moved).pred)
    linear = PipelineAdapter.combine(handle.adapter, pipe, moved, weights, sample=None, step=0)
    assert (linear - pipe.guider.forward(*moved).pred).norm() > 1e-3 * linear.norm()


# ---- LTX-2: video guided, audio passed through ----------------------------------------------------


@pytest.mark.slow
def test_ltx2_combination_rebuilds_cfg_stg_modality_and_rescale(estimators, monkeypatch):
    """The tiny call runs the pipeline's defaults: CFG 3, spatio-temporal guidance 1 (a third call),
    modality isolation 3 (a fourth), guidance_rescale 0.7, all made on clean estimates. A faithful
    update re-runs the three calls and must rebuild the output the pipeline stepped with; the
    linear fit cannot (the rescale), and is refused."""
    pipe = T.tiny_ltx2_pipeline(0)
    config = T.tiny_guidance_config(**LAST_STEP, denoiser_grad=True)
    counter = CountingForward(pipe.transformer)
    with attach(pipe, estimators, config) as handle:
        call(pipe)
        # 4 steps of 3 calls; the step's 2 updates replay the 3 differentiated, then once more at the
        # guided sample for the model output the scheduler steps with
        assert counter.n == 4 * 3 + 3 * (2 + 1)
        assert len(handle.log) == 2
        call(pipe, guidance_rescale=0.0, stg_scale=0.0, audio_stg_scale=0.0, modality_scale=1.0,
             audio_modality_scale=1.0)  # CFG alone: 1 batched call
        assert len(handle.log) == 2
        monkeypatch.setattr(LTX2Adapter, "combine", PipelineAdapter.combine)
        with pytest.raises(ValueError, match="cannot rebuild the model output"):
            call(pipe)
    counter.handle.remove()


def _audio_inputs(pipe):
    """The audio latents the transformer sees at each pipeline step (a forward pre-hook; the
    guidance below is fast, so that every transformer call is one of the pipeline's own)."""
    seen = []

    def keep(module, args, kwargs):
        seen.append(kwargs["audio_hidden_states"].detach().clone())

    return seen, pipe.transformer.register_forward_pre_hook(keep, with_kwargs=True)


def test_ltx2_audio_is_untouched_by_guidance_until_the_video_it_hears_changes(estimators):
    """LTX-2's one transformer predicts audio from the video latents too (cross-attention), so what
    holds: guidance never writes the audio latents or steps the audio scheduler, the audio latents
    are bit-identical with and without guidance up to the step after the first guided one (that
    step's audio prediction was made before the update), and differ from then on. Guiding the
    last step only leaves the audio output bit-identical."""
    reference_pipe, pipe = T.tiny_ltx2_pipeline(0), T.tiny_ltx2_pipeline(0)
    minimal = dict(guidance_scale=1.0, audio_guidance_scale=1.0, stg_scale=0.0, audio_stg_scale=0.0,
                   modality_scale=1.0, audio_modality_scale=1.0)  # one call per step
    reference_audio, hook = _audio_inputs(reference_pipe)
    reference = call(reference_pipe, **minimal)
    hook.remove()

    last = T.tiny_guidance_config(**LAST_STEP, denoiser_grad=False)
    with attach(pipe, estimators, last) as handle:
        guided = call(pipe, **minimal)
    assert len(handle.log) == 2 and not torch.equal(guided.frames, reference.frames)
    assert torch.equal(guided.audio, reference.audio)

    early = T.tiny_guidance_config(**{**LAST_STEP, "repeats": "0x1,1x1,0x2"}, denoiser_grad=False)
    audio, hook = _audio_inputs(pipe)
    with attach(pipe, estimators, early) as handle:
        call(pipe, **minimal)
    hook.remove()
    assert [e["step"] for e in handle.log] == [1] and len(audio) == len(reference_audio) == 4
    assert [torch.equal(a, b) for a, b in zip(audio, reference_audio)] == [True, True, True, False]


def test_a_deep_copy_of_the_hooked_scheduler_steps_itself_unguided(estimators):
    """LTX-2 steps its audio with ``copy.deepcopy(pipe.scheduler)``: the copy must step its own
    state as an unhooked scheduler does (not the hooked scheduler's, which would then skip every
    other video step)."""
    pipe = T.tiny_wan_pipeline(0, scheduler="euler")
    pipe.scheduler.set_timesteps(4)
    plain = copy.deepcopy(pipe.scheduler)
    sample = torch.randn(1, 4, 3, 4, 6, generator=torch.Generator().manual_seed(0))
    with attach(pipe, estimators, T.tiny_guidance_config(**LAST_STEP)):
        twin = copy.deepcopy(pipe.scheduler)
        stepped = twin.step(torch.ones_like(sample), twin.timesteps[0], sample, return_dict=False)[0]
        assert twin.step_index == 1 and pipe.scheduler.step_index is None
    assert torch.equal(stepped, plain.step(torch.ones_like(sample), plain.timesteps[0], sample, return_dict=False)[0])


# ---- registration --------------------------------------------------------------------------------


def test_the_new_pipelines_are_registered():
    names = supported_pipelines()
    for name in ("WanPipeline", "HunyuanVideo15Pipeline", "HunyuanVideo15ImageToVideoPipeline", "LTX2Pipeline"):
        assert name in names
    assert adapter_for(T.tiny_ltx2_pipeline(0)).name == "LTX-2"
