"""Checkpoint, payloads, outbox, CAN output schedule, discovery and sd_notify in isolation."""

from __future__ import annotations

import asyncio
import gc
import json
import logging
import os
import socket
from pathlib import Path

import jsonschema
import numpy as np
import pytest
from daemon_helpers import SCHEMA_DIR, make_settings
from hypothesis import given, settings
from hypothesis import strategies as st

from bmsid.config.cell import CellConfig, paper_cell
from bmsid.config.engine import build_bank
from bmsid.config.settings import Settings
from bmsid.daemon.canout import CellCycler, frame_bits, frames_budget, plan_output
from bmsid.daemon.checkpoint import CheckpointKey, load_checkpoint, save_checkpoint
from bmsid.daemon.core import Daemon
from bmsid.daemon.sdnotify import SdNotifier
from bmsid.errors import UserError
from bmsid.estimate.bank import EstimatorBank
from bmsid.estimate.types import Estimates
from bmsid.publish import payloads
from bmsid.publish.discovery import cell_sensor_keys, discovery_messages
from bmsid.publish.outbox import Outbox, OutMessage

KEY = CheckpointKey("p1", 3, "abc")


def _run_bank(bank: EstimatorBank, t: np.ndarray, seed: int = 0) -> list[Estimates]:
    rng = np.random.default_rng(seed)
    out = []
    for tk in t:
        i = 50.0 * np.sin(tk / 7.0) + 20.0 * np.sign(np.sin(tk / 31.0))
        v = 3.7 - 0.002 * i + rng.normal(0, 5e-4, bank.n)
        e = bank.update(float(tk), float(i), v)
        if e is not None:
            out.append(e)
    return out


def test_checkpoint_round_trip_continues_identically(tmp_path: Path) -> None:
    cell = paper_cell()
    a = build_bank(cell, 3)
    _run_bank(a, np.arange(0.0, 400.0))
    path = tmp_path / "c.npz"
    save_checkpoint(path, KEY, a.state_dict(), extra={"seq": 7})
    assert [p.name for p in tmp_path.iterdir()] == ["c.npz"]  # no temp file left behind
    ck = load_checkpoint(path, KEY)
    assert ck is not None and ck.extra["seq"] == 7
    b = build_bank(cell, 3)
    b.load_state_dict(ck.state)
    ea = _run_bank(a, np.arange(400.0, 450.0), seed=1)
    eb = _run_bank(b, np.arange(400.0, 450.0), seed=1)
    for x, y in zip(ea, eb, strict=True):
        np.testing.assert_array_equal(x.soc, y.soc)
        np.testing.assert_array_equal(x.R0_ohm, y.R0_ohm)


@pytest.mark.parametrize(
    "other",
    [CheckpointKey("p2", 3, "abc"), CheckpointKey("p1", 4, "abc"), CheckpointKey("p1", 3, "xyz")],
)
def test_checkpoint_for_another_setup_is_ignored(tmp_path: Path, other: CheckpointKey) -> None:
    path = tmp_path / "c.npz"
    save_checkpoint(path, KEY, {"x": np.arange(3.0), "n": {"y": 1.5, "s": "z"}})
    assert load_checkpoint(path, other) is None
    ck = load_checkpoint(path, KEY)
    assert ck is not None and ck.state["n"] == {"y": 1.5, "s": "z"}


def test_checkpoint_of_another_setup_names_what_differs(
    tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    """One readable line naming the changed parts (it printed both keys as Python dicts, the
    config as a bare hash)."""
    cell = paper_cell()

    def key(s: Settings, c: CellConfig = cell) -> CheckpointKey:
        return CheckpointKey(s.pack_id, s.can.n_cells, s.config_hash(c), s.config_parts(c))

    was = make_settings(tmp_path, None)
    now = make_settings(
        tmp_path, None, can={"n_cells": 4}, estimator={"variant": "hy-affrls", "tuning": {}}
    )
    path = tmp_path / "c.npz"
    save_checkpoint(path, key(was), {"x": np.arange(3.0)})
    other_cell = cell.model_copy(update={"name": "my-cell"})
    with caplog.at_level(logging.WARNING, logger="bmsid.daemon.checkpoint"):
        assert load_checkpoint(path, key(now)) is None
        assert load_checkpoint(path, key(was, other_cell)) is None
        assert load_checkpoint(path, CheckpointKey("p1", was.can.n_cells, "old")) is None
        save_checkpoint(path, KEY, {"x": np.arange(3.0)})  # a header without the parts
        assert load_checkpoint(path, CheckpointKey("p1", 3, "xyz")) is None
    assert [r.getMessage() for r in caplog.records] == [
        f"checkpoint {path} is for another setup (n_cells {was.can.n_cells}, not 4; "
        "estimator.variant 'hy-affrls-lpso', not 'hy-affrls'; estimator.tuning changed): "
        "starting fresh",
        f"checkpoint {path} is for another setup (cell config '{cell.name}', not 'my-cell'): "
        "starting fresh",
        f"checkpoint {path} is for another setup (pack_id 'testpack', not 'p1'): starting fresh",
        f"checkpoint {path} is for another setup (estimator.variant, estimator.tuning or the "
        "cell config changed): starting fresh",
    ]


def test_corrupt_or_missing_checkpoint_starts_fresh(tmp_path: Path) -> None:
    path = tmp_path / "c.npz"
    assert load_checkpoint(path, KEY) is None
    path.write_bytes(b"PK\x03\x04 torn write")
    assert load_checkpoint(path, KEY) is None


def _estimates(n: int, rng: np.random.Generator) -> Estimates:
    def r(lo: float, hi: float) -> np.ndarray:
        return rng.uniform(lo, hi, n)

    v_model, v_meas = r(2.5, 4.2), np.where(rng.random(n) < 0.2, np.nan, r(2.5, 4.2))
    cells = {
        "R0_ohm": r(1e-4, 0.1),
        "R1_ohm": r(1e-4, 0.1),
        "C1_F": r(10, 1e6),
        "R2_ohm": r(1e-4, 0.1),
        "C2_F": r(10, 1e6),
        "tau1_s": r(0.5, 200),
        "tau2_s": r(20, 8000),
        "lambda_": r(0.9, 1.0),
        "h": r(-1, 1),
        "soc": r(0, 1),
        "soc_std": r(0, 0.1),
        "capacity_Ah": r(1, 300),
        "capacity_std_Ah": r(0, 5),
        "current_offset_A": np.full(n, float(rng.uniform(-1, 1))),  # one per pack
        "v_model_V": v_model,
        "v_meas_V": v_meas,
        "v_error_V": v_meas - v_model,
        "M_V": r(0, 0.05),
        "ocv_offset_V": r(-0.1, 0.1),
        "arx_error_V": r(-0.01, 0.01),
    }
    return Estimates(
        t_s=1.7e9 + rng.uniform(0, 1e5),
        current_A=float(rng.uniform(-300, 300)),
        cells=cells,
        quality=rng.integers(0, 5, n).astype(np.int64),
    )


@settings(max_examples=40, deadline=None)
@given(seed=st.integers(0, 2**32 - 1), n=st.integers(1, 12))
def test_payloads_validate_against_published_schemas(seed: int, n: int) -> None:
    schemas = {k: json.loads((SCHEMA_DIR / f"{k}.json").read_text()) for k in ("cell", "pack")}
    e = _estimates(n, np.random.default_rng(seed))
    for i in range(n):
        body = json.loads(payloads.encode(payloads.cell_payload(e, i, "p-1", seq=i)))
        jsonschema.validate(body, schemas["cell"])
        assert body["R0_ohm"] == float(e.R0_ohm[i])
        assert (body["v_meas_V"] is None) == bool(np.isnan(e.v_meas_V[i]))
    pack = json.loads(payloads.encode(payloads.pack_payload(e, "p-1", 5, payloads.health_bits(e))))
    jsonschema.validate(pack, schemas["pack"])
    assert pack["weakest_cell"] == int(np.argmax(e.R0_ohm))
    assert sum(pack["quality_counts"].values()) == n
    assert pack["current_offset_A"] == pytest.approx(float(e.current_offset_A[0]))


def test_status_payloads_validate() -> None:
    schema = json.loads((SCHEMA_DIR / "status.json").read_text())
    jsonschema.validate(payloads.status_payload("offline", "p"), schema)
    online = payloads.status_payload(
        "online",
        "p",
        can_state="up",
        uptime_s=3.0,
        counters={
            "frames": 1,
            "decode_errors": 0,
            "samples": 1,
            "ticks": 1,
            "reader_drops": 0,
            "loop_lag_max_ms": 0.3,
            "seq": 0,
        },
        mqtt={"state": "connected", "last_error": None},
        soc_init="window_fit",
    )
    jsonschema.validate(online, schema)
    with pytest.raises(jsonschema.ValidationError):  # how SOC started is one of the engine's
        jsonschema.validate({**online, "soc_init": "default 50 %"}, schema)
    with pytest.raises(jsonschema.ValidationError):
        jsonschema.validate({**online, "counters": {}}, schema)
    with pytest.raises(jsonschema.ValidationError):
        jsonschema.validate({**online, "mqtt": {"state": "connected"}}, schema)


def test_outbox_keeps_newest_in_order_and_counts_drops() -> None:
    async def main() -> None:
        box = Outbox(3)
        msgs = [OutMessage("t", str(k).encode()) for k in range(5)]
        for m in msgs:
            box.put(m)
        assert box.dropped == 2 and [m.payload for m in box.peek(10)] == [b"2", b"3", b"4"]
        head = box.peek(2)
        box.put(OutMessage("t", b"5"))  # overflow while a batch is in flight
        assert box.remove_delivered(head) == 1  # b"2" was already dropped: only b"3" goes
        assert [m.payload for m in box.peek(10)] == [b"4", b"5"]
        await asyncio.wait_for(box.wait(), 1)

    asyncio.run(main())


def test_can_output_respects_the_bus_share() -> None:
    bits = frame_bits(8, True)
    assert 150 <= bits <= 170
    cyc = plan_output(96, 3, bits, 500_000, 0.05, 0.1)
    assert 1 + 3 * cyc.per_round <= frames_budget(500_000, 0.05, 0.1, bits)
    seen = [c for _ in range(96 // cyc.per_round + 1) for c in cyc.next_round()]
    assert set(seen) == set(range(96))  # every cell goes out within one cycle
    with pytest.raises(UserError, match="max_bus_share"):
        plan_output(96, 3, bits, 125_000, 0.01, 0.05)


def test_cell_cycler_wraps() -> None:
    c = CellCycler(5, 2)
    assert [c.next_round() for _ in range(3)] == [[0, 1], [2, 3], [4, 0]]


def test_discovery_messages() -> None:
    msgs = discovery_messages("homeassistant", "bmsid", "p-1", 2, "0.1.0")
    assert len(msgs) == 2 * len(cell_sensor_keys()) + 3
    ids = set()
    for topic, payload in msgs:
        cfg = json.loads(payload)
        assert topic.startswith("homeassistant/sensor/bmsid_p_1/") and topic.endswith("/config")
        assert cfg["availability_topic"] == "bmsid/p-1/status"
        assert cfg["state_topic"].startswith("bmsid/p-1/")
        ids.add(cfg["unique_id"])
    assert len(ids) == len(msgs)


def test_sd_notify_sends_datagrams(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    path = str(tmp_path / "notify")
    with socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM) as srv:
        srv.bind(path)
        monkeypatch.setenv("NOTIFY_SOCKET", path)
        monkeypatch.setenv("WATCHDOG_USEC", "4000000")
        sd = SdNotifier()
        assert sd.active and sd.watchdog_s == 4.0
        assert sd.notify("READY=1", "STATUS=ok")
        assert srv.recv(100) == b"READY=1\nSTATUS=ok"
    monkeypatch.delenv("NOTIFY_SOCKET")
    assert not SdNotifier().notify("READY=1")
    assert os.environ.get("NOTIFY_SOCKET") is None


def test_docs_carry_the_published_schemas() -> None:
    docs = Path(__file__).resolve().parents[2] / "docs" / "mqtt-schemas"
    for name in ("cell", "pack", "status"):
        assert (docs / f"{name}.json").read_text() == (SCHEMA_DIR / f"{name}.json").read_text()
        jsonschema.Draft202012Validator.check_schema(
            json.loads((SCHEMA_DIR / f"{name}.json").read_text())
        )


def test_docs_status_example_is_a_whole_payload(tmp_path: Path) -> None:
    """docs/mqtt.md's status example validates and carries every field an online status has
    (it lacked mqtt, soc_init and inputs) and every counter the daemon sends with MQTT on."""
    doc = (Path(__file__).resolve().parents[2] / "docs" / "mqtt.md").read_text(encoding="utf-8")
    example = json.loads(doc.split("## Status", 1)[1].split("```json", 1)[1].split("```", 1)[0])
    schema = json.loads((SCHEMA_DIR / "status.json").read_text())
    jsonschema.Draft202012Validator(schema).validate(example)
    assert set(example) == set(schema["properties"])
    daemon = Daemon(make_settings(tmp_path, 1883))
    counters = list(daemon.snapshot())  # before run(): without the MQTT client's five
    mqtt = ["publishes", "mqtt_drops", "mqtt_backlog", "mqtt_reconnects", "mqtt_connect_failures"]
    assert list(example["counters"]) == counters + mqtt
    assert set(example["lifetime"]) == set(daemon.lifetime())


def test_an_outbox_backlog_adds_no_work_for_the_garbage_collector() -> None:
    """A broker outage queues many messages; a full collection on the loop must not walk them."""

    async def main() -> tuple[int, int]:
        box = Outbox(20_000)
        gc.collect()
        before = len(gc.get_objects())
        for k in range(20_000):
            box.put(OutMessage(f"bmsid/p/cell/{k % 96}", b'{"seq": %d}' % k, t_sample_mono=1.0))
        gc.collect()
        return len(gc.get_objects()) - before, len(box)

    added, held = asyncio.run(main())
    assert held == 20_000
    assert added < 1_000
