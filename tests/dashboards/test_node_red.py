"""The shipped Node-RED flow in a real Node-RED with FlowFuse Dashboard 2 (pinned, installed by
scripts/install-dashboard-tools), fed by bmsid's own payloads through a real Mosquitto.

Asserted: Node-RED loads the flow with no missing node type and starts it; the MQTT nodes
connect; every widget receives messages; the charts place each point at the sample time t_s
(a replay an hour old is drawn an hour ago, not now) and a null value as y = null (a gap); the
R0 gauge's range follows the data (0 to twice the best cell, not 0-10 mOhm).

How the test sees inside: it adds a probe tab to a copy of the flow, wired from the outputs of
the flow's functions (what each widget gets) and of its charts and gauges (what they made of
it), writing each message to a file. About 6 s (Node-RED starts in about 3 s).
"""

from __future__ import annotations

import json
import math
import os
import time
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from dashboard_tools import (
    REPO,
    TOOLS_DIR,
    Process,
    pin,
    publish,
    read_jsonl,
    require_path,
    wait_until,
)

from bmsid.estimate.fields import CELL_FIELDS
from bmsid.estimate.types import Estimates, Quality
from bmsid.publish import payloads
from conftest import require_tool

FLOW = REPO / "deploy" / "dashboard" / "node-red-flow.json"
NODE_RED_DIR = TOOLS_DIR / "node-red"
START_TIMEOUT_S = 60.0
N_CELLS = 2
#: a replay's sample times: an hour before now, 1 s apart
T0_S = math.floor(time.time()) - 3600.0


def estimates(t_s: float, r0_ohm: float, *, voltage: bool = True) -> Estimates:
    """Estimates of N_CELLS cells; without ``voltage`` the voltage-based fields are NaN (a lost
    voltage frame), published as null."""
    cells = {s.name: np.full(N_CELLS, 0.5) for s in CELL_FIELDS}
    cells["R0_ohm"] = np.array([r0_ohm, 1.2 * r0_ohm])
    if not voltage:
        for name in ("v_meas_V", "v_model_V", "v_error_V"):
            cells[name] = np.full(N_CELLS, np.nan)
    return Estimates(t_s, 1.0, cells, np.full(N_CELLS, int(Quality.CONVERGED)))


def data_messages(est: Estimates, seq: int) -> list[tuple[str, bytes, bool]]:
    out = [
        (
            payloads.topic("bmsid", "p1", "cell", i),
            payloads.encode(payloads.cell_payload(est, i, "p1", seq + i)),
            False,
        )
        for i in range(N_CELLS)
    ]
    pack = payloads.pack_payload(est, "p1", seq + N_CELLS, 0)
    out.append((payloads.topic("bmsid", "p1", "pack"), payloads.encode(pack), False))
    return out


def probed_flow(port: int, probe_file: Path) -> list[dict[str, Any]]:
    """The shipped flow on the test broker, plus a probe tab that writes what every function
    sends to each widget, and what each chart and gauge sends on, to ``probe_file``."""
    flow: list[dict[str, Any]] = json.loads(FLOW.read_text(encoding="utf-8"))
    by_id = {n["id"]: n for n in flow}
    broker = by_id["bmsid_broker"]
    broker["broker"], broker["port"] = "127.0.0.1", str(port)
    probes: list[dict[str, Any]] = [{"id": "probe_tab", "type": "tab", "label": "probe"}]
    record = (
        "msg.payload = JSON.stringify({from: %s, topic: msg.topic, payload: msg.payload, "
        "ui_update: msg.ui_update, datapoint: msg._datapoint});\nreturn msg;"
    )

    def probe(name: str) -> str:
        probe_id = f"probe_{len(probes)}"
        probes.append({
            # x and y: without them the runtime takes a node for a config node
            "id": probe_id, "type": "function", "z": "probe_tab", "name": "probe", "x": 1, "y": 1,
            "func": record % json.dumps(name), "outputs": 1, "wires": [["probe_file"]],
        })  # fmt: skip
        return probe_id

    for node in flow:
        if node["type"] == "function":  # what each widget gets: "to:<widget id>"
            for outputs in node["wires"]:
                outputs.append(probe("to:" + outputs[0]))
        elif node["type"] == "ui-chart":  # what the chart made of it: its id
            node["wires"][0].append(probe(node["id"]))
    probes.append({
        "id": "probe_file", "type": "file", "z": "probe_tab", "x": 2, "y": 2,
        "filename": str(probe_file),
        "filenameType": "str", "appendNewline": True, "createDir": True, "overwriteFile": "false",
        "encoding": "utf8", "wires": [],
    })  # fmt: skip
    return flow + probes


@pytest.fixture
def node_red_home() -> Path:
    require_tool("node")
    red = require_path(NODE_RED_DIR / "node_modules" / "node-red" / "red.js", "Node-RED")
    dashboard = NODE_RED_DIR / "node_modules" / "@flowfuse" / "node-red-dashboard"
    require_path(dashboard / "package.json", "@flowfuse/node-red-dashboard")
    versions = {
        "node-red": json.loads((red.parent / "package.json").read_text())["version"],
        "dashboard": json.loads((dashboard / "package.json").read_text())["version"],
    }
    assert versions == {"node-red": pin("NODE_RED_VERSION"),
                        "dashboard": pin("DASHBOARD2_VERSION")}  # fmt: skip
    return NODE_RED_DIR


def test_flow_runs_on_dashboard_2_at_sample_time_with_gaps(
    tmp_path: Path, mosquitto_broker: Any, node_red_home: Path
) -> None:
    from conftest import free_loopback_port

    port = free_loopback_port()
    user_dir = tmp_path / "node-red"
    user_dir.mkdir()
    # Node-RED finds node modules in <userDir>/node_modules, declared in its package.json
    (user_dir / "node_modules").symlink_to(node_red_home / "node_modules")
    (user_dir / "package.json").write_text(json.dumps({
        "name": "bmsid-test", "private": True,
        "dependencies": {"@flowfuse/node-red-dashboard": pin("DASHBOARD2_VERSION")},
    }))  # fmt: skip
    probe_file = tmp_path / "probe.jsonl"
    (user_dir / "flows.json").write_text(
        json.dumps(probed_flow(mosquitto_broker.port, probe_file)), encoding="utf-8"
    )
    (user_dir / "settings.js").write_text(
        "module.exports = {uiHost: '127.0.0.1', flowFile: 'flows.json', credentialSecret: false,"
        " externalModules: {autoInstall: false, palette: {allowInstall: false}},"
        " diagnostics: {enabled: false}, telemetry: {enabled: false},"
        " logging: {console: {level: 'info', metrics: false, audit: false}}};\n"
    )
    red = Process(
        [require_tool("node"), str(node_red_home / "node_modules" / "node-red" / "red.js"),
         "--userDir", str(user_dir), "--port", str(port), "--settings",
         str(user_dir / "settings.js")],
        tmp_path / "node-red.log", user_dir, {**os.environ, "NODE_RED_ENABLE_PROJECTS": ""},
    )  # fmt: skip
    try:
        t_start = time.monotonic()
        red.wait_port(port, START_TIMEOUT_S, "Node-RED")
        wait_until(lambda: "Started flows" in red.log(), START_TIMEOUT_S, "Started flows", red)
        wait_until(lambda: "Connected to broker" in red.log(), 30, "the MQTT connection", red)
        started_s = time.monotonic() - t_start
        # the daemon's retained status first: once it is through, the subscriptions are in place
        status = payloads.status_payload("online", "p1", can_state="up", version="test")
        publish(mosquitto_broker.port, [(payloads.topic("bmsid", "p1", "status"),
                                         payloads.encode(status), True)])  # fmt: skip
        wait_until(
            lambda: any(r["from"] == "to:bmsid_text_state" for r in read_jsonl(probe_file)),
            30, "the status message", red,
        )  # fmt: skip
        # a replay: sample times an hour old; the second tick lost its voltage frames
        publish(
            mosquitto_broker.port,
            data_messages(estimates(T0_S, 0.080), 0)
            + data_messages(estimates(T0_S + 1.0, 0.082, voltage=False), 10)
            + data_messages(estimates(T0_S + 2.0, 0.081), 20),
        )

        def done() -> bool:
            records = read_jsonl(probe_file)
            return (
                sum(r["from"] == "bmsid_chart_verr" for r in records) >= 3 * N_CELLS
                and sum(r["from"] == "to:bmsid_text_spread" for r in records) >= 3
            )

        wait_until(done, 30, "the chart points and pack messages", red)
    finally:
        red.stop()
    log = red.log()
    assert "missing" not in log.lower(), log  # "Waiting for missing types to be registered"
    assert "[error]" not in log, log
    # a node's warning names the node: "[warn] [function:...]" (the runtime's own two about
    # this test's settings, projects and credentials, do not)
    assert "[warn] [" not in log, log
    records = read_jsonl(probe_file)
    got = {r["from"] for r in records}
    # every widget of the flow got messages, and every chart drew points
    flow = json.loads(FLOW.read_text(encoding="utf-8"))
    widgets = {n["id"] for n in flow if n["type"].startswith("ui-") and "group" in n}
    assert {"to:" + w for w in widgets} <= got
    assert {n["id"] for n in flow if n["type"] == "ui-chart"} <= got
    # the charts: x = t_s in ms (sample time, not arrival), the lost tick a null y
    verr = sorted(
        (r["datapoint"]["x"], r["topic"], r["datapoint"]["y"]) for r in records
        if r["from"] == "bmsid_chart_verr"
    )  # fmt: skip
    assert [x for x, _, _ in verr] == [1000.0 * (T0_S + k) for k in range(3) for _ in range(2)]
    assert [y is None for _, _, y in verr] == [False, False, True, True, False, False]
    r0 = sorted(
        (r["datapoint"]["x"], r["datapoint"]["y"]) for r in records
        if r["from"] == "bmsid_chart_r0" and r["topic"] == "p1 cell 0"
    )  # fmt: skip
    assert r0 == [(1000.0 * T0_S, 80.0), (1000.0 * (T0_S + 1), 82.0), (1000.0 * (T0_S + 2), 81.0)]
    # the R0 gauge: the largest R0 (cell 1, 1.2 x) on 0 .. twice the best cell, rounded up
    gauge = [r for r in records if r["from"] == "to:bmsid_gauge_r0max"]
    assert gauge[-1]["payload"] == pytest.approx(1.2 * 81.0)
    assert gauge[-1]["ui_update"]["min"] == 0 and gauge[-1]["ui_update"]["max"] == 200
    print(f"Node-RED {pin('NODE_RED_VERSION')} up and flows started in {started_s:.1f} s")
