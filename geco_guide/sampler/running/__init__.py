"""How a machine runs guidance: run options and memory plans, the anchor decode strategies, several
devices, context parallelism, fast decode, our hooks in diffusers' registry, and the guidance
context of one call."""

__all__: list[str] = []
