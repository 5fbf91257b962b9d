"""bmsid's discovery and data in a real Home Assistant (pinned, installed by
scripts/install-dashboard-tools), through a real Mosquitto.

Home Assistant runs as its users run it, only lighter (``ha_tools.running_home_assistant``).
bmsid's messages are what the daemon publishes (``discovery_messages``, ``payloads``), a lost
voltage frame as null; test_home_assistant_replay.py feeds HA from the daemon itself.

Asserted: every entity bmsid announces exists under its ``default_entity_id`` with its unit,
device class and state; a null gives ``unknown`` (not the stale value); quality is an enum;
internals are disabled; configs cleared by bmsid remove their entities; and HA's log has no
error, no template error and no deprecation warning. About 15 s (HA starts in about 6 s).
"""

from __future__ import annotations

import json
import time
from pathlib import Path
from typing import Any

import numpy as np
from dashboard_tools import pin, publish, wait_until
from ha_tools import log_problems, running_home_assistant

from bmsid.estimate.fields import CELL_FIELDS
from bmsid.estimate.types import Estimates, Quality
from bmsid.publish import payloads
from bmsid.publish.discovery import discovery_messages, quality_options, with_clears

PACK = "p1"
N_CELLS = 2


def estimates(t_s: float, *, lost_cell: int | None = None) -> Estimates:
    """Two cells' estimates; ``lost_cell`` lost its voltage frame and has no SOC (null)."""
    cells = {s.name: np.full(N_CELLS, 0.5) for s in CELL_FIELDS}
    cells["R0_ohm"] = np.array([0.0800, 0.0950])
    cells["soc"] = np.array([0.712, 0.705])
    cells["v_error_V"] = np.array([0.0012, -0.0008])
    if lost_cell is not None:
        for name in ("v_meas_V", "v_model_V", "v_error_V", "soc", "soc_std"):
            cells[name][lost_cell] = np.nan
    quality = np.array([int(Quality.CONVERGED), int(Quality.CONVERGING)])
    return Estimates(t_s, 2.0, cells, quality)


def data(est: Estimates, seq: int) -> list[tuple[str, bytes, bool]]:
    out = [
        (payloads.topic("bmsid", PACK, "cell", i),
         payloads.encode(payloads.cell_payload(est, i, PACK, seq + i)), False)
        for i in range(N_CELLS)
    ]  # fmt: skip
    pack = payloads.pack_payload(est, PACK, seq + N_CELLS, payloads.health_bits(est))
    return [*out, (payloads.topic("bmsid", PACK, "pack"), payloads.encode(pack), False)]


def test_home_assistant_shows_bmsid_with_unknown_for_null_and_no_errors(
    tmp_path: Path, mosquitto_broker: Any
) -> None:
    configs = discovery_messages("homeassistant", "bmsid", PACK, N_CELLS, "0.1.0")
    with running_home_assistant(tmp_path, mosquitto_broker.port) as (ha, hass, started_s):
        status = payloads.status_payload("online", PACK, can_state="up", version="0.1.0")
        publish(
            mosquitto_broker.port,
            [(t, p, True) for t, p in configs]
            + [(payloads.topic("bmsid", PACK, "status"), payloads.encode(status), True)],
        )
        soc0 = "sensor.bmsid_p1_cell0_soc"
        wait_until(lambda: soc0 in ha.states(), 60, "the discovered entities", hass)

        # a first tick with every value, then one where cell 1's voltage frame was lost
        # (sent again each second, as bmsid does, until HA shows it: an entity appears in the
        # states a moment before its subscription is in place)
        def tick(messages: list[tuple[str, bytes, bool]], entity: str, state: str) -> None:
            def shown() -> bool:
                publish(mosquitto_broker.port, messages)
                time.sleep(1.0)
                return bool(ha.states()[entity]["state"] == state)

            wait_until(shown, 30, f"{entity} = {state}", hass)

        tick(data(estimates(1000.0), 0), soc0, "71.2")
        verr1 = "sensor.bmsid_p1_cell1_v_error_v"
        soc1 = "sensor.bmsid_p1_cell1_soc"
        # the model error is an internal (disabled): SOC shows that the null arrived
        tick(data(estimates(1001.0, lost_cell=1), 10), soc1, "unknown")
        states = ha.states()
        # bmsid clears cell 1 (n_cells reduced to 1): its entities go
        one_cell = discovery_messages("homeassistant", "bmsid", PACK, 1, "0.1.0")
        clears = [(t, p, True) for t, p in with_clears(one_cell, [t for t, _ in configs])
                  if p == b""]  # fmt: skip
        publish(mosquitto_broker.port, clears)
        wait_until(lambda: soc1 not in ha.states(), 30, "cell 1's entities removed", hass)
        after_clear = ha.states()

    enabled = [json.loads(p) for _, p in configs if json.loads(p).get("enabled_by_default", True)]
    disabled = [json.loads(p) for _, p in configs if not json.loads(p).get("enabled_by_default", 1)]
    assert disabled and verr1 in {c["default_entity_id"] for c in disabled}
    for cfg in enabled:  # each under its default_entity_id, with its unit and class
        state = states[cfg["default_entity_id"]]
        attrs = state["attributes"]
        assert attrs.get("unit_of_measurement") == cfg.get("unit_of_measurement"), cfg["name"]
        assert attrs.get("device_class") == cfg.get("device_class"), cfg["name"]
        assert attrs["friendly_name"] == f"bmsid pack {PACK} {cfg['name']}"
        assert state["state"] != "unavailable", cfg["name"]  # availability: status online
    for cfg in disabled:  # internals: registered but disabled, so no state
        assert cfg["default_entity_id"] not in states
    assert states["sensor.bmsid_p1_cell0_r0_ohm"]["state"] == "80.0"
    assert states["sensor.bmsid_p1_cell1_r0_ohm"]["state"] == "95.0"
    assert states["sensor.bmsid_p1_cell0_soc"]["state"] == "71.2"
    assert states[soc1]["state"] == "unknown"  # null: unknown, not the stale 70.5
    quality = states["sensor.bmsid_p1_cell0_quality"]
    assert quality["state"] == "converged"
    assert quality["attributes"]["options"] == quality_options()
    assert states["sensor.bmsid_p1_cell1_quality"]["state"] == "converging"
    assert states["sensor.bmsid_p1_pack_r0_max"]["state"] == "95.0"
    assert states["sensor.bmsid_p1_pack_weakest_cell"]["state"] == "1"
    assert states["sensor.bmsid_p1_pack_soc_mean"]["state"] == "71.2"  # cell 1 has none
    assert not [e for e in after_clear if e.startswith("sensor.bmsid_p1_cell1_")]
    assert "sensor.bmsid_p1_cell0_soc" in after_clear
    # the log: no error, no template error, no deprecation, nothing about bmsid's configs
    bad = log_problems(hass.log())
    assert not bad, "\n".join(bad)
    print(f"Home Assistant {pin('HOME_ASSISTANT_VERSION')} listening after {started_s:.1f} s")
