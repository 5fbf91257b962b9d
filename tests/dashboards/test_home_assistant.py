"""bmsid's discovery and data in a real Home Assistant (pinned, installed by
scripts/install-dashboard-tools), through a real Mosquitto.

Home Assistant runs as its users run it, only lighter: ``hass`` with a minimal
configuration.yaml (http on loopback, api, onboarding, mqtt and what HA always sets up),
``--skip-pip`` (nothing is fetched at test time), the owner created through the onboarding API
(which hands out the access token), the MQTT integration added through its config flow, as a
user does in the UI. bmsid's messages are what the daemon publishes (``discovery_messages``,
``payloads``), a lost voltage frame as null.

Asserted: every entity bmsid announces exists under its ``default_entity_id`` with its unit,
device class and state; a null gives ``unknown`` (not the stale value); quality is an enum;
internals are disabled; configs cleared by bmsid remove their entities; and HA's log has no
error, no template error and no deprecation warning. About 15 s (HA starts in about 6 s).
"""

from __future__ import annotations

import json
import os
import time
import urllib.parse
import urllib.request
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from dashboard_tools import TOOLS_DIR, Process, pin, publish, require_path, wait_until

from bmsid.estimate.fields import CELL_FIELDS
from bmsid.estimate.types import Estimates, Quality
from bmsid.publish import payloads
from bmsid.publish.discovery import discovery_messages, quality_options, with_clears
from conftest import free_loopback_port

HA_DIR = TOOLS_DIR / "home-assistant"
START_TIMEOUT_S = 120.0
PACK = "p1"
N_CELLS = 2
#: HA's own lines about this test's set-up, not about bmsid's entities
SETUP_WARNINGS = (
    "Skipping pip installation of required modules",  # --skip-pip: nothing fetched at test time
    "zlib_ng and isal are not available",  # an optional speed-up of its web server
    "We found a custom integration",  # never: none is installed (kept for the message)
)


class HomeAssistant:
    """The REST API of a running HA, with the owner's access token."""

    def __init__(self, port: int) -> None:
        self.base = f"http://127.0.0.1:{port}"
        self.token = ""

    def call(self, method: str, path: str, body: Any = None, *, form: bool = False) -> Any:
        headers = {"Authorization": f"Bearer {self.token}"} if self.token else {}
        data = None
        if body is not None:
            if form:
                data = urllib.parse.urlencode(body).encode()
                headers["Content-Type"] = "application/x-www-form-urlencoded"
            else:
                data = json.dumps(body).encode()
                headers["Content-Type"] = "application/json"
        request = urllib.request.Request(self.base + path, data, headers, method=method)
        with urllib.request.urlopen(request, timeout=30) as response:
            return json.loads(response.read() or b"null")

    def onboard(self) -> None:
        """Create the owner through onboarding and take its access token (no UI, no storage
        edits: the same two calls the frontend makes)."""
        client_id = self.base + "/"
        user = {"client_id": client_id, "name": "test", "username": "test",
                "password": "bmsid-test-password", "language": "en"}  # fmt: skip
        code = self.call("POST", "/api/onboarding/users", user)["auth_code"]
        grant = {"grant_type": "authorization_code", "code": code, "client_id": client_id}
        self.token = self.call("POST", "/auth/token", grant, form=True)["access_token"]

    def add_mqtt(self, port: int) -> None:
        """Settings > Devices & services > Add integration > MQTT, as a user does."""
        flow = self.call("POST", "/api/config/config_entries/flow", {"handler": "mqtt"})
        result = self.call(
            "POST", f"/api/config/config_entries/flow/{flow['flow_id']}",
            {"broker": "127.0.0.1", "port": port},
        )  # fmt: skip
        assert result["type"] == "create_entry" and result["result"]["state"] == "loaded", result

    def states(self) -> dict[str, dict[str, Any]]:
        return {s["entity_id"]: s for s in self.call("GET", "/api/states")}


def installed_version(venv: Path) -> str:
    (dist,) = venv.glob("lib/python3.*/site-packages/homeassistant-*.dist-info")
    return dist.name.removeprefix("homeassistant-").removesuffix(".dist-info")


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


@pytest.fixture
def hass_exe() -> Path:
    exe = require_path(HA_DIR / "bin" / "hass", "Home Assistant")
    assert installed_version(HA_DIR) == pin("HOME_ASSISTANT_VERSION")
    return exe


def test_home_assistant_shows_bmsid_with_unknown_for_null_and_no_errors(
    tmp_path: Path, mosquitto_broker: Any, hass_exe: Path
) -> None:
    port = free_loopback_port()
    config = tmp_path / "ha"
    config.mkdir()
    (config / "configuration.yaml").write_text(
        "homeassistant:\n  name: bmsid test\n  latitude: 0\n  longitude: 0\n  elevation: 0\n"
        "  unit_system: metric\n  time_zone: UTC\n  currency: EUR\n  country: DE\n"
        "  language: en\n"
        f"http:\n  server_host: 127.0.0.1\n  server_port: {port}\n"
        "api:\nonboarding:\nlogger:\n  default: warning\n",
        encoding="utf-8",
    )
    ha = HomeAssistant(port)
    hass = Process(
        [str(hass_exe), "--config", str(config), "--skip-pip", "--log-no-color"],
        tmp_path / "hass.log", config, {**os.environ, "PYTHONDONTWRITEBYTECODE": "1"},
    )  # fmt: skip
    configs = discovery_messages("homeassistant", "bmsid", PACK, N_CELLS, "0.1.0")
    try:
        started_s = hass.wait_port(port, START_TIMEOUT_S, "Home Assistant")
        ha.onboard()
        ha.add_mqtt(mosquitto_broker.port)
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
    finally:
        hass.stop()

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
    log_lines = hass.log().splitlines()
    bad = [
        line for line in log_lines
        if (" ERROR " in line or " WARNING " in line or "Traceback" in line
            or "Template" in line or "deprecat" in line.lower())
        and not any(ok in line for ok in SETUP_WARNINGS)
    ]  # fmt: skip
    assert not bad, "\n".join(bad)
    print(f"Home Assistant {pin('HOME_ASSISTANT_VERSION')} listening after {started_s:.1f} s")
