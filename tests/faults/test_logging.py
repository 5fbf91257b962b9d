"""Logging like a service: ``bmsid run`` tells its lifecycle at INFO with no flag, the way the
shipped unit starts it, and ``-v``/``-q`` work on either side of the command.

The end-to-end case runs ``bmsid run --config configs/bmsid.replay.toml`` (the config a newcomer
is pointed at) as a process against a real Mosquitto, stops and restarts the broker under it, and
stops it with SIGTERM (~15 s here). The rest are in-process unit checks (< 1 s each).
"""

from __future__ import annotations

import argparse
import logging
import os
import re
import shlex
import signal
import subprocess
import sys
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import pytest

from bmsid.cli import logsetup
from bmsid.cli.main import build_parser, main

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "daemon"))
from daemon_helpers import MqttCapture

REPO = Path(__file__).resolve().parents[2]
REPLAY_CONFIG = REPO / "configs" / "bmsid.replay.toml"
UNIT = REPO / "deploy" / "systemd" / "bmsid.service"
SERVICE = REPO / "service"


# --------------------------------------------------------------------------------- levels


def _level(argv: list[str]) -> int:
    """The log level main() would configure for ``argv`` (parsed by the real parser)."""
    args = build_parser().parse_args(argv)
    return logsetup.log_level(
        getattr(args, "log_level", logging.WARNING),
        args.verbose + args.sub_verbose,
        args.quiet + args.sub_quiet,
    )


def test_run_logs_at_info_without_a_flag_other_commands_at_warning() -> None:
    assert _level(["run", "--config", "f.toml"]) == logging.INFO
    assert _level(["check-config", "f.toml"]) == logging.WARNING
    assert _level(["make-log", "x.csv", "--out", "x.log"]) == logging.WARNING


@pytest.mark.parametrize(
    ("argv", "level"),
    [
        (["-v", "run", "--config", "f.toml"], logging.DEBUG),
        (["run", "--config", "f.toml", "-v"], logging.DEBUG),
        (["run", "-v", "--config", "f.toml"], logging.DEBUG),
        (["run", "--config", "f.toml", "-q"], logging.WARNING),
        (["-q", "run", "--config", "f.toml", "-q"], logging.ERROR),
        (["run", "--config", "f.toml", "-qqqq"], logging.ERROR),
        (["-vv", "check-config", "f.toml"], logging.DEBUG),
        (["check-config", "f.toml", "--verbose"], logging.INFO),
        (["check-config", "f.toml", "--quiet"], logging.ERROR),
        (["-v", "run", "--config", "f.toml", "-q"], logging.INFO),
    ],
)
def test_verbose_and_quiet_anywhere_on_the_command_line(argv: list[str], level: int) -> None:
    assert _level(argv) == level


def test_check_config_accepts_v_after_the_command(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """Measured: `bmsid check-config f -v` was rejected (`-v` had to come first)."""
    config = tmp_path / "c.toml"
    config.write_text('pack_id = "p"\n[can]\nn_cells = 2\n', encoding="utf-8")
    assert main(["check-config", str(config), "-v"]) == 0
    assert main(["check-config", str(config), "-q"]) == 0
    assert "valid" in capsys.readouterr().out


def test_shipped_unit_runs_the_daemon_at_info() -> None:
    """``journalctl -u bmsid -f`` shows the lifecycle only if the unit's command logs INFO."""
    exec_start = next(
        line.split("=", 1)[1] for line in UNIT.read_text().splitlines()
        if line.startswith("ExecStart=")
    )  # fmt: skip
    script = shlex.split(exec_start)[-1]  # /bin/sh -c '...; exec .../bmsid run --config ...'
    command = shlex.split(script.rsplit("exec ", 1)[1])
    assert command[0].endswith("/bmsid")
    assert _level(command[1:]) == logging.INFO


# --------------------------------------------------------------------------------- format


def _record(level: int, msg: str) -> logging.LogRecord:
    return logging.LogRecord("bmsid.x", level, __file__, 1, msg, None, None)


def test_journal_lines_carry_their_syslog_priority() -> None:
    fmt = logsetup.JournalFormatter(logsetup.JOURNAL_FORMAT)
    assert fmt.format(_record(logging.INFO, "started")) == "<6>INFO bmsid.x: started"
    assert fmt.format(_record(logging.WARNING, "CAN down")) == "<4>WARNING bmsid.x: CAN down"
    assert fmt.format(_record(logging.ERROR, "a\nb")).splitlines() == [
        "<3>ERROR bmsid.x: a",
        "<3>b",
    ]


def test_journal_stream_is_recognised_by_device_and_inode(tmp_path: Path) -> None:
    """systemd sets $JOURNAL_STREAM to the stream's dev:inode; a redirected stderr (a file, a
    pipe) inherits the variable but not the stream, and must get the terminal format."""
    probe = (
        "import os,sys; from bmsid.cli import logsetup; "
        "st=os.fstat(2); os.environ['JOURNAL_STREAM']=f'{st.st_dev}:{st.st_ino}' "
        "if sys.argv[1]=='same' else '1:2'; print(logsetup.stderr_is_journal())"
    )
    env = {**os.environ, "PYTHONPATH": str(SERVICE)}
    out = {}
    for case in ("same", "other"):
        with (tmp_path / f"{case}.err").open("w") as err:
            out[case] = subprocess.run(
                [sys.executable, "-c", probe, case], stderr=err, capture_output=False,
                stdout=subprocess.PIPE, env=env, check=True, text=True,
            ).stdout.strip()  # fmt: skip
    assert out == {"same": "True", "other": "False"}


# --------------------------------------------------------------------------------- end to end


def _wait_for_line(
    path: Path, pattern: str, timeout_s: float, proc: subprocess.Popen[bytes]
) -> str:
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        text = path.read_text(encoding="utf-8", errors="replace")
        if re.search(pattern, text):
            return text
        if proc.poll() is not None:
            raise AssertionError(f"bmsid exited with {proc.returncode} before {pattern!r}:\n{text}")
        time.sleep(0.1)
    raise AssertionError(f"no line {pattern!r} within {timeout_s} s:\n{path.read_text()}")


def _start(log: Path, env: dict[str, str]) -> subprocess.Popen[bytes]:
    with log.open("ab") as fh:
        return subprocess.Popen(
            [sys.executable, "-m", "bmsid.cli.main", "run", "--config", str(REPLAY_CONFIG)],
            stdout=fh, stderr=subprocess.STDOUT, env=env, cwd=log.parent,
        )  # fmt: skip


def _stop(proc: subprocess.Popen[bytes]) -> int:
    proc.send_signal(signal.SIGTERM)
    try:
        return proc.wait(30)
    finally:
        if proc.poll() is None:
            proc.kill()


def test_replay_config_runs_logs_its_lifecycle_publishes_and_stops_cleanly(
    tmp_path: Path, mosquitto_factory: Any, require_tool: Callable[[str], str]
) -> None:
    """`bmsid run --config configs/bmsid.replay.toml` with no flag, no vcan, no root: the
    journal-worthy lines at INFO (start with bus, pack and broker; fresh start; CAN up; MQTT
    connected; first data; counters; MQTT lost and back; stopping; stopped), cell messages of
    the 8 cells with contiguous seq, exit code 0 on SIGTERM; a second start says "restored"."""
    broker = mosquitto_factory()
    capture = MqttCapture(require_tool("mosquitto_sub"), broker.port, tmp_path / "mqtt.txt")
    capture.wait_ready(require_tool("mosquitto_pub"), broker.port)
    env = {
        **os.environ,
        "PYTHONPATH": str(SERVICE),
        "BMSID_MQTT__URL": f"mqtt://127.0.0.1:{broker.port}",
        "BMSID_MQTT__RECONNECT_MAX_S": "0.5",
        "BMSID_STATE__DIRECTORY": str(tmp_path / "state"),
        "BMSID_LOG_PERIOD_S": "1",
    }
    env.pop("JOURNAL_STREAM", None)
    log = tmp_path / "bmsid.log"
    proc = _start(log, env)
    try:
        _wait_for_line(log, r"first data", 60, proc)
        _wait_for_line(log, r"INFO bmsid\.daemon\.core: counters: can=up mqtt=connected", 10, proc)
        broker.stop()
        _wait_for_line(log, r"MQTT connection to \S+ lost", 15, proc)
        _wait_for_line(log, r"MQTT connect to \S+ failed \[unreachable\]", 15, proc)
        broker.start()
        _wait_for_line(log, r"MQTT connected to \S+ after \d+ failed attempt", 15, proc)
        assert _stop(proc) == 0
    finally:
        if proc.poll() is None:
            proc.kill()
    text = log.read_text(encoding="utf-8")
    assert "Traceback" not in text, text
    expected_in_order = [
        rf"INFO bmsid\.daemon\.core: bmsid \S+ starting: pack replay, 8 cells \(.+\); "
        rf"CAN virtual/bmsid-replay \(bmsid\) replaying \S+demo_pack\.log at 20x; "
        rf"MQTT 127\.0\.0\.1:{broker.port} as bmsid-replay under bmsid/replay/; state in ",
        r"INFO bmsid\.daemon\.core: fresh start \(no checkpoint \S+replay\.ckpt\.npz yet\)",
        r"INFO bmsid\.daemon\.core: CAN virtual/bmsid-replay up",
        r"INFO bmsid\.publish\.mqtt: MQTT connected to",
        r"INFO bmsid\.daemon\.core: first data: \d+ samples of 8 cells",
        r"INFO bmsid\.daemon\.core: counters: can=up mqtt=connected frames=\d+",
        r"WARNING bmsid\.publish\.mqtt: MQTT connection to \S+ lost",
        r"WARNING bmsid\.publish\.mqtt: MQTT connect to \S+ failed \[unreachable\]",
        r"INFO bmsid\.publish\.mqtt: MQTT connected to \S+ after",
        r"INFO bmsid\.daemon\.core: stopping",
        r"INFO bmsid\.daemon\.core: stopped: after \d+ s, frames=\d+",
    ]
    pos = 0
    for pattern in expected_in_order:
        m = re.compile(pattern).search(text, pos)
        assert m is not None, f"{pattern!r} missing (or out of order) in:\n{text}"
        pos = m.end()

    cells = [(t, p) for t, p in capture.messages("bmsid/replay/") if "/cell/" in t]
    assert {t.rsplit("/", 1)[1] for t, _ in cells} == {str(c) for c in range(8)}
    # (the subscriber, too, was cut off by the broker's restart: repeats are checked, not gaps)
    seqs = [p["seq"] for _, p in capture.messages("bmsid/replay/") if "seq" in p]
    assert seqs[0] == 0 and len(seqs) > 8
    assert len(set(seqs)) == len(seqs), "a seq published twice"

    # The second start restores what the first checkpointed at its stop.
    proc = _start(log, env)
    try:
        _wait_for_line(log, r"restored \S+replay\.ckpt\.npz .*MQTT seq continues at", 60, proc)
        assert _stop(proc) == 0
    finally:
        if proc.poll() is None:
            proc.kill()
        capture.stop()


def test_counters_line_follows_log_period_not_status_period(
    tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    """status_period_s feeds the status topic (every 10 s by default): the log gets a counters
    line only every log_period_s, so a healthy gateway's journal does not fill up."""
    import asyncio

    from bmsid.config.settings import Settings
    from bmsid.daemon.core import Daemon

    settings = Settings(
        pack_id="p",
        systemd_notify=False,
        status_period_s=0.05,
        log_period_s=0.4,
        can={"interface": "virtual", "channel": f"t{time.monotonic_ns()}", "n_cells": 2},
        estimator={"isolation": "thread"},
        mqtt={"enabled": False},
        state={"directory": tmp_path / "state"},
    )

    async def run_for(seconds: float) -> None:
        """`seconds` of the running daemon. Its periodic tasks start once the bank is up (and
        the bus with them), after the bank's kernels are loaded: ~1.5 s in a process that has
        not loaded them yet (the first daemon of a pytest-xdist worker), instant after."""
        daemon = Daemon(settings)
        task = asyncio.create_task(daemon.run())
        deadline = time.monotonic() + 120
        while daemon.can_state != "up" and not task.done() and time.monotonic() < deadline:
            await asyncio.sleep(0.01)
        assert daemon.can_state == "up", daemon.snapshot()
        await asyncio.sleep(seconds)
        daemon.request_stop()
        assert await task == 0

    with caplog.at_level(logging.INFO, logger="bmsid"):
        asyncio.run(run_for(1.5))
    counters = [r for r in caplog.records if r.getMessage().startswith("counters:")]
    assert all(r.levelno == logging.INFO for r in counters)
    assert 2 <= len(counters) <= 4, [r.getMessage() for r in counters]
    assert "no checkpoint" in caplog.text and "stopped: after" in caplog.text


def test_a_missing_can_interface_is_one_state_change_and_thinned_retries(
    tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    """can0 missing: one "down" line, then the reopen failures of that outage at the 1st and
    10th attempt only (it retried every 30 s for ever, one WARNING each)."""
    import asyncio

    from bmsid.config.settings import Settings
    from bmsid.daemon.core import Daemon

    settings = Settings(
        pack_id="p",
        systemd_notify=False,
        can={"channel": "bmsidnone0", "n_cells": 2, "reopen_min_s": 0.02, "reopen_max_s": 0.02},
        estimator={"isolation": "thread"},
        mqtt={"enabled": False},
        state={"directory": tmp_path / "state"},
    )

    async def run_until_attempts(n: int) -> Daemon:
        daemon = Daemon(settings)
        task = asyncio.create_task(daemon.run())
        deadline = time.monotonic() + 20
        while daemon.counters["can_open_failures"] < n and time.monotonic() < deadline:
            await asyncio.sleep(0.02)
        daemon.request_stop()
        assert await task == 0
        return daemon

    with caplog.at_level(logging.INFO, logger="bmsid"):
        daemon = asyncio.run(run_until_attempts(15))
    assert daemon.counters["can_open_failures"] >= 15
    lines = [r.getMessage() for r in caplog.records if "bmsidnone0" in r.getMessage()]
    assert lines.count("CAN socketcan/bmsidnone0 down") == 1
    opens = [line for line in lines if "cannot be opened" in line]
    assert [re.search(r"\((\d+) attempt", line).group(1) for line in opens] == ["1", "10"]  # type: ignore[union-attr]
    assert "no network interface 'bmsidnone0'" in opens[0]


def test_argparse_namespace_of_run_has_its_default_level() -> None:
    args = build_parser("run").parse_args(["run", "--config", "x"])
    assert isinstance(args, argparse.Namespace) and args.log_level == logging.INFO
