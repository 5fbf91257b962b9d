"""Recursive least squares with an adaptive forgetting factor (AFFRLS, Eq. 16-21), batched.

Pure functions over N independent problems at once (one per cell): theta (N, n), P (N, n, n),
phi (N, n). Parameters live in normalised coordinates (theta_n = theta / scale) so that one
covariance bound and one initial covariance fit resistances in mOhm and offsets in V alike.
"""

from __future__ import annotations

import numpy as np
import numpy.typing as npt

from bmsid.estimate.tuning import EstimatorTuning

FloatArray = npt.NDArray[np.float64]
BoolArray = npt.NDArray[np.bool_]


def adaptive_lambda(
    e_V: FloatArray,
    e_base_V: FloatArray,
    lambda_min: FloatArray | float,
    lambda_max: FloatArray | float,
    base: float,
) -> FloatArray:
    """Eq. 21: eps = round((e / e_base)^2, 2); lambda = lmin + (lmax - lmin) base^eps.

    Large surprises push lambda to ``lambda_min`` (forget fast), small ones to ``lambda_max``.
    """
    # round(x, 2) as ndarray.round computes it (x * 100, rint, / 100), without its dispatch
    eps = np.rint((e_V / e_base_V) ** 2 * 100.0) / 100.0
    eps = np.minimum(eps, 1.0e3)  # base^1000 underflows to 0 cleanly; avoids inf exponents
    return np.asarray(lambda_min + (lambda_max - lambda_min) * base**eps, dtype=np.float64)


def rls_update(
    theta: FloatArray,
    P: FloatArray,
    phi: FloatArray,
    e: FloatArray,
    lam: FloatArray,
    active: BoolArray,
    trace_max: float,
) -> tuple[FloatArray, FloatArray]:
    """One AFFRLS step (Eq. 18-20) for the rows where ``active``; ``e`` is the a-priori error.

    Joseph-free form with explicit symmetrisation; trace(P) is capped at ``trace_max`` by scaling
    (bounded-trace safeguard). Inactive rows are returned unchanged.
    """
    Pphi = (P @ phi[:, :, None])[:, :, 0]
    denom = lam + (phi * Pphi).sum(axis=1)
    K = Pphi / denom[:, None]
    theta_new = theta + K * e[:, None]
    P_new = (P - K[:, :, None] * Pphi[:, None, :]) / lam[:, None, None]
    P_new = 0.5 * (P_new + P_new.transpose(0, 2, 1))
    tr = np.einsum("nii->n", P_new)
    if tr.max() > trace_max:
        P_new *= np.minimum(trace_max / tr, 1.0)[:, None, None]
    if np.count_nonzero(active) == active.size:  # ndarray.all() costs 5x more on few rows
        return theta_new, P_new
    act = active[:, None]
    return np.where(act, theta_new, theta), np.where(act[:, :, None], P_new, P)


def reset_covariance(n_rows: int, n_params: int, p0: float) -> FloatArray:
    """P = p0 I for every row (the reset policy after a gap or a configuration change)."""
    return np.repeat(np.eye(n_params)[None, :, :] * p0, n_rows, axis=0)


def fusion_covariance(P: FloatArray) -> FloatArray:
    """Zero the OCV offset's rows and columns of P: the AFFRLS leaves the offset alone.

    Under a steady mean current the offset is collinear with R2 x2; tracked per tick it drifts
    along that unobservable direction. It is refit with each swarm window instead, under the
    prior ``ocv_offset_prior_V``.
    """
    P = P.copy()
    P[..., 4, :] = 0.0
    P[..., :, 4] = 0.0
    return P


def swarm_covariance(
    P_fit: FloatArray, tuning: EstimatorTuning, fit_scale: bool, *, restart: bool, keep_r0: bool
) -> FloatArray:
    """The covariance (5, 5, normalised) the RLS continues with after a swarm re-seeded theta
    from a window fit whose covariance is ``P_fit``.

    ``restart``: everything restarts at ``p0`` but R0 with ``keep_r0``, which keeps its window
    variance (capped at ``p0``: restarted, R0 jumped by up to 14 % after each swarm on the
    constant synthetic cell; a cell without hysteresis restarts it too, which tracks the
    physics-based records' SOC-dependent R0 better). Carrying the fit's covariance saturates
    the filter between swarms (the paper's "filter saturation": the window's R1/R2 correlations
    hold the branches where the window left them); restarted, the RLS tracks them again.
    Measured (README, issue 11): every real-cell row better (CALCE 0 degC DST 9.48 -> 6.53 mV),
    the multi-day records' R0+R1+R2 too. Without ``restart`` the fit's covariance is kept, its
    trace capped at ``trace_max``. Coordinates the RLS does not fit (the hysteresis scale
    without ``fit_scale``, the OCV offset unless identified) get ``p0``; a covariance that is
    not finite or not positive restarts in full.
    """
    p0 = tuning.p0
    P = P_fit.copy()
    if not fit_scale:
        P[3, 3] = p0
    if not tuning.identify_ocv_offset:
        P[4, 4] = p0
    tr = float(np.trace(P))
    if not np.all(np.isfinite(P)) or tr <= 0:
        return np.eye(5) * p0
    if restart:
        return np.diag([min(float(P[0, 0]), p0) if keep_r0 else p0] + [p0] * 4)
    if tr > tuning.trace_max:
        P = P * (tuning.trace_max / tr)
    return P
