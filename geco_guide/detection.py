"""``python -m geco_guide.detection``: per-frame GeCo detection maps of a video (:mod:`geco_guide.cli.detection`)."""

import sys

from .cli.detection import main

if __name__ == "__main__":
    sys.exit(main())
