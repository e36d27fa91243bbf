"""The commands' stderr lines that come from library code.

The package's modules log (``logging.getLogger(__name__)``) rather than print, so that a program
using them decides what it shows; a command calls :func:`log_to_stderr` once to show those records
as it shows its own lines: the message alone, one line each, on stderr.
"""

from __future__ import annotations

import logging
import re
import sys

__all__ = ["KNOWN_NOTICES", "log_to_stderr", "quiet_known_notices"]

#: Third-party notices a command shows nothing of, by logger: each says nothing its user can act
#: on, and each came again on every run. transformers falls back to an image processor without
#: torchvision (the PIL one, which the estimators' inputs do not use); diffusers calls its
#: guiders experimental whenever one is made (the modular Wan pipelines make one per CFG). Other
#: records of these loggers pass.
KNOWN_NOTICES = {
    "transformers.utils.import_utils": re.compile(r"`\w+` requires torchvision \(not installed\); falling back to"),
    "diffusers.guiders.guider_utils": re.compile(r"Guiders are currently an experimental feature"),
}


class _CurrentStderr(logging.StreamHandler):
    """Writes to ``sys.stderr`` as it is when a record comes, not as it was when the handler was
    made: a command run in-process (a test, a notebook) may have its stderr swapped in between."""

    def __init__(self) -> None:
        logging.Handler.__init__(self)

    @property
    def stream(self):
        return sys.stderr


class _KnownNotice(logging.Filter):
    """Drops the records of one logger whose message starts as ``pattern``."""

    def __init__(self, pattern: re.Pattern[str]) -> None:
        super().__init__()
        self.pattern = pattern

    def filter(self, record: logging.LogRecord) -> bool:
        return self.pattern.match(record.getMessage()) is None


def quiet_known_notices() -> None:
    """Drop the :data:`KNOWN_NOTICES` where they are logged (a filter on each one's logger: nothing
    else is muted); once per process however often it is called."""
    for name, pattern in KNOWN_NOTICES.items():
        logger = logging.getLogger(name)
        if not any(isinstance(f, _KnownNotice) for f in logger.filters):
            logger.addFilter(_KnownNotice(pattern))


def log_to_stderr(level: int = logging.INFO) -> logging.Handler:
    """Show the package's records of ``level`` and above on stderr, as plain lines; the handler;
    and the third-party notices a command shows nothing of dropped (:func:`quiet_known_notices`).

    Calling it again adds no second handler (each line would show twice): it sets the level only.
    """
    quiet_known_notices()
    package = logging.getLogger("geco_guide")
    handler = next((h for h in package.handlers if isinstance(h, _CurrentStderr)), None)
    if handler is None:
        handler = _CurrentStderr()
        handler.setFormatter(logging.Formatter("%(message)s"))
        package.addHandler(handler)
    package.setLevel(level)
    return handler
