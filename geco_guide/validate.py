"""``python -m geco_guide.validate``: score built WarpBench/OccluBench clips against their ground truth (:mod:`geco_guide.bench.validate`)."""

import sys

from .bench.validate import main

if __name__ == "__main__":
    sys.exit(main())
