"""One-state hysteresis (Plett; the paper's Eq. 5-6 with the corrected sign).

``h`` lies in [-1, 1]; discharge (i > 0) drives it to -1, charge to +1, zero current leaves it.
Exact zero-order-hold step: ``h+ = exp(-|kappa i| dt) h - (1 - exp(-|kappa i| dt)) sgn(i)``.
"""

from __future__ import annotations

import numpy as np
import numpy.typing as npt

FloatArray = npt.NDArray[np.float64]


def kappa_per_As(
    gamma: float | FloatArray, capacity_As: float, eta: float | FloatArray = 1.0
) -> FloatArray:
    """The paper's decay factor kappa in 1/(A s) from Plett's dimensionless rate gamma (Eq. 5-6)."""
    return np.asarray(np.asarray(eta) * np.asarray(gamma) / capacity_As, dtype=np.float64)


def hysteresis_step(
    h: FloatArray,
    current_A: FloatArray | float,
    dt_s: FloatArray | float,
    kappa: FloatArray | float,
) -> FloatArray:
    """Advance the hysteresis state over ``dt_s`` with the current held (Eq. 8, last row)."""
    decay = np.exp(-np.abs(np.asarray(kappa) * current_A) * dt_s)
    return np.asarray(decay * h - (1.0 - decay) * np.sign(current_A), dtype=np.float64)
