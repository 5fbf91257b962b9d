"""The 2RC impedance as a 5-parameter ARX model via the bilinear transform (Eq. 11-15, 22-23).

``U_E(k) = th1 U_E(k-1) + th2 U_E(k-2) + th3 I(k) + th4 I(k-1) + th5 I(k-2)`` (Eq. 15) with
``U_E = U_L - OCV - h M``. ``params_to_theta`` is Eq. 12 + Eq. 14; ``theta_to_params`` is the
corrected Eq. 22 (m3 = (1 + th2) T / (1 - th1 - th2)) followed by Eq. 23.

Branch ordering: branch 1 is always the FAST branch (tau1 < tau2). Eq. 23 as printed takes the
larger root as tau1; here tau_slow = (m3 + sqrt(m3^2 - 4 m2)) / 2 goes to branch 2 and
``R_slow = [tau_slow (m4 - m1) + m1 m3 - m5] / (tau_slow - tau_fast)``.

Failures are explicit: every output set carries a ``MapStatus``; invalid sets hold zeros, never NaN.
Conditioning: the map divides by ``1 - th1 - th2`` ~ T^2 / (tau1 tau2), i.e. 5e-5 for
tau = 32 s / 600 s at T = 1 s, so small RLS errors in th1, th2 explode in R and C.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from enum import IntEnum

import numpy as np
import numpy.typing as npt

FloatArray = npt.NDArray[np.float64]
IntArray = npt.NDArray[np.int64]


class MapStatus(IntEnum):
    """Result of mapping ARX coefficients back to circuit parameters."""

    OK = 0
    NOT_FINITE = 1  #: theta contains NaN/inf
    UNSTABLE = 2  #: 1 - th1 - th2 <= 0 or 1 + th1 - th2 <= 0 (poles outside the unit circle)
    COMPLEX_POLES = 3  #: m3^2 - 4 m2 <= 0: no two real time constants
    NONPOSITIVE_TAU = 4
    NONPOSITIVE_R = 5  #: some of R0, R1, R2 <= 0 (so C would be negative or infinite)


@dataclass(frozen=True)
class CircuitParams:
    """R in ohm, tau in s, C in F; arrays of equal shape. Branch 1 = fast."""

    R0_ohm: FloatArray
    R1_ohm: FloatArray
    tau1_s: FloatArray
    R2_ohm: FloatArray
    tau2_s: FloatArray

    @property
    def C1_F(self) -> FloatArray:
        return np.asarray(self.tau1_s / np.where(self.R1_ohm > 0, self.R1_ohm, np.inf))

    @property
    def C2_F(self) -> FloatArray:
        return np.asarray(self.tau2_s / np.where(self.R2_ohm > 0, self.R2_ohm, np.inf))


def params_to_theta(
    R0_ohm: FloatArray | float,
    R1_ohm: FloatArray | float,
    tau1_s: FloatArray | float,
    R2_ohm: FloatArray | float,
    tau2_s: FloatArray | float,
    T_s: float,
) -> FloatArray:
    """theta1..theta5 (last axis) from circuit parameters at sample period ``T_s`` (Eq. 12, 14)."""
    r0, r1, r2 = (np.asarray(x, dtype=np.float64) for x in (R0_ohm, R1_ohm, R2_ohm))
    t1, t2 = np.asarray(tau1_s, dtype=np.float64), np.asarray(tau2_s, dtype=np.float64)
    m1, m2, m3, m4 = r0, t1 * t2, t1 + t2, r0 + r1 + r2
    m5 = r0 * m3 + r1 * t2 + r2 * t1
    T = T_s
    den = T * T + 2 * m3 * T + 4 * m2
    th1 = -(2 * T * T - 8 * m2) / den
    th2 = -(T * T - 2 * m3 * T + 4 * m2) / den
    th3 = -(m4 * T * T + 2 * m5 * T + 4 * m1 * m2) / den
    th4 = -(2 * m4 * T * T - 8 * m1 * m2) / den
    th5 = -(m4 * T * T - 2 * m5 * T + 4 * m1 * m2) / den
    return np.stack([th1, th2, th3, th4, th5], axis=-1)


def theta_to_params(theta: FloatArray, T_s: float) -> tuple[CircuitParams, IntArray]:
    """Circuit parameters and a ``MapStatus`` per set from theta (..., 5) (corrected Eq. 22, 23)."""
    rows, status = theta_to_rows(theta, T_s)
    p = CircuitParams(
        R0_ohm=rows[0].copy(), R1_ohm=rows[1].copy(), tau1_s=rows[4].copy(),
        R2_ohm=rows[2].copy(), tau2_s=rows[3].copy(),
    )  # fmt: skip
    return p, status


def theta_to_rows(theta: FloatArray, T_s: float) -> tuple[FloatArray, IntArray]:
    """``theta_to_params`` as one array (5, ...) of rows R0, R1, R2, tau2, tau1 (branch 2 before
    branch 1: the finiteness check reads R0..tau2 as one block), and the status per set."""
    th = np.asarray(theta, dtype=np.float64)
    if th.ndim == 2 and th.shape[0] <= SCALAR_ROWS:
        return _theta_to_params_rows(th, T_s)
    with np.errstate(all="ignore"):  # huge but finite theta may overflow: caught below
        return _theta_to_params(th, T_s)


#: Up to this many sets are mapped one by one in Python floats (a single cell's tick: ~6 us
#: instead of ~40 us of numpy calls on length-1 arrays); the same IEEE operations in the same
#: order, so the same numbers to the bit (``tests/model/test_arx.py``).
SCALAR_ROWS = 4


def _theta_to_params_rows(th: FloatArray, T_s: float) -> tuple[FloatArray, IntArray]:
    rows = [_map_one(row, T_s) for row in th.tolist()]
    cols = np.array(rows, dtype=np.float64).reshape(len(rows), 6).T
    return cols[1:], cols[0].astype(np.int64)


def _map_one(theta: list[float], T: float) -> tuple[float, float, float, float, float, float]:
    """``_theta_to_params`` for one set in Python floats: (status, R0, R1, R2, tau2, tau1)."""
    t1, t2, t3, t4, t5 = theta
    fail = (0.0, 0.0, 0.0, 0.0, 0.0)
    if not (math.isfinite(t1) and math.isfinite(t2) and math.isfinite(t3)
            and math.isfinite(t4) and math.isfinite(t5)):  # fmt: skip
        return (float(_NOT_FINITE), *fail)
    dm = 1.0 - t1 - t2
    dp = 1.0 + t1 - t2
    if not (dm > 0 and dp > 0):
        return (float(_UNSTABLE), *fail)
    m1 = (t4 - t3 - t5) / dp
    m2 = dp * T * T / (4.0 * dm)
    m3 = (1.0 + t2) * T / dm
    m4 = (-t3 - t4 - t5) / dm
    m5 = (t5 - t3) * T / dm
    disc = m3 * m3 - 4.0 * m2
    if disc <= 0:
        return (float(_COMPLEX), *fail)
    root = math.sqrt(disc) if disc > 0 else 0.0  # NaN: 0, as the array path
    tau_f = 0.5 * (m3 - root)
    tau_s = 0.5 * (m3 + root)
    spread = tau_s - tau_f
    gap = spread if spread > 0 else 1.0
    r_slow = (tau_s * (m4 - m1) + m1 * m3 - m5) / gap
    r_fast = m4 - m1 - r_slow
    if tau_f <= 0 or tau_s <= 0:
        return (float(_NONPOS_TAU), *fail)
    if m1 <= 0 or r_fast <= 0 or r_slow <= 0:
        return (float(_NONPOS_R), *fail)
    if not (math.isfinite(m1) and math.isfinite(r_fast) and math.isfinite(r_slow)
            and math.isfinite(tau_s)):  # fmt: skip
        return (float(_NOT_FINITE), *fail)
    return (float(_OK), m1, r_fast, r_slow, tau_s, tau_f)


def _theta_to_params(th: FloatArray, T_s: float) -> tuple[FloatArray, IntArray]:
    # Every tick maps every cell and, in the 96-cell DST bench, most sets fail some check: numpy
    # calls, not arithmetic, are the cost. So the results go into one array, the checks are a
    # few reductions over its rows and the status is assigned last check first (the first
    # failing check wins, as in the scalar path); the arithmetic is the same IEEE operations.
    finite: npt.NDArray[np.bool_] | None = None
    if not math.isfinite(np.add.reduce(th, axis=None)):  # a finite sum has finite terms
        finite = np.all(np.isfinite(th), axis=-1)
        th = np.where(finite[..., None], th, 0.0)
    t1, t2, t3, t4, t5 = (th[..., j] for j in range(5))
    dm = 1.0 - t1 - t2
    dp = 1.0 + t1 - t2
    stable = np.minimum(dm, dp) > 0  # NaN-propagating: as (dm > 0) & (dp > 0)
    all_stable = np.count_nonzero(stable) == stable.size
    dm_s = dm if all_stable else np.where(dm > 0, dm, 1.0)
    dp_s = dp if all_stable else np.where(dp > 0, dp, 1.0)
    T = T_s
    by_T = T != 1.0  # x * 1.0 is x to the bit: at the usual T = 1 s those products are skipped
    out = np.empty((5, *th.shape[:-1]))
    m1, r_fast, r_slow, tau_s, tau_f = (out[j, ...] for j in range(5))  # m1 is R0
    np.divide(t4 - t3 - t5, dp_s, out=m1)
    m2 = (dp_s * T * T if by_T else dp_s) / (4.0 * dm_s)
    m3 = ((1.0 + t2) * T if by_T else 1.0 + t2) / dm_s
    m4 = (-t3 - t4 - t5) / dm_s
    m5 = ((t5 - t3) * T if by_T else t5 - t3) / dm_s
    disc = m3 * m3 - 4.0 * m2
    root = np.sqrt(np.fmax(disc, 0.0))  # NaN and <= 0: 0 (disc is never -0)
    np.multiply(0.5, m3 - root, out=tau_f)
    np.multiply(0.5, m3 + root, out=tau_s)
    spread = tau_s - tau_f
    gap = np.where(spread > 0, spread, 1.0)
    m41 = m4 - m1
    np.divide(tau_s * m41 + m1 * m3 - m5, gap, out=r_slow)
    np.subtract(m41, r_slow, out=r_fast)
    # fmin skips NaN, so "fmin(a, b) <= 0" is "a <= 0 or b <= 0" as the scalar path tests it.
    status = np.where(np.logical_and.reduce(np.isfinite(out[:4])), _OK, _NOT_FINITE)
    np.copyto(status, _NONPOS_R, where=np.fmin.reduce(out[:3], axis=0) <= 0)
    np.copyto(status, _NONPOS_TAU, where=np.fmin(tau_f, tau_s) <= 0)
    np.copyto(status, _COMPLEX, where=disc <= 0)
    if not all_stable:
        np.copyto(status, _UNSTABLE, where=~stable)
    if finite is not None:
        np.copyto(status, _NOT_FINITE, where=~finite)
    if np.count_nonzero(status):
        np.copyto(out, 0.0, where=status != _OK)
    return out, status


# Plain ints for the vectorised path (IntEnum item assignment into arrays is slow).
_OK, _NOT_FINITE, _UNSTABLE, _COMPLEX, _NONPOS_TAU, _NONPOS_R = (int(m) for m in MapStatus)


def denominator_condition(theta: FloatArray) -> FloatArray:
    """``1 - th1 - th2``: the divisor of Eq. 22; tiny values mean an ill-conditioned mapping."""
    th = np.asarray(theta, dtype=np.float64)
    return np.asarray(1.0 - th[..., 0] - th[..., 1])
