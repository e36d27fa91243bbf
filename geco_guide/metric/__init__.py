"""Scoring any video with GeCo: the protocol, evaluate_video, per-frame detection maps, rendering. Imports no diffusion code."""

__all__: list[str] = []
