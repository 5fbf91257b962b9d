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
    with np.errstate(all="ignore"):  # huge but finite theta may overflow: caught below
        return _theta_to_params(np.asarray(theta, dtype=np.float64), T_s)


def _theta_to_params(th: FloatArray, T_s: float) -> tuple[CircuitParams, IntArray]:
    finite = np.all(np.isfinite(th), axis=-1)
    th = np.where(finite[..., None], th, 0.0)
    t1, t2, t3, t4, t5 = (th[..., j] for j in range(5))
    dm = 1.0 - t1 - t2
    dp = 1.0 + t1 - t2
    stable = (dm > 0) & (dp > 0)
    dm_s = np.where(dm > 0, dm, 1.0)
    dp_s = np.where(dp > 0, dp, 1.0)
    T = T_s
    m1 = (t4 - t3 - t5) / dp_s
    m2 = dp_s * T * T / (4.0 * dm_s)
    m3 = (1.0 + t2) * T / dm_s
    m4 = (-t3 - t4 - t5) / dm_s
    m5 = (t5 - t3) * T / dm_s
    disc = m3 * m3 - 4.0 * m2
    root = np.sqrt(np.where(disc > 0, disc, 0.0))
    tau_f = 0.5 * (m3 - root)
    tau_s = 0.5 * (m3 + root)
    gap = np.where(tau_s - tau_f > 0, tau_s - tau_f, 1.0)
    r_slow = (tau_s * (m4 - m1) + m1 * m3 - m5) / gap
    r_fast = m4 - m1 - r_slow
    fin = np.isfinite(m1) & np.isfinite(r_fast) & np.isfinite(r_slow) & np.isfinite(tau_s)
    # The first failing check names the status (np.select takes the first true condition).
    status = np.select(
        [~finite, ~stable, disc <= 0, (tau_f <= 0) | (tau_s <= 0),
         (m1 <= 0) | (r_fast <= 0) | (r_slow <= 0), ~fin],
        [_NOT_FINITE, _UNSTABLE, _COMPLEX, _NONPOS_TAU, _NONPOS_R, _NOT_FINITE],
        _OK,
    ).astype(np.int64)  # fmt: skip
    good = status == _OK
    out = CircuitParams(
        R0_ohm=np.where(good, m1, 0.0),
        R1_ohm=np.where(good, r_fast, 0.0),
        tau1_s=np.where(good, tau_f, 0.0),
        R2_ohm=np.where(good, r_slow, 0.0),
        tau2_s=np.where(good, tau_s, 0.0),
    )
    return out, status


# Plain ints for the vectorised path (IntEnum item assignment into arrays is slow).
_OK, _NOT_FINITE, _UNSTABLE, _COMPLEX, _NONPOS_TAU, _NONPOS_R = (int(m) for m in MapStatus)


def denominator_condition(theta: FloatArray) -> FloatArray:
    """``1 - th1 - th2``: the divisor of Eq. 22; tiny values mean an ill-conditioned mapping."""
    th = np.asarray(theta, dtype=np.float64)
    return np.asarray(1.0 - th[..., 0] - th[..., 1])
