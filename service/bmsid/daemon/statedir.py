"""The state directory as a contract: writable, one daemon per pack, atomic files, bad files aside.

What lives in ``state.directory``, per pack: ``<pack_id>.ckpt.npz`` (the estimator state),
``<pack_id>.seq`` (the MQTT sequence numbers reserved so far), ``<pack_id>.spool`` (messages
a shutdown could not deliver) and ``<pack_id>.lock``. The promises they carry (a restart
continues the estimation, a ``seq`` is never published twice, a backlog survives a stop) hold
only if the daemon can write there and no other daemon writes the same files, so:

- :func:`check_writable` at start: a directory the daemon cannot write is refused with one
  line (exit 2), not run degraded. Running without it would publish ``seq`` numbers that no
  file reserves (measured: 0..1,592 published twice over two restarts) or publish nothing;
  either way the operator must act, and a refusal says so at once, where systemd shows it.
- :class:`StateLock`: an exclusive ``flock`` on ``<pack_id>.lock``, held for the daemon's
  life and released by the kernel when it dies (even by SIGKILL), so a second daemon for the
  same pack refuses with one line instead of reusing the first one's numbers. Per pack, not
  per directory: packs share nothing there, and one directory may serve several.
- :func:`atomic_write`: temp file, fsync, rename, fsync of the directory: a crash leaves the
  old file or the new one, never a torn one (and perhaps the temp file, which
  :func:`remove_stale_temps` removes at the next start, under the lock).
- :func:`quarantine`: a file that cannot be used is renamed beside itself with a UTC time
  stamp (kept for a post-mortem, never read again) and the daemon starts fresh.
"""

from __future__ import annotations

import contextlib
import errno
import fcntl
import glob
import logging
import os
import time
from collections.abc import Callable, Iterable
from pathlib import Path
from typing import BinaryIO

from bmsid.errors import UserError

log = logging.getLogger(__name__)


def _reason(exc: OSError) -> str:
    return exc.strerror or type(exc).__name__


def writable_problem(directory: Path) -> str | None:
    """Why the daemon could not write ``directory``, or None; creates nothing.

    For ``check-config``, which may run as another user than the daemon: an existing
    directory must be writable for the caller (``access(2)``); one that does not exist yet
    is left to whoever creates it (the daemon, or systemd's ``StateDirectory=``), unless the
    file system it would be on is read-only, which refuses everyone.
    """
    path = directory
    while not path.exists():
        if path.parent == path:
            return f"no existing parent of {directory}"
        path = path.parent
    if not path.is_dir():
        return f"{path} is not a directory"
    try:
        read_only = bool(os.statvfs(path).f_flag & os.ST_RDONLY)
    except OSError as exc:
        return f"{path}: {_reason(exc)}"
    if read_only:
        return f"{path} is on a read-only file system"
    if path == directory and not os.access(path, os.W_OK | os.X_OK):
        return f"{path} is not writable"
    return None


def check_writable(directory: Path) -> None:
    """Create ``directory`` if needed and write, fsync and remove a probe file in it.

    Raises:
        UserError: one line naming ``state.directory`` and the system's reason.
    """
    probe = directory / f".bmsid-probe.{os.getpid()}"
    try:
        directory.mkdir(parents=True, exist_ok=True)
        fd = os.open(probe, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o600)
        try:
            os.write(fd, b"probe\n")
            os.fsync(fd)
        finally:
            os.close(fd)
        probe.unlink()
    except OSError as exc:
        with contextlib.suppress(OSError):
            probe.unlink()
        raise UserError(
            f"state.directory {directory} is not writable ({_reason(exc)}): bmsid keeps its "
            "checkpoint and the MQTT sequence numbers there and does not run without them; "
            "make it writable for the daemon's user or point state.directory elsewhere"
        ) from None


class StateLock:
    """An exclusive lock of one pack's files in the state directory (see the module doc)."""

    def __init__(self, path: Path, fd: int) -> None:
        self.path = path
        self._fd: int | None = fd

    @classmethod
    def acquire(cls, directory: Path, pack_id: str) -> StateLock:
        """Lock ``<directory>/<pack_id>.lock`` or refuse.

        Raises:
            UserError: another process holds it (its pid is named), or it cannot be opened.
        """
        path = directory / f"{pack_id}.lock"
        try:
            fd = os.open(path, os.O_RDWR | os.O_CREAT | os.O_CLOEXEC, 0o600)
        except OSError as exc:
            raise UserError(f"state.directory: cannot open {path}: {_reason(exc)}") from None
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except OSError as exc:
            holder = os.pread(fd, 32, 0).decode("ascii", "replace").strip() or "unknown"
            os.close(fd)
            if exc.errno not in (errno.EWOULDBLOCK, errno.EAGAIN):
                raise UserError(f"state.directory: cannot lock {path}: {_reason(exc)}") from None
            raise UserError(
                f"another bmsid (pid {holder}) is running for pack {pack_id!r} with "
                f"state.directory {directory}: two daemons would reuse each other's sequence "
                "numbers and overwrite each other's checkpoint; stop it, or give this one "
                "another pack_id or state.directory"
            ) from None
        # For the refusal message above only: the lock is the flock, not this content.
        with contextlib.suppress(OSError):
            os.ftruncate(fd, 0)
            os.pwrite(fd, f"{os.getpid()}\n".encode("ascii"), 0)
        return cls(path, fd)

    def release(self) -> None:
        """Unlock (the file stays: removing it would race with a daemon locking it)."""
        if self._fd is not None:
            os.close(self._fd)
            self._fd = None


def fsync_directory(directory: Path) -> None:
    """Make a rename in ``directory`` durable."""
    fd = os.open(directory, os.O_RDONLY)
    try:
        os.fsync(fd)
    finally:
        os.close(fd)


def atomic_write(path: Path, write: Callable[[BinaryIO], object]) -> None:
    """Write ``path`` through ``write(fh)`` so that a crash leaves the old or the new file.

    Temp file in the same directory -> flush -> fsync -> rename over ``path`` -> fsync of
    the directory. Raises what the file system raises (OSError); the temp file is removed.
    """
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f".{path.name}.{os.getpid()}.tmp")
    try:
        with tmp.open("wb") as fh:
            write(fh)
            fh.flush()
            os.fsync(fh.fileno())
        os.replace(tmp, path)
    finally:
        tmp.unlink(missing_ok=True)
    fsync_directory(path.parent)


def remove_stale_temps(directory: Path, names: Iterable[str]) -> int:
    """Remove the temp files :func:`atomic_write` left for ``names`` in ``directory`` when its
    process was killed mid-write (``.<name>.<pid>.tmp``); returns how many. Only with the
    pack's :class:`StateLock` held: then no live process writes them."""
    removed = 0
    for name in names:
        for tmp in directory.glob(f".{glob.escape(name)}.*.tmp"):
            if tmp.name[len(name) + 2 : -len(".tmp")].isdigit():  # not another pack's file
                with contextlib.suppress(OSError):
                    tmp.unlink()
                    removed += 1
    if removed:
        log.info("removed %d temp file(s) a killed bmsid left in %s", removed, directory)
    return removed


def quarantine(path: Path, what: str, why: str) -> Path | None:
    """Move an unusable ``path`` aside as ``<name>.bad-<UTC time>`` and log one WARNING line.

    Returns the new path (None when even the rename failed; the line says so). ``what``
    names the file for the reader ("checkpoint"), ``why`` is the reason in a few words.
    """
    stamp = time.strftime("%Y%m%dT%H%M%SZ", time.gmtime())
    target = path.with_name(f"{path.name}.bad-{stamp}")
    n = 1
    while target.exists():
        n += 1
        target = path.with_name(f"{path.name}.bad-{stamp}-{n}")
    try:
        os.replace(path, target)
        fsync_directory(path.parent)
    except OSError as exc:
        log.warning(
            "%s %s unusable (%s) and cannot be moved aside (%s): starting fresh",
            what,
            path,
            why,
            _reason(exc),
        )
        return None
    log.warning("%s %s unusable (%s): moved to %s, starting fresh", what, path, why, target.name)
    return target
