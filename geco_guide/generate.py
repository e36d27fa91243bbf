"""``python -m geco_guide.generate``: generate a video with GeCo guidance (:mod:`geco_guide.cli.generate`)."""

import sys

from .cli.generate import main

__all__: list[str] = []

if __name__ == "__main__":
    sys.exit(main())
