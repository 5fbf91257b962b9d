"""Open-circuit voltage of the paper's Eq. 4 and the hysteresis half-gap of Eq. 10/32.

``U_ocv(z) = a0 + a1 z + a2 z^2 + a3/z + a4 ln z + a5 ln(1-z)`` in volts, z = SOC as a fraction.
The curve is linear in its coefficients, so fitting is linear least squares on ``ocv_basis``.
z is always clamped to ``[soc_min, soc_max]`` first: Eq. 4 is singular at 0 and 1.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

FloatArray = npt.NDArray[np.float64]


def ocv_basis(z: FloatArray | float) -> FloatArray:
    """Columns [1, z, z^2, 1/z, ln z, ln(1-z)] of Eq. 4; z must already lie in (0, 1)."""
    zz = np.asarray(z, dtype=np.float64)
    return np.stack([np.ones_like(zz), zz, zz * zz, 1.0 / zz, np.log(zz), np.log1p(-zz)], axis=-1)


def eval_ocv(coeffs: FloatArray | list[float], z: FloatArray | float) -> FloatArray:
    """Eq. 4 in volts at SOC ``z`` (already clamped to the valid range)."""
    return np.asarray(ocv_basis(z) @ np.asarray(coeffs, dtype=np.float64), dtype=np.float64)


@dataclass(frozen=True)
class OcvModel:
    """A cell's mean OCV curve (Eq. 4), its hysteresis table M(z) (Eq. 32) and their derivatives.

    Precomputes an inverse table for SOC-from-voltage (used to initialise SOC at rest).
    """

    coeffs: FloatArray
    soc_min: float
    soc_max: float
    m_soc: FloatArray
    m_V: FloatArray
    _inv_v: FloatArray
    _inv_z: FloatArray

    @classmethod
    def from_coeffs(
        cls,
        mean: FloatArray | list[float],
        soc_min: float,
        soc_max: float,
        m_soc: FloatArray | list[float],
        m_V: FloatArray | list[float],
    ) -> OcvModel:
        """From the Eq. 4 coefficients (V) valid on [soc_min, soc_max] and the M(z) table
        (SOC fractions, half-gap V; Eq. 32)."""
        coeffs = np.asarray(mean, dtype=np.float64)
        grid = np.linspace(soc_min, soc_max, 2001)
        v = eval_ocv(coeffs, grid)
        # Force monotonicity for the inverse: a fitted curve may wiggle on flat (LFP) plateaus.
        v_mono = np.maximum.accumulate(v)
        return cls(
            coeffs=coeffs,
            soc_min=soc_min,
            soc_max=soc_max,
            m_soc=np.asarray(m_soc, dtype=np.float64),
            m_V=np.asarray(m_V, dtype=np.float64),
            _inv_v=v_mono,
            _inv_z=grid,
        )

    def clamp(self, z: FloatArray) -> tuple[FloatArray, npt.NDArray[np.bool_]]:
        """SOC clamped to the valid range, and a boolean flag array where clamping happened."""
        zc = np.asarray(np.clip(z, self.soc_min, self.soc_max), dtype=np.float64)
        return zc, np.asarray(zc != z, dtype=np.bool_)

    def ocv(self, z: FloatArray) -> FloatArray:
        """Mean-branch OCV in volts (Eq. 4) at SOC ``z`` (clamped)."""
        zc = np.minimum(np.maximum(np.asarray(z, dtype=np.float64), self.soc_min), self.soc_max)
        c = self.coeffs
        return np.asarray(
            c[0] + zc * (c[1] + c[2] * zc) + c[3] / zc + c[4] * np.log(zc) + c[5] * np.log1p(-zc),
            dtype=np.float64,
        )

    def docv_dz(self, z: FloatArray) -> FloatArray:
        """dOCV/dz in volts per unit SOC (for sensitivity and SOC-error reasoning)."""
        zc = np.clip(np.asarray(z, dtype=np.float64), self.soc_min, self.soc_max)
        c = self.coeffs
        return np.asarray(
            c[1] + 2 * c[2] * zc - c[3] / zc**2 + c[4] / zc - c[5] / (1 - zc), dtype=np.float64
        )

    def hysteresis_M(self, z: FloatArray) -> FloatArray:
        """Hysteresis half-gap M(z) in volts, piecewise linear (Eq. 32), ends held."""
        return np.asarray(np.interp(z, self.m_soc, self.m_V), dtype=np.float64)

    def soc_from_ocv(self, v_V: FloatArray | float) -> FloatArray:
        """Invert the mean OCV curve: SOC whose OCV is ``v_V`` (clamped to the valid range)."""
        return np.asarray(np.interp(v_V, self._inv_v, self._inv_z), dtype=np.float64)
