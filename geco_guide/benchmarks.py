"""``python -m geco_guide.benchmarks``: build WarpBench/OccluBench clips (:mod:`geco_guide.bench.datasets`)."""

import sys

from .bench.datasets import main

if __name__ == "__main__":
    sys.exit(main())
