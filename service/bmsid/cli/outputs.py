"""Where commands write, and the numbers they are given, checked before any work is done.

An identification that runs for minutes and then finds ``--out`` read-only has wasted the
minutes: the commands call these first, and each problem is one ``UserError`` line naming the
option. Writability is probed by creating a file, not by ``os.access``: root passes every
permission check but still fails on a read-only file system.
"""

from __future__ import annotations

import math
import os
import tempfile
from pathlib import Path

from bmsid.errors import UserError


def _reason(exc: OSError) -> str:
    return exc.strerror or type(exc).__name__


def output_dir(path: Path, option: str = "--out") -> Path:
    """``path`` as a directory that exists (created with its parents) and takes new files."""
    if path.exists() and not path.is_dir():
        raise UserError(f"{option} {path} exists and is not a directory")
    try:
        path.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise UserError(f"{option} {path}: cannot create the directory: {_reason(exc)}") from None
    try:
        fd, probe = tempfile.mkstemp(dir=path, prefix=".bmsid-write-test-")
    except OSError as exc:
        raise UserError(f"{option} {path}: cannot write in it: {_reason(exc)}") from None
    os.close(fd)
    os.unlink(probe)
    return path


def output_file(path: Path, option: str = "--out") -> Path:
    """``path`` as a file that can be written: not a directory, in a writable directory, and
    when it exists, writable itself (it is replaced)."""
    if path.is_dir():
        raise UserError(f"{option} {path} is a directory, not a file name")
    output_dir(path.parent, f"{option} {path}: its directory")
    if path.exists() and not os.access(path, os.W_OK):
        raise UserError(f"{option} {path} exists and cannot be written")
    return path


def positive(value: float | None, option: str, *, maximum: float = math.inf) -> None:
    """A finite number > 0 (and <= ``maximum``), or None (the option's default)."""
    if value is None:
        return
    if not math.isfinite(value) or value <= 0.0:
        raise UserError(f"{option} must be a finite number > 0, got {value}")
    if value > maximum:
        raise UserError(f"{option} must be at most {maximum:g}, got {value:g}")
