"""``python -m geco_guide.evaluate``: score videos with the GeCo metric (:mod:`geco_guide.cli.evaluate`)."""

import sys

from .cli.evaluate import main

if __name__ == "__main__":
    sys.exit(main())
