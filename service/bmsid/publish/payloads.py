"""MQTT payloads as plain dicts (pure functions; schemas in ``publish/schemas/*.json``).

Topics: ``<prefix>/<pack_id>/cell/<n>`` (n = 0-based cell index, as the CAN ``CellIndex``),
``<prefix>/<pack_id>/pack`` and ``<prefix>/<pack_id>/status`` (retained). Every quantity carries
its unit in the key; values that are not finite (a missing cell voltage) are ``null``. A cell of
quality ``no_data`` (no valid reading since its start, or for ``gap_s``) has every field
``null``: nothing is invented for it, and it counts in no pack aggregate.
"""

from __future__ import annotations

import json
import math
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

from bmsid.estimate import fields
from bmsid.estimate.fields import FieldSpec
from bmsid.estimate.types import Estimates, Quality

SCHEMA_VERSION = 1

#: Health bits of the pack summary (MQTT ``health``; on CAN, ``PackState``'s ``Health`` holds
#: every bit, ``PackSummary``'s ``Health`` bits 1..8 and its ``Diverged`` bit 16).
HEALTH_CONVERGING = 1  #: at least one cell still converging
HEALTH_POORLY_EXCITED = 2  #: the current carries too little information
HEALTH_OUT_OF_BOUNDS = 4  #: at least one cell hit its bounds (its last good values are published)
#: no sample within the staleness window (set by the daemon), or a cell without a valid reading
HEALTH_INPUT_STALE = 8
HEALTH_DIVERGED = 16  #: at least one cell diverged (held, being re-initialised)
#: the latest checkpoint or ``.seq`` reservation could not be written (state directory
#: read-only, full, failing): a restart would lose state, data messages may be withheld
HEALTH_STATE_DIR = 32


def topic(prefix: str, pack_id: str, *levels: str | int) -> str:
    return "/".join([prefix, pack_id, *(str(x) for x in levels)])


def _num(x: float) -> float | None:
    return float(x) if math.isfinite(x) else None


def cell_payload(est: Estimates, i: int, pack_id: str, seq: int) -> dict[str, Any]:
    """Everything identified for cell ``i`` at ``est.t_s`` (sample time, s): every field of
    ``CELL_FIELDS`` published on MQTT, under its ``out_key`` (units in the key), then quality."""
    out: dict[str, Any] = {
        "schema": SCHEMA_VERSION,
        "pack_id": pack_id,
        "cell": i,
        "seq": seq,
        "t_s": float(est.t_s),
    }
    for spec in fields.CELL_FIELDS:  # read at call time: the table is the one list
        if spec.mqtt:
            out[spec.out_key] = _num(float(est.cells[spec.name][i]))
    q = int(est.quality[i])
    out["quality"] = q
    out["quality_name"] = Quality(q).name.lower() if q in Quality._value2member_map_ else "unknown"
    return out


#: The cell schema as shipped (``python -m bmsid.docgen`` rewrites it from :func:`cell_schema`).
CELL_SCHEMA_PATH = Path(__file__).resolve().parent / "schemas" / "cell.json"

#: Cell-schema entries that are not fields of the table: they come before the fields.
_CELL_SCHEMA_HEAD: dict[str, dict[str, Any]] = {
    "schema": {"const": SCHEMA_VERSION},
    "pack_id": {"type": "string", "pattern": "^[A-Za-z0-9_.-]{1,64}$"},
    "cell": {
        "type": "integer",
        "minimum": 0,
        "maximum": 511,
        "description": "0-based cell index (CAN CellIndex)",
    },
    "seq": {
        "type": "integer",
        "minimum": 0,
        "description": "sequence number over all data messages (cell and pack) of the pack; "
        "contiguous unless the outbox overflowed",
    },
    "t_s": {
        "type": "number",
        "description": "sample time, s (the CAN frames' clock: Unix time on SocketCAN)",
    },
}


def _json_number(x: float) -> float | int:
    """``1`` rather than ``1.0`` in the schema file, as written by hand before it was generated."""
    return int(x) if float(x).is_integer() else float(x)


def field_schema(spec: FieldSpec) -> dict[str, Any]:
    """JSON-schema entry of one table field: a number (or null where ``spec.nullable``) within
    the spec's bounds, described with its unit."""
    entry: dict[str, Any] = {"type": ["number", "null"] if spec.nullable else "number"}
    if spec.positive:
        entry["exclusiveMinimum"] = 0
    if spec.lo is not None:
        entry["minimum"] = _json_number(spec.lo)
    if spec.hi is not None:
        entry["maximum"] = _json_number(spec.hi)
    entry["description"] = f"{spec.description} [{spec.unit}]" if spec.unit else spec.description
    return entry


def cell_schema() -> dict[str, Any]:
    """The JSON schema (draft 2020-12) of :func:`cell_payload`, built from ``CELL_FIELDS``."""
    props: dict[str, Any] = dict(_CELL_SCHEMA_HEAD)
    props |= {s.out_key: field_schema(s) for s in fields.CELL_FIELDS if s.mqtt}
    specs = [s for s in fields.CELL_FIELDS if s.mqtt]
    # Every field may be null, but only a NO_DATA cell has non-nullable fields null.
    for s in specs:
        props[s.out_key]["type"] = ["number", "null"]
    props["quality"] = {
        "type": "integer",
        "enum": [int(q) for q in Quality],
        "description": ", ".join(f"{int(q)} {q.name.lower().replace('_', ' ')}" for q in Quality),
    }
    props["quality_name"] = {"enum": [q.name.lower() for q in Quality] + ["unknown"]}
    return {
        "$schema": "https://json-schema.org/draft/2020-12/schema",
        "$id": "https://bmsid.invalid/schemas/cell.json",
        "title": "bmsid cell parameters: <prefix>/<pack_id>/cell/<n>",
        "type": "object",
        "properties": props,
        "required": list(props),
        "additionalProperties": False,
        "if": {"properties": {"quality": {"const": int(Quality.NO_DATA)}}},
        "then": {"properties": {s.out_key: {"type": "null"} for s in specs}},
        "else": {"properties": {s.out_key: {"type": "number"} for s in specs if not s.nullable}},
    }


def schema_text(schema: dict[str, Any]) -> str:
    """A schema as its file holds it (2-space indent, trailing newline)."""
    return json.dumps(schema, indent=2, ensure_ascii=False) + "\n"


def health_bits(est: Estimates, *, state_dir_failing: bool = False) -> int:
    """The ``HEALTH_*`` bits of ``est``'s cells, and :data:`HEALTH_STATE_DIR` if
    ``state_dir_failing`` (a stale input, seen over time, is the daemon's to add)."""
    q = est.quality
    bits = HEALTH_STATE_DIR if state_dir_failing else 0
    if np.any(q == Quality.CONVERGING):
        bits |= HEALTH_CONVERGING
    if np.any(q == Quality.POORLY_EXCITED):
        bits |= HEALTH_POORLY_EXCITED
    if np.any(q == Quality.OUT_OF_BOUNDS):
        bits |= HEALTH_OUT_OF_BOUNDS
    if np.any(q == Quality.DIVERGED):
        bits |= HEALTH_DIVERGED
    if np.any(q == Quality.NO_DATA):
        bits |= HEALTH_INPUT_STALE
    return bits


def pack_payload(
    est: Estimates, pack_id: str, seq: int, health: int, missing: Sequence[int] = ()
) -> dict[str, Any]:
    """Pack summary: R0 and SOC spread, the weakest cell (largest R0), the current-sensor
    offset (one per pack: the mean of the cells' finite values), quality counts, and the
    configured cells that never carried a reading (``missing``, 0-based). Aggregates are over
    the cells with data only (a ``no_data`` cell's fields are NaN)."""
    r0 = np.asarray(est.R0_ohm, dtype=np.float64)
    soc = np.asarray(est.soc, dtype=np.float64)
    offset = np.asarray(est.cells["current_offset_A"], dtype=np.float64)
    fin = np.isfinite(r0)
    weakest = int(np.flatnonzero(fin)[int(np.argmax(r0[fin]))]) if fin.any() else None
    counts = {q.name.lower(): int(np.sum(est.quality == q)) for q in Quality}

    def stat(a: np.ndarray[Any, np.dtype[np.float64]], f: str) -> float | None:
        a = a[np.isfinite(a)]
        return _num(float(getattr(np, f)(a))) if a.size else None

    return {
        "schema": SCHEMA_VERSION,
        "pack_id": pack_id,
        "seq": seq,
        "t_s": float(est.t_s),
        "current_A": _num(float(est.current_A)),
        "current_offset_A": stat(offset, "mean"),
        "n_cells": est.n_cells,
        "R0_min_ohm": stat(r0, "min"),
        "R0_mean_ohm": stat(r0, "mean"),
        "R0_max_ohm": stat(r0, "max"),
        "weakest_cell": weakest,
        "soc_min": stat(soc, "min"),
        "soc_mean": stat(soc, "mean"),
        "soc_max": stat(soc, "max"),
        "health": int(health),
        "quality_counts": counts,
        "missing_cells": [int(c) for c in missing],
    }


def status_payload(
    state: str,
    pack_id: str,
    *,
    can_state: str = "unknown",
    uptime_s: float = 0.0,
    counters: dict[str, float] | None = None,
    lifetime: dict[str, int] | None = None,
    version: str = "",
    mqtt: dict[str, str | None] | None = None,
    inputs: dict[str, Any] | None = None,
    state_dir: str | None = None,
    soc_init: str | None = None,
) -> dict[str, Any]:
    """``online``/``offline`` with the daemon's counters since its process started (the will
    carries ``offline`` only); ``lifetime`` the estimator state's samples, ticks and swarms since
    it began, carried across restarts by the checkpoint;
    ``mqtt`` is the connection's ``{"state", "last_error"}`` (never a secret); ``inputs`` what
    the plausibility gates refused per cell, and the missing and no-data cells
    (``bmsid.gates.GateState.report``); ``state_dir`` ``"ok"`` or ``"failing"``
    (:data:`HEALTH_STATE_DIR`); ``soc_init`` how the bank's SOC started
    (``EstimatorBank.soc_init_method``)."""
    out: dict[str, Any] = {"schema": SCHEMA_VERSION, "state": state, "pack_id": pack_id}
    if version:
        out["version"] = version
    if state == "online":
        out["can"] = can_state
        if mqtt is not None:
            out["mqtt"] = dict(mqtt)
        if state_dir is not None:
            out["state_dir"] = state_dir
        if soc_init is not None:
            out["soc_init"] = soc_init
        out["uptime_s"] = round(float(uptime_s), 3)
        out["counters"] = dict(counters or {})
        if lifetime is not None:
            out["lifetime"] = dict(lifetime)
        if inputs is not None:
            out["inputs"] = inputs
    return out


def encode(payload: dict[str, Any]) -> bytes:
    """Compact JSON; floats keep their full repr (what is published is what was computed)."""
    return json.dumps(payload, separators=(",", ":"), allow_nan=False).encode()
