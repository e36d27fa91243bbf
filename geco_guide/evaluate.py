"""``python -m geco_guide.evaluate``: score videos with the GeCo metric (:mod:`geco_guide.metric.evaluate`)."""

import sys

from .metric.evaluate import main

if __name__ == "__main__":
    sys.exit(main())
