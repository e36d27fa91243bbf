"""The library's log lines as a command shows them: on stderr, the message alone, once each."""

from __future__ import annotations

import contextlib
import io
import logging

from geco_guide.io.logs import log_to_stderr


def test_package_records_show_on_stderr_as_plain_lines_once(capsys):
    log_to_stderr()  # conftest's command_logs called it already: a second call adds no handler
    logging.getLogger("geco_guide.bench.runs").info("3 of 4 videos already done")
    logging.getLogger("geco_guide.bench.runs").debug("below the level")
    assert capsys.readouterr().err == "3 of 4 videos already done\n"


def test_the_lines_follow_stderr_when_it_is_swapped():
    swapped = io.StringIO()
    with contextlib.redirect_stderr(swapped):
        logging.getLogger("geco_guide.perf.measure").warning("warning: result.json is damaged")
    assert swapped.getvalue() == "warning: result.json is damaged\n"


class _Kept(logging.Handler):
    """The records that reach a logger's own handlers (its filters ran before)."""

    def __init__(self) -> None:
        super().__init__()
        self.messages: list[str] = []

    def emit(self, record: logging.LogRecord) -> None:
        self.messages.append(record.getMessage())


def test_the_known_third_party_notices_are_dropped_and_their_loggers_other_records_kept():
    from geco_guide.io.logs import KNOWN_NOTICES, quiet_known_notices

    log_to_stderr()
    quiet_known_notices()  # again: one filter per logger
    kept = {}
    for name in KNOWN_NOTICES:
        logger = logging.getLogger(name)
        # ours, once (diffusers adds a filter of its own to its loggers once it is imported)
        assert sum(type(f).__name__ == "_KnownNotice" for f in logger.filters) == 1
        kept[name] = _Kept()
        logger.addHandler(kept[name])
    try:
        logging.getLogger("transformers.utils.import_utils").warning(
            "`CLIPImageProcessor` requires torchvision (not installed); falling back to `CLIPImageProcessorPil` for "
            "backward compatibility.")
        logging.getLogger("transformers.utils.import_utils").warning("Could not load PIL fallback")
        from diffusers import ClassifierFreeGuidance

        ClassifierFreeGuidance(guidance_scale=5.0)  # diffusers' own notice, as a modular Wan pipeline makes it
        logging.getLogger("diffusers.guiders.guider_utils").warning("another guider warning")
    finally:
        for name, handler in kept.items():
            logging.getLogger(name).removeHandler(handler)
    assert kept["transformers.utils.import_utils"].messages == ["Could not load PIL fallback"]
    assert kept["diffusers.guiders.guider_utils"].messages == ["another guider warning"]
