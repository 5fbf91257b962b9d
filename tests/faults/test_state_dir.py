"""Faults of the state directory (issue 16, cases 3 and 5): each leaves the daemon starting
fresh or refusing with one line, never a traceback, and no MQTT ``seq`` published twice.

Runs in ~15 s: the checkpoint cases drive the bank host directly (what the daemon's worker
runs at start); the refusals run ``bmsid run`` as a gateway does (a few seconds each).
"""

from __future__ import annotations

import contextlib
import json
import logging
import os
import subprocess
import sys
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any, NoReturn

import jsonschema
import numpy as np
import pytest

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "daemon"))
from daemon_helpers import SCHEMA_DIR, drive_samples, make_settings

from bmsid.cli.main import main
from bmsid.config.cell import paper_cell
from bmsid.daemon import bank_worker
from bmsid.daemon.bank_worker import BankHost, BankSpec
from bmsid.daemon.checkpoint import CheckpointKey, save_checkpoint
from bmsid.daemon.core import Daemon
from bmsid.daemon.statedir import StateLock, remove_stale_temps
from bmsid.errors import UserError
from bmsid.estimate.tuning import EstimatorTuning
from bmsid.publish.outbox import Outbox, OutMessage, encode_spool
from bmsid.publish.payloads import HEALTH_STATE_DIR
from bmsid.samples import SampleBlock

REPO = Path(__file__).resolve().parents[2]
N_CELLS = 4


def _spec(state: Path, **kw: Any) -> BankSpec:
    base: dict[str, Any] = {
        "cell": paper_cell(),
        "n_cells": N_CELLS,
        "variant": "hy-affrls",
        "tuning": EstimatorTuning(),
        "soc0": 0.8,
        "restore": True,
        "ckpt_path": state / "p.ckpt.npz",
        "ckpt_key": CheckpointKey("p", N_CELLS, "h"),
        "pack_id": "p",
        "topic_prefix": "bmsid",
        "mqtt_enabled": True,
        "qos": 1,
        "publish_period_s": 0.0,
    }
    return BankSpec(**(base | kw))


def _samples(t0: float, n: int) -> SampleBlock:
    return drive_samples(t0, n, N_CELLS)


def _seqs(messages: list[Any]) -> list[int]:
    return [json.loads(m.payload)["seq"] for m in messages]


def _warnings(caplog: pytest.LogCaptureFixture) -> list[str]:
    return [r.getMessage() for r in caplog.records if r.levelno >= logging.WARNING]


def _ran_and_checkpointed(state: Path) -> BankHost:
    host = BankHost(_spec(state))
    host.start()
    host.update(_samples(0.0, 30))
    host.checkpoint(clean=True)
    return host


def _assert_quarantined(state: Path, caplog: pytest.LogCaptureFixture, why: str) -> Path:
    """The checkpoint moved aside with one WARNING line naming why and where it went."""
    moved = sorted(state.glob("p.ckpt.npz.bad-*"))
    assert len(moved) == 1, sorted(p.name for p in state.iterdir())
    assert not (state / "p.ckpt.npz").exists()
    lines = _warnings(caplog)
    assert len(lines) == 1, lines
    assert why in lines[0] and moved[0].name in lines[0] and "starting fresh" in lines[0]
    return moved[0]


def _rewrite_checkpoint(state: Path, change: Callable[[dict[str, Any]], None]) -> None:
    """Load the checkpoint's arrays, ``change`` them, save them again under the same key."""
    path = state / "p.ckpt.npz"
    with np.load(path, allow_pickle=False) as npz:
        header = json.loads(str(npz["__header__"]))
        scalars = json.loads(str(npz["__scalars__"]))
        flat = {k: npz[k] for k in npz.files if not k.startswith("__")}
    change(flat)
    state_dict: dict[str, Any] = {}
    for key, value in {**flat, **scalars}.items():
        *parents, leaf = key.split("/")
        node = state_dict
        for p in parents:
            node = node.setdefault(p, {})
        node[leaf] = value
    save_checkpoint(path, CheckpointKey("p", N_CELLS, "h"), state_dict, header["extra"])


def test_zero_byte_checkpoint_is_moved_aside_and_the_start_is_fresh(
    tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    (tmp_path / "p.ckpt.npz").write_bytes(b"")
    with caplog.at_level(logging.WARNING):
        info = BankHost(_spec(tmp_path)).start()  # raised EOFError at every start before
    assert not info.restored and info.seq == 0
    moved = _assert_quarantined(tmp_path, caplog, "unreadable")
    assert moved.read_bytes() == b""  # kept for a post-mortem, as it was


def test_truncated_checkpoint_is_moved_aside_and_seq_continues(
    tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    before = _ran_and_checkpointed(tmp_path)
    path = tmp_path / "p.ckpt.npz"
    path.write_bytes(path.read_bytes()[: path.stat().st_size // 2])
    with caplog.at_level(logging.WARNING):
        info = BankHost(_spec(tmp_path)).start()
    assert not info.restored
    assert info.seq == before.seq  # the numbering does not depend on the checkpoint
    _assert_quarantined(tmp_path, caplog, "unreadable")


def test_nan_checkpoint_is_moved_aside_not_restored(
    tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    before = _ran_and_checkpointed(tmp_path)

    def poison(flat: dict[str, Any]) -> None:
        flat["params/R0"] = np.full_like(flat["params/R0"], np.nan)

    _rewrite_checkpoint(tmp_path, poison)
    with caplog.at_level(logging.WARNING):
        host = BankHost(_spec(tmp_path))
        info = host.start()
    assert not info.restored and info.seq == before.seq
    _assert_quarantined(tmp_path, caplog, "non-finite values in params/R0")
    # the fresh state publishes numbers, not nulls, and nothing invented: seq continues
    messages = host.update(_samples(100.0, 5)).messages
    assert _seqs(messages) == list(range(before.seq, before.seq + 5 * (N_CELLS + 1)))
    assert json.loads(messages[0].payload)["R0_ohm"] is not None


def test_inconsistent_checkpoint_is_moved_aside(
    tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    _ran_and_checkpointed(tmp_path)

    def drop_a_cell(flat: dict[str, Any]) -> None:
        flat["params/R0"] = flat["params/R0"][:-1]

    _rewrite_checkpoint(tmp_path, drop_a_cell)
    with caplog.at_level(logging.WARNING):
        info = BankHost(_spec(tmp_path)).start()
    assert not info.restored
    _assert_quarantined(tmp_path, caplog, "inconsistent")


def test_checkpoint_of_another_setup_is_one_line_kept_and_the_start_is_fresh(
    tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    """README row "checkpoint ... is for another setup (...): starting fresh": a changed config
    starts fresh with one WARNING, leaves the file as it was (restoring the old config before
    the next checkpoint keeps the state) and continues the numbering."""
    before = _ran_and_checkpointed(tmp_path)
    path = tmp_path / "p.ckpt.npz"
    kept = path.read_bytes()
    changed = _spec(tmp_path, ckpt_key=CheckpointKey("p", N_CELLS, "another tuning"))
    with caplog.at_level(logging.WARNING):
        info = BankHost(changed).start()
    assert not info.restored and info.seq == before.seq
    lines = _warnings(caplog)
    assert len(lines) == 1, lines
    assert lines[0] == (
        f"checkpoint {path} is for another setup (estimator.variant, estimator.tuning or the "
        "cell config changed): starting fresh"
    )
    assert path.read_bytes() == kept and not list(tmp_path.glob("*.bad-*"))
    back = BankHost(_spec(tmp_path)).start()  # the old config again: its state is there
    assert back.restored and back.seq == before.seq


def test_a_nan_state_is_never_checkpointed(
    tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    host = _ran_and_checkpointed(tmp_path)
    good = (tmp_path / "p.ckpt.npz").read_bytes()
    state = host.bank.state_dict()
    state["params"]["R0"][:] = np.nan  # a lost state, however it came about
    host.bank.load_state_dict(state)
    with caplog.at_level(logging.WARNING):
        counters = host.checkpoint()
        host.checkpoint()
    assert (tmp_path / "p.ckpt.npz").read_bytes() == good  # the last good one is kept
    assert counters["checkpoints_refused"] == 1 and host.counters["checkpoints_refused"] == 2
    lines = _warnings(caplog)
    assert len(lines) == 1 and "params/R0" in lines[0], lines  # not one per checkpoint
    assert BankHost(_spec(tmp_path)).start().restored


@contextlib.contextmanager
def _read_only(path: Path, missing: Callable[[str], NoReturn]) -> Iterator[None]:
    """``path`` read-only for this process: chmod for a user, a read-only bind mount for
    root (whom permissions do not stop); EROFS then, as on a file system remounted ro."""
    if os.geteuid() != 0:
        path.chmod(0o555)
        try:
            yield
        finally:
            path.chmod(0o755)
        return
    cmd = ["mount", "--bind", "-o", "ro", str(path), str(path)]
    done = subprocess.run(cmd, capture_output=True, text=True, check=False, timeout=30)
    if done.returncode != 0:
        missing(f"a read-only directory: {' '.join(cmd)} failed: {done.stderr.strip()}")
    try:
        yield
    finally:
        subprocess.run(["umount", str(path)], check=True, timeout=30)


def test_state_dir_read_only_mid_run_never_publishes_a_seq_twice(
    tmp_path: Path,
    caplog: pytest.LogCaptureFixture,
    monkeypatch: pytest.MonkeyPatch,
    real_part_missing: Callable[[str], NoReturn],
) -> None:
    # Small blocks, so that reservations fall due within the test (normally 100,000).
    monkeypatch.setattr(bank_worker, "SEQ_BLOCK", 40)
    published: list[int] = []
    first = BankHost(_spec(tmp_path))
    first.start()
    published += _seqs(first.update(_samples(0.0, 10)).messages)
    withheld = 0
    with _read_only(tmp_path, real_part_missing), caplog.at_level(logging.WARNING):
        more = first.update(_samples(10.0, 20))  # its reservation falls due and fails
        published += _seqs(more.messages)
        withheld += more.counters["mqtt_withheld"]
        assert withheld > 0 and more.counters["seq_file_errors"] >= 1
        # crash, then two restarts on the read-only directory
        for k in range(2):
            host = BankHost(_spec(tmp_path))
            host.start()
            out = host.update(_samples(100.0 * (k + 1), 10))
            published += _seqs(out.messages)
            withheld += out.counters["mqtt_withheld"]
    assert len(published) == len(set(published)), "a seq was published twice"
    assert withheld >= 2 * 10 * (N_CELLS + 1)  # the restarts published nothing unreserved
    errors = [r.getMessage() for r in caplog.records if r.levelno >= logging.ERROR]
    assert errors and all("withheld" in e for e in errors)
    # writable again: the numbering resumes above everything published
    again = BankHost(_spec(tmp_path))
    again.start()
    after = _seqs(again.update(_samples(400.0, 5)).messages)
    assert min(after) > max(published)


def _config(tmp_path: Path, state: Path, port: int) -> Path:
    path = tmp_path / "bmsid.toml"
    path.write_text(
        f"""pack_id = "faultpack"
systemd_notify = false
[can]
interface = "virtual"
channel = "statedir-{tmp_path.name}"
n_cells = 8
[mqtt]
url = "mqtt://127.0.0.1:{port}"
[state]
directory = "{state}"
""",
        encoding="utf-8",
    )
    return path


def _bmsid(*args: str) -> subprocess.CompletedProcess[str]:
    env = {**os.environ, "PYTHONPATH": str(REPO / "service")}
    return subprocess.run(
        [sys.executable, "-m", "bmsid.cli.main", *args],
        capture_output=True,
        text=True,
        env=env,
        timeout=60,
        check=False,
    )


def test_read_only_state_dir_refuses_every_start_with_one_line(
    tmp_path: Path,
    mosquitto_broker: Any,
    require_tool: Callable[[str], str],
    real_part_missing: Callable[[str], NoReturn],
) -> None:
    state = tmp_path / "state"
    state.mkdir()
    sub = tmp_path / "sub.txt"
    with sub.open("wb") as fh:
        watcher = subprocess.Popen(
            [require_tool("mosquitto_sub"), "-p", str(mosquitto_broker.port), "-t", "bmsid/#"],
            stdout=fh,
            stderr=subprocess.STDOUT,
        )
    try:
        with _read_only(state, real_part_missing):
            config = _config(tmp_path, state, mosquitto_broker.port)
            runs = [_bmsid("run", "--config", str(config)) for _ in range(2)]
    finally:
        watcher.terminate()
        watcher.wait(10)
    for done in runs:
        assert done.returncode == 2, done.stderr
        lines = done.stderr.strip().splitlines()
        assert len(lines) == 1, done.stderr  # one line, no traceback
        assert "state.directory" in lines[0] and "not writable" in lines[0]
        assert "Read-only file system" in lines[0] or "Permission denied" in lines[0]
    assert sub.read_bytes() == b""  # nothing published, so no seq published twice


def test_check_config_reports_a_read_only_state_dir(
    tmp_path: Path,
    capsys: pytest.CaptureFixture[str],
    real_part_missing: Callable[[str], NoReturn],
) -> None:
    state = tmp_path / "state"
    state.mkdir()
    config = _config(tmp_path, state, 1883)
    assert main(["check-config", str(config)]) == 0
    capsys.readouterr()
    with _read_only(state, real_part_missing):
        code = main(["check-config", str(config)])
    err = capsys.readouterr().err.strip().splitlines()
    assert code == 2
    assert len(err) == 1 and "state.directory" in err[0] and str(state) in err[0], err


def test_second_daemon_on_the_same_state_dir_refuses_with_one_line(tmp_path: Path) -> None:
    state = tmp_path / "state"
    state.mkdir()
    config = _config(tmp_path, state, 1)
    held = StateLock.acquire(state, "faultpack")  # the first daemon (this process)
    try:
        done = _bmsid("run", "--config", str(config))
    finally:
        held.release()
    assert done.returncode == 2, done.stderr
    lines = done.stderr.strip().splitlines()
    assert len(lines) == 1, done.stderr
    assert f"another bmsid (pid {os.getpid()})" in lines[0] and "faultpack" in lines[0]
    assert not (state / "faultpack.seq").exists()  # it touched nothing
    # once released, the lock is free (a daemon killed with SIGKILL releases it too)
    StateLock.acquire(state, "faultpack").release()


# ------------------------------------------------------------------ the sequence file
def test_unreadable_seq_file_refuses_the_start_with_one_line(tmp_path: Path) -> None:
    state = tmp_path / "state"
    state.mkdir()
    seq = state / "faultpack.seq"
    seq.write_bytes(b"12\x00garbage\n")  # torn by hand or a disk error: no number
    done = _bmsid("run", "--config", str(_config(tmp_path, state, 1)))
    assert done.returncode == 2, done.stderr
    # the lifecycle's INFO lines (the start), then one line, no traceback, nothing else said
    *info, refusal = done.stderr.strip().splitlines()
    assert all(" INFO " in line for line in info), done.stderr
    assert refusal.startswith("bmsid run: error: ") and "Traceback" not in done.stderr
    assert f"sequence file {seq} is unreadable" in refusal and "not a number" in refusal
    assert seq.read_bytes() == b"12\x00garbage\n"  # left for the operator, not overwritten
    assert not (state / "faultpack.ckpt.npz").exists()  # nothing ran


def test_removed_seq_file_restarts_numbering_from_the_checkpoint(tmp_path: Path) -> None:
    """README row "sequence file ... is unreadable": removing the file is the other way out;
    numbering restarts from the checkpoint's ``seq``, never below it."""
    host = _ran_and_checkpointed(tmp_path)
    host.update(_samples(30.0, 3))  # published after the checkpoint: these may be reused
    host.checkpoint(clean=False)
    after_ckpt = host.seq
    host.update(_samples(33.0, 3))
    (tmp_path / "p.seq").unlink()
    info = BankHost(_spec(tmp_path)).start()
    assert info.restored and info.seq == after_ckpt < host.seq


def test_seq_file_the_system_cannot_read_refuses_the_start(tmp_path: Path) -> None:
    (tmp_path / "p.seq").mkdir()  # read(2) fails (EISDIR), as on an I/O error
    with pytest.raises(UserError) as refused:
        BankHost(_spec(tmp_path)).start()
    text = str(refused.value)
    assert "\n" not in text
    assert f"sequence file {tmp_path / 'p.seq'} is unreadable (Is a directory)" in text


# ------------------------------------------------------------------ the MQTT spool
def _spooled(k: int) -> OutMessage:
    return OutMessage(f"bmsid/faultpack/cell/{k % 8}", b'{"seq":%d}' % k, 1)


def test_damaged_spool_is_quarantined_its_readable_part_kept_and_the_rest_counted(
    tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    settings = make_settings(tmp_path, 1)
    daemon = Daemon(settings)
    spool = daemon.spool_path
    spool.parent.mkdir(parents=True)
    sent = [_spooled(k) for k in range(10)]
    lines = encode_spool(settings.pack_id, sent).splitlines(keepends=True)
    lines[5] = lines[5][: len(lines[5]) // 2] + b"\n"  # message 4 torn, 5..9 behind it
    spool.write_bytes(b"".join(lines))
    box = Outbox(100)
    with caplog.at_level(logging.WARNING):
        daemon._load_spool(box)
    # nothing lost that could be read, nothing invented, the rest counted
    assert [(m.topic, m.payload) for m in box.peek(100)] == [(m.topic, m.payload) for m in sent[:4]]
    assert box.dropped == 6  # mqtt_drops: the seq gap 4..9 a subscriber will see
    moved = sorted(spool.parent.glob("testpack.spool.bad-*"))
    assert len(moved) == 1 and moved[0].read_bytes() == b"".join(lines)  # for a post-mortem
    warned = _warnings(caplog)
    assert len(warned) == 1, warned
    assert "line 6 is damaged" in warned[0] and "4 messages recovered, 6 lost" in warned[0]
    # the readable part is spooled again until delivered: a crash now loses nothing more
    again = Outbox(100)
    Daemon(settings)._load_spool(again)
    assert len(again) == 4 and again.dropped == 6
    daemon.outbox = box
    box.pop(4)  # delivered
    daemon._on_published(sent[3])
    assert not spool.exists()


# ------------------------------------------------------------------ failures during a run
def test_state_dir_failing_mid_run_shows_in_health_and_status(
    tmp_path: Path,
    monkeypatch: pytest.MonkeyPatch,
    real_part_missing: Callable[[str], NoReturn],
) -> None:
    monkeypatch.setattr(bank_worker, "SEQ_BLOCK", 40)  # a reservation falls due in the test
    pack_schema = json.loads((SCHEMA_DIR / "pack.json").read_text())
    status_schema = json.loads((SCHEMA_DIR / "status.json").read_text())

    def health(messages: list[Any]) -> list[int]:
        out = [json.loads(m.payload) for m in messages if m.topic.endswith("/pack")]
        for body in out:
            jsonschema.validate(body, pack_schema)
        return [body["health"] & HEALTH_STATE_DIR for body in out]

    host = BankHost(_spec(tmp_path))
    host.start()
    ok = host.update(_samples(0.0, 3))
    assert health(ok.messages) == [0, 0, 0] and ok.counters["state_dir_failing"] == 0
    with _read_only(tmp_path, real_part_missing):
        failed = host.checkpoint()
        after_ckpt = host.update(_samples(3.0, 3))  # within the reserved seq block
        withheld = host.update(_samples(6.0, 10))  # the next reservation fails too
    assert failed["checkpoint_errors"] == 1 and failed["state_dir_failing"] == 1
    assert health(after_ckpt.messages) == [HEALTH_STATE_DIR] * 3
    assert withheld.counters["mqtt_withheld"] > 0 and withheld.counters["state_dir_failing"] == 1
    # the daemon's view: CAN health and the retained status say so, not only the counters
    daemon = Daemon(make_settings(tmp_path / "d", 1))
    assert json.loads(daemon._online_payload())["state_dir"] == "ok"
    daemon._merge_bank_counters(withheld.counters)
    assert after_ckpt.estimates
    est = after_ckpt.estimates[-1]
    assert daemon._health(est) & HEALTH_STATE_DIR
    status = json.loads(daemon._online_payload())
    jsonschema.validate(status, status_schema)
    assert status["state_dir"] == "failing"
    summary, state = (
        daemon.encoder.decode(f) for f in daemon.encoder.pack_frames(est, daemon._health(est))
    )
    assert summary is not None and summary["health"] == daemon._health(est) & 31  # no room for 32
    assert state is not None and state["health"] == daemon._health(est)  # PackState carries it
    # writable again: the next reservation and checkpoint clear it
    resumed = host.update(_samples(16.0, 3))
    assert resumed.messages and resumed.counters["state_dir_failing"] == 1  # checkpoint pending
    cleared = host.checkpoint()
    assert cleared["state_dir_failing"] == 0
    assert health(host.update(_samples(19.0, 2)).messages) == [0, 0]
    daemon._merge_bank_counters(cleared)
    assert not daemon._health(est) & HEALTH_STATE_DIR
    assert json.loads(daemon._online_payload())["state_dir"] == "ok"


def test_temp_files_of_a_killed_writer_are_removed_at_the_next_start(tmp_path: Path) -> None:
    # A worker killed mid-write (with its daemon) leaves atomic_write's temp file behind.
    settings = make_settings(tmp_path, None)
    state = settings.state.directory
    state.mkdir()
    daemon = Daemon(settings)
    left = [state / f".{p.name}.4242.tmp" for p in daemon._state_files()]
    other = [state / ".testpack.seq.seq.4242.tmp", state / ".testpack.seq.x.tmp"]
    for path in left + other:  # another pack's ("testpack.seq"), a name not atomic_write's
        path.write_bytes(b"torn")
    assert remove_stale_temps(state, (p.name for p in daemon._state_files())) == 3
    assert sorted(p.name for p in state.iterdir()) == sorted(p.name for p in other)
