"""Incremental OCV tests (a pulse, a long rest, a pulse, ...): the rests' voltages are the points.

Many OCV tests move SOC in steps of a few percent at C/5-1C and rest tens of minutes to hours
after each (an incremental OCV or GITT-like test; CALCE's rest tables come from such tests): no
branch runs at C/20, and the low-rate path (``ocv_fit.extract_branches``) refuses it as too
fast. Here each long rest's last voltage is an OCV point at the rest's counted SOC, on the
branch of the pulse before it; the rest before the first pulse closes the charge (or discharge)
that brought the cell to its start, the other branch. The points then go to
``ocv_fit.fit_rest_points`` as rest tables do (``fit-ocv --points``): no IR correction (a rest
carries no current), M(z) from the branches' gap, the rested ends as ``v_empty_V``/``v_full_V``.

SOC is counted from the start (full for a discharge-first test, empty for a charge-first one)
over the measured capacity, the charge from that start to the deepest point, or the given one;
the charge counting factor (coulombic efficiency) is the given one, else the ratio of the
charge out to the charge in where the test returns to where it started (Plett's method), else
1. What is left of the relaxation at a rest's end moves its point towards its pulse's side
(discharge points low, charge points high: a larger gap); the report gives how fast the
rests' last ten minutes still moved. Pure numpy.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np
import numpy.typing as npt

from bmsid.offline.ocv_fit import REST_FRACTION, OcvTestPart, charge_counts, file_runs, joined

FloatArray = npt.NDArray[np.float64]
Points = tuple[FloatArray, FloatArray]

#: A rest this long (s) gives an OCV point.
MIN_POINT_REST_S = 600.0
#: Pulses of one sign needed, each moving at least ``MIN_PULSE_SHARE`` of the test's swing (the
#: charge of its larger direction).
MIN_PULSES = 4
MIN_PULSE_SHARE = 0.01
#: A test whose largest pulse moves more than this share of its sign's charge has a branch: it
#: is a low-rate test (or a drive), not an incremental one.
MAX_PULSE_SHARE = 0.5
#: A point's voltage: the mean over its rest's last this many seconds (the noise averaged).
END_WINDOW_S = 60.0
#: The relaxation left at a rest's end: the voltage's slope over its last this many seconds.
DRIFT_WINDOW_S = 600.0
#: The test returns to its start (so the charge out over the charge in is the counting factor)
#: when its last rest lies within this of its first one, V.
RETURN_TOL_V = 0.005


@dataclass(frozen=True)
class IncrementalPoints:
    """The OCV points of an incremental test per branch (SOC fraction, V), the capacity (Ah)
    used and measured, the charge counting factor and report lines."""

    discharge: Points | None
    charge: Points | None
    capacity_Ah: float
    measured_capacity_Ah: float
    eta: float
    info: list[str] = field(default_factory=list)


def _span_s(t: FloatArray, a: int, b: int) -> float:
    """How long the run [a, b) lasts, s, its last sample's interval included (a 10 min rest at
    1 s is 600 samples), within its file."""
    return float(t[b - 1] - t[a] + (t[b - 1] - t[b - 2] if b - a >= 2 else 0.0))


def _pulses(
    sign: npt.NDArray[np.int64], ah: FloatArray, s: int, swing_Ah: float,
    file_start: npt.NDArray[np.bool_],
) -> tuple[list[int], float]:  # fmt: skip
    """(the last sample of each pulse of sign ``s`` that moves at least ``MIN_PULSE_SHARE`` of
    ``swing_Ah``, the larger of the test's two directions, the largest pulse's share of this
    sign's charge). Smaller pulses (an HPPC test's 10 s ones) leave the hysteresis state where
    it was: they do not set a rest's branch."""
    runs = file_runs(sign == s, file_start)
    per = np.array([abs(float(ah[b] - ah[a])) for a, b in runs]) if runs else np.zeros(0)
    total = float(per.sum())
    if total <= 0:
        return [], 1.0
    ends = [b - 1 for (_, b), q in zip(runs, per, strict=True) if q >= MIN_PULSE_SHARE * swing_Ah]
    return ends, float(per.max() / total)


def incremental_points(
    parts: Sequence[OcvTestPart], capacity_Ah: float | None = None,
    coulombic_efficiency: float | None = None,
) -> IncrementalPoints | None:  # fmt: skip
    """The points of ``parts`` (in time order) if they are an incremental OCV test (module
    doc): at least ``MIN_PULSES`` pulses of the first pulse's sign, none of them carrying more
    than ``MAX_PULSE_SHARE`` of that sign's charge; else None (a low-rate test)."""
    t, i, v, file_start = joined(parts)
    i_max = float(np.max(np.abs(i))) if i.size else 0.0
    if i_max <= 0:
        return None
    sign = np.where(i > REST_FRACTION * i_max, 1, np.where(i < -REST_FRACTION * i_max, -1, 0))
    d_cum, c_cum = charge_counts(t, i, file_start)
    swing = max(float(d_cum[-1]), float(c_cum[-1]))
    dis, share_d = _pulses(sign, d_cum, 1, swing, file_start)
    chg, share_c = _pulses(sign, c_cum, -1, swing, file_start)
    if not dis and not chg:
        return None
    s1 = 1 if dis and (not chg or dis[0] < chg[0]) else -1  # +1: starts full, discharges first
    first, share_first = (dis, share_d) if s1 > 0 else (chg, share_c)
    n_first = len(first)
    if n_first < MIN_PULSES or share_first > MAX_PULSE_SHARE:
        return None
    ends = np.array(sorted(dis + chg), dtype=np.int64)  # the pulses that set a rest's branch
    rests = file_runs(sign == 0, file_start)
    rests = [(a, b) for a, b in rests if _span_s(t, a, b) >= MIN_POINT_REST_S]
    if len(rests) < MIN_PULSES:
        return None

    f0 = int(np.flatnonzero(sign != 0)[0])  # the start: SOC 1 (discharge first) or 0
    tot_d, tot_c = float(d_cum[-1] - d_cum[f0]), float(c_cum[-1] - c_cum[f0])
    v_end = [_end_voltage(t, v, a, b) for a, b in rests]
    returns = abs(v_end[-1] - v_end[0]) <= RETURN_TOL_V and tot_d > 0 and tot_c > 0
    if coulombic_efficiency is not None:
        eta, eta_src = coulombic_efficiency, "given"
    elif returns:
        eta, eta_src = tot_d / tot_c, "the charge out over the charge in: the test returns to "
        eta_src += "its start"
    else:
        eta, eta_src = 1.0, "1: the test does not return to its start (last rest "
        eta_src += f"{1e3 * (v_end[-1] - v_end[0]):+.1f} mV from the first)"
    q = d_cum - eta * c_cum  # Ah out, charge counted by eta
    measured = float(np.max(s1 * (q - q[f0])))
    if measured <= 0:
        return None
    cap = capacity_Ah if capacity_Ah is not None else measured
    z = (1.0 if s1 > 0 else 0.0) - (q - q[f0]) / cap

    pts: dict[int, tuple[list[float], list[float]]] = {1: ([], []), -1: ([], [])}
    drift: list[float] = []
    for (a, b), u in zip(rests, v_end, strict=True):
        before = ends[ends < a]
        branch = int(sign[before[-1]]) if before.size else -s1
        if not np.isfinite(u):
            continue  # a rest without a voltage at its end
        pts[branch][0].append(float(z[b]))
        pts[branch][1].append(u)
        drift.append(_drift_V_per_h(t, v, a, b))

    def arrays(s: int) -> Points | None:
        zs, vs = pts[s]
        return (np.array(zs), np.array(vs)) if zs else None

    n_d, n_c = len(pts[1][0]), len(pts[-1][0])
    info = [
        f"an incremental OCV test ({n_first} {'discharge' if s1 > 0 else 'charge'} pulses of at "
        f"most {100 * share_first:.0f} % of the charge, rests between): the last "
        f"{END_WINDOW_S:.0f} s of each of its {len(rests)} rests of >= {MIN_POINT_REST_S:.0f} s "
        f"are the OCV points, {n_d} on the discharge branch and {n_c} on the charge branch",
        f"capacity measured from the test: {measured:.4f} Ah (used: {cap:.4f} Ah); SOC counted "
        f"from {'full' if s1 > 0 else 'empty'} at the start; charge counting factor "
        f"{eta:.4f} ({eta_src})",
        f"relaxation left at the rests' ends (slope over their last {DRIFT_WINDOW_S:.0f} s): "
        f"median {np.median(np.abs(drift)):.2f} mV/h, largest {np.max(np.abs(drift)):.2f} mV/h "
        "(it moves a point towards its pulse's side)",
    ]
    return IncrementalPoints(arrays(1), arrays(-1), cap, measured, eta, info)


def _end_voltage(t: FloatArray, v: FloatArray, a: int, b: int) -> float:
    """Mean voltage over the rest's last ``END_WINDOW_S`` (at least its last sample), V."""
    k = int(np.searchsorted(t[a:b], t[b - 1] - END_WINDOW_S)) + a
    seg = v[min(k, b - 1) : b]
    return float(np.mean(seg[np.isfinite(seg)])) if np.isfinite(seg).any() else float("nan")


def _drift_V_per_h(t: FloatArray, v: FloatArray, a: int, b: int) -> float:
    """The voltage's slope over the rest's last ``DRIFT_WINDOW_S``, mV per hour."""
    k = int(np.searchsorted(t[a:b], t[b - 1] - DRIFT_WINDOW_S)) + a
    tt, vv = t[k:b], v[k:b]
    ok = np.isfinite(vv)
    if np.count_nonzero(ok) < 3 or np.ptp(tt[ok]) <= 0:
        return 0.0
    return float(np.polyfit(tt[ok], vv[ok], 1)[0]) * 3.6e6
