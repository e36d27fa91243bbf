"""What a WarpBench/OccluBench clip is built as, and the synthetic scenes it can be built from
(:mod:`geco_guide.bench.datasets` builds them). Imports nothing, so that the command's parser
offers them without loading torch."""

__all__ = ["KINDS", "SYNTHETIC", "SYNTHETIC_3D"]

KINDS = ("warp", "occlusion")
SYNTHETIC = "synthetic"  # the gallery scene (rigid_clip): any edit
SYNTHETIC_3D = "synthetic-3d"  # occlusion_swap_clip: an occlusion inconsistency built in 3D
