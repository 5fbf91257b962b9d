"""Logging of the command line: the level from ``-v``/``-q``, the format from where it goes.

``bmsid run`` is a service: its lifecycle (start, restore, first data, counters, connection
changes, stop) is logged at INFO by default, so ``journalctl -u bmsid -f`` shows it with the
shipped unit. The other commands print their own results and log only warnings by default.
Each ``-v`` moves one level towards DEBUG, each ``-q`` one towards ERROR.

Under systemd (stderr is the journal's stream) every line starts with its syslog priority
(``<4>``), which journald turns into the entry's priority (``journalctl -p warning`` works) and
strips; journald adds the time stamp, so the line carries none.
"""

from __future__ import annotations

import logging
import os
import sys

from bmsid.quiet_logs import quiet_libraries

#: -v/-q steps, most verbose first
LEVELS = (logging.DEBUG, logging.INFO, logging.WARNING, logging.ERROR)
#: syslog priorities (RFC 5424) of the logging levels
_SYSLOG_PRIORITY = {
    logging.DEBUG: 7,
    logging.INFO: 6,
    logging.WARNING: 4,
    logging.ERROR: 3,
    logging.CRITICAL: 2,
}
TERMINAL_FORMAT = "%(asctime)s %(levelname)s %(name)s: %(message)s"
JOURNAL_FORMAT = "%(levelname)s %(name)s: %(message)s"
_HANDLER_NAME = "bmsid-cli"


def log_level(default: int, verbose: int, quiet: int) -> int:
    """The level ``default`` moved ``verbose`` steps towards DEBUG and ``quiet`` towards ERROR."""
    i = LEVELS.index(default) - verbose + quiet
    return LEVELS[min(max(i, 0), len(LEVELS) - 1)]


def stderr_is_journal() -> bool:
    """True when stderr is systemd's journal stream (``$JOURNAL_STREAM`` names its device and
    inode, as sd_journal_stream_fd(3) documents), not a terminal or a file."""
    stream = os.environ.get("JOURNAL_STREAM", "")
    dev, _, ino = stream.partition(":")
    try:
        st = os.fstat(sys.stderr.fileno())
        return (st.st_dev, st.st_ino) == (int(dev), int(ino))
    except (ValueError, OSError, AttributeError):
        return False


class JournalFormatter(logging.Formatter):
    """``<priority>`` before each line, for journald's SyslogLevelPrefix (on by default)."""

    def format(self, record: logging.LogRecord) -> str:
        prefix = f"<{_SYSLOG_PRIORITY.get(record.levelno, 6)}>"
        # a traceback's continuation lines get the same priority as the record
        return "\n".join(prefix + line for line in super().format(record).splitlines())


def configure(level: int, *, journal: bool | None = None) -> None:
    """Log to stderr at ``level``; ``journal`` None detects systemd's journal stream."""
    handler = logging.StreamHandler(sys.stderr)
    if stderr_is_journal() if journal is None else journal:
        handler.setFormatter(JournalFormatter(JOURNAL_FORMAT))
    else:
        handler.setFormatter(logging.Formatter(TERMINAL_FORMAT))
    handler.set_name(_HANDLER_NAME)
    root = logging.getLogger()
    # replace only our own handler: a host's (pytest's capture, an embedding program's) stays
    root.handlers[:] = [h for h in root.handlers if h.get_name() != _HANDLER_NAME] + [handler]
    root.setLevel(level)
    quiet_libraries(level)
