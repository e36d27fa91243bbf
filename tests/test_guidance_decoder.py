"""guidance.decoder='tiny': the tiny decoder decodes the loss' anchor frames, the VAE the video."""

from __future__ import annotations

import pytest
import torch

from geco_guide import tiny as T
from geco_guide.estimators.tiny_decoder import CONTEXT_LATENTS, TinyDecoder
from geco_guide.sampler.config import GuidanceConfig
from geco_guide.sampler.hooks import attach_geco_guidance

PROMPT = "a marble bust on a table"


def run(pipe, seed=0, **kwargs):
    args = dict(T.TINY_CALL_KWARGS, output_type="pt")
    args.update(kwargs)
    return pipe(PROMPT, generator=torch.Generator().manual_seed(seed), **args)


class Counted:
    """Counts the calls of one method of an instance."""

    def __init__(self, obj, name):
        self.calls, original = 0, getattr(obj, name)

        def counted(*args, **kwargs):
            self.calls += 1
            return original(*args, **kwargs)

        setattr(obj, name, counted)


def test_the_context_is_the_shortest_that_gives_the_whole_sequence_frame():
    decoder = TinyDecoder.random("cogvideox", seed=0)
    latents = torch.randn(1, 13, 16, 4, 6, generator=torch.Generator().manual_seed(0))
    with torch.no_grad():
        whole = decoder.decode(latents)[:, -1]
        exact = decoder.decode(latents[:, -CONTEXT_LATENTS:])[:, -1]
        shorter = decoder.decode(latents[:, -(CONTEXT_LATENTS - 1):])[:, -1]
    assert torch.equal(exact, whole)
    assert not torch.equal(shorter, whole)


def test_anchor_chunks_follow_the_decoder():
    vae, tiny = GuidanceConfig(), GuidanceConfig(decoder="tiny")
    assert [c.stop - c.start for c in vae.anchor_chunks(49, 4)] == [3, 3, 3, 3]
    # latent 3 has only 4 latents up to it; the later anchors get the whole context
    assert [c.stop - c.start for c in tiny.anchor_chunks(49, 4)] == [4, 7, CONTEXT_LATENTS, CONTEXT_LATENTS]
    with pytest.raises(ValueError, match="decoder"):
        GuidanceConfig(decoder="taesd")


def test_pipeline_guides_with_the_tiny_decoder_and_decodes_the_video_with_the_vae():
    pipe = T.tiny_pipeline(0)
    pipe.register_modules(guidance_decoder=T.tiny_guidance_decoder("cogvideox"))
    assert pipe.components["guidance_decoder"] is pipe.guidance_decoder
    tiny_calls, vae_calls = Counted(pipe.guidance_decoder, "decode"), Counted(pipe.vae, "decode")
    out = run(pipe, guidance={"decoder": "tiny"})
    assert out.guidance_log and all(e["grad_norm"] > 0 and not e["skipped"] for e in out.guidance_log)
    assert tiny_calls.calls >= len(out.guidance_log) and vae_calls.calls == 1  # the final video only
    assert out.guidance["decoder"] == "tiny"
    # the guided latents differ from the VAE-guided run (another gradient), the frames are finite
    exact = run(pipe)
    assert torch.isfinite(out.frames).all() and not torch.equal(out.frames, exact.frames)
    assert all(p.requires_grad is False for p in pipe.guidance_decoder.parameters())


def test_the_tiny_decoder_moves_with_the_pipeline():
    pipe = T.tiny_pipeline(0, guidance_config=T.tiny_guidance_config(decoder="tiny"))
    pipe.register_modules(guidance_decoder=T.tiny_guidance_decoder("cogvideox").to(torch.float64))
    pipe.to("cpu")
    assert pipe.guidance_decoder.device.type == "cpu" and pipe.guidance_decoder.dtype == torch.float64


def test_tiny_without_a_decoder_or_with_the_wrong_one_is_one_line_before_any_step():
    pipe = T.tiny_pipeline(0)
    steps = Counted(pipe.transformer, "forward")
    with pytest.raises(ValueError, match="needs a tiny decoder: pass guidance_decoder=") as err:
        run(pipe, guidance={"decoder": "tiny"})
    assert "\n" not in str(err.value)
    pipe.register_modules(guidance_decoder=T.tiny_guidance_decoder("cogvideox", latent_channels=48))
    with pytest.raises(ValueError, match="takes 48 latent channels but this VAE makes 4"):
        run(pipe, guidance={"decoder": "tiny"})
    assert steps.calls == 0


def test_the_hook_takes_the_tiny_decoder_too():
    estimators = T.tiny_estimators(0)
    pipe = T.tiny_wan_pipeline(0)
    config = T.tiny_guidance_config(anchors=[4, 8], chunk_latents=3, repeats="0x3,2x1", time_travel=[], eta=1.0,
                                    decoder="tiny")
    decoder = T.tiny_guidance_decoder("wan2.1")
    tiny_calls = Counted(decoder, "decode")
    with attach_geco_guidance(pipe, config, geometry_estimator=estimators[0], flow_estimator=estimators[1],
                              decoder=decoder) as handle:
        pipe(PROMPT, generator=torch.Generator().manual_seed(0), **T.tiny_call_kwargs(pipe, num_inference_steps=4),
             output_type="pt")
    assert len(handle.log) == 2 and tiny_calls.calls >= 2
    with attach_geco_guidance(pipe, config, geometry_estimator=estimators[0], flow_estimator=estimators[1]):
        with pytest.raises(ValueError, match="needs a tiny decoder"):
            pipe(PROMPT, generator=torch.Generator().manual_seed(0), **T.tiny_call_kwargs(pipe, num_inference_steps=4),
                 output_type="pt")
