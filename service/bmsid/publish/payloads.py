"""MQTT payloads as plain dicts (pure functions; schemas in ``publish/schemas/*.json``).

Topics: ``<prefix>/<pack_id>/cell/<n>`` (n = 0-based cell index, as the CAN ``CellIndex``),
``<prefix>/<pack_id>/pack`` and ``<prefix>/<pack_id>/status`` (retained). Every quantity carries
its unit in the key; values that are not finite (a missing cell voltage) are ``null``.
"""

from __future__ import annotations

import json
import math
from typing import Any

import numpy as np

from bmsid.estimate.types import Estimates, Quality

SCHEMA_VERSION = 1

#: Health bits of the pack summary (CAN ``Health`` 0..15 and MQTT ``health``).
HEALTH_CONVERGING = 1  #: at least one cell still converging
HEALTH_POORLY_EXCITED = 2  #: the current carries too little information
HEALTH_OUT_OF_BOUNDS = 4  #: at least one cell was clamped to its bounds
HEALTH_INPUT_STALE = 8  #: no sample within the staleness window (set by the daemon)

_CELL_FIELDS: tuple[tuple[str, str], ...] = (
    ("R0_ohm", "R0_ohm"),
    ("R1_ohm", "R1_ohm"),
    ("R2_ohm", "R2_ohm"),
    ("C1_F", "C1_F"),
    ("C2_F", "C2_F"),
    ("tau1_s", "tau1_s"),
    ("tau2_s", "tau2_s"),
    ("M_V", "M_V"),
    ("ocv_offset_V", "ocv_offset_V"),
    ("lambda", "lambda_"),
    ("h", "h"),
    ("soc", "soc"),
    ("v_model_V", "v_model_V"),
    ("v_meas_V", "v_meas_V"),
)


def topic(prefix: str, pack_id: str, *levels: str | int) -> str:
    return "/".join([prefix, pack_id, *(str(x) for x in levels)])


def _num(x: float) -> float | None:
    return float(x) if math.isfinite(x) else None


def cell_payload(est: Estimates, i: int, pack_id: str, seq: int) -> dict[str, Any]:
    """Everything identified for cell ``i`` at ``est.t_s`` (sample time, s)."""
    out: dict[str, Any] = {
        "schema": SCHEMA_VERSION,
        "pack_id": pack_id,
        "cell": i,
        "seq": seq,
        "t_s": float(est.t_s),
    }
    for key, attr in _CELL_FIELDS:
        out[key] = _num(float(getattr(est, attr)[i]))
    out["v_error_V"] = _num(float(est.v_meas_V[i] - est.v_model_V[i]))
    q = int(est.quality[i])
    out["quality"] = q
    out["quality_name"] = Quality(q).name.lower() if q in Quality._value2member_map_ else "unknown"
    return out


def health_bits(est: Estimates) -> int:
    q = est.quality
    bits = 0
    if np.any(q == Quality.CONVERGING):
        bits |= HEALTH_CONVERGING
    if np.any(q == Quality.POORLY_EXCITED):
        bits |= HEALTH_POORLY_EXCITED
    if np.any(q == Quality.OUT_OF_BOUNDS):
        bits |= HEALTH_OUT_OF_BOUNDS
    return bits


def pack_payload(est: Estimates, pack_id: str, seq: int, health: int) -> dict[str, Any]:
    """Pack summary: R0 and SOC spread, the weakest cell (largest R0), quality counts."""
    r0 = np.asarray(est.R0_ohm, dtype=np.float64)
    soc = np.asarray(est.soc, dtype=np.float64)
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
    }


def status_payload(
    state: str,
    pack_id: str,
    *,
    can_state: str = "unknown",
    uptime_s: float = 0.0,
    counters: dict[str, float] | None = None,
    version: str = "",
    mqtt: dict[str, str | None] | None = None,
) -> dict[str, Any]:
    """``online``/``offline`` with the daemon's counters (the will carries ``offline`` only);
    ``mqtt`` is the connection's ``{"state", "last_error"}`` (never a secret)."""
    out: dict[str, Any] = {"schema": SCHEMA_VERSION, "state": state, "pack_id": pack_id}
    if version:
        out["version"] = version
    if state == "online":
        out["can"] = can_state
        if mqtt is not None:
            out["mqtt"] = dict(mqtt)
        out["uptime_s"] = round(float(uptime_s), 3)
        out["counters"] = dict(counters or {})
    return out


def encode(payload: dict[str, Any]) -> bytes:
    """Compact JSON; floats keep their full repr (what is published is what was computed)."""
    return json.dumps(payload, separators=(",", ":"), allow_nan=False).encode()
