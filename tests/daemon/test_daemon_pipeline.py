"""The daemon end to end on python-can's virtual bus with a real Mosquitto (host tests)."""

from __future__ import annotations

import asyncio
import json
import random
import subprocess
from pathlib import Path
from typing import Any

import can
import jsonschema
import pytest
from daemon_helpers import (
    SCHEMA_DIR,
    MqttCapture,
    assert_matches_offline,
    contiguous,
    demo_frames,
    full_can_output_cycle,
    make_settings,
    offline_estimates,
    run_with_frames,
    send_virtual,
    wait_for,
)

from bmsid.canbus.encoder import ParameterEncoder
from bmsid.daemon.core import Daemon
from bmsid.publish.discovery import discovery_messages


def _validators() -> dict[str, jsonschema.Draft202012Validator]:
    return {
        name: jsonschema.Draft202012Validator(json.loads((SCHEMA_DIR / f"{name}.json").read_text()))
        for name in ("cell", "pack", "status")
    }


def _kind(topic: str) -> str:
    return "cell" if "/cell/" in topic else topic.rsplit("/", 1)[-1]


@pytest.fixture
def capture(tmp_path: Path, mosquitto_broker: Any, require_tool: Any) -> Any:
    cap = MqttCapture(require_tool("mosquitto_sub"), mosquitto_broker.port, tmp_path / "sub.txt")
    cap.wait_ready(require_tool("mosquitto_pub"), mosquitto_broker.port)
    yield cap
    cap.stop()


def test_end_to_end_values_equal_offline_and_validate(
    tmp_path: Path, mosquitto_broker: Any, capture: MqttCapture
) -> None:
    settings = make_settings(tmp_path, mosquitto_broker.port)
    frames = demo_frames(600.0)
    ref = offline_estimates(frames, settings)
    out_frames: list[can.Message] = []
    listener = can.Bus(interface="virtual", channel=settings.can.channel)

    async def collect_output(d: Daemon) -> None:
        while (m := listener.recv(0)) is not None:
            out_frames.append(m)

    async def main() -> Daemon:
        daemon = Daemon(settings)

        async def during(d: Daemon) -> None:
            await collect_output(d)

        # then the last frames of every cell carry the final estimates
        await run_with_frames(daemon, frames, during=during, after=full_can_output_cycle)
        return daemon

    daemon = asyncio.run(main())
    while (m := listener.recv(0)) is not None:
        out_frames.append(m)
    listener.shutdown()
    capture.stop()
    msgs = capture.messages()
    validators = _validators()
    for topic, payload in msgs:
        validators[_kind(topic)].validate(payload)
    cells = [p for t, p in msgs if _kind(t) == "cell"]
    # every tick of every cell was published, and equals the offline bank exactly
    assert len(cells) == len(ref) * settings.can.n_cells
    for p in cells:
        assert_matches_offline(p, ref[p["t_s"]])
    assert daemon.bank_counters["swarms"] > 0  # the fusion ran, not only the AFFRLS
    seqs = [p["seq"] for t, p in msgs if _kind(t) in ("cell", "pack")]
    assert seqs == list(range(len(seqs)))
    status = [p for t, p in msgs if _kind(t) == "status"]
    assert status[0]["state"] == "online" and status[-1]["state"] == "offline"
    assert any(p.get("counters", {}).get("frames", 0) > 0 for p in status)
    # the parameter frames on the bus decode to the final estimates, within resolution
    enc = ParameterEncoder()
    last = ref[max(ref)]
    decoded: dict[int, dict[str, float]] = {}
    for m in out_frames:
        d = enc.decode(m)
        if d is not None and "cell" in d:
            decoded.setdefault(int(d["cell"]), {}).update(d)
    assert set(decoded) == set(range(settings.can.n_cells))
    for c, d in decoded.items():
        assert d["R0_ohm"] == pytest.approx(last.R0_ohm[c], abs=1.1e-6)
        assert d["tau2_s"] == pytest.approx(last.tau2_s[c], abs=0.026)
        assert d["soc"] == pytest.approx(last.soc[c], abs=1.3e-4)


def _malformed(rng: random.Random, t: float) -> can.Message:
    kind = rng.randrange(6)
    if kind == 0:  # current frame with the wrong length
        return can.Message(
            timestamp=t,
            arbitration_id=0x100,
            is_extended_id=False,
            data=bytes(rng.randrange(256) for _ in range(rng.randrange(8))),
        )
    if kind == 1:  # cell voltages, group index beyond the pack
        data = bytes([rng.randrange(2, 128)]) + bytes(rng.randrange(256) for _ in range(7))
        return can.Message(timestamp=t, arbitration_id=0x110, is_extended_id=False, data=data)
    if kind == 2:
        return can.Message(
            timestamp=t,
            arbitration_id=0x100,
            is_extended_id=False,
            is_error_frame=True,
            data=bytes(8),
        )
    if kind == 3:
        return can.Message(
            timestamp=t, arbitration_id=0x110, is_extended_id=False, is_remote_frame=True, dlc=8
        )
    if kind == 4:  # unknown identifier
        return can.Message(
            timestamp=t,
            arbitration_id=rng.choice([0x7FF, 0x111, 0x101]),
            is_extended_id=False,
            data=bytes(8),
        )
    # the right identifier as an extended frame: another message
    return can.Message(timestamp=t, arbitration_id=0x110, is_extended_id=True, data=bytes(8))


def test_malformed_frame_flood_changes_no_estimate(
    tmp_path: Path, mosquitto_broker: Any, capture: MqttCapture
) -> None:
    settings = make_settings(tmp_path, mosquitto_broker.port)
    clean = demo_frames(400.0)
    ref = offline_estimates(clean, settings)
    rng = random.Random(5)
    flooded: list[can.Message] = []
    for m in clean:
        flooded.extend(_malformed(rng, m.timestamp) for _ in range(rng.randrange(6)))
        flooded.append(m)
    n_bad = len(flooded) - len(clean)
    assert n_bad > 2 * len(clean)

    async def main() -> Daemon:
        daemon = Daemon(settings)
        await run_with_frames(daemon, flooded)
        return daemon

    daemon = asyncio.run(main())
    capture.stop()
    cells = [p for t, p in capture.messages() if _kind(t) == "cell"]
    assert len(cells) == len(ref) * settings.can.n_cells
    for p in cells:
        assert_matches_offline(p, ref[p["t_s"]])
    snap = daemon.snapshot()
    assert snap["decode_errors"] == n_bad
    assert snap["samples"] == daemon.bank_counters["samples"]


def test_status_counters_after_a_restart_count_this_process(tmp_path: Path) -> None:
    """After a restore every status counter counts since the process started (ticks and swarms
    once included the checkpoint's totals, frames and samples did not); the state's totals are
    in ``lifetime``."""
    settings = make_settings(tmp_path, None)
    everything = demo_frames(900.0)
    first_frames = demo_frames(450.0)
    seen: dict[str, Any] = {}

    async def look(d: Daemon) -> None:
        seen["snap"], seen["status"] = d.snapshot(), json.loads(d._online_payload())

    async def run(frames: list[can.Message]) -> Daemon:
        daemon = Daemon(settings)
        await run_with_frames(daemon, frames, after=look)
        return daemon

    first = asyncio.run(run(first_frames))
    before = first.lifetime()
    assert before["ticks"] > 0 and before["swarms"] > 0
    second = asyncio.run(run(everything[len(first_frames) :]))
    assert second.restored
    snap, status = seen["snap"], seen["status"]
    _validators()["status"].validate(status)
    after = status["lifetime"]
    assert snap["frames"] == len(everything) - len(first_frames)
    assert snap["samples"] == after["samples"] - before["samples"] > 0
    assert snap["ticks"] == after["ticks"] - before["ticks"] > 0
    assert snap["swarms"] == after["swarms"] - before["swarms"]
    assert status["counters"] == snap and after == second.lifetime()


def test_broker_outage_loses_no_message(
    tmp_path: Path, mosquitto_factory: Any, require_tool: Any, request: pytest.FixtureRequest
) -> None:
    """Broker down for 30 s mid-run (as the issue asks): the outbox holds the messages, the
    client reconnects with backoff, the backlog goes out in order. The broker keeps the
    subscriber's persistent session across its restart."""
    state = tmp_path / "broker"
    state.mkdir()
    broker = mosquitto_factory(
        f"allow_anonymous true\npersistence true\npersistence_location {state}/\n"
        "max_queued_messages 0\n"
    )
    cap = MqttCapture(
        require_tool("mosquitto_sub"),
        broker.port,
        tmp_path / "sub.txt",
        persistent_id="outage-test",
    )
    request.addfinalizer(cap.stop)
    cap.wait_ready(require_tool("mosquitto_pub"), broker.port)
    settings = make_settings(tmp_path, broker.port)
    frames = demo_frames(500.0)
    seen: dict[str, float] = {}

    async def outage(d: Daemon) -> None:
        await wait_for(lambda: d.seq > 200, 60, "messages before the outage")
        await asyncio.to_thread(broker.stop)
        await wait_for(lambda: not d.mqtt or not d.mqtt.connected, 10, "the disconnect")
        await asyncio.sleep(30.0)
        assert d.outbox is not None
        seen["backlog"] = len(d.outbox)
        await asyncio.to_thread(broker.start)

    async def main() -> Daemon:
        daemon = Daemon(settings)
        await run_with_frames(daemon, frames, pace_s=0.01, during=outage)
        return daemon

    daemon = asyncio.run(main())
    # mosquitto_sub reconnects by itself; give it the queued messages
    assert daemon.mqtt is not None
    total = daemon.seq

    def received() -> list[int]:
        return [p["seq"] for t, p in cap.messages() if _kind(t) in ("cell", "pack")]

    async def settle() -> None:
        await wait_for(lambda: len(set(received())) >= total, 30, "all messages at the sub")

    asyncio.run(settle())
    cap.stop()
    seqs = received()
    assert seen["backlog"] > 50  # the outage really held messages back
    assert daemon.mqtt.counters["reconnects"] >= 1
    assert daemon.outbox is not None and daemon.outbox.dropped == 0
    assert contiguous(seqs) and min(seqs) == 0 and max(seqs) == total - 1
    # delivered in order: apart from re-sends after the reconnect, seq never goes back
    firsts = [s for k, s in enumerate(seqs) if s not in set(seqs[:k])]
    assert firsts == sorted(firsts)


def test_outbox_overflow_drops_oldest_and_counts(tmp_path: Path) -> None:
    """No broker at all: the outbox keeps the newest messages, counts the dropped ones."""
    settings = make_settings(tmp_path, 1, mqtt={"outbox_size": 50, "reconnect_max_s": 0.2})
    frames = demo_frames(60.0)

    async def main() -> Daemon:
        daemon = Daemon(settings, shutdown_timeout_s=0.5)
        task = asyncio.create_task(daemon.run())
        await wait_for(lambda: daemon.can_state == "up", 20, "the bus")
        send_virtual(settings.can.channel, frames).join()
        await wait_for(lambda: daemon.bank_counters["samples"] >= 60, 30, "samples")
        daemon.request_stop()
        await task
        return daemon

    daemon = asyncio.run(main())
    assert daemon.outbox is not None
    assert len(daemon.outbox) == 50
    assert daemon.outbox.dropped == daemon.seq - 50
    newest = json.loads(daemon.outbox.peek(50)[-1].payload)
    assert newest["seq"] == daemon.seq - 1  # the newest were kept
    assert daemon.mqtt is not None and daemon.mqtt.counters["connect_failures"] >= 1


def test_home_assistant_discovery_and_republish_on_ha_birth(
    tmp_path: Path, mosquitto_broker: Any, require_tool: Any, request: pytest.FixtureRequest
) -> None:
    sub, pub = require_tool("mosquitto_sub"), require_tool("mosquitto_pub")
    cap = MqttCapture(sub, mosquitto_broker.port, tmp_path / "ha.txt", topic="homeassistant/#")
    request.addfinalizer(cap.stop)
    cap.wait_ready(pub, mosquitto_broker.port)
    settings = make_settings(
        tmp_path,
        mosquitto_broker.port,
        mqtt={
            "homeassistant": {"enabled": True},
            "publish_period_s": 0.0,
            "url": f"mqtt://127.0.0.1:{mosquitto_broker.port}",
        },
    )
    n_configs = len(discovery_messages("homeassistant", "bmsid", "testpack", 8, "x"))

    def configs() -> list[dict[str, Any]]:
        return [p for t, p in cap.messages("homeassistant/sensor/") if t.endswith("/config")]

    async def main() -> Daemon:
        daemon = Daemon(settings)
        task = asyncio.create_task(daemon.run())
        await wait_for(lambda: len(configs()) >= n_configs, 30, "discovery")
        await asyncio.to_thread(
            subprocess.run,
            [pub, "-p", str(mosquitto_broker.port), "-t", "homeassistant/status", "-m", "online"],
            check=True,
        )
        await wait_for(lambda: len(configs()) >= 2 * n_configs, 30, "re-published discovery")
        daemon.request_stop()
        await task
        return daemon

    daemon = asyncio.run(main())
    cap.stop()
    assert daemon.mqtt is not None and daemon.mqtt.counters["discovery_sent"] == 2 * n_configs
    cfgs = configs()
    assert {c["unique_id"] for c in cfgs} == {c["unique_id"] for c in cfgs[:n_configs]}
    assert all(c["availability_topic"] == "bmsid/testpack/status" for c in cfgs)
