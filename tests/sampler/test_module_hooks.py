"""Our hooks in diffusers' HookRegistry (geco_guide/sampler/running/module_hooks.py) and the denoiser's partial
checkpointing made of them: a hook registered before ours stays in effect, and on exit, even after
an error, every module's registry and forward are as they were found."""

from __future__ import annotations

import pytest
import torch
from counting import CountingHook
from diffusers.hooks import HookRegistry
from torch import nn

from geco_guide.sampler.running.context import partial_checkpointing
from geco_guide.sampler.running.module_hooks import CHECKPOINT_HOOK, CheckpointedForward, hooked
from geco_guide.tiny import TinySizes, tiny_cogvideox_components


def register(module, hook, name):
    HookRegistry.check_if_exists_or_initialize(module).register_hook(hook, name)
    return hook


def hook_names(module):
    """The names in ``module``'s registry in the order they were registered, ``None`` without one."""
    registry = module.__dict__.get("_diffusers_hook")
    return None if registry is None else list(registry.hooks)


def output_and_grad(module, x):
    x = x.detach().requires_grad_(True)
    out = module(x)
    (grad,) = torch.autograd.grad(out.square().sum(), x)
    return out.detach(), grad


def test_a_hook_registered_before_ours_stays_in_effect_and_its_registry_is_left_as_found():
    torch.manual_seed(0)
    layer = nn.Sequential(nn.Linear(3, 4), nn.Tanh(), nn.Linear(4, 2))
    x = torch.randn(5, 3)
    expected = output_and_grad(layer, x)
    counting = register(layer, CountingHook(), "counting")
    forward = layer.__dict__["forward"]
    with hooked(layer, CheckpointedForward(), CHECKPOINT_HOOK):
        assert hook_names(layer) == ["counting", CHECKPOINT_HOOK]
        out, grad = output_and_grad(layer, x)
    assert counting.n == 2  # the forward, and its recomputation by the backward: the counter runs inside our region
    assert torch.equal(out, expected[0]) and torch.equal(grad, expected[1])
    assert hook_names(layer) == ["counting"] and layer.__dict__["forward"] is forward
    output_and_grad(layer, x)
    assert counting.n == 3


def test_a_module_without_hooks_is_left_without_a_registry_or_a_forward_even_after_an_error():
    layer = nn.Linear(3, 2)
    with pytest.raises(RuntimeError, match="inside"), hooked(layer, CheckpointedForward(), CHECKPOINT_HOOK):
        assert hook_names(layer) == [CHECKPOINT_HOOK] and "forward" in layer.__dict__
        raise RuntimeError("inside")
    assert "forward" not in layer.__dict__ and hook_names(layer) is None


def test_an_empty_registry_found_is_left_empty():
    layer = nn.Linear(3, 2)
    registry = HookRegistry.check_if_exists_or_initialize(layer)
    with hooked(layer, CheckpointedForward(), CHECKPOINT_HOOK):
        pass
    assert layer._diffusers_hook is registry and hook_names(layer) == [] and "forward" not in layer.__dict__


def test_the_checkpointed_forward_runs_once_without_gradients():
    layer = nn.Linear(3, 2)
    counting = register(layer, CountingHook(), "counting")
    with hooked(layer, CheckpointedForward(), CHECKPOINT_HOOK), torch.no_grad():
        layer(torch.randn(1, 3))
    assert counting.n == 1


def denoiser_output_and_grad(transformer):
    """The tiny transformer's output and its gradient w.r.t. the latents: the guidance's backward."""
    generator = torch.Generator().manual_seed(1)
    latents = torch.randn(1, 2, 4, 4, 6, generator=generator).requires_grad_(True)
    text = torch.randn(1, 16, 16, generator=generator)
    out = transformer(hidden_states=latents, encoder_hidden_states=text, timestep=torch.tensor([500]),
                      return_dict=False)[0]
    (grad,) = torch.autograd.grad((out * torch.linspace(-1, 1, out.shape[-1])).sum(), latents)
    return out.detach(), grad


def test_partial_checkpointing_keeps_a_hook_of_the_blocks_and_changes_nothing():
    torch.manual_seed(0)
    transformer = tiny_cogvideox_components(0, TinySizes(layers=4))["transformer"].requires_grad_(False)
    blocks = transformer.transformer_blocks
    counting = register(blocks[1], CountingHook(), "counting")
    expected = denoiser_output_and_grad(transformer)
    assert counting.n == 1
    with partial_checkpointing(transformer, 2):
        assert [CHECKPOINT_HOOK in (hook_names(b) or []) for b in blocks] == [False, True, False, True]
        out, grad = denoiser_output_and_grad(transformer)
    assert counting.n == 1 + 2  # block 1 checkpointed with its hook inside: run again by the backward
    assert torch.equal(out, expected[0]) and torch.equal(grad, expected[1])
    assert [hook_names(b) for b in blocks] == [None, ["counting"], None, None]
    assert ["forward" in b.__dict__ for b in blocks] == [False, True, False, False]


def test_partial_checkpointing_removes_its_hooks_after_an_error():
    transformer = tiny_cogvideox_components(0, TinySizes(layers=3))["transformer"]
    with pytest.raises(RuntimeError, match="inside"), partial_checkpointing(transformer, 2):
        assert hook_names(transformer.transformer_blocks[1]) == [CHECKPOINT_HOOK]
        raise RuntimeError("inside")
    assert not [name for name, m in transformer.named_modules() if "forward" in m.__dict__ or hook_names(m) is not None]
