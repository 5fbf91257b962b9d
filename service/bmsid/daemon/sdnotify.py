"""systemd's notify protocol (READY=1, WATCHDOG=1, STATUS=..., STOPPING=1): one datagram to
``$NOTIFY_SOCKET``. A no-op outside systemd. No dependency needed for a dozen lines."""

from __future__ import annotations

import logging
import os
import socket

log = logging.getLogger(__name__)


class SdNotifier:
    def __init__(self, enabled: bool = True) -> None:
        addr = os.environ.get("NOTIFY_SOCKET", "") if enabled else ""
        if addr.startswith("@"):  # abstract namespace
            addr = "\0" + addr[1:]
        self._addr = addr
        usec = os.environ.get("WATCHDOG_USEC", "")
        self.watchdog_s: float | None = int(usec) / 1e6 if usec.isdigit() and enabled else None

    @property
    def active(self) -> bool:
        return bool(self._addr)

    def notify(self, *fields: str) -> bool:
        """Send ``fields`` (``KEY=value``) as one message; False when not under systemd/failed."""
        if not self._addr:
            return False
        try:
            with socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM) as sock:
                # never wait on the event loop: a reader that lags (a full queue) costs this
                # message (one warning), not the daemon's progress
                sock.setblocking(False)
                sock.connect(self._addr)
                sock.sendall("\n".join(fields).encode())
        except OSError as exc:
            log.warning("sd_notify to %s failed: %s", self._addr, exc)
            return False
        return True
