"""Test time written as text, as cyclers export it, read as seconds.

Digatron and Neware write the test time as ``hh:mm:ss`` (``00:01:02.500``; hours past 24 go on
counting), Maccor as ``d.hh:mm:ss`` or ``d hh:mm:ss``, and many loggers a date and time of day
(ISO 8601, ``2024-03-01 12:00:01.5`` or with a ``T``). A column of one of these forms is read as
seconds: durations as they stand, dates and times as seconds since the Unix epoch (the engine
needs differences only). Anything else (a 12-hour clock, a date without a time, mixed forms) is
not guessed at: the caller reports the column as non-numeric.
"""

from __future__ import annotations

import re
from collections.abc import Sequence

import numpy as np
import numpy.typing as npt

FloatArray = npt.NDArray[np.float64]

#: [days (". ", " " or "-" after them)] hours:minutes:seconds[.fraction]
_DURATION = re.compile(r"^(?:(\d+)[.\s-])?(\d+):([0-5]?\d):([0-5]?\d(?:[.,]\d*)?)$")
#: an ISO 8601 date and time of day, without a zone
_DATETIME = re.compile(r"^\d{4}-\d{2}-\d{2}[T ]\d{2}:\d{2}(?::\d{2}(?:\.\d+)?)?$")

#: how a time column was read (for the run's first line)
DURATION = "h:mm:ss durations"
DATETIME = "ISO dates and times (s since the Unix epoch)"


def seconds_from_text(values: Sequence[str]) -> tuple[FloatArray, str] | None:
    """The column as seconds and the form it was read in, or None when not every value is one
    form above (blank values are not times: the time stamp must be there)."""
    text = [v.strip() for v in values]
    if not text:
        return None
    if _DURATION.match(text[0]):
        t = _durations(text)
        return None if t is None else (t, DURATION)
    if _DATETIME.match(text[0]):
        t = _datetimes(text)
        return None if t is None else (t, DATETIME)
    return None


def _durations(text: Sequence[str]) -> FloatArray | None:
    out = np.empty(len(text))
    for k, s in enumerate(text):
        m = _DURATION.match(s)
        if m is None:
            return None
        days, h, mi, sec = m.groups()
        out[k] = (
            (int(days) * 86400 if days else 0) + int(h) * 3600 + int(mi) * 60
            + float(sec.replace(",", "."))
        )  # fmt: skip
    return out


def _datetimes(text: Sequence[str]) -> FloatArray | None:
    if not all(_DATETIME.match(s) for s in text):
        return None
    try:  # the pattern lets through what no calendar has (month 13, 24:61)
        stamps = np.array([s.replace(" ", "T") for s in text], dtype="datetime64[us]")
    except ValueError:
        return None
    return np.asarray((stamps - np.datetime64(0, "us")) / np.timedelta64(1, "s"), dtype=float)
