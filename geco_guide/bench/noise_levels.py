"""The noise levels the robustness sweep (:mod:`geco_guide.bench.robustness`) adds to depth and
flow by default. Imports nothing, so that the command's parser shows them without loading torch."""

__all__ = ["DEPTH_SIGMAS", "FLOW_SIGMAS"]

#: Relative depth errors: each depth is multiplied by ``exp(sigma n)``, ``n ~ N(0, 1)``.
DEPTH_SIGMAS = (0.0, 0.01, 0.02, 0.05, 0.1, 0.15, 0.2, 0.3, 0.5, 1.0)
#: Flow errors in pixels: ``sigma n`` is added to each flow vector.
FLOW_SIGMAS = (0.0, 0.25, 0.5, 1.0, 2.0, 5.0, 10.0, 20.0)
