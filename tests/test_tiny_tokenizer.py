"""The tiny tokenizer cuts long prompts at the pipeline's max_sequence_length, quietly."""

from __future__ import annotations

import torch

from geco_guide import tiny as T

LONG = ("a marble bust of an old man on a wooden table in a small room, the camera orbiting slowly around it "
        "at sunset with golden light")


def test_long_prompts_are_truncated_like_the_pipeline_without_a_warning(capfd):
    pipe = T.tiny_pipeline(0)
    words = LONG.replace(",", " ,").split()
    assert len(words) + 1 > T.TINY_MAX_SEQUENCE_LENGTH  # longer than the tiny preset's sequence, with </s>
    with torch.no_grad():
        long_embeds, _ = pipe.encode_prompt(LONG, do_classifier_free_guidance=False,
                                            max_sequence_length=T.TINY_MAX_SEQUENCE_LENGTH, device="cpu")
        # what the real pipeline keeps: the first max_sequence_length - 1 tokens and </s>
        cut = " ".join(words[: T.TINY_MAX_SEQUENCE_LENGTH - 1])
        cut_embeds, _ = pipe.encode_prompt(cut, do_classifier_free_guidance=False,
                                           max_sequence_length=T.TINY_MAX_SEQUENCE_LENGTH, device="cpu")
    captured = capfd.readouterr()
    printed = captured.out + captured.err
    assert "longer than the specified maximum" not in printed and "truncated" not in printed
    assert "<unk>" not in printed
    assert long_embeds.shape == (1, T.TINY_MAX_SEQUENCE_LENGTH, pipe.text_encoder.config.d_model)
    assert torch.equal(long_embeds, cut_embeds)


def test_an_explicit_call_still_decides():
    tok = T.tiny_tokenizer()
    ids = tok(LONG).input_ids
    assert len(ids) == T.TINY_MAX_SEQUENCE_LENGTH and ids[-1] == tok.eos_token_id
    assert len(tok(LONG, truncation=False).input_ids) > T.TINY_MAX_SEQUENCE_LENGTH
    padded = tok("a bust", padding="max_length", max_length=8, truncation=True).input_ids
    assert len(padded) == 8 and padded[-1] == tok.pad_token_id
