"""The loss' mode choices the command line offers, here without torch so that ``--help`` and
argparse's refusals answer before anything heavy loads.

:data:`MOVER_MODES`: what dynamic masks do to what they cover (``loss.movers``): ``drop`` (left
out) or ``rigid`` (each mover scored against its own rigid motion, :mod:`geco_guide.loss.movers`).
"""

from __future__ import annotations

__all__ = ["MOVER_MODES"]

MOVER_MODES = ("drop", "rigid")
