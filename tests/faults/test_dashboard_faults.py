"""Faults of the Home Assistant discovery (issue 16, case 8): cells removed, a pack renamed, the
record of published configs unreadable or unwritable. Each asserts what the broker retains (via
``mosquitto_sub --retained-only``, an independent peer) or the one line logged.

About 6 s in all (five short in-process daemon runs against a real Mosquitto, the bank in a
thread); the two checks of the configs themselves (no ``object_id``, internals disabled) are pure.
"""

from __future__ import annotations

import asyncio
import json
import logging
import subprocess
import sys
from pathlib import Path
from typing import Any

import pytest

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "daemon"))
from daemon_helpers import make_settings, wait_for

from bmsid.daemon.core import Daemon
from bmsid.publish.discovery import (
    RECORD_FILE,
    PublishedConfigs,
    discovery_messages,
    ha_fields,
    is_internal,
)


def retained_configs(sub: str, port: int) -> dict[str, dict[str, Any]]:
    """Every retained Home Assistant config on the broker, topic -> config."""
    out = subprocess.run(
        [sub, "-h", "127.0.0.1", "-p", str(port), "-t", "homeassistant/#", "-v",
         "--retained-only", "-W", "1"],
        capture_output=True, text=True, check=False, timeout=10,
    ).stdout  # fmt: skip
    lines = (line.partition(" ") for line in out.splitlines())
    return {t: json.loads(p) for t, _, p in lines if t.endswith("/config")}


def run_daemon(tmp_path: Path, port: int, state: Path, pack_id: str, n_cells: int) -> Daemon:
    """Start a daemon, wait until it published its discovery, stop it."""
    settings = make_settings(
        tmp_path,
        port,
        pack_id=pack_id,
        can={"n_cells": n_cells},
        estimator={"isolation": "thread"},  # no bank process to spawn: discovery is the point
        mqtt={"homeassistant": {"enabled": True}},
        state={"directory": str(state), "checkpoint_period_s": 1.0},
    )
    record = state / RECORD_FILE

    async def main() -> Daemon:
        daemon = Daemon(settings)
        task = asyncio.create_task(daemon.run())

        def recorded() -> bool:  # sent() rewrote the record: every config acknowledged
            try:
                topics = json.loads(record.read_text())["topics"]
            except (OSError, ValueError):
                return False
            return len(topics) == len(discovery_messages("homeassistant", "bmsid", pack_id,
                                                         n_cells, "x"))  # fmt: skip

        await wait_for(
            lambda: (
                daemon.mqtt is not None
                and daemon.mqtt.counters["discovery_sent"] > 0
                and recorded()
            ),
            30,
            "discovery",
        )
        daemon.request_stop()
        await task
        return daemon

    return asyncio.run(main())


def expected_topics(pack_id: str, n_cells: int) -> set[str]:
    return {t for t, _ in discovery_messages("homeassistant", "bmsid", pack_id, n_cells, "x")}


def test_fewer_cells_clear_the_removed_cells_configs(
    tmp_path: Path, mosquitto_broker: Any, require_tool: Any
) -> None:
    sub, port, state = require_tool("mosquitto_sub"), mosquitto_broker.port, tmp_path / "state"
    run_daemon(tmp_path, port, state, "p1", 8)
    assert set(retained_configs(sub, port)) == expected_topics("p1", 8)
    run_daemon(tmp_path, port, state, "p1", 5)
    # cells 5-7 are gone from the broker (Home Assistant removes their entities); 0-4 stay
    assert set(retained_configs(sub, port)) == expected_topics("p1", 5)


def test_renamed_pack_clears_the_old_name_and_spares_another_live_pack(
    tmp_path: Path, mosquitto_broker: Any, require_tool: Any
) -> None:
    sub, port = require_tool("mosquitto_sub"), mosquitto_broker.port
    run_daemon(tmp_path, port, tmp_path / "other", "other", 2)  # a second gateway's pack
    run_daemon(tmp_path, port, tmp_path / "state", "old", 2)
    run_daemon(tmp_path, port, tmp_path / "state", "new", 2)
    assert set(retained_configs(sub, port)) == expected_topics("new", 2) | expected_topics(
        "other", 2
    )


def test_unreadable_record_costs_one_line_and_publishes_everything(
    tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    (tmp_path / RECORD_FILE).write_text('{"format": 1, "topics": [1, 2')  # truncated
    current = discovery_messages("homeassistant", "bmsid", "p1", 2, "x")
    with caplog.at_level(logging.WARNING):
        record = PublishedConfigs(tmp_path)
        assert record.messages(current) == current  # nothing cleared, nothing lost
        record.sent()
    lines = [r.getMessage() for r in caplog.records]
    assert len(lines) == 1 and RECORD_FILE in lines[0] and "unreadable" in lines[0]
    # and the record is whole again
    assert PublishedConfigs(tmp_path).messages(current) == current


def test_unwritable_record_costs_one_line_and_still_clears_within_the_run(
    tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    blocker = tmp_path / "state"
    blocker.write_text("a file where the state directory should be")
    eight = discovery_messages("homeassistant", "bmsid", "p1", 8, "x")
    five = discovery_messages("homeassistant", "bmsid", "p1", 5, "x")
    with caplog.at_level(logging.WARNING):
        record = PublishedConfigs(blocker)
        assert record.messages(eight) == eight
        record.sent()
        out = record.messages(five)
        record.sent()
    lines = [r.getMessage() for r in caplog.records]
    assert len(lines) == 1 and RECORD_FILE in lines[0]
    cleared = [t for t, p in out if p == b""]
    assert set(cleared) == {t for t, _ in eight} - {t for t, _ in five}
    assert out[len(cleared) :] == five


def _configs(n_cells: int) -> list[dict[str, Any]]:
    return [
        json.loads(p) for _, p in discovery_messages("homeassistant", "bmsid", "p1", n_cells, "x")
    ]


def test_no_config_carries_the_deprecated_object_id() -> None:
    """README row 'HA repair "uses the deprecated option object_id"': none of bmsid's configs
    has it (HA 2025.10 raises one repair per entity, 2026.4 drops it); ``default_entity_id``
    keeps each entity id what ``object_id`` made it: ``sensor.<unique_id>``."""
    configs = _configs(3)
    assert len(configs) == len({c["unique_id"] for c in configs})
    for cfg in configs:
        assert "object_id" not in cfg, cfg["unique_id"]
        assert cfg["default_entity_id"] == f"sensor.{cfg['unique_id']}"


def test_estimator_internals_are_diagnostic_and_disabled_by_default() -> None:
    """README row "estimator internals ... missing in HA": disabled by default (enable them on
    the device page), always diagnostic; the cell values a user reads stay enabled."""
    configs = _configs(1)
    disabled = {c["unique_id"] for c in configs if c.get("enabled_by_default") is False}
    internals = {
        f"bmsid_p1_cell0_{spec.out_key}".lower() for spec, ha in ha_fields() if is_internal(ha)
    }
    assert disabled == internals and internals
    assert all(c["entity_category"] == "diagnostic" for c in configs if c["unique_id"] in disabled)
    enabled = {c["unique_id"] for c in configs} - disabled
    assert {f"bmsid_p1_cell0_{k}" for k in ("soc", "r0_ohm", "tau1_s", "quality")} <= enabled
