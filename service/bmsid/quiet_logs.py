"""Libraries whose log lines say nothing a bmsid user acts on, held at WARNING (the CLI's and
the bank worker's logging set-up both apply it: a worker process does not inherit levels)."""

from __future__ import annotations

import logging

#: python-can's bus set-up (INFO); numba's compiler (at DEBUG it dumps the bytecode of every
#: kernel it compiles: megabytes, and a compile that takes minutes instead of seconds)
QUIET_LIBRARIES = ("can", "numba")


def quiet_libraries(level: int) -> None:
    """Hold ``QUIET_LIBRARIES`` at WARNING or above, whatever ``level`` the root logger has."""
    for name in QUIET_LIBRARIES:
        logging.getLogger(name).setLevel(max(level, logging.WARNING))
