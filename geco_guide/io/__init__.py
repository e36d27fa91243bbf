"""Video files, atomic writes, plots and devices: the ground floor's I/O."""

__all__: list[str] = []
