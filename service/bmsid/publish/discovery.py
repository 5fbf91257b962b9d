"""Home Assistant MQTT discovery: one device per pack, one sensor per cell and parameter.

Config messages are retained under ``<ha_prefix>/sensor/<node>/<object>/config``; availability
follows bmsid's retained status topic (``value_json.state``). What current Home Assistant
(2025.10 and later, checked against a real one by ``tests/dashboards/test_home_assistant.py``)
expects of them:

- ``default_entity_id`` (``sensor.<node>_<object>``), not ``object_id``: deprecated in 2025.10
  with a repair issue per entity, removed in 2026.4;
- an ``origin`` block naming the application that published the config;
- value templates that render ``none`` when the payload's value is null (a missing cell voltage,
  a pack without a finite R0): Home Assistant then shows ``unknown`` instead of keeping the stale
  value and logging a template error for ``None * 1000``;
- ``quality`` as an enum sensor whose options are the codes of ``estimate.types.Quality``.

A configured cell that has not been on the bus in this run (``missing_cells`` in the status:
``n_cells`` larger than the pack, or a cell whose first frames were lost) is not published, so
its sensors show ``unknown``, as every value bmsid does not have (the status's
``missing_cells`` says why). The configs are published at connect for every configured cell,
before any frame tells which are there: withholding them would remove the entities (and their
history) of a pack that is merely asleep at a restart.

Estimator internals (the table's ``diagnostic`` fields: forgetting factor, hysteresis state,
model error, the uncertainties, the pack's current offset repeated per cell) are
``entity_category: diagnostic`` and ``enabled_by_default: false``: they describe the estimator,
not the cell, and a user who wants them enables them. The quality stays enabled: it tells
whether the parameters beside it can be trusted.

Configs published earlier that are not in the current set (``n_cells`` reduced, ``pack_id``
renamed) are cleared with an empty retained payload, which removes the entity from Home
Assistant. :class:`PublishedConfigs` remembers the set in the state directory: only the daemon
knows that it was another pack before, while the broker's retained configs of a renamed pack
look exactly like those of a second live pack on the same broker, which must not be cleared.
"""

from __future__ import annotations

import contextlib
import importlib.metadata
import json
import keyword
import logging
import os
from collections.abc import Iterable, Sequence
from pathlib import Path
from typing import Any

from bmsid.estimate import fields
from bmsid.estimate.fields import FieldSpec, HaSensor
from bmsid.estimate.types import Quality

log = logging.getLogger(__name__)

#: Payload key of the per-cell quality sensor, offered after the table's fields.
QUALITY_SENSOR = "quality"

#: File in the state directory that lists the config topics published last.
RECORD_FILE = "ha-discovery.json"
_RECORD_FORMAT = 1

Message = tuple[str, bytes]


def ha_fields() -> list[tuple[FieldSpec, HaSensor]]:
    """The table's fields offered as Home Assistant sensors (read at call time), in table order."""
    return [(s, s.ha) for s in fields.CELL_FIELDS if s.ha is not None]


def cell_sensor_keys() -> list[str]:
    """Payload key of every per-cell sensor; a sensor's object id is ``cell<n>_<key>``
    lowercased (Home Assistant's entity ids derive from it: it must never change)."""
    return [s.out_key for s, _ in ha_fields()] + [QUALITY_SENSOR]


def quality_options() -> list[str]:
    """States of the quality enum sensor: the names of ``Quality``'s codes (read at call time)."""
    return [q.name.lower() for q in Quality]


def is_internal(ha: HaSensor) -> bool:
    """An estimator internal: disabled by default in Home Assistant (see the module docstring)."""
    return ha.diagnostic


def _ref(key: str) -> str:
    # `value_json.lambda` is not valid there (a reserved word): such keys are subscripted
    plain = key.isidentifier() and not keyword.iskeyword(key)
    return f"value_json.{key}" if plain else f"value_json['{key}']"


def number_template(key: str, scale: float = 1.0, digits: int = 4) -> str:
    """Jinja template of a numeric payload value x ``scale`` rounded to ``digits`` decimals, or
    ``none`` (state ``unknown``) when the value is null or absent."""
    ref = _ref(key)
    expr = ref if scale == 1.0 else f"{ref} * {scale:g}"
    return f"{{{{ ({expr}) | round({digits}) if {ref} is number else none }}}}"


def value_template(spec: FieldSpec, ha: HaSensor) -> str:
    """Template of a table field's sensor: the payload value (SI) x ``ha.scale``, rounded to
    ``ha.digits`` decimals, ``none`` when null."""
    return number_template(spec.out_key, ha.scale, ha.digits)


def quality_template() -> str:
    """The quality's name when it is one of the enum's options, else ``none`` (an enum sensor
    refuses a state outside its options with an error)."""
    ref = _ref("quality_name")
    return f"{{{{ {ref} if {ref} in {quality_options()!r} else none }}}}"


def node_id(pack_id: str) -> str:
    """Discovery node id (and entity id prefix) of a pack."""
    return f"bmsid_{pack_id}".replace(".", "_").replace("-", "_")


def origin(version: str) -> dict[str, str]:
    """The ``origin`` block: bmsid, its version and, when the installed package names one, its
    project URL (Home Assistant links it from the device page)."""
    out = {"name": "bmsid", "sw_version": version}
    url = _project_url()
    if url is not None:
        out["support_url"] = url
    return out


def _project_url() -> str | None:
    try:
        meta = importlib.metadata.metadata("bmsid")
    except importlib.metadata.PackageNotFoundError:
        return None
    for entry in meta.get_all("Project-URL") or ():
        url = str(entry).partition(",")[2].strip()
        if url.startswith(("http://", "https://")):
            return url
    return None


def discovery_messages(
    ha_prefix: str, topic_prefix: str, pack_id: str, n_cells: int, version: str
) -> list[Message]:
    """Retained config messages for every cell's sensors and the pack summary."""
    node = node_id(pack_id)
    common: dict[str, Any] = {
        "device": {
            "identifiers": [node],
            "name": f"bmsid pack {pack_id}",
            "manufacturer": "bmsid",
            "model": "online cell parameter identification (2RC + hysteresis)",
            "sw_version": version,
        },
        "origin": origin(version),
        "availability_topic": f"{topic_prefix}/{pack_id}/status",
        "availability_template": "{{ value_json.state }}",
        "payload_available": "online",
        "payload_not_available": "offline",
    }

    def sensor(obj: str, name: str, state: str, template: str, **extra: Any) -> Message:
        cfg = {
            **common,
            "name": name,
            "unique_id": f"{node}_{obj}",
            "default_entity_id": f"sensor.{node}_{obj}",
            "state_topic": state,
            "value_template": template,
            **extra,
        }
        return f"{ha_prefix}/sensor/{node}/{obj}/config", _dump(cfg)

    out: list[Message] = []
    sensors = ha_fields()
    for c in range(n_cells):
        state = f"{topic_prefix}/{pack_id}/cell/{c}"
        for spec, ha in sensors:
            extra: dict[str, Any] = {"state_class": "measurement"}
            if ha.unit is not None:
                extra["unit_of_measurement"] = ha.unit
            if ha.device_class is not None:
                extra["device_class"] = ha.device_class
            if ha.diagnostic:
                extra["entity_category"] = "diagnostic"
            if is_internal(ha):
                extra["enabled_by_default"] = False
            obj = f"cell{c}_{spec.out_key}".lower()
            out.append(sensor(obj, f"cell {c} {ha.name}", state, value_template(spec, ha), **extra))
        out.append(
            sensor(
                f"cell{c}_{QUALITY_SENSOR}",
                f"cell {c} quality",
                state,
                quality_template(),
                device_class="enum",
                options=quality_options(),
                entity_category="diagnostic",
            )
        )
    pack = f"{topic_prefix}/{pack_id}/pack"
    out.append(sensor("pack_weakest_cell", "pack weakest cell", pack, number_template(
        "weakest_cell", digits=0)))  # fmt: skip
    out.append(sensor("pack_r0_max", "pack R0 max", pack, number_template("R0_max_ohm", 1000.0),
                      unit_of_measurement="mΩ", state_class="measurement"))  # fmt: skip
    out.append(sensor("pack_soc_mean", "pack SOC mean", pack, number_template("soc_mean", 100.0, 2),
                      unit_of_measurement="%", state_class="measurement"))  # fmt: skip
    return out


def _dump(cfg: dict[str, Any]) -> bytes:
    return json.dumps(cfg, separators=(",", ":"), ensure_ascii=False).encode()


def with_clears(current: Sequence[Message], previous: Iterable[str]) -> list[Message]:
    """An empty retained payload (Home Assistant removes the entity) for each topic of
    ``previous`` that ``current`` lacks, sorted, then ``current``."""
    keep = {t for t, _ in current}
    return [(t, b"") for t in sorted(set(previous) - keep)] + list(current)


class PublishedConfigs:
    """The config topics this daemon has published, kept in ``<state directory>/RECORD_FILE``.

    ``messages(current)`` returns the clears of what was published before and is not in
    ``current``, then ``current``; it first records the union, so a connection lost half-way
    leaves nothing forgotten. ``sent()`` (after the broker acknowledged all of them) records
    ``current`` alone. A record that cannot be read or written costs one warning line: the
    configs are published all the same, only stale ones of an earlier run may stay.
    """

    def __init__(self, directory: Path) -> None:
        self.path = directory / RECORD_FILE
        self._warned = False  # one line per run about the record, whatever goes wrong
        self._known: set[str] = self._load()
        self._current: set[str] = set()

    def _load(self) -> set[str]:
        try:
            doc = json.loads(self.path.read_text(encoding="utf-8"))
            topics = doc["topics"] if doc.get("format") == _RECORD_FORMAT else None
            if not isinstance(topics, list) or not all(isinstance(t, str) for t in topics):
                raise ValueError("not a list of topics")
        except FileNotFoundError:
            return set()
        except (OSError, ValueError, KeyError, TypeError, AttributeError) as exc:
            self._warned = True
            log.warning(
                "%s unreadable (%s): configs of removed cells or a renamed pack published "
                "before stay in Home Assistant (delete them there)",
                self.path,
                exc,
            )
            return set()
        return set(topics)

    def messages(self, current: Sequence[Message]) -> list[Message]:
        out = with_clears(current, self._known)
        self._current = {t for t, _ in current}
        self._known |= self._current
        self._save(self._known)
        return out

    def sent(self) -> None:
        self._known = set(self._current)
        self._save(self._known)

    def _save(self, topics: set[str]) -> None:
        tmp = self.path.with_name(f".{self.path.name}.{os.getpid()}.tmp")
        try:
            self.path.parent.mkdir(parents=True, exist_ok=True)
            with tmp.open("w", encoding="utf-8") as fh:
                json.dump({"format": _RECORD_FORMAT, "topics": sorted(topics)}, fh, indent=0)
                fh.flush()
                os.fsync(fh.fileno())
            os.replace(tmp, self.path)
        except OSError as exc:
            with contextlib.suppress(OSError):
                tmp.unlink(missing_ok=True)
            if not self._warned:
                self._warned = True
                log.warning(
                    "cannot record the published Home Assistant configs in %s (%s): configs "
                    "of cells removed later may stay in Home Assistant",
                    self.path,
                    exc,
                )
