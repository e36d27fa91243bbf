"""Which frame pairs a GeCo window compares: the ``pairs`` option of
:class:`~geco_guide.loss.geco.GeCoLossConfig`. Imports nothing, so that a command's parser offers
the modes without loading torch."""

__all__ = ["PAIR_MODES"]

#: adjacent: (i, i+1), n-1 pairs; center: every frame with the middle one, 2(n-1); all: every
#: ordered pair, n(n-1) (the paper's evaluation script).
PAIR_MODES = ("adjacent", "center", "all")
