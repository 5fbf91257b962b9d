"""Open-circuit voltage of the paper's Eq. 4 and the hysteresis half-gap of Eq. 10/32.

``U_ocv(z) = a0 + a1 z + a2 z^2 + a3/z + a4 ln z + a5 ln(1-z)`` in volts, z = SOC as a fraction.
The curve is linear in its coefficients, so fitting is linear least squares on ``ocv_basis``.
Eq. 4 is singular at 0 and 1, so it is used on [eq4_min, eq4_max] only.

Ends (optional): where the measured rested voltage at empty (z = 0) and/or full (z = 1) is
known, the curve is extended to it by a cubic Hermite segment that takes Eq. 4's value and slope
at the join (C1) and reaches the measured voltage at the end; its end slope is the quadratic's
(the simplest curve through those three conditions) when that is >= 0, else 0, which keeps it
monotone by the Fritsch-Carlson condition as long as Eq. 4's slope at the join is at most three
times the segment's secant slope (``end_segment`` refuses anything else). Without ends, z is
clamped to [eq4_min, eq4_max] = [soc_min, soc_max], exactly as before ends existed; with them
``soc_min``/``soc_max`` widen to 0/1 and SOC runs over the whole range.

Correction table (optional): Eq. 4's six terms cannot follow every cell (graphite's staging
steps leave 6-18 mV of systematic residual on a C/20 test), so the mean curve may carry a table
dU(z) on top: ``U(z) = Eq. 4(z) + dU(z)`` on [eq4_min, eq4_max], Eq. 4 itself unchanged. dU is a
C1 piecewise cubic (Hermite) through the knots ``corr_soc``/``corr_V`` with Fritsch-Carlson
slopes (scipy's PCHIP, ``pchip_slopes``): it never overshoots its knot values, so a table of mV
stays mV between knots, and the EKF's slope dU/dz is continuous; where the corrected curve is
flat the slopes are limited so that it keeps increasing (``table_slopes``). The knots must cover
[eq4_min, eq4_max], where the table is used (z is clamped to it, or the end segments take
over), so the curve is C1 wherever it is evaluated; the end knots keep their one-sided slopes
(held at 0 instead, the corrected slope at a join would be Eq. 4's, exactly where Eq. 4 is
worst: the LFP test's Eq. 4 falls beyond 96 %). Beyond its knots dU would hold its end value.
The end segments join the corrected curve's value and slope. A table must leave the corrected
curve increasing over [eq4_min, eq4_max] (``OcvModel.from_coeffs`` refuses it otherwise): the
SOC observer divides by that slope.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

FloatArray = npt.NDArray[np.float64]

#: Largest ratio (Eq. 4 slope at the join) / (segment secant slope) a monotone cubic allows
#: with a zero end slope (Fritsch & Carlson 1980, the 2 alpha + beta <= 3 region).
MAX_JOIN_SLOPE_RATIO = 3.0
#: The deepest dip (V) below its running maximum that a corrected curve may have and still
#: count as increasing: a tenth of the finest cell-voltage step BMS front-ends report (100 uV),
#: invisible to any measurement. Between two knots of equal corrected value (a flat LFP
#: plateau, pooled by the monotone step) ``table_slopes`` makes the table's cubic flat, and what
#: is left is Eq. 4 bending away from its own cubic: a slope of -5e-4 V per unit SOC, a dip of
#: microvolts. Refused as a fall, it cost the plateau its knots one by one (fit-ocv's fallback:
#: a 17.5 % SOC gap, the curve 5 mV off where the knots had been).
MAX_DIP_V = 1e-5
#: Sub-intervals per knot interval on which ``correction_fall`` checks a table's curve (the
#: slope of a cubic between knots is a quadratic: its minimum is found to well under 1 %).
CHECK_POINTS_PER_INTERVAL = 32


def ocv_basis(z: FloatArray | float) -> FloatArray:
    """Columns [1, z, z^2, 1/z, ln z, ln(1-z)] of Eq. 4; z must already lie in (0, 1)."""
    zz = np.asarray(z, dtype=np.float64)
    return np.stack([np.ones_like(zz), zz, zz * zz, 1.0 / zz, np.log(zz), np.log1p(-zz)], axis=-1)


def eval_ocv(coeffs: FloatArray | list[float], z: FloatArray | float) -> FloatArray:
    """Eq. 4 in volts at SOC ``z`` (already clamped to the valid range)."""
    return np.asarray(ocv_basis(z) @ np.asarray(coeffs, dtype=np.float64), dtype=np.float64)


def eval_docv_dz(coeffs: FloatArray | list[float], z: FloatArray | float) -> FloatArray:
    """dEq. 4/dz in volts per unit SOC at ``z`` in (0, 1)."""
    c = np.asarray(coeffs, dtype=np.float64)
    zz = np.asarray(z, dtype=np.float64)
    return np.asarray(
        c[1] + 2 * c[2] * zz - c[3] / zz**2 + c[4] / zz - c[5] / (1 - zz), dtype=np.float64
    )


def end_segment(
    coeffs: FloatArray | list[float],
    z_join: float,
    z_end: float,
    v_end_V: float,
    *,
    join: tuple[float, float] | None = None,
) -> FloatArray:
    """Cubic Hermite from Eq. 4 at ``z_join`` (value and slope) to ``v_end_V`` at ``z_end``.

    ``join``: the value (V) and slope (V per unit SOC) to join instead of Eq. 4's (the curve
    with its correction table). Returns the polynomial coefficients in ``s = z - z_join``
    (highest power first, V per unit SOC^k). ``z_end`` is 0 (empty) or 1 (full). Raises
    ValueError when no monotone C1 segment of this form exists: the end voltage on the wrong
    side of the join's, or the curve at the join more than ``MAX_JOIN_SLOPE_RATIO`` times
    steeper than the segment's secant (move the join inwards).
    """
    if join is None:
        v_join = float(eval_ocv(coeffs, z_join))
        d_join = float(eval_docv_dz(coeffs, z_join))
    else:
        v_join, d_join = float(join[0]), float(join[1])
    secant = (v_end_V - v_join) / (z_end - z_join)
    where = "empty" if z_end < z_join else "full"
    curve = "Eq. 4" if join is None else "the corrected curve"
    if not secant > 0:
        raise ValueError(
            f"the {where} voltage {v_end_V:.4f} V does not continue {curve}'s {v_join:.4f} V at "
            f"SOC {z_join:g} monotonically"
        )
    if not 0 <= d_join <= MAX_JOIN_SLOPE_RATIO * secant:
        raise ValueError(
            f"{curve}'s slope {d_join:.3g} V at SOC {z_join:g} allows no monotone segment to the "
            f"{where} voltage {v_end_V:.4f} V (secant {secant:.3g} V): move the join inwards"
        )
    d_end = max(2.0 * secant - d_join, 0.0)  # the quadratic's end slope, else a flat end
    x = np.array([min(z_join, z_end), max(z_join, z_end)])
    y = np.array([v_join, v_end_V]) if z_end > z_join else np.array([v_end_V, v_join])
    dy = np.array([d_join, d_end]) if z_end > z_join else np.array([d_end, d_join])
    # scipy imported here: config validation calls this, and the daemon process (which loads
    # the config) must not load scipy (~65 MB resident); only the bank worker needs it.
    from scipy.interpolate import CubicHermiteSpline  # noqa: PLC0415

    spline = CubicHermiteSpline(x, y, dy)
    # Re-expand about z_join so evaluation is one Horner polynomial in (z - z_join).
    poly = np.poly1d(spline.c[:, 0])(np.poly1d([1.0, z_join - x[0]]))
    return np.asarray(poly.coeffs, dtype=np.float64)


def pchip_slopes(x: FloatArray, y: FloatArray) -> FloatArray:
    """Fritsch-Carlson slopes of a correction table (knots ``x`` strictly increasing, values
    ``y``), as scipy's PCHIP: at an interior knot the weighted harmonic mean of the two secants
    (Fritsch & Butland 1984), 0 where they differ in sign or one is 0; at an end knot the
    one-sided three-point estimate, 0 where its sign is not the end secant's and at most three
    times that secant where the secants change sign (shape-preserving, no overshoot)."""
    x = np.asarray(x, dtype=np.float64)
    y = np.asarray(y, dtype=np.float64)
    h = np.diff(x)
    delta = np.diff(y) / h
    if x.shape[0] == 2:
        return np.array([delta[0], delta[0]])
    d = np.zeros_like(x)
    w1 = 2.0 * h[1:] + h[:-1]
    w2 = h[1:] + 2.0 * h[:-1]
    same = delta[:-1] * delta[1:] > 0
    dl = np.where(same, delta[:-1], 1.0)
    dr = np.where(same, delta[1:], 1.0)
    # a secant near 0 (subnormal) overflows w / d to inf: the harmonic mean's limit, 0
    with np.errstate(over="ignore"):
        d[1:-1] = np.where(same, (w1 + w2) / (w1 / dl + w2 / dr), 0.0)
    for at, h0, h1, m0, m1 in ((0, h[0], h[1], delta[0], delta[1]),
                               (-1, h[-1], h[-2], delta[-1], delta[-2])):  # fmt: skip
        e = ((2.0 * h0 + h1) * m0 - h0 * m1) / (h0 + h1)
        if np.sign(e) != np.sign(m0):
            e = 0.0
        elif np.sign(m0) != np.sign(m1) and abs(e) > abs(3.0 * m0):
            e = 3.0 * m0
        d[at] = e
    return d


def table_slopes(
    coeffs: FloatArray | list[float], x: FloatArray, y: FloatArray, lo: float, hi: float
) -> FloatArray:
    """The correction table's slopes at its knots: ``pchip_slopes`` of dU, limited at each knot
    in the curve's range [lo, hi] where the corrected curve rises to its neighbours in that
    range (one at the range's edge), so that its slope there, Eq. 4's + dU's, lies in
    [0, 3 x the smaller secant of the corrected knot values]: Fritsch & Carlson's monotone
    region. Where the curve is flat (an LFP plateau, dU nearly -Eq. 4) PCHIP of dU alone
    leaves the sum falling between knots; elsewhere the limit does not bind and dU's own slopes
    stand. Knots beyond [lo, hi] (where Eq. 4 may be singular) keep their PCHIP slopes."""
    x = np.asarray(x, dtype=np.float64)
    y = np.asarray(y, dtype=np.float64)
    d = pchip_slopes(x, y)
    inside = np.flatnonzero((x >= lo) & (x <= hi))
    if inside.shape[0] < 2:
        return d
    xi = x[inside]
    base = eval_docv_dz(coeffs, xi)
    sec = np.diff(eval_ocv(coeffs, xi) + y[inside]) / np.diff(xi)
    left = np.concatenate([sec[:1], sec])  # an edge knot: its one secant on both sides
    right = np.concatenate([sec, sec[-1:]])
    lim = np.minimum(left, right)
    rising = lim >= 0
    di = d[inside]
    total = np.where(rising, np.clip(base + di, 0.0, 3.0 * np.maximum(lim, 0.0)), base + di)
    d[inside] = np.where(rising, total - base, di)
    return d


def hermite_table(
    x: FloatArray, y: FloatArray, d: FloatArray, z: FloatArray, deriv: bool
) -> FloatArray:
    """The correction table's value (or slope) at ``z``: the cubic Hermite through (x, y) with
    slopes ``d`` on [x0, x_last], the end values (slope 0) beyond (``OcvModel`` never asks
    there: its table covers the curve's range), NaN at NaN.
    ``observer_kernel``'s ``corr_at`` computes the same operations in the same order."""
    zz = np.asarray(z, dtype=np.float64)
    k = x.shape[0]
    j = np.clip(np.searchsorted(x, zz, side="right") - 1, 0, k - 2)
    h = x[j + 1] - x[j]
    t = (zz - x[j]) / h
    dy = y[j + 1] - y[j]
    c1 = h * d[j]
    c2 = 3.0 * dy - h * (2.0 * d[j] + d[j + 1])
    c3 = h * (d[j] + d[j + 1]) - 2.0 * dy
    if deriv:
        inner = (c1 + t * (2.0 * c2 + t * (3.0 * c3))) / h
        return np.asarray(np.where((zz < x[0]) | (zz > x[-1]), 0.0, inner), dtype=np.float64)
    inner = y[j] + t * (c1 + t * (c2 + t * c3))
    out = np.where(zz < x[0], y[0], np.where(zz > x[-1], y[-1], inner))
    return np.asarray(out, dtype=np.float64)


def check_table(soc: FloatArray | list[float], dU_V: FloatArray | list[float]) -> None:
    """ValueError unless a correction table has >= 2 finite knots, strictly increasing in
    [0, 1], and as many finite values."""
    x = np.asarray(soc, dtype=np.float64)
    y = np.asarray(dU_V, dtype=np.float64)
    if x.ndim != 1 or x.shape != y.shape or x.shape[0] < 2:
        raise ValueError("a correction table needs as many values as knots, at least 2")
    if not (np.all(np.isfinite(x)) and np.all(np.isfinite(y))):
        raise ValueError("a correction table's knots and values must be finite")
    if np.any(np.diff(x) <= 0) or x[0] < 0 or x[-1] > 1:
        raise ValueError("a correction table's knots must increase strictly within [0, 1]")


def correction_fall(
    coeffs: FloatArray | list[float], soc: FloatArray, dU_V: FloatArray, lo: float, hi: float
) -> tuple[float, float] | None:
    """Where Eq. 4 plus the table (``soc``, ``dU_V``) falls on [lo, hi]: (SOC, dip V) of its
    deepest dip below its running maximum when that exceeds ``MAX_DIP_V``, else None. Checked
    on ``CHECK_POINTS_PER_INTERVAL`` points per knot interval and 2001 across [lo, hi]."""
    x = np.asarray(soc, dtype=np.float64)
    y = np.asarray(dU_V, dtype=np.float64)
    d = table_slopes(coeffs, x, y, lo, hi)
    u = np.linspace(0.0, 1.0, CHECK_POINTS_PER_INTERVAL + 1)
    pts = (x[:-1, None] + np.diff(x)[:, None] * u[None, :]).ravel()
    grid = np.unique(np.concatenate([np.linspace(lo, hi, 2001), pts[(pts >= lo) & (pts <= hi)]]))
    v = eval_ocv(coeffs, grid) + hermite_table(x, y, d, grid, False)
    dip = np.maximum.accumulate(v) - v
    at = int(np.argmax(dip))
    return (float(grid[at]), float(dip[at])) if dip[at] > MAX_DIP_V else None


def table_join(
    coeffs: FloatArray | list[float],
    table: tuple[FloatArray, FloatArray, FloatArray] | None,
    z: float,
) -> tuple[float, float] | None:
    """Value (V) and slope (V per unit SOC) of Eq. 4 plus a correction ``table`` (knots, values,
    slopes) at ``z``, where an end segment joins the corrected curve (``end_segment``'s
    ``join``); None without a table: the segment joins Eq. 4's own, computed as before tables
    existed."""
    if table is None:
        return None
    x, y, d = table
    zz = np.array([z])
    return (
        float((eval_ocv(coeffs, zz) + hermite_table(x, y, d, zz, False))[0]),
        float((eval_docv_dz(coeffs, zz) + hermite_table(x, y, d, zz, True))[0]),
    )


def _horner(p: FloatArray, s: FloatArray) -> FloatArray:
    out = np.zeros_like(s)
    for c in p:
        out = out * s + c
    return out


@dataclass(frozen=True)
class OcvModel:
    """A cell's mean OCV curve (Eq. 4, optionally with a correction table and end segments),
    its hysteresis table M(z) (Eq. 32) and their derivatives.

    ``soc_min``/``soc_max``: the range SOC is clamped to (0/1 at an end that has a segment);
    ``eq4_min``/``eq4_max``: where Eq. 4 (plus the table) is used; ``corr_soc``/``corr_V``: the
    correction table's knots (fractions) and values (V), None without one. Precomputes an
    inverse table for SOC-from-voltage (used to initialise SOC at rest).
    """

    coeffs: FloatArray
    soc_min: float
    soc_max: float
    m_soc: FloatArray
    m_V: FloatArray
    _inv_v: FloatArray
    _inv_z: FloatArray
    eq4_min: float = 0.0
    eq4_max: float = 1.0
    _low: FloatArray | None = None
    _high: FloatArray | None = None
    corr_soc: FloatArray | None = None
    corr_V: FloatArray | None = None
    _corr_d: FloatArray | None = None

    @classmethod
    def from_coeffs(
        cls,
        mean: FloatArray | list[float],
        soc_min: float,
        soc_max: float,
        m_soc: FloatArray | list[float],
        m_V: FloatArray | list[float],
        *,
        v_empty_V: float | None = None,
        v_full_V: float | None = None,
        corr_soc: FloatArray | list[float] | None = None,
        corr_V: FloatArray | list[float] | None = None,
    ) -> OcvModel:
        """From the Eq. 4 coefficients (V) valid on [soc_min, soc_max], the M(z) table (SOC
        fractions, half-gap V; Eq. 32), the optional rested voltages at empty and full (V)
        that the end segments reach and the optional correction table (SOC fractions, V; see
        the module doc). ValueError when the ends cannot be joined monotonically or the table
        leaves the curve falling."""
        coeffs = np.asarray(mean, dtype=np.float64)
        cx = cy = cd = None
        if (corr_soc is None) != (corr_V is None):
            raise ValueError("a correction table needs both its knots and its values")
        if corr_soc is not None and corr_V is not None:
            check_table(corr_soc, corr_V)
            cx = np.asarray(corr_soc, dtype=np.float64)
            cy = np.asarray(corr_V, dtype=np.float64)
            if cx[0] > soc_min or cx[-1] < soc_max:
                raise ValueError(
                    f"the OCV correction table's knots (SOC {100 * cx[0]:g}-{100 * cx[-1]:g} %) "
                    f"must cover the curve's range SOC {100 * soc_min:g}-{100 * soc_max:g} %"
                )
            cd = table_slopes(coeffs, cx, cy, soc_min, soc_max)
            fall = correction_fall(coeffs, cx, cy, soc_min, soc_max)
            if fall is not None:
                eq4 = float(eval_docv_dz(coeffs, fall[0]))
                raise ValueError(
                    f"the OCV correction table leaves the mean curve falling at SOC "
                    f"{100 * fall[0]:.2f} % ({1e3 * fall[1]:.3g} mV below the curve before it; "
                    f"Eq. 4's slope there {eq4:.3g} V per unit SOC): it must increase over SOC "
                    f"{100 * soc_min:g}-{100 * soc_max:g} %"
                )

        def curve(z: FloatArray, deriv: bool) -> FloatArray:
            base = eval_docv_dz(coeffs, z) if deriv else eval_ocv(coeffs, z)
            if cx is None or cy is None or cd is None:
                return base
            return np.asarray(base + hermite_table(cx, cy, cd, z, deriv), dtype=np.float64)

        table = None if cx is None or cy is None or cd is None else (cx, cy, cd)

        def join(z: float) -> tuple[float, float] | None:
            return table_join(coeffs, table, z)

        low = (
            None
            if v_empty_V is None
            else end_segment(coeffs, soc_min, 0.0, v_empty_V, join=join(soc_min))
        )
        high = (
            None
            if v_full_V is None
            else end_segment(coeffs, soc_max, 1.0, v_full_V, join=join(soc_max))
        )
        grid = np.linspace(soc_min, soc_max, 2001)
        v = curve(grid, False)
        if low is not None:
            g = np.linspace(0.0, soc_min, 201)[:-1]
            grid, v = np.concatenate([g, grid]), np.concatenate([_horner(low, g - soc_min), v])
        if high is not None:
            g = np.linspace(soc_max, 1.0, 201)[1:]
            grid, v = np.concatenate([grid, g]), np.concatenate([v, _horner(high, g - soc_max)])
        # Force monotonicity for the inverse: a fitted curve may wiggle on flat (LFP) plateaus.
        v_mono = np.maximum.accumulate(v)
        return cls(
            coeffs=coeffs,
            soc_min=0.0 if low is not None else soc_min,
            soc_max=1.0 if high is not None else soc_max,
            m_soc=np.asarray(m_soc, dtype=np.float64),
            m_V=np.asarray(m_V, dtype=np.float64),
            _inv_v=v_mono,
            _inv_z=grid,
            eq4_min=soc_min,
            eq4_max=soc_max,
            _low=low,
            _high=high,
            corr_soc=cx,
            corr_V=cy,
            _corr_d=cd,
        )

    @property
    def has_table(self) -> bool:
        """True when a correction table adds to Eq. 4."""
        return self.corr_soc is not None

    def correction(self, z: FloatArray, deriv: bool = False) -> FloatArray:
        """The correction table dU (V) or its slope (V per unit SOC) at ``z`` (0 without one);
        like Eq. 4 it is evaluated at z clamped to [eq4_min, eq4_max] by ``ocv``."""
        x, y, d = self.corr_soc, self.corr_V, self._corr_d
        if x is None or y is None or d is None:
            return np.zeros_like(np.asarray(z, dtype=np.float64))
        return hermite_table(x, y, d, z, deriv)

    @property
    def has_ends(self) -> bool:
        """True when at least one end segment extends Eq. 4."""
        return self._low is not None or self._high is not None

    def clamp(self, z: FloatArray) -> tuple[FloatArray, npt.NDArray[np.bool_]]:
        """SOC clamped to the valid range, and a boolean flag array where clamping happened."""
        zc = np.asarray(np.clip(z, self.soc_min, self.soc_max), dtype=np.float64)
        return zc, np.asarray(zc != z, dtype=np.bool_)

    def _ends(self, z: FloatArray, v: FloatArray, deriv: bool) -> FloatArray:
        """Replace ``v`` by the end segments (or their slopes) where z lies beyond Eq. 4."""
        for poly, beyond, z0 in (
            (self._low, z < self.eq4_min, self.eq4_min),
            (self._high, z > self.eq4_max, self.eq4_max),
        ):
            if poly is not None and np.count_nonzero(beyond):  # np.any: 10x the cost a tick
                p = np.asarray(np.polyder(poly) if deriv else poly, dtype=np.float64)
                zc = np.clip(z, self.soc_min, self.soc_max)
                v = np.where(beyond, _horner(p, zc - z0), v)
        return v

    def ocv(self, z: FloatArray) -> FloatArray:
        """Mean-branch OCV in volts (Eq. 4 plus the correction table, end segments beyond) at
        SOC ``z`` (clamped)."""
        zz = np.asarray(z, dtype=np.float64)
        zc = np.minimum(np.maximum(zz, self.eq4_min), self.eq4_max)
        c = self.coeffs
        v = np.asarray(
            c[0] + zc * (c[1] + c[2] * zc) + c[3] / zc + c[4] * np.log(zc) + c[5] * np.log1p(-zc),
            dtype=np.float64,
        )
        if self.corr_soc is not None:
            v = v + self.correction(zc)
        return self._ends(zz, v, deriv=False) if self.has_ends else v

    def docv_dz(self, z: FloatArray) -> FloatArray:
        """dOCV/dz in volts per unit SOC (for sensitivity and SOC-error reasoning)."""
        zz = np.asarray(z, dtype=np.float64)
        zc = np.clip(zz, self.eq4_min, self.eq4_max)
        c = self.coeffs
        d = np.asarray(
            c[1] + 2 * c[2] * zc - c[3] / zc**2 + c[4] / zc - c[5] / (1 - zc), dtype=np.float64
        )
        if self.corr_soc is not None:
            d = d + self.correction(zc, deriv=True)
        return self._ends(zz, d, deriv=True) if self.has_ends else d

    def hysteresis_M(self, z: FloatArray) -> FloatArray:
        """Hysteresis half-gap M(z) in volts, piecewise linear (Eq. 32), ends held."""
        return np.asarray(np.interp(z, self.m_soc, self.m_V), dtype=np.float64)

    def soc_from_ocv(self, v_V: FloatArray | float) -> FloatArray:
        """Invert the mean OCV curve: SOC whose OCV is ``v_V`` (clamped to the valid range)."""
        return np.asarray(np.interp(v_V, self._inv_v, self._inv_z), dtype=np.float64)

    def secant_slope(self, z: FloatArray, v_V: FloatArray) -> tuple[FloatArray, FloatArray]:
        """(slope V per unit SOC, z') from SOC ``z`` to z' = ``soc_from_ocv(v_V)``: the OCV
        curve's secant, dOCV/dz where z' is within 1e-3 of z. A Kalman update linearised at z
        moves SOC by e / dOCV/dz(z); across a curved OCV that overshoots (a 30-point jump from
        63 % on the flat middle of an NMC curve lands at 100 %), along the secant it lands on z'
        when the prior is weak."""
        z = np.asarray(z, dtype=np.float64)
        z_to = self.soc_from_ocv(v_V)
        dz = z_to - z
        far = np.abs(dz) > 1e-3
        secant = (self.ocv(z_to) - self.ocv(z)) / np.where(far, dz, 1.0)
        return np.asarray(np.where(far, secant, self.docv_dz(z)), dtype=np.float64), z_to
