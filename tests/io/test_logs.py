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
