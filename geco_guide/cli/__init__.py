"""The commands: one argparse kit and each command's ``main``."""
