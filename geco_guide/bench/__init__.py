"""The benchmarks: GeCo-Eval, WarpBench/OccluBench, synthetic scenes, the detection tasks' statistics, robustness sweeps."""

__all__: list[str] = []
