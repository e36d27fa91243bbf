"""The video models' native frame rates, the table GeCo-Eval times its windows with: read from the
one model registry (:mod:`geco_guide.families`), which imports nothing heavy, so that the metric
and the commands' parsers read it without loading torch."""

from ..families import paper_fps

__all__ = ["PAPER_MODEL_FPS"]

#: Native frame rate of each video model (GeCo paper, supplement "Frame rate of evaluated
#: models"; the models it has no row for at their model card's export rate). GeCo-Eval times its
#: windows with these rates, not with the rate written in the file.
PAPER_MODEL_FPS = paper_fps()
