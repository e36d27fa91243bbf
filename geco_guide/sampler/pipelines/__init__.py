"""The front doors and how a config opens them: GeCoCogVideoXPipeline, the hooks on stock pipelines
with one adapter per family, the Modular Diffusers blocks, and loading a pipeline and its call."""

__all__: list[str] = []
