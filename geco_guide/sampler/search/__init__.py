"""Particle search with GeCo as the verifier: its options, the particles and their scoring."""

__all__: list[str] = []
