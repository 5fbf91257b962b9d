"""Home Assistant MQTT discovery: one device per pack, one sensor per cell and parameter.

Config messages are retained under ``<ha_prefix>/sensor/<node>/<object>/config``; availability
follows bmsid's retained status topic (``value_json.state``). Estimator internals are
``entity_category: diagnostic`` so that a default dashboard shows the parameters first. The
per-cell sensors are the fields of ``CELL_FIELDS`` that have an ``ha`` entry, plus the quality.
"""

from __future__ import annotations

import json
import keyword
from typing import Any

from bmsid.estimate import fields
from bmsid.estimate.fields import FieldSpec, HaSensor

#: Payload key of the per-cell quality sensor, offered after the table's fields.
QUALITY_SENSOR = "quality"


def ha_fields() -> list[tuple[FieldSpec, HaSensor]]:
    """The table's fields offered as Home Assistant sensors (read at call time), in table order."""
    return [(s, s.ha) for s in fields.CELL_FIELDS if s.ha is not None]


def cell_sensor_keys() -> list[str]:
    """Payload key of every per-cell sensor; a sensor's object id is ``cell<n>_<key>``
    lowercased (Home Assistant's entity ids derive from it: it must never change)."""
    return [s.out_key for s, _ in ha_fields()] + [QUALITY_SENSOR]


def value_template(spec: FieldSpec, ha: HaSensor) -> str:
    """Jinja template of a field's sensor: the payload value (SI) x ``ha.scale``, rounded to
    ``ha.digits`` decimals."""
    key = spec.out_key
    # `value_json.lambda` is not valid there (a reserved word): such keys are subscripted
    plain = key.isidentifier() and not keyword.iskeyword(key)
    ref = f"value_json.{key}" if plain else f"value_json['{key}']"
    expr = ref if ha.scale == 1.0 else f"{ref} * {ha.scale:g}"
    return f"{{{{ ({expr}) | round({ha.digits}) }}}}"


def _cell_sensor(
    common: dict[str, Any], node: str, c: int, state: str, key: str, name: str, template: str
) -> tuple[str, dict[str, Any]]:
    obj = f"cell{c}_{key}".lower()
    cfg = {
        **common,
        "name": f"cell {c} {name}",
        "unique_id": f"{node}_{obj}",
        "object_id": f"{node}_{obj}",
        "state_topic": state,
        "value_template": template,
    }
    return obj, cfg


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
    sensors = ha_fields()
    for c in range(n_cells):
        state = f"{topic_prefix}/{pack_id}/cell/{c}"
        for spec, ha in sensors:
            template = value_template(spec, ha)
            obj, cfg = _cell_sensor(common, node, c, state, spec.out_key, ha.name, template)
            cfg["state_class"] = "measurement"
            if ha.unit is not None:
                cfg["unit_of_measurement"] = ha.unit
            if ha.device_class is not None:
                cfg["device_class"] = ha.device_class
            if ha.diagnostic:
                cfg["entity_category"] = "diagnostic"
            out.append((f"{ha_prefix}/sensor/{node}/{obj}/config", _dump(cfg)))
        obj, cfg = _cell_sensor(
            common, node, c, state, QUALITY_SENSOR, "quality", "{{ value_json.quality_name }}"
        )
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
