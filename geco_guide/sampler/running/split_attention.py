"""What a denoiser's attention needs under ``run.context_parallel`` beyond diffusers' split
(docs/context_parallel.md): attentions run on each process alone where their keys are whole on
every process, HunyuanVideo's mask cut to each process's tokens, LTX-2's video keys gathered for
its whole audio stream, and HunyuanVideo 1.5's joint attention with its text whole on every
process."""

from __future__ import annotations

from typing import Any

import torch
from diffusers.hooks import ModelHook
from torch import Tensor, nn

from ..diffusers_private import without_parallel_config

__all__ = ["GATHERED_KEYS_HOOK", "PADDED_TOKENS_HOOK", "SHARDED_MASK_HOOK", "CogVideoXContextParallelAttention",
           "GatheredVideoKeys", "HunyuanVideo15ContextParallelAttention", "PaddedTokens", "ShardedJointMask",
           "attend_within_process"]


def attend_within_process(denoiser: nn.Module, within: Any) -> None:
    """Run the attentions of ``denoiser`` whose name ``within(name)`` picks on each process alone,
    without diffusers' Ulysses all-to-all: those whose queries are the process's own tokens and
    whose keys are whole on every process (the text; LTX-2's audio). Each gets a processor of its
    own (a fresh one of its class) with no parallel config, after ``enable_parallelism`` gave one
    to all; exact, as one process's attention of those queries."""
    from diffusers.models.attention import AttentionModuleMixin

    for name, module in denoiser.named_modules():
        if isinstance(module, AttentionModuleMixin) and within(name):
            module.set_processor(type(module.processor)())
            without_parallel_config(module.processor)


#: the name of :class:`GatheredVideoKeys` in a module's ``HookRegistry``
GATHERED_KEYS_HOOK = "geco_gathered_video_keys"


class GatheredVideoKeys(ModelHook):
    """On LTX-2's video-to-audio attention under context parallelism: the process's video tokens
    (its keys, ``encoder_hidden_states [B, S/N, C]``) and their rotary tables (``key_rotary_emb``,
    split on the token dimension: 2 for the split rotary type, else 1) gathered over the processes
    into the whole video, which the whole audio stream of every process attends to. The tokens'
    gather sums the gradient over the processes in the backward: each process's audio copy carries
    the gradient of its own share of the loss (the video shard it is attended by)."""

    def __init__(self, split_rotary: bool):
        super().__init__()
        self.token_dim = 2 if split_rotary else 1

    def pre_forward(self, module, *args, **kwargs):
        from torch.distributed import group
        from torch.distributed._functional_collectives import all_gather_single

        kwargs["encoder_hidden_states"] = all_gather_single(kwargs["encoder_hidden_states"].contiguous(), 1, group.WORLD)
        kwargs["key_rotary_emb"] = tuple(all_gather_single(t.contiguous(), self.token_dim, group.WORLD)
                                         for t in kwargs["key_rotary_emb"])
        return args, kwargs


class HunyuanVideo15ContextParallelAttention:
    """HunyuanVideo 1.5's joint video-text attention, computed as diffusers'
    ``HunyuanVideo15AttnProcessor2_0`` computes it, for a process holding a shard of the video tokens
    and the whole text. The Ulysses all-to-all lines up every process's ``[video, text]``: the keys
    hold ``N`` copies of the text, of which the mask lets only rank 0's be seen (with the text
    padding masked), so each query sees the keys one process's attention sees, once. The mask is
    of keys only, ``[B, 1, 1, S + T]``: the stock one also masks the padding text tokens' queries,
    whose outputs no real token ever reads (they are masked as keys everywhere)."""

    _attention_backend = None
    _parallel_config = None  # set by diffusers' enable_parallelism

    def __call__(self, attn, hidden_states: Tensor, encoder_hidden_states: Tensor, attention_mask: Tensor,
                 image_rotary_emb: tuple[Tensor, Tensor] | None = None) -> tuple[Tensor, Tensor]:
        """``hidden_states [B, S, C]`` (this process's video tokens), ``encoder_hidden_states [B, T,
        C]`` (the whole text), ``attention_mask [B, T]`` (the text's, True: a real token) -> both
        after attention and the output projections."""
        import torch.distributed as dist
        from diffusers.models.attention_dispatch import dispatch_attention_fn
        from diffusers.models.embeddings import apply_rotary_emb

        def heads(x: Tensor) -> Tensor:
            return x.unflatten(2, (attn.heads, -1))

        query, key = attn.norm_q(heads(attn.to_q(hidden_states))), attn.norm_k(heads(attn.to_k(hidden_states)))
        if image_rotary_emb is not None:
            query = apply_rotary_emb(query, image_rotary_emb, sequence_dim=1)
            key = apply_rotary_emb(key, image_rotary_emb, sequence_dim=1)
        text_query, text_key = heads(attn.add_q_proj(encoder_hidden_states)), heads(attn.add_k_proj(encoder_hidden_states))
        if attn.norm_added_q is not None:
            text_query = attn.norm_added_q(text_query)
        if attn.norm_added_k is not None:
            text_key = attn.norm_added_k(text_key)
        query, key = torch.cat([query, text_query], dim=1), torch.cat([key, text_key], dim=1)
        value = torch.cat([heads(attn.to_v(hidden_states)), heads(attn.add_v_proj(encoder_hidden_states))], dim=1)
        text_seen = attention_mask.bool() & (dist.get_rank() == 0)
        mask = torch.cat([text_seen.new_ones(text_seen.shape[0], hidden_states.shape[1]), text_seen], dim=1)
        out = dispatch_attention_fn(query, key, value, attn_mask=mask[:, None, None], backend=self._attention_backend,
                                    parallel_config=self._parallel_config).flatten(2, 3).to(query.dtype)
        video, text = out[:, : hidden_states.shape[1]], out[:, hidden_states.shape[1] :]
        return attn.to_out[1](attn.to_out[0](video)), attn.to_add_out(text)


#: the name of :class:`ShardedJointMask` in a block's ``HookRegistry``
SHARDED_MASK_HOOK = "geco_sharded_joint_mask"


class ShardedJointMask(ModelHook):
    """A HunyuanVideo block's ``attention_mask`` ``[B, 1, 1, V + T]`` (the video tokens, then the
    text tokens, padding masked) cut to this process's tokens under context parallelism: its shard
    of the video part, then its shard of the text part, the order of the block's local
    ``[video, text]`` sequence. The Ulysses attention gathers the processes' masks in the order
    it gathers their tokens, so every key keeps its own mask entry."""

    def pre_forward(self, module, *args, **kwargs):
        import torch.distributed as dist

        args = list(args)
        hidden, text = (kwargs["hidden_states"] if "hidden_states" in kwargs else args[0],
                        kwargs["encoder_hidden_states"] if "encoder_hidden_states" in kwargs else args[1])
        positional = "attention_mask" not in kwargs
        mask = args[3] if positional else kwargs["attention_mask"]
        processes, rank = dist.get_world_size(), dist.get_rank()
        if mask is None or mask.shape[-1] != (hidden.shape[1] + text.shape[1]) * processes:
            return tuple(args), kwargs  # not the whole sequence's mask: nothing to cut
        video = hidden.shape[1] * processes
        local = torch.cat([mask[..., :video].chunk(processes, dim=-1)[rank],
                           mask[..., video:].chunk(processes, dim=-1)[rank]], dim=-1)
        if positional:
            args[3] = local
        else:
            kwargs["attention_mask"] = local
        return tuple(args), kwargs


class CogVideoXContextParallelAttention:
    """CogVideoX's joint text-video self-attention, computed as diffusers' ``CogVideoXAttnProcessor2_0``
    computes it but through diffusers' attention dispatch, where context parallelism runs its
    Ulysses all-to-all (the stock processor calls ``scaled_dot_product_attention`` itself, and so
    cannot be split). Under the split each process holds a shard of the text tokens and a shard
    of the video tokens; the all-to-all lines up every process's ``[text, video]`` shards one after
    the other, an order of the keys that the attention does not depend on but for the order of its
    sums. Padding tokens (:class:`PaddedTokens`) are masked as keys.

    Attributes:
        tokens: ``(text, video)``, the unpadded token counts of the current call (set by
            :class:`PaddedTokens`); the call pads where either does not divide among the processes.
    """

    _attention_backend = None
    _parallel_config = None  # set by diffusers' enable_parallelism

    def __init__(self):
        self.tokens: tuple[int, int] | None = None

    def __call__(self, attn, hidden_states: Tensor, encoder_hidden_states: Tensor, attention_mask: Tensor | None = None,
                 image_rotary_emb: tuple[Tensor, Tensor] | None = None) -> tuple[Tensor, Tensor]:
        """``hidden_states [B, S, C]`` (this process's video tokens), ``encoder_hidden_states [B, T, C]``
        (its text tokens) -> both after attention and the output projection."""
        import torch.distributed as dist
        from diffusers.models.attention_dispatch import dispatch_attention_fn
        from diffusers.models.embeddings import apply_rotary_emb

        if attention_mask is not None:
            raise ValueError("CogVideoX's attention under context parallelism takes no attention mask")
        processes, rank = dist.get_world_size(), dist.get_rank()
        text, video = encoder_hidden_states.shape[1], hidden_states.shape[1]
        tokens = torch.cat([encoder_hidden_states, hidden_states], dim=1)
        # [B, T + S, heads, head_dim]: the layout diffusers' dispatch takes
        query, key, value = (proj(tokens).unflatten(2, (attn.heads, -1)) for proj in (attn.to_q, attn.to_k, attn.to_v))
        if attn.norm_q is not None:
            query = attn.norm_q(query)
        if attn.norm_k is not None:
            key = attn.norm_k(key)
        if image_rotary_emb is not None:  # this process's rows of the tables [S, D] (padded: any rows)
            rows = video * processes - image_rotary_emb[0].shape[0]
            shard = tuple(torch.nn.functional.pad(t, (0, 0, 0, rows)).chunk(processes)[rank] for t in image_rotary_emb)

            def rotate(x: Tensor) -> Tensor:
                return torch.cat([x[:, :text], apply_rotary_emb(x[:, text:], shard, sequence_dim=1)], dim=1)

            query = rotate(query)
            key = key if attn.is_cross_attention else rotate(key)
        out = dispatch_attention_fn(query, key, value, attn_mask=self.key_mask(text, video, tokens),
                                    backend=self._attention_backend, parallel_config=self._parallel_config)
        out = attn.to_out[1](attn.to_out[0](out.flatten(2, 3).to(query.dtype)))
        return out[:, text:], out[:, :text]

    def key_mask(self, text: int, video: int, tokens: Tensor) -> Tensor | None:
        """``[B, T + S]`` (True: a real token) for this process's ``text`` + ``video`` tokens where
        the call is padded, None where it is not (the same on every process: the mask is gathered)."""
        import torch.distributed as dist

        processes, rank = dist.get_world_size(), dist.get_rank()
        if self.tokens is None or self.tokens == (text * processes, video * processes):
            return None
        index = torch.arange(text + video, device=tokens.device)
        real = torch.where(index < text, index + rank * text < self.tokens[0],
                           index - text + rank * video < self.tokens[1])
        return real.expand(tokens.shape[0], -1)


#: the name of :class:`PaddedTokens` (and its cut) in a module's ``HookRegistry``
PADDED_TOKENS_HOOK = "geco_padded_tokens"


class PaddedTokens(ModelHook):
    """On CogVideoX's first block under context parallelism: the video and text tokens padded
    (zeros at the end) to a multiple of the processes, so that diffusers' plan splits them into
    equal shards; the attention masks the padding as keys (:class:`CogVideoXContextParallelAttention`),
    and :attr:`cut`, on ``proj_out``, drops it from the gathered video tokens. Real tokens never
    see a padding token, so the padding changes no value but the order of sums."""

    def __init__(self, attention: CogVideoXContextParallelAttention):
        super().__init__()
        self.attention = attention
        self.cut = _CutPadding(attention)

    def pre_forward(self, module, *args, **kwargs):
        import torch.distributed as dist

        names = ("hidden_states", "encoder_hidden_states")
        args = list(args)
        values = [kwargs[name] if name in kwargs else args[i] for i, name in enumerate(names)]
        self.attention.tokens = (values[1].shape[1], values[0].shape[1])
        processes = dist.get_world_size()
        for i, (name, value) in enumerate(zip(names, values)):
            padded = torch.nn.functional.pad(value, (0, 0, 0, -value.shape[1] % processes))
            if name in kwargs:
                kwargs[name] = padded
            else:
                args[i] = padded
        return tuple(args), kwargs


class _CutPadding(ModelHook):
    """The gathered video tokens of ``proj_out`` without the padding."""

    def __init__(self, attention: CogVideoXContextParallelAttention):
        super().__init__()
        self.attention = attention

    def post_forward(self, module, output):
        return output[:, : self.attention.tokens[1]]
