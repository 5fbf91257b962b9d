"""Windowed fit of the full hysteresis model with the time constants fixed (variable projection).

With tau1, tau2 (and the hysteresis rate) fixed, the terminal voltage of Eq. 9 is linear in
R0, R1, R2, the hysteresis scale and an OCV offset:

    y_k = V_k - OCV(z_k) = -R0 i_k - R1 x1_k - R2 x2_k + s M(z_k) h_k + off + c1 a1^k + c2 a2^k

where x_j is the current through the unit-gain ZOH filter of branch j (U_j = R_j x_j) and the
last two columns carry the unknown branch voltages at the window start. So the LPSO searches only
ln(tau1), ln(tau2), and every fitness evaluation is one small linear least-squares problem. This
is far better conditioned than mapping ARX coefficients back through Eq. 22.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import lru_cache

import numpy as np
import numpy.typing as npt

from bmsid.estimate import fixed_rmse_kernel, varpro_kernel
from bmsid.model.ecm import rc_decay

FloatArray = npt.NDArray[np.float64]

#: Order of the linear parameters everywhere in the fusion: R0, R1, R2 (ohm), hysteresis scale, V.
LINEAR_NAMES = ("R0_ohm", "R1_ohm", "R2_ohm", "M_scale", "ocv_offset_V")


@dataclass(frozen=True)
class Window:
    """Buffered identification ticks of one cell (uniform period ``dt_s``)."""

    current_A: FloatArray  # (W,)
    y_V: FloatArray  # (W,) V - OCV(z)
    hm_V: FloatArray  # (W,) h M(z)
    dt_s: float
    use_hysteresis: bool
    use_offset: bool


@dataclass(frozen=True)
class LinearFit:
    """Per candidate (P,): linear parameters (P, 5), weighted RMSE (V), branch states at the last
    tick (P, 2, unit-gain, initial conditions included), normalised covariance (P, 5, 5)."""

    theta: FloatArray
    rmse_V: FloatArray
    x_last: FloatArray
    cov: FloatArray


def fit_linear(
    w: Window,
    tau1_s: FloatArray,
    tau2_s: FloatArray,
    scale: FloatArray,
    weights: FloatArray | None = None,
    offset_prior: float = 0.0,
    with_cov: bool = False,
) -> LinearFit:
    """Solve the linear sub-problem for every (tau1, tau2) candidate at once.

    ``scale`` (5,) normalises the linear parameters (typical magnitudes) so the returned
    covariance is in the same normalised units the AFFRLS uses. ``offset_prior`` is a ridge
    (normalised units, i.e. noise variance / prior variance of offset/scale) that pulls the OCV
    offset to 0 along the direction the data cannot resolve (offset vs R2 x2 under a steady mean
    current). The covariance is only computed when ``with_cov``.
    """
    a1, a2, s_full, idx, j_off = fit_columns(w, tau1_s, tau2_s, scale)
    wts = np.ones(w.current_A.shape[0]) if weights is None else weights
    G, b, x_last = varpro_kernel.normal_equations(
        w.current_A, w.y_V, w.hm_V, wts, a1, a2, s_full, w.use_hysteresis, w.use_offset
    )
    theta, rmse, x_last, cov5 = varpro_kernel.SOLVE.impl(
        G, b, x_last, w.y_V, wts, a1, a2, s_full, idx, offset_prior, j_off, with_cov
    )
    return LinearFit(theta=theta, rmse_V=rmse, x_last=x_last, cov=cov5)


def fit_columns(
    w: Window, tau1_s: FloatArray, tau2_s: FloatArray, scale: FloatArray
) -> tuple[FloatArray, FloatArray, FloatArray, npt.NDArray[np.intp], int]:
    """What the window kernels take besides the window: the poles (a1, a2), the active
    columns' scales and indices, and the offset's column (-1: none)."""
    s_full, idx, j_off = column_layout(w.use_hysteresis, w.use_offset, scale)
    return rc_decay(w.dt_s, tau1_s), rc_decay(w.dt_s, tau2_s), s_full, idx, j_off


def column_layout(
    use_hysteresis: bool, use_offset: bool, scale: FloatArray
) -> tuple[FloatArray, npt.NDArray[np.intp], int]:
    """The active columns' scales (``scale``: (..., 5), one row per cell or one cell; the two
    window-start columns' scales are 1), their indices, and the offset's column (-1: none)."""
    idx = _active_columns(use_hysteresis, use_offset)
    j_off = 3 + int(use_hysteresis) if use_offset else -1
    ones = np.ones((*scale.shape[:-1], 2))
    return np.concatenate((scale, ones), axis=-1)[..., idx], idx, j_off


@lru_cache(maxsize=4)
def _active_columns(use_hysteresis: bool, use_offset: bool) -> npt.NDArray[np.intp]:
    """Indices of the active columns of (R0, R1, R2, M scale, offset, c1, c2): the same four
    arrays again (never written: the solve only reads them)."""
    active = np.array([True, True, True, use_hysteresis, use_offset, True, True])
    return np.flatnonzero(active)


def fixed_rmse(
    w: Window, tau1_s: float, tau2_s: float, theta: FloatArray, weights: FloatArray
) -> float:
    """Weighted window RMSE (V) of one fixed parameter set: theta (5,) physical (R0, R1, R2 ohm,
    hysteresis scale, offset V) at (tau1_s, tau2_s), only the two branch voltages at the window
    start solved for (as in :func:`fit_linear`). What a clipped swarm result really gives, to
    compare it with the parameters in force before they are replaced
    (``fixed_rmse_kernel``)."""
    a1, a2 = float(rc_decay(w.dt_s, tau1_s)), float(rc_decay(w.dt_s, tau2_s))
    return fixed_rmse_kernel.KERNEL.impl(
        w.current_A, w.y_V, w.hm_V, weights, a1, a2, np.asarray(theta, dtype=np.float64),
        w.use_hysteresis, w.use_offset,
    )  # fmt: skip
