"""A real Home Assistant for the dashboard tests (pinned, installed by
scripts/install-dashboard-tools), run as its users run it, only lighter.

``running_home_assistant`` starts ``hass`` with a minimal configuration.yaml (http on loopback,
api, onboarding, what HA always sets up), ``--skip-pip`` (nothing is fetched at test time),
creates the owner through the onboarding API (which hands out the access token) and adds the
MQTT integration through its config flow, as a user does in the UI. ``log_problems`` is the one
rule for what HA's log may not hold. HA listens after about 6 s.
"""

from __future__ import annotations

import json
import os
import subprocess
import urllib.parse
import urllib.request
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

from dashboard_tools import TOOLS_DIR, Process, pin, require_path

from conftest import free_loopback_port

HA_DIR = TOOLS_DIR / "home-assistant"
START_TIMEOUT_S = 120.0
#: HA's own lines about the tests' set-up, not about bmsid's entities
SETUP_WARNINGS = (
    "Skipping pip installation of required modules",  # --skip-pip: nothing fetched at test time
    "zlib_ng and isal are not available",  # an optional speed-up of its web server
    "We found a custom integration",  # never: none is installed (kept for the message)
)

#: A websocket API client run by HA's own interpreter (its aiohttp): the entity registry has no
#: REST API, and the tests' venv has no websocket client. argv: url, token, JSON list of commands.
_WS_CLIENT = """
import asyncio, json, sys
import aiohttp

async def main(url, token, commands):
    async with aiohttp.ClientSession() as session, session.ws_connect(url) as ws:
        await ws.receive_json()  # auth_required
        await ws.send_json({"type": "auth", "access_token": token})
        if (await ws.receive_json())["type"] != "auth_ok":
            sys.exit("websocket authentication refused")
        for n, command in enumerate(commands, 1):
            await ws.send_json({"id": n, **command})
            result = await ws.receive_json()
            if not result.get("success"):
                sys.exit(json.dumps(result))

asyncio.run(main(sys.argv[1], sys.argv[2], json.loads(sys.argv[3])))
"""


class HomeAssistant:
    """The REST (and websocket) API of a running HA, with the owner's access token."""

    def __init__(self, port: int) -> None:
        self.base = f"http://127.0.0.1:{port}"
        self.token = ""
        self.mqtt_entry_id = ""

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
        self.mqtt_entry_id = result["result"]["entry_id"]

    def states(self) -> dict[str, dict[str, Any]]:
        return {s["entity_id"]: s for s in self.call("GET", "/api/states")}

    def enable_entity(self, entity_id: str) -> None:
        """Settings > Entities > (a disabled entity) > Enabled, then reload the MQTT integration
        at once. HA reloads it again 30 s after the change (a timer this cannot cancel): a
        test that runs longer must survive entities resubscribing (the messages in between
        are lost to HA)."""
        commands = [{"type": "config/entity_registry/update", "entity_id": entity_id,
                     "disabled_by": None}]  # fmt: skip
        url = self.base.replace("http://", "ws://") + "/api/websocket"
        done = subprocess.run(
            [str(HA_DIR / "bin" / "python"), "-c", _WS_CLIENT, url, self.token,
             json.dumps(commands)],
            capture_output=True, text=True, check=False, timeout=60,
        )  # fmt: skip
        assert done.returncode == 0, f"enabling {entity_id}: {done.stderr or done.stdout}"
        self.call("POST", f"/api/config/config_entries/entry/{self.mqtt_entry_id}/reload")


def installed_version(venv: Path) -> str:
    (dist,) = venv.glob("lib/python3.*/site-packages/homeassistant-*.dist-info")
    return dist.name.removeprefix("homeassistant-").removesuffix(".dist-info")


def require_hass() -> Path:
    """The pinned ``hass``; missing: fails (real parts required) or skips the test."""
    exe = require_path(HA_DIR / "bin" / "hass", "Home Assistant")
    assert installed_version(HA_DIR) == pin("HOME_ASSISTANT_VERSION")
    return exe


@contextmanager
def running_home_assistant(
    workdir: Path, mqtt_port: int
) -> Iterator[tuple[HomeAssistant, Process, float]]:
    """A fresh HA in ``workdir/ha``, onboarded, its MQTT integration on ``mqtt_port``:
    (API, process, seconds until it listened). Stopped on exit."""
    exe = require_hass()
    port = free_loopback_port()
    config = workdir / "ha"
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
        [str(exe), "--config", str(config), "--skip-pip", "--log-no-color"],
        workdir / "hass.log", config, {**os.environ, "PYTHONDONTWRITEBYTECODE": "1"},
    )  # fmt: skip
    try:
        started_s = hass.wait_port(port, START_TIMEOUT_S, "Home Assistant")
        ha.onboard()
        ha.add_mqtt(mqtt_port)
        yield ha, hass, started_s
    finally:
        hass.stop()


def log_problems(log: str) -> list[str]:
    """HA's log lines that are an error, a warning, a template error or a deprecation, apart
    from the set-up's own (``SETUP_WARNINGS``)."""
    return [
        line for line in log.splitlines()
        if (" ERROR " in line or " WARNING " in line or "Traceback" in line
            or "Template" in line or "deprecat" in line.lower())
        and not any(ok in line for ok in SETUP_WARNINGS)
    ]  # fmt: skip
