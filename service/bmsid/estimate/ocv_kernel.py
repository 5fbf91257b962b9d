"""The OCV curve (Eq. 4, its correction table, its end segments) and its slope at one SOC, as
the compiled kernels call them (``observer_kernel.py``): ``model/ocv.py``'s ``OcvModel.ocv`` /
``docv_dz`` with the same operations in the same order, over the float vector that
``state_jit.ocv_params`` packs (layout below). Plain Python marked ``@helper``; the kernels that
embed these name this file in ``jit.Kernel``'s ``depends`` (numba's cache follows the kernel's
own file only).
"""

from __future__ import annotations

import math

from bmsid.estimate.jit_helpers import helper
from bmsid.estimate.stage import FloatArray

#: Layout of the OCV vector (``state_jit.ocv_params``): Eq. 4's six coefficients (0-5), its
#: range, the SOC range, the end flags, the end cubics (4 coefficients each, highest power
#: first, padded with leading zeros) and their derivatives (3 each), the correction table's knot
#: count K (0: none) and, from ``CORR``, its K knots, K values and K slopes: ``N_OCV`` + 3 K
#: numbers in all (the kernels' signatures do not depend on the table).
EQ4_MIN, EQ4_MAX, SOC_MIN, SOC_MAX, HAS_LOW, HAS_HIGH = 6, 7, 8, 9, 10, 11
LOW, HIGH, DLOW, DHIGH, CORR_N, CORR, N_OCV = 12, 16, 20, 23, 26, 27, 27


@helper
def _max(a: float, b: float) -> float:
    """np.maximum of two floats (NaN propagates)."""
    return a if a >= b or math.isnan(a) else b


@helper
def _min(a: float, b: float) -> float:
    """np.minimum of two floats (NaN propagates)."""
    return a if a <= b or math.isnan(a) else b


@helper
def _horner(p: FloatArray, i0: int, k: int, s: float) -> float:
    out = 0.0
    for j in range(i0, i0 + k):
        out = out * s + p[j]
    return out


@helper
def _end(p: FloatArray, z: float, v: float, deriv: bool) -> float:
    """``OcvModel._ends`` at one SOC: the end segment (or its slope) beyond Eq. 4."""
    if p[HAS_LOW] != 0.0 and z < p[EQ4_MIN]:
        zc = _min(_max(z, p[SOC_MIN]), p[SOC_MAX])
        return _horner(p, DLOW, 3, zc - p[EQ4_MIN]) if deriv else _horner(
            p, LOW, 4, zc - p[EQ4_MIN])  # fmt: skip
    if p[HAS_HIGH] != 0.0 and z > p[EQ4_MAX]:
        zc = _min(_max(z, p[SOC_MIN]), p[SOC_MAX])
        return _horner(p, DHIGH, 3, zc - p[EQ4_MAX]) if deriv else _horner(
            p, HIGH, 4, zc - p[EQ4_MAX])  # fmt: skip
    return v


@helper
def corr_at(p: FloatArray, z: float, deriv: bool) -> float:
    """``model.ocv.hermite_table`` at one SOC: the correction table's value (or slope)."""
    k = int(p[CORR_N])
    x0, y0, d0 = CORR, CORR + k, CORR + 2 * k
    if math.isnan(z):
        return z
    if z < p[x0]:
        return 0.0 if deriv else float(p[y0])
    if z > p[x0 + k - 1]:
        return 0.0 if deriv else float(p[y0 + k - 1])
    lo, hi = 0, k - 1  # the last j with x[j] <= z (searchsorted right - 1), at most k - 2
    while hi - lo > 1:
        mid = (lo + hi) // 2
        if p[x0 + mid] <= z:
            lo = mid
        else:
            hi = mid
    j = lo
    h = p[x0 + j + 1] - p[x0 + j]
    t = (z - p[x0 + j]) / h
    dy = p[y0 + j + 1] - p[y0 + j]
    c1 = h * p[d0 + j]
    c2 = 3.0 * dy - h * (2.0 * p[d0 + j] + p[d0 + j + 1])
    c3 = h * (p[d0 + j] + p[d0 + j + 1]) - 2.0 * dy
    if deriv:
        return float((c1 + t * (2.0 * c2 + t * (3.0 * c3))) / h)
    return float(p[y0 + j] + t * (c1 + t * (c2 + t * c3)))


@helper
def ocv_at(p: FloatArray, z: float) -> float:
    """``OcvModel.ocv`` at one SOC (V)."""
    zc = _min(_max(z, p[EQ4_MIN]), p[EQ4_MAX])
    v = (p[0] + zc * (p[1] + p[2] * zc) + p[3] / zc + p[4] * math.log(zc)
         + p[5] * math.log1p(-zc))  # fmt: skip
    if p[CORR_N] > 0:
        v = v + corr_at(p, zc, False)
    return _end(p, z, v, False)


@helper
def docv_dz_at(p: FloatArray, z: float) -> float:
    """``OcvModel.docv_dz`` at one SOC (V per unit SOC)."""
    zc = _min(_max(z, p[EQ4_MIN]), p[EQ4_MAX])
    d = p[1] + 2 * p[2] * zc - p[3] / (zc * zc) + p[4] / zc - p[5] / (1 - zc)
    if p[CORR_N] > 0:
        d = d + corr_at(p, zc, True)
    return _end(p, z, d, True)
