"""Counters for the tests: forward calls ("nothing ran before the error") and host syncs."""

from collections import Counter

from diffusers.hooks import ModelHook
from torch.utils._python_dispatch import TorchDispatchMode


class CountingForward:
    """Counts forward calls of ``module`` (a forward pre-hook; ``handle.remove()`` detaches it)."""

    def __init__(self, module):
        self.n = 0
        self.handle = module.register_forward_pre_hook(self)

    def __call__(self, *args):
        self.n += 1


class CountingHook(ModelHook):
    """Counts the calls of a module's forward as a hook in diffusers' ``HookRegistry`` (register
    it with ``HookRegistry.check_if_exists_or_initialize(module).register_hook(hook, name)``)."""

    def __init__(self):
        super().__init__()
        self.n = 0

    def pre_forward(self, module, *args, **kwargs):
        self.n += 1
        return args, kwargs


class HostSyncCounter(TorchDispatchMode):
    """Counts the ATen ops that make the host wait for the device on a GPU (``.item()``,
    ``float(t)``, ``bool(t)``, ``torch.equal``, data-dependent shapes), also when running on CPU.

    Device-to-host copies (``.cpu()``, ``.tolist()``) are not ops on CPU tensors and so are not
    seen here.
    """

    SYNCING = frozenset({"_local_scalar_dense", "is_nonzero", "equal", "nonzero", "masked_select", "unique", "_unique2"})

    def __init__(self):
        super().__init__()
        self.counts = Counter()

    @property
    def total(self) -> int:
        return sum(self.counts.values())

    def __torch_dispatch__(self, func, types, args=(), kwargs=None):
        name = func.overloadpacket.__name__
        if name in self.SYNCING:
            self.counts[name] += 1
        return func(*args, **(kwargs or {}))
