"""Call counters for the tests' "nothing ran before the error" checks."""


class CountingForward:
    """Counts forward calls of ``module`` (a forward pre-hook; ``handle.remove()`` detaches it)."""

    def __init__(self, module):
        self.n = 0
        self.handle = module.register_forward_pre_hook(self)

    def __call__(self, *args):
        self.n += 1
