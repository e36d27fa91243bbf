"""The commands' stderr lines that come from library code.

The package's modules log (``logging.getLogger(__name__)``) rather than print, so that a program
using them decides what it shows; a command calls :func:`log_to_stderr` once to show those records
as it shows its own lines: the message alone, one line each, on stderr.
"""

from __future__ import annotations

import logging
import sys

__all__ = ["log_to_stderr"]


class _CurrentStderr(logging.StreamHandler):
    """Writes to ``sys.stderr`` as it is when a record comes, not as it was when the handler was
    made: a command run in-process (a test, a notebook) may have its stderr swapped in between."""

    def __init__(self) -> None:
        logging.Handler.__init__(self)

    @property
    def stream(self):
        return sys.stderr


def log_to_stderr(level: int = logging.INFO) -> logging.Handler:
    """Show the package's records of ``level`` and above on stderr, as plain lines; the handler.

    Calling it again adds no second handler (each line would show twice): it sets the level only.
    """
    package = logging.getLogger("geco_guide")
    handler = next((h for h in package.handlers if isinstance(h, _CurrentStderr)), None)
    if handler is None:
        handler = _CurrentStderr()
        handler.setFormatter(logging.Formatter("%(message)s"))
        package.addHandler(handler)
    package.setLevel(level)
    return handler
