"""Home Assistant MQTT discovery: one device per pack, one sensor per cell and parameter.

Config messages are retained under ``<ha_prefix>/sensor/<node>/<object>/config``; availability
follows bmsid's retained status topic (``value_json.state``). Estimator internals are
``entity_category: diagnostic`` so that a default dashboard shows the parameters first.
"""

from __future__ import annotations

import json
from typing import Any

#: (payload key, name, unit, value template expression, device class, diagnostic)
SENSORS: tuple[tuple[str, str, str | None, str, str | None, bool], ...] = (
    ("R0_ohm", "R0", "mΩ", "value_json.R0_ohm * 1000", None, False),
    ("R1_ohm", "R1", "mΩ", "value_json.R1_ohm * 1000", None, False),
    ("R2_ohm", "R2", "mΩ", "value_json.R2_ohm * 1000", None, False),
    ("tau1_s", "tau1", "s", "value_json.tau1_s", "duration", False),
    ("tau2_s", "tau2", "s", "value_json.tau2_s", "duration", False),
    ("C1_F", "C1", "F", "value_json.C1_F", None, False),
    ("C2_F", "C2", "F", "value_json.C2_F", None, False),
    ("soc", "SOC", "%", "value_json.soc * 100", "battery", False),
    ("quality", "quality", None, "value_json.quality_name", None, True),
    ("lambda", "lambda", None, "value_json['lambda']", None, True),
    ("h", "hysteresis state", None, "value_json.h", None, True),
    ("v_error_V", "model error", "mV", "value_json.v_error_V * 1000", "voltage", True),
)


def discovery_messages(
    ha_prefix: str, topic_prefix: str, pack_id: str, n_cells: int, version: str
) -> list[tuple[str, bytes]]:
    """Retained config messages for every cell's sensors and the pack summary."""
    node = f"bmsid_{pack_id}".replace(".", "_").replace("-", "_")
    device = {
        "identifiers": [node],
        "name": f"bmsid pack {pack_id}",
        "manufacturer": "bmsid",
        "model": "online cell parameter identification (2RC + hysteresis)",
        "sw_version": version,
    }
    status = f"{topic_prefix}/{pack_id}/status"
    common: dict[str, Any] = {
        "device": device,
        "availability_topic": status,
        "availability_template": "{{ value_json.state }}",
        "payload_available": "online",
        "payload_not_available": "offline",
    }
    out: list[tuple[str, bytes]] = []
    for c in range(n_cells):
        state = f"{topic_prefix}/{pack_id}/cell/{c}"
        for key, name, unit, expr, dev_class, diag in SENSORS:
            obj = f"cell{c}_{key}".lower()
            cfg: dict[str, Any] = {
                **common,
                "name": f"cell {c} {name}",
                "unique_id": f"{node}_{obj}",
                "object_id": f"{node}_{obj}",
                "state_topic": state,
                "value_template": (
                    f"{{{{ {expr} }}}}" if key == "quality" else f"{{{{ ({expr}) | round(4) }}}}"
                ),
            }
            if key != "quality":
                cfg["state_class"] = "measurement"
            if unit is not None:
                cfg["unit_of_measurement"] = unit
            if dev_class is not None:
                cfg["device_class"] = dev_class
            if diag:
                cfg["entity_category"] = "diagnostic"
            out.append((f"{ha_prefix}/sensor/{node}/{obj}/config", _dump(cfg)))
    pack = f"{topic_prefix}/{pack_id}/pack"
    for key, name, unit, expr in (
        ("weakest_cell", "weakest cell", None, "value_json.weakest_cell"),
        ("r0_max", "R0 max", "mΩ", "(value_json.R0_max_ohm * 1000) | round(4)"),
        ("soc_mean", "SOC mean", "%", "(value_json.soc_mean * 100) | round(2)"),
    ):
        cfg = {
            **common,
            "name": f"pack {name}",
            "unique_id": f"{node}_pack_{key}",
            "object_id": f"{node}_pack_{key}",
            "state_topic": pack,
            "value_template": f"{{{{ {expr} }}}}",
        }
        if unit is not None:
            cfg["unit_of_measurement"] = unit
            cfg["state_class"] = "measurement"
        out.append((f"{ha_prefix}/sensor/{node}/pack_{key}/config", _dump(cfg)))
    return out


def _dump(cfg: dict[str, Any]) -> bytes:
    return json.dumps(cfg, separators=(",", ":"), ensure_ascii=False).encode()
