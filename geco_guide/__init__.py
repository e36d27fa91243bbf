"""GeCo: geometric-consistency metric and guidance for diffusers video models."""
