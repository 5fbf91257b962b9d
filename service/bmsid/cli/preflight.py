"""Checks of the files a daemon config names, shared by ``bmsid run`` and ``check-config``.

Each check answers before the daemon starts, in one line: a replay log that cannot be read is
an error (the daemon would otherwise run on a bus nobody sends to), a secret that every user
of the machine can read is a warning (the daemon still works; the secret is no longer one).
"""

from __future__ import annotations

import stat
import tomllib
from pathlib import Path

from bmsid.config.settings import Settings
from bmsid.errors import UserError


def check_replay_log(settings: Settings) -> None:
    """UserError naming ``can.replay.log`` when it is missing, not a file or unreadable."""
    replay = settings.can.replay
    if replay is None:
        return
    try:
        with replay.log.open("rb") as fh:
            fh.read(1)
    except IsADirectoryError:
        raise UserError(f"can.replay.log: {replay.log} is a directory, not a CAN log") from None
    except FileNotFoundError:
        raise UserError(f"can.replay.log: file not found: {replay.log}") from None
    except OSError as exc:
        raise UserError(f"can.replay.log: cannot read {replay.log}: {exc.strerror}") from None


def _world_readable(path: Path) -> str | None:
    """``path``'s mode as ``0644`` when every user may read it, else None (also when it cannot
    be examined: the daemon's own read reports that)."""
    try:
        mode = stat.S_IMODE(path.stat().st_mode)
    except OSError:
        return None
    return f"{mode:04o}" if mode & stat.S_IROTH else None


def _file_holds_password(config: Path) -> bool:
    try:
        data = tomllib.loads(config.read_text(encoding="utf-8"))
    except (OSError, UnicodeDecodeError, tomllib.TOMLDecodeError):
        return False
    mqtt = data.get("mqtt")
    return isinstance(mqtt, dict) and "password" in mqtt


def secret_file_warnings(config: Path, settings: Settings) -> list[str]:
    """One line per secret that every local user can read: a config holding
    ``mqtt.password``, ``mqtt.password_file``, ``mqtt.key_file`` (a client key)."""
    out: list[str] = []
    if _file_holds_password(config) and (mode := _world_readable(config)) is not None:
        out.append(
            f"config {config} holds mqtt.password and every user can read it (mode {mode}): "
            f"chmod o-r {config}, or move the password to mqtt.password_file (mode 600)"
        )
    m = settings.mqtt
    for field, path in (("mqtt.password_file", m.password_file), ("mqtt.key_file", m.key_file)):
        if path is not None and (mode := _world_readable(path)) is not None:
            out.append(f"{field} {path} is readable by every user (mode {mode}): chmod 600 {path}")
    return out
