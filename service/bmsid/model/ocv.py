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
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

FloatArray = npt.NDArray[np.float64]

#: Largest ratio (Eq. 4 slope at the join) / (segment secant slope) a monotone cubic allows
#: with a zero end slope (Fritsch & Carlson 1980, the 2 alpha + beta <= 3 region).
MAX_JOIN_SLOPE_RATIO = 3.0


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
    coeffs: FloatArray | list[float], z_join: float, z_end: float, v_end_V: float
) -> FloatArray:
    """Cubic Hermite from Eq. 4 at ``z_join`` (value and slope) to ``v_end_V`` at ``z_end``.

    Returns the polynomial coefficients in ``s = z - z_join`` (highest power first, V per unit
    SOC^k). ``z_end`` is 0 (empty) or 1 (full). Raises ValueError when no monotone C1 segment of
    this form exists: the end voltage on the wrong side of the join's, or Eq. 4 at the join
    more than ``MAX_JOIN_SLOPE_RATIO`` times steeper than the segment's secant (move the join
    inwards).
    """
    v_join = float(eval_ocv(coeffs, z_join))
    d_join = float(eval_docv_dz(coeffs, z_join))
    secant = (v_end_V - v_join) / (z_end - z_join)
    where = "empty" if z_end < z_join else "full"
    if not secant > 0:
        raise ValueError(
            f"the {where} voltage {v_end_V:.4f} V does not continue Eq. 4's {v_join:.4f} V at "
            f"SOC {z_join:g} monotonically"
        )
    if not 0 <= d_join <= MAX_JOIN_SLOPE_RATIO * secant:
        raise ValueError(
            f"Eq. 4's slope {d_join:.3g} V at SOC {z_join:g} allows no monotone segment to the "
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


def _horner(p: FloatArray, s: FloatArray) -> FloatArray:
    out = np.zeros_like(s)
    for c in p:
        out = out * s + c
    return out


@dataclass(frozen=True)
class OcvModel:
    """A cell's mean OCV curve (Eq. 4, optionally with end segments), its hysteresis table
    M(z) (Eq. 32) and their derivatives.

    ``soc_min``/``soc_max``: the range SOC is clamped to (0/1 at an end that has a segment);
    ``eq4_min``/``eq4_max``: where Eq. 4 itself is used. Precomputes an inverse table for
    SOC-from-voltage (used to initialise SOC at rest).
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
    ) -> OcvModel:
        """From the Eq. 4 coefficients (V) valid on [soc_min, soc_max], the M(z) table (SOC
        fractions, half-gap V; Eq. 32) and the optional rested voltages at empty and full (V)
        that the end segments reach (see the module doc; ValueError when they cannot)."""
        coeffs = np.asarray(mean, dtype=np.float64)
        low = None if v_empty_V is None else end_segment(coeffs, soc_min, 0.0, v_empty_V)
        high = None if v_full_V is None else end_segment(coeffs, soc_max, 1.0, v_full_V)
        grid = np.linspace(soc_min, soc_max, 2001)
        v = eval_ocv(coeffs, grid)
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
        )

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
        """Mean-branch OCV in volts (Eq. 4, end segments beyond it) at SOC ``z`` (clamped)."""
        zz = np.asarray(z, dtype=np.float64)
        zc = np.minimum(np.maximum(zz, self.eq4_min), self.eq4_max)
        c = self.coeffs
        v = np.asarray(
            c[0] + zc * (c[1] + c[2] * zc) + c[3] / zc + c[4] * np.log(zc) + c[5] * np.log1p(-zc),
            dtype=np.float64,
        )
        return self._ends(zz, v, deriv=False) if self.has_ends else v

    def docv_dz(self, z: FloatArray) -> FloatArray:
        """dOCV/dz in volts per unit SOC (for sensitivity and SOC-error reasoning)."""
        zz = np.asarray(z, dtype=np.float64)
        zc = np.clip(zz, self.eq4_min, self.eq4_max)
        c = self.coeffs
        d = np.asarray(
            c[1] + 2 * c[2] * zc - c[3] / zc**2 + c[4] / zc - c[5] / (1 - zc), dtype=np.float64
        )
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
