"""A throw-away Mosquitto on 127.0.0.1, for ``bmsid demo`` and the daemon benchmarks.

Not for production: anonymous, no persistence, a free port chosen here. It lives outside
``bmsid.cli`` so the benchmarks (and later tests) need not import a command's module.
"""

from __future__ import annotations

import shutil
import socket
import subprocess
import time
from pathlib import Path

#: where distributions install ``mosquitto`` (often not on a user's PATH)
SBIN = ("/usr/local/sbin", "/usr/sbin", "/sbin")
#: how long the broker may take to accept connections, s
START_TIMEOUT_S = 10.0


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port: int = s.getsockname()[1]
        return port


def start_mosquitto(workdir: Path) -> tuple[subprocess.Popen[bytes], int] | None:
    """Start ``mosquitto`` listening on a free local port; ``(process, port)`` once it accepts
    connections, or None when it is not installed or does not come up.

    Its config and log go to ``workdir`` (``mosquitto.conf``, ``mosquitto.log``). The caller
    stops it (``terminate()`` then ``wait()``).
    """
    exe = shutil.which("mosquitto") or shutil.which("mosquitto", path=":".join(SBIN))
    if exe is None:
        return None
    port = _free_port()
    conf = workdir / "mosquitto.conf"
    conf.write_text(f"listener {port} 127.0.0.1\nallow_anonymous true\npersistence false\n")
    with (workdir / "mosquitto.log").open("wb") as log:
        proc = subprocess.Popen([exe, "-c", str(conf)], stdout=log, stderr=subprocess.STDOUT)
    deadline = time.monotonic() + START_TIMEOUT_S
    while time.monotonic() < deadline:
        if proc.poll() is not None:
            return None
        try:
            socket.create_connection(("127.0.0.1", port), timeout=0.5).close()
            return proc, port
        except OSError:
            time.sleep(0.05)
    proc.terminate()
    proc.wait(5)
    return None
