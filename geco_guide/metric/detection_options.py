"""The choices of the per-frame detection maps (:mod:`geco_guide.metric.detection`). Imports
nothing, so that the command's parser offers them without loading torch."""

__all__ = ["ANCHORS", "FORMATS"]

#: Where a frame sits in its window.
ANCHORS = ("start", "center", "end")
#: What the maps are written as: an mp4, a gif, a folder of PNG frames.
FORMATS = ("mp4", "gif", "png")
