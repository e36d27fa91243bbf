"""What guidance computes, free of how it runs: its options and presets, the schedule, noise-level
arithmetic, anchor slicing, the guided step, the anchor objective, dynamic masks while guiding."""

__all__: list[str] = []
