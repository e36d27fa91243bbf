"""``python -m geco_guide.robustness``: the metric's robustness sweeps on synthetic scenes (:mod:`geco_guide.cli.robustness`)."""

import sys

from .cli.robustness import main

if __name__ == "__main__":
    sys.exit(main())
