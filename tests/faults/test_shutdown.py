"""Faults at shutdown (issue 16, cases 4 and 7): a stop against a broker that is away or
refuses the login makes a few connection attempts within a time limit and spools its backlog;
SIGHUP is ignored; SIGKILL leaves no semaphore, no process, and no seq reused.

Runs in ~60 s on 2 busy cores: two in-process daemons per broker case, two daemon processes
for the signal cases (each starts a worker process that imports the estimator stack).
"""

from __future__ import annotations

import asyncio
import errno
import gc
import io
import json
import logging
import os
import signal
import subprocess
import sys
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import pytest

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "daemon"))
from daemon_helpers import (
    MqttCapture,
    demo_frames,
    make_settings,
    run_with_frames,
    send_virtual,
    start_daemon,
    wait_for,
)

from bmsid.config.settings import Settings
from bmsid.daemon.core import Daemon
from bmsid.daemon.demo_data import DEMO_LOG, T0_S
from bmsid.publish import outbox
from bmsid.publish.outbox import Outbox, OutMessage
from conftest import free_loopback_port

REPO = Path(__file__).resolve().parents[2]
#: The shutdown's time limit for the MQTT flush in these tests, s (the daemon's default is 10).
STOP_S = 3.0
#: Connection attempts the backoff (0.5 s doubling) places within STOP_S, plus the one under way.
FEW_ATTEMPTS = 4


def _settings(tmp_path: Path, port: int, **mqtt: Any) -> Settings:
    # The shipped backoff (0.5 s doubling to 30 s), not the tests' usual 0.1-0.5 s.
    return make_settings(
        tmp_path,
        port,
        estimator={"isolation": "thread"},
        mqtt={"reconnect_min_s": 0.5, "reconnect_max_s": 30.0, **mqtt},
    )


def _attempts(daemon: Daemon) -> int:
    assert daemon.mqtt is not None
    return daemon.mqtt.counters["connects"] + daemon.mqtt.counters["connect_failures"]


async def _run_then_stop(daemon: Daemon, frames: list[Any], hold_s: float) -> tuple[int, float]:
    """Feed ``frames``, wait until they are processed and ``hold_s`` more, stop; returns the
    connection attempts made during the stop and how long the stop took, s."""
    task = asyncio.create_task(daemon.run())
    await wait_for(lambda: daemon.can_state == "up" or task.done(), 30, "the bus")
    sender = send_virtual(daemon.settings.can.channel, frames)
    n = len(frames)

    def processed() -> bool:
        q = daemon._samples
        return task.done() or (
            not sender.is_alive()
            and daemon.f2s.counters["frames"] >= n
            and q is not None
            and q.empty()
            and daemon.counters["batches_in_flight"] == 0
        )

    await wait_for(processed, 120, "the frames to be processed")
    await asyncio.sleep(hold_s)
    before = _attempts(daemon)
    t0 = time.monotonic()
    daemon.request_stop()
    assert await asyncio.wait_for(task, 60) == 0
    return _attempts(daemon) - before, time.monotonic() - t0


def _data_seqs(cap: MqttCapture) -> list[int]:
    return [p["seq"] for t, p in cap.messages() if "/cell/" in t or t.endswith("/pack")]


def test_sigterm_while_broker_down_spools_and_restart_delivers_every_seq(
    tmp_path: Path,
    mosquitto_factory: Any,
    require_tool: Callable[[str], str],
    caplog: pytest.LogCaptureFixture,
) -> None:
    port = free_loopback_port()  # nothing listens there yet: the broker is down
    settings = _settings(tmp_path, port)
    frames = demo_frames(240)
    half = next(k for k, m in enumerate(frames) if m.timestamp - frames[0].timestamp >= 120)
    spool = tmp_path / "state" / "testpack.spool"

    first = Daemon(settings, shutdown_timeout_s=STOP_S)
    with caplog.at_level(logging.INFO):
        attempts, took_s = asyncio.run(_run_then_stop(first, frames[:half], 1.0))
    assert first.outbox is not None and first.seq > 0
    backlog = len(first.outbox)
    assert backlog == first.seq  # nothing was delivered: every message is in the backlog
    assert attempts <= FEW_ATTEMPTS, attempts  # was 43,167 in 10 s
    assert took_s < STOP_S + 2.0
    assert spool.exists()
    assert [m for m in caplog.messages if "spooled to" in m] == [
        f"MQTT: {backlog} messages not delivered at shutdown (connection refused by 127.0.0.1:"
        f"{port}: is the broker running on that port?): spooled to {spool}, sent first after "
        "the restart"
    ]

    broker = mosquitto_factory(port=port)  # the broker is back
    cap = MqttCapture(require_tool("mosquitto_sub"), broker.port, tmp_path / "sub.txt")
    try:
        cap.wait_ready(require_tool("mosquitto_pub"), broker.port)
        second = Daemon(settings, shutdown_timeout_s=STOP_S)
        asyncio.run(run_with_frames(second, frames[half:]))
        time.sleep(0.5)  # the subscriber's last messages
    finally:
        cap.stop()
    seqs = _data_seqs(cap)
    assert seqs == list(range(second.seq))  # every seq, once, in order: the spooled first
    assert second.seq > backlog
    assert second.outbox is not None and second.outbox.dropped == 0  # mqtt_drops
    assert not spool.exists()  # delivered, so not sent again after the next start
    gc.collect()  # a task whose exception nobody retrieved is reported when collected
    assert not [r for r in caplog.records if r.name == "asyncio" and r.levelno >= logging.ERROR]


def test_wrong_password_at_shutdown_makes_few_connects(
    tmp_path: Path,
    mosquitto_factory: Any,
    require_tool: Callable[[str], str],
    caplog: pytest.LogCaptureFixture,
) -> None:
    passwd = tmp_path / "mosquitto.passwd"
    subprocess.run(
        [require_tool("mosquitto_passwd"), "-b", "-c", str(passwd), "bmsid", "right"],
        check=True,
        timeout=20,
    )
    passwd.chmod(0o600)
    broker = mosquitto_factory(f"allow_anonymous false\npassword_file {passwd}\n")
    settings = _settings(tmp_path, broker.port, username="bmsid", password="wrong")
    daemon = Daemon(settings, shutdown_timeout_s=STOP_S)
    with caplog.at_level(logging.INFO):
        during_stop, took_s = asyncio.run(_run_then_stop(daemon, demo_frames(60), 2.0))
    assert daemon.mqtt is not None and "not authorised" in (daemon.mqtt.last_error or "")
    # one quick retry, then reconnect_max_s (30 s): the stop adds none within 3 s
    assert during_stop == 0 and took_s < STOP_S + 2.0
    assert _attempts(daemon) <= 2
    refused = broker.log_text().count("not authorised")
    assert 1 <= refused <= 2, broker.log_text()[-2000:]  # the broker's count agrees (was 18,269)
    spool = tmp_path / "state" / "testpack.spool"
    lines = spool.read_text().splitlines()
    assert json.loads(lines[0])["messages"] == daemon.seq == len(lines) - 1  # all kept


# ------------------------------------------------------------------ a spool too large
def _disk_that_takes(limit_bytes: int, monkeypatch: pytest.MonkeyPatch) -> None:
    """The state directory takes files up to ``limit_bytes`` (a full disk, a quota); larger
    ones fail with ENOSPC (0: every write fails with EROFS, a file system gone read-only)."""
    real = outbox.atomic_write

    def write(path: Path, fill: Callable[[Any], object]) -> None:
        buf = io.BytesIO()
        fill(buf)
        if limit_bytes == 0:
            raise OSError(errno.EROFS, os.strerror(errno.EROFS), str(path))
        if len(buf.getvalue()) > limit_bytes:
            raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC), str(path))
        real(path, fill)

    monkeypatch.setattr(outbox, "atomic_write", write)


def _stopped_with_backlog(tmp_path: Path, n: int) -> tuple[Settings, Daemon]:
    """A daemon at the end of its stop, ``n`` messages left that the flush could not deliver."""
    settings = make_settings(tmp_path, 1)
    settings.state.directory.mkdir()
    daemon = Daemon(settings)
    daemon.outbox = Outbox(1000)
    for k in range(n):
        daemon.outbox.put(OutMessage(f"bmsid/testpack/cell/{k % 8}", b'{"seq":%d}' % k))
    return settings, daemon


def _errors(caplog: pytest.LogCaptureFixture) -> list[str]:
    return [r.getMessage() for r in caplog.records if r.levelno >= logging.ERROR]


def test_spool_too_large_for_the_disk_carries_its_count_to_the_next_start(
    tmp_path: Path, caplog: pytest.LogCaptureFixture, monkeypatch: pytest.MonkeyPatch
) -> None:
    settings, daemon = _stopped_with_backlog(tmp_path, 50)  # a ~1.5 kB spool
    _disk_that_takes(200, monkeypatch)
    with caplog.at_level(logging.WARNING):
        daemon._spool_backlog()
    assert daemon.outbox is not None and daemon.outbox.dropped == 50  # this run's mqtt_drops
    assert _errors(caplog) == [
        "MQTT: 50 messages not delivered at shutdown (no connection) and not spooled (No space "
        "left on device): lost, a seq gap counted in mqtt_drops now and after the restart"
    ]
    caplog.clear()
    box = Outbox(1000)
    with caplog.at_level(logging.WARNING):
        Daemon(settings)._load_spool(box)
    assert box.dropped == 50 and len(box) == 0  # counted, nothing invented
    assert len(caplog.messages) == 1 and "50 messages" in caplog.messages[0], caplog.messages
    assert not daemon.spool_path.exists()  # the start after does not count it again
    again = Outbox(1000)
    Daemon(settings)._load_spool(again)
    assert again.dropped == 0


def test_read_only_state_dir_at_shutdown_says_the_count_is_not_kept(
    tmp_path: Path, caplog: pytest.LogCaptureFixture, monkeypatch: pytest.MonkeyPatch
) -> None:
    _, daemon = _stopped_with_backlog(tmp_path, 50)
    _disk_that_takes(0, monkeypatch)
    with caplog.at_level(logging.WARNING):
        daemon._spool_backlog()
    assert daemon.outbox is not None and daemon.outbox.dropped == 50
    [line] = _errors(caplog)
    assert "50 messages not delivered" in line and "Read-only file system" in line
    assert "counted in mqtt_drops now but not after the restart" in line
    assert not daemon.spool_path.exists()


# ------------------------------------------------------------------ signals, as a gateway runs it
def _config(tmp_path: Path, port: int) -> Path:
    path = tmp_path / "bmsid.toml"
    path.write_text(
        f"""pack_id = "sigpack"
systemd_notify = false
status_period_s = 1.0
[can]
interface = "virtual"
channel = "sig-{tmp_path.name}"
n_cells = 8
[can.replay]
log = "{DEMO_LOG}"
speed = 30.0
start_delay_s = 0.2
[mqtt]
url = "mqtt://127.0.0.1:{port}"
publish_period_s = 0.0
[state]
directory = "{tmp_path / "state"}"
checkpoint_period_s = 1.0
""",
        encoding="utf-8",
    )
    return path


def _group(pgid: int) -> list[int]:
    """Live processes of process group ``pgid``."""
    out = []
    for stat in Path("/proc").glob("[0-9]*/stat"):
        try:
            fields = stat.read_text().rsplit(")", 1)[1].split()
        except OSError:
            continue
        if int(fields[2]) == pgid and fields[0] != "Z":
            out.append(int(stat.parent.name))
    return out


def _semaphores(pids: list[int]) -> set[str]:
    """POSIX semaphores (``/dev/shm/sem.*``) mapped by ``pids``: what a SIGKILL can leak."""
    out = set()
    for pid in pids:
        try:
            maps = Path(f"/proc/{pid}/maps").read_text()
        except OSError:
            continue
        out |= {line.split()[-1] for line in maps.splitlines() if "/dev/shm/sem." in line}
    return out


def _wait(cond: Callable[[], bool], timeout_s: float, what: str, log: Path) -> None:
    deadline = time.monotonic() + timeout_s
    while not cond():
        if time.monotonic() > deadline:
            raise AssertionError(f"timed out waiting for {what}:\n{log.read_text()[-3000:]}")
        time.sleep(0.05)


def test_sighup_is_ignored_and_the_stop_still_checkpoints(
    tmp_path: Path, mosquitto_broker: Any
) -> None:
    config = _config(tmp_path, mosquitto_broker.port)
    log = tmp_path / "daemon.log"
    ckpt = tmp_path / "state" / "sigpack.ckpt.npz"
    proc = start_daemon(config, log, new_session=True)
    try:
        _wait(lambda: ckpt.exists() and len(_group(proc.pid)) >= 2, 60, "a checkpoint", log)
        os.killpg(proc.pid, signal.SIGHUP)  # the daemon and its worker, as a closed terminal
        time.sleep(1.5)
        assert proc.poll() is None, log.read_text()[-3000:]  # SIGHUP used to kill it
        hup_t = time.time()
        os.kill(proc.pid, signal.SIGTERM)
        assert proc.wait(60) == 0
    finally:
        if proc.poll() is None:
            proc.kill()
    text = log.read_text()
    assert text.count("SIGHUP ignored") == 1
    assert ckpt.stat().st_mtime > hup_t  # the stop after it still checkpointed
    assert "stopped:" in text
    assert "Traceback" not in text and "never retrieved" not in text


def test_sigkill_leaks_no_semaphore_or_process_and_never_reuses_a_seq(
    tmp_path: Path, mosquitto_broker: Any, require_tool: Callable[[str], str]
) -> None:
    cap = MqttCapture(require_tool("mosquitto_sub"), mosquitto_broker.port, tmp_path / "sub.txt")
    try:
        cap.wait_ready(require_tool("mosquitto_pub"), mosquitto_broker.port)
        config = _config(tmp_path, mosquitto_broker.port)
        log = tmp_path / "daemon.log"
        proc = start_daemon(config, log, new_session=True)
        _wait(
            lambda: any(p["t_s"] - T0_S >= 240 for _, p in cap.messages() if "t_s" in p),
            90,
            "240 s of data published",
            log,
        )
        group = _group(proc.pid)
        assert len(group) >= 2  # the daemon and its bank worker (and a resource tracker)
        assert _semaphores(group) == set()  # nothing that a SIGKILL could leave in /dev/shm
        os.killpg(proc.pid, signal.SIGKILL)  # systemd's cgroup kill: every process at once
        proc.wait(10)
        _wait(lambda: not _group(proc.pid), 10, "every process of the group to end", log)
        before = _data_seqs(cap)
        second = start_daemon(config, log, new_session=True)
        try:
            _wait(lambda: len(_data_seqs(cap)) > len(before) + 20, 90, "a restart", log)
            os.kill(second.pid, signal.SIGTERM)
            assert second.wait(60) == 0
        finally:
            if second.poll() is None:
                second.kill()
    finally:
        cap.stop()
    after = _data_seqs(cap)[len(before) :]
    assert min(after) > max(before)  # continues above every seq published before the kill
    assert len(set(before + after)) == len(before + after)
    assert "never retrieved" not in log.read_text()


#: Runs ``bmsid run`` as a subreaper (orphans are re-parented to it, so it can read how the
#: bank worker ended), SIGKILLs the daemon alone once it checkpointed, and reports the worker's
#: end: ``{"signal": n or null, "code": n or null, "ckpt_changed": bool}``.
_KILL_DAEMON_ALONE = """
import ctypes, json, os, signal, subprocess, sys, time
from pathlib import Path

config, ckpt = sys.argv[1], Path(sys.argv[2])
ctypes.CDLL(None, use_errno=True).prctl(36, 1, 0, 0, 0)  # PR_SET_CHILD_SUBREAPER
daemon = subprocess.Popen(
    [sys.executable, "-m", "bmsid.cli.main", "run", "--config", config],
    stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL,
)

def worker():
    for stat in Path("/proc").glob("[0-9]*/stat"):
        try:
            ppid = int(stat.read_text().rsplit(")", 1)[1].split()[1])
            cmd = (stat.parent / "cmdline").read_bytes()
        except (OSError, ValueError, IndexError):
            continue
        if ppid == daemon.pid and b"spawn_main" in cmd:
            return int(stat.parent.name)
    return None

deadline = time.monotonic() + 60
while not (ckpt.exists() and worker()) and time.monotonic() < deadline:
    time.sleep(0.05)
pid = worker()
if pid is None:
    sys.exit("no worker and checkpoint within 60 s")
daemon.send_signal(signal.SIGKILL)  # the daemon only, as the OOM killer picks one process
daemon.wait()
seen = ckpt.stat().st_mtime_ns
_, status = os.waitpid(pid, 0)  # re-parented to this subreaper
changed = ckpt.stat().st_mtime_ns != seen
while True:  # the resource tracker, if any, ends with its pipe
    try:
        os.waitpid(-1, 0)
    except ChildProcessError:
        break
print(json.dumps({
    "signal": os.WTERMSIG(status) if os.WIFSIGNALED(status) else None,
    "code": os.WEXITSTATUS(status) if os.WIFEXITED(status) else None,
    "ckpt_changed": changed,
}))
"""


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="PR_SET_PDEATHSIG is Linux's")
def test_worker_dies_with_a_daemon_killed_alone(tmp_path: Path) -> None:
    # The lock died with the daemon: a worker living on (it polled its parent every 0.5 s and
    # exited 0) could write a checkpoint over the one the next daemon restored. The kernel now
    # kills it with its parent, before it runs another instruction.
    config = _config(tmp_path, 1)  # no broker needed: MQTT retries in the background
    env = {**os.environ, "PYTHONPATH": str(REPO / "service")}
    ckpt = tmp_path / "state" / "sigpack.ckpt.npz"
    done = subprocess.run(
        [sys.executable, "-c", _KILL_DAEMON_ALONE, str(config), str(ckpt)],
        capture_output=True,
        text=True,
        env=env,
        cwd=tmp_path,
        timeout=120,
        check=False,
    )
    assert done.returncode == 0, done.stderr
    end = json.loads(done.stdout.strip().splitlines()[-1])
    assert end == {"signal": signal.SIGKILL, "code": None, "ckpt_changed": False}
