"""``python -m geco_guide.generate``: generate a video with GeCo guidance (:mod:`geco_guide.cli.generate`)."""

import sys

from .cli.generate import main

if __name__ == "__main__":
    sys.exit(main())
