"""Module forwards patched through diffusers' hook registry (``diffusers.hooks.HookRegistry``).

diffusers' context parallelism, caches and group offloading rewrite a module's ``forward``
through the same registry, so a patch of ours made there composes with theirs: each patch is a
``ModelHook`` in the module's chain, registered for a region by :func:`hooked` and removed on
exit, even on error. A hook registered before ours runs inside ours (ours calls the chain below it
as its ``fn_ref.original_forward``), one registered after ours wraps it.
"""

from __future__ import annotations

import contextlib
from collections.abc import Callable, Iterator
from typing import Any

import torch
from diffusers.hooks import HookRegistry, ModelHook
from torch import nn
from torch.utils.checkpoint import checkpoint

from ..diffusers_private import hook_registry, remove_hook_registry

__all__ = ["CHECKPOINT_HOOK", "CheckpointedForward", "hooked", "register_hook"]

#: The name of :class:`CheckpointedForward` in a module's registry.
CHECKPOINT_HOOK = "geco_checkpointed_forward"


def register_hook(module: nn.Module, hook: ModelHook, name: str) -> Callable[[], None]:
    """Register ``hook`` on ``module`` as ``name``; returns the function that removes it again and
    leaves the module as found: no registry where it had none, no instance ``forward`` where it had
    none (removing a registry's last hook leaves the module's bound ``forward`` behind as one)."""
    had_registry = hook_registry(module) is not None
    had_forward = "forward" in module.__dict__
    registry = HookRegistry.check_if_exists_or_initialize(module)
    try:
        registry.register_hook(hook, name)
    except BaseException:
        _leave_as_found(module, registry, had_registry, had_forward)
        raise

    def remove() -> None:
        registry.remove_hook(name, recurse=False)  # recursing would remove a same-named hook of a submodule too
        _leave_as_found(module, registry, had_registry, had_forward)

    return remove


@contextlib.contextmanager
def hooked(module: nn.Module, hook: ModelHook, name: str) -> Iterator[ModelHook]:
    """``hook`` registered on ``module`` as ``name`` for the duration (:func:`register_hook`);
    removed on exit, even on error, and the module left as found."""
    remove = register_hook(module, hook, name)
    try:
        yield hook
    finally:
        remove()


def _leave_as_found(module: nn.Module, registry: HookRegistry, had_registry: bool, had_forward: bool) -> None:
    if registry.hooks:  # another party's hooks still rewrite the forward
        return
    if not had_forward:
        module.__dict__.pop("forward", None)
    if not had_registry:
        remove_hook_registry(module)


class CheckpointedForward(ModelHook):
    """The module's forward in a checkpointed region while gradients are enabled (as diffusers'
    own block checkpointing: non-reentrant), plain otherwise. Hooks registered before this one
    run inside the region, so they run again when the backward recomputes it."""

    def new_forward(self, module: nn.Module, *args: Any, **kwargs: Any) -> Any:
        forward = self.fn_ref.original_forward
        if not torch.is_grad_enabled():
            return forward(*args, **kwargs)
        return checkpoint(forward, *args, use_reentrant=False, **kwargs)

