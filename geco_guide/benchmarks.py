"""``python -m geco_guide.benchmarks``: build WarpBench/OccluBench clips (:mod:`geco_guide.cli.benchmarks`)."""

import sys

from .cli.benchmarks import main

if __name__ == "__main__":
    sys.exit(main())
