"""``python -m geco_guide.validate``: score built WarpBench/OccluBench clips against their ground truth (:mod:`geco_guide.cli.validate`)."""

import sys

from .cli.validate import main

if __name__ == "__main__":
    sys.exit(main())
