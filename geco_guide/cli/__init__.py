"""The commands: one argparse kit and each command's ``main``."""

__all__: list[str] = []
