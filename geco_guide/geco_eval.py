"""``python -m geco_guide.geco_eval``: run the GeCo-Eval benchmark (:mod:`geco_guide.cli.geco_eval`)."""

import sys

from .cli.geco_eval import main

if __name__ == "__main__":
    sys.exit(main())
