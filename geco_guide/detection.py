"""``python -m geco_guide.detection``: per-frame GeCo detection maps of a video (:mod:`geco_guide.metric.detection`)."""

import sys

from .metric.detection import main

if __name__ == "__main__":
    sys.exit(main())
