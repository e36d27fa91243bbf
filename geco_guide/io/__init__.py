"""Video files, atomic writes, plots and devices: the ground floor's I/O."""
