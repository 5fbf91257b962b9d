"""Every CLI path ends in one clear line, never a traceback (issue 16, case 7).

Each case asserts the outcome: the exit code, exactly one line on stderr naming the option or
file and the reason, no traceback, and nothing lost or invented (an existing file is left as
it was, no output is half-written). In-process, except the missing replay log, which runs
``bmsid run`` as a gateway does; ~10 s in all here.
"""

from __future__ import annotations

import logging
import os
import stat
import subprocess
import sys
import tempfile
from collections.abc import Iterator
from pathlib import Path

import can
import pytest

import bmsid.cli.check_config
from bmsid.canbus.logs import write_log
from bmsid.cli.main import main
from bmsid.cli.preflight import secret_file_warnings
from bmsid.config.settings import load_settings
from bmsid.daemon.demo_data import DEMO_LOG
from bmsid.daemon.sources import LogReplayer
from bmsid.errors import UserError

REPO = Path(__file__).resolve().parents[2]


def _writable(directory: Path) -> bool:
    try:
        fd, probe = tempfile.mkstemp(dir=directory)
    except OSError:
        return False
    os.close(fd)
    os.unlink(probe)
    return True


@pytest.fixture
def read_only_dir(tmp_path: Path) -> Iterator[Path]:
    """A directory in which no file can be created by this user: mode 0555, or for root (who
    ignores modes) sysfs, which refuses new files to everyone."""
    d = tmp_path / "ro"
    d.mkdir()
    d.chmod(stat.S_IRUSR | stat.S_IXUSR | stat.S_IRGRP | stat.S_IXGRP | stat.S_IROTH)
    try:
        if not _writable(d):
            yield d
            return
        sysfs = Path("/sys/fs")
        if sysfs.is_dir() and not _writable(sysfs):
            yield sysfs
            return
        pytest.fail("no read-only directory to test with (root without /sys?)")
    finally:
        d.chmod(stat.S_IRWXU)


def _one_line(err: str) -> str:
    lines = err.strip().splitlines()
    assert len(lines) == 1, err
    assert "Traceback" not in err
    return lines[0]


def test_demo_speed_beyond_the_replay_limit_is_one_line(
    capsys: pytest.CaptureFixture[str],
) -> None:
    """Measured: `demo --speed 1e9` ended in a pydantic traceback."""
    assert main(["demo", "--speed", "1e9", "--no-mqtt"]) == 2
    line = _one_line(capsys.readouterr().err)
    assert line.startswith("bmsid demo: error: --speed 1e+09:") and "100000" in line


@pytest.mark.parametrize("value", ["nan", "inf", "-3", "0"])
def test_demo_speed_not_a_positive_number_is_one_line(
    value: str, capsys: pytest.CaptureFixture[str]
) -> None:
    assert main(["demo", "--speed", value, "--no-mqtt"]) == 2
    assert "--speed must be a finite number > 0" in _one_line(capsys.readouterr().err)


@pytest.mark.parametrize("value", ["nan", "-1", "0"])
def test_demo_duration_not_a_positive_number_is_one_line(
    value: str, capsys: pytest.CaptureFixture[str]
) -> None:
    """`--duration-s nan` ran the whole log (no comparison with nan is true)."""
    assert main(["demo", "--duration-s", value, "--no-mqtt"]) == 2
    assert "--duration-s must be a finite number > 0" in _one_line(capsys.readouterr().err)


def test_demo_out_an_existing_file_is_one_line_and_the_file_is_kept(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """Measured: `demo --out FILE` ended in FileExistsError's traceback."""
    f = tmp_path / "notes.txt"
    f.write_text("keep me\n")
    assert main(["demo", "--out", str(f), "--no-mqtt"]) == 2
    assert _one_line(capsys.readouterr().err) == (
        f"bmsid demo: error: --out {f} exists and is not a directory"
    )
    assert f.read_text() == "keep me\n"


def test_demo_out_in_a_read_only_directory_is_one_line(
    read_only_dir: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """Measured: `demo --out` on a read-only directory ran, then failed with a traceback."""
    assert main(["demo", "--out", str(read_only_dir), "--no-mqtt"]) == 2
    line = _one_line(capsys.readouterr().err)
    assert line.startswith(f"bmsid demo: error: --out {read_only_dir}: cannot write in it: ")
    assert main(["demo", "--out", str(read_only_dir / "new"), "--no-mqtt"]) == 2
    line = _one_line(capsys.readouterr().err)
    assert "cannot create the directory" in line
    assert not (read_only_dir / "new").exists()


def test_identify_out_in_a_read_only_directory_fails_before_identifying(
    read_only_dir: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """Measured: `identify --out` on a read-only directory identified the whole record and
    then ended in PermissionError's traceback. Now: one line, before any work (no progress
    bar, no summary on stdout)."""
    assert main(["identify", str(DEMO_LOG), "--out", str(read_only_dir)]) == 2
    captured = capsys.readouterr()
    line = _one_line(captured.err)
    assert line.startswith(f"bmsid identify: error: --out {read_only_dir}: cannot write in it")
    assert captured.out == ""


@pytest.mark.parametrize(
    ("command", "name"),
    [
        (["make-log", "{csv}", "--out"], "x.log"),
        (["fit-ocv", "{csv}", "--out"], "cell.toml"),
    ],
)
def test_file_outputs_in_a_read_only_directory_are_one_line(
    command: list[str],
    name: str,
    read_only_dir: Path,
    tmp_path: Path,
    capsys: pytest.CaptureFixture[str],
) -> None:
    csv = tmp_path / "in.csv"
    csv.write_text("t_s,current_A,voltage_V\n0,1,3.7\n1,1,3.69\n")
    out = read_only_dir / name
    argv = [a.format(csv=csv) for a in command] + [str(out)]
    assert main(argv) == 2
    line = _one_line(capsys.readouterr().err)
    assert f"--out {out}: its directory {read_only_dir}: cannot write in it" in line
    assert not out.exists()


def test_make_log_rate_not_a_number_is_one_line(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    csv = tmp_path / "in.csv"
    csv.write_text("t_s,current_A,voltage_V\n0,1,3.7\n1,1,3.69\n")
    assert main(["make-log", str(csv), "--out", str(tmp_path / "x.log"), "--rate-hz", "nan"]) == 2
    assert "--rate-hz must be a finite number > 0" in _one_line(capsys.readouterr().err)
    assert not (tmp_path / "x.log").exists()


def _replay_config(tmp_path: Path, log: Path, extra: str = "") -> Path:
    config = tmp_path / "replay.toml"
    config.write_text(
        f'pack_id = "p"\nsystemd_notify = false\n[can]\ninterface = "virtual"\n'
        f'channel = "t{os.getpid()}"\nn_cells = 8\n[can.replay]\nlog = "{log}"\n'
        f'[mqtt]\nenabled = false\n[state]\ndirectory = "{tmp_path / "state"}"\n{extra}',
        encoding="utf-8",
    )
    return config


def test_run_with_a_missing_replay_log_exits_with_one_line(tmp_path: Path) -> None:
    """Measured: a missing replay log printed a traceback from the replay thread and the daemon
    kept running on a silent bus. Now `bmsid run` (a process, as a gateway runs it) exits 2
    with one line, before it starts."""
    config = _replay_config(tmp_path, tmp_path / "gone.log")
    env = {**os.environ, "PYTHONPATH": str(REPO / "service")}
    proc = subprocess.run(
        [sys.executable, "-m", "bmsid.cli.main", "run", "--config", str(config)],
        capture_output=True, text=True, env=env, timeout=60, check=False,
    )  # fmt: skip
    assert proc.returncode == 2, proc.stderr
    assert _one_line(proc.stderr) == (
        f"bmsid run: error: can.replay.log: file not found: {tmp_path / 'gone.log'}"
    )
    assert not (tmp_path / "state").exists()  # nothing started


def test_check_config_names_a_missing_replay_log(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    config = _replay_config(tmp_path, tmp_path / "gone.log")
    assert main(["check-config", str(config)]) == 2
    assert "can.replay.log: file not found" in _one_line(capsys.readouterr().err)


def test_check_config_refuses_what_run_refuses(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """Found by a sweep: check-config called a config valid whose can.output_dbc is missing
    (run then failed with "dbc: file not found", naming no field), and one replaying a log of
    two packs on can0 and can1. Both are now one line naming the field, in both commands."""
    base = (
        f'pack_id = "p"\nsystemd_notify = false\n[mqtt]\nenabled = false\n'
        f'[state]\ndirectory = "{tmp_path / "state"}"\n'
    )
    dbc = tmp_path / "config.toml"
    dbc.write_text(
        base + f'[can]\ninterface = "virtual"\nchannel = "t{os.getpid()}"\nn_cells = 8\n'
        f'output_dbc = "{tmp_path / "gone.dbc"}"\n', encoding="utf-8",
    )  # fmt: skip
    assert main(["check-config", str(dbc)]) == 2
    assert _one_line(capsys.readouterr().err) == (
        f"bmsid check-config: error: can.output_dbc: dbc: file not found: {tmp_path / 'gone.dbc'}"
    )
    assert main(["run", "--config", str(dbc)]) == 2
    assert "can.output_dbc: dbc: file not found" in _one_line(capsys.readouterr().err)
    lines = DEMO_LOG.read_text(encoding="ascii").splitlines()
    two = tmp_path / "two.log"
    two.write_text("\n".join([*lines, *(ln.replace(" can0 ", " can1 ") for ln in lines)]) + "\n")
    config = _replay_config(tmp_path, two)
    assert main(["check-config", str(config)]) == 2
    err = _one_line(capsys.readouterr().err)
    assert err.startswith("bmsid check-config: error: can.replay.channel: ")
    assert 'set can.replay.channel = "NAME" (one of can0, can1)' in err


def test_replayer_refuses_a_log_that_vanished_after_the_check(tmp_path: Path) -> None:
    """The daemon opens the bus, then the replayer: a log gone in between is the same one line
    (a UserError that stops the daemon), not a thread's traceback."""
    with pytest.raises(UserError, match=r"can.replay.log: cannot read .*gone\.log"):
        LogReplayer(tmp_path / "gone.log", f"t{os.getpid()}", 1.0, 0.0)


def test_replay_older_than_the_restored_checkpoint_sends_nothing_and_says_so(
    tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    """README row "replay of LOG: all N frames are older than the restored checkpoint, none
    sent": a restarted replay daemon whose state is past the log's end feeds nothing again
    (no sample seen twice) and says why in one WARNING."""
    log = tmp_path / "short.log"
    frames = [
        can.Message(timestamp=100.0 + k, arbitration_id=0x100, is_extended_id=False, data=b"\0" * 8)
        for k in range(20)
    ]
    write_log(log, frames)
    channel = f"t{os.getpid()}-replay-old"
    listener = can.Bus(interface="virtual", channel=channel)
    try:
        with caplog.at_level(logging.INFO, logger="bmsid"):
            replayer = LogReplayer(log, channel, 1000.0, 0.0, resume_after_s=119.0)
            replayer.start()
            assert replayer.done.wait(10)
            replayer.stop()
        assert listener.recv(0.2) is None  # nothing sent
    finally:
        listener.shutdown()
    assert (replayer.sent, replayer.skipped) == (0, 20)
    lines = [r for r in caplog.records if "replay of" in r.getMessage()]
    assert len(lines) == 1 and lines[0].levelno == logging.WARNING
    said = lines[0].getMessage()
    assert said.startswith(f"replay of {log}: all 20 frames are older than the restored checkpoint")
    assert "none sent" in said


def _mqtt_config(tmp_path: Path, mqtt: str, mode: int) -> Path:
    config = tmp_path / "bmsid.toml"
    config.write_text(
        'pack_id = "p"\n[can]\nn_cells = 2\n[mqtt]\nurl = "mqtt://127.0.0.1:1883"\n'
        f'username = "bmsid"\n{mqtt}\n',
        encoding="utf-8",
    )
    config.chmod(mode)
    return config


@pytest.mark.parametrize(("mode", "warned"), [(0o644, True), (0o640, False), (0o600, False)])
def test_config_holding_a_password_readable_by_all_gets_one_warning(
    tmp_path: Path, mode: int, warned: bool, capsys: pytest.CaptureFixture[str]
) -> None:
    config = _mqtt_config(tmp_path, 'password = "s3cret"', mode)
    assert main(["check-config", str(config)]) == 0
    out = capsys.readouterr().out
    warnings = [line for line in out.splitlines() if line.startswith("# WARNING")]
    assert "s3cret" not in out
    if warned:
        assert warnings == [
            f"# WARNING: config {config} holds mqtt.password and every user can read it "
            f"(mode 0644): chmod o-r {config}, or move the password to mqtt.password_file "
            "(mode 600)"
        ]
    else:
        assert warnings == []


def test_world_readable_config_without_a_secret_is_fine(tmp_path: Path) -> None:
    """/etc/bmsid/bmsid.toml is world-readable by design when it holds no secret."""
    config = _mqtt_config(tmp_path, "", 0o644)
    assert secret_file_warnings(config, load_settings(config)) == []


@pytest.mark.parametrize(("mode", "warned"), [(0o644, True), (0o600, False)])
def test_password_file_readable_by_all_gets_one_warning(
    tmp_path: Path, mode: int, warned: bool, capsys: pytest.CaptureFixture[str]
) -> None:
    pw = tmp_path / "mqtt.password"
    pw.write_text("s3cret\n")
    pw.chmod(mode)
    config = _mqtt_config(tmp_path, f'password_file = "{pw}"', 0o644)
    assert main(["check-config", str(config)]) == 0
    out = capsys.readouterr().out
    warnings = [line for line in out.splitlines() if line.startswith("# WARNING")]
    assert "s3cret" not in out
    expected = [f"# WARNING: mqtt.password_file {pw} is readable by every user (mode 0644): "
                f"chmod 600 {pw}"]  # fmt: skip
    assert warnings == (expected if warned else [])


def test_run_logs_the_permission_warning_before_it_starts(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, caplog: pytest.LogCaptureFixture
) -> None:
    """`bmsid run` gives the same line as a WARNING in the journal (the daemon still starts:
    the password works, it is just no longer a secret)."""
    pw = tmp_path / "mqtt.password"
    pw.write_text("s3cret\n")
    pw.chmod(0o604)
    config = _mqtt_config(tmp_path, f'password_file = "{pw}"', 0o600)
    started: list[object] = []

    def run_daemon(settings: object) -> int:
        started.append(settings)
        return 0

    monkeypatch.setattr("bmsid.daemon.core.run_daemon", run_daemon)
    assert main(["run", "--config", str(config)]) == 0
    warnings = [r for r in caplog.records if r.levelname == "WARNING"]
    assert [r.getMessage() for r in warnings] == [
        f"mqtt.password_file {pw} is readable by every user (mode 0604): chmod 600 {pw}"
    ]
    assert len(started) == 1


def test_an_os_error_is_one_line_with_the_file(
    monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str], tmp_path: Path
) -> None:
    """A file the system refuses where no command checked it: the reason and the file."""

    def refuse(args: object) -> int:
        raise PermissionError(13, "Permission denied", str(tmp_path / "x"))

    config = _mqtt_config(tmp_path, "", 0o600)
    monkeypatch.setattr(bmsid.cli.check_config, "run", refuse)
    assert main(["check-config", str(config)]) == 1
    assert _one_line(capsys.readouterr().err) == (
        f"bmsid check-config: error: Permission denied: {tmp_path / 'x'}"
    )


def test_an_internal_error_is_one_line_with_its_place(
    monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str], tmp_path: Path
) -> None:
    """A bug: one line to quote in a report (type, message, file:line), the traceback only
    with -vv."""

    def broken(args: object) -> int:
        return 1 // 0

    config = _mqtt_config(tmp_path, "", 0o600)
    monkeypatch.setattr(bmsid.cli.check_config, "run", broken)
    assert main(["check-config", str(config)]) == 1
    line = _one_line(capsys.readouterr().err)
    assert line.startswith("bmsid check-config: internal error: ZeroDivisionError: ")
    assert "test_cli_edges.py:" in line and "-vv logs the traceback" in line
    assert main(["check-config", str(config), "-vv"]) == 1
    assert "Traceback" in capsys.readouterr().err


@pytest.mark.parametrize(
    ("option", "value", "says"),
    [
        ("--t0", "nan", "--t0 must be a Unix time"),
        ("--t0", "1e30", "--t0 must be a Unix time"),
        ("--t0", "-5", "--t0 must be a Unix time"),
        ("--channel", "", "--channel must be an interface name"),
        ("--channel", "can 0", "--channel must be an interface name"),
    ],
)
def test_make_log_refuses_values_that_would_write_an_unreadable_log(
    option: str, value: str, says: str, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """Found by fuzzing: `make-log --t0 nan` wrote "(nan) can0 ..." lines and said "wrote"."""
    csv = tmp_path / "in.csv"
    csv.write_text("t_s,current_A,voltage_V\n0,1,3.7\n1,1,3.69\n")
    out = tmp_path / "x.log"
    assert main(["make-log", str(csv), "--out", str(out), option, value]) == 2
    assert says in _one_line(capsys.readouterr().err)
    assert not out.exists()
