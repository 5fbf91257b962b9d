"""The window RMSE of one fixed parameter set (``varpro.fixed_rmse``), compiled.

A swarm's result is applied only when, clipped as it will be published, it fits the window
about as well as the parameters in force (``fusion._apply_swarm``): two of these per swarm, each
the model voltage over the window (Eq. 9 with the taus fixed) and a least-squares fit of the two
branch voltages at the window start. In numpy that was ~250 us a call on an 1,800-tick window
(two ``lfilter`` recursions, two powers, a stack and a solve): a tenth of a 96-cell bank's time
with swarms (issue 12). Here it is two passes over the window:

* ``fixed_rmse_numpy``: the reference (scipy's ``lfilter`` for the recursions, numpy's solve);
* a compiled source: the recursions, the residual and the 2x2 normal equations of the
  window-start columns in one pass, the weighted sum of squares in a second. It agrees with the
  reference to rounding (``tests/estimate/test_fixed_rmse_kernel.py``).
"""

from __future__ import annotations

import math
from collections.abc import Callable

import numpy as np
import numpy.typing as npt

from bmsid.estimate import jit
from bmsid.model.ecm import rc_filter

FloatArray = npt.NDArray[np.float64]

#: Ridge on the window-start columns' normal equations (as ``varpro_kernel``'s solve: these
#: columns are near-collinear when the two taus meet).
RIDGE = 1e-12

#: (current A, y V, h M V, weights, a1, a2, theta (R0, R1, R2 ohm, M scale, offset V), use h M,
#: use offset) -> weighted RMSE, V
FixedRmse = Callable[
    [FloatArray, FloatArray, FloatArray, FloatArray, float, float, FloatArray, bool, bool], float
]


def fixed_rmse_numpy(
    current_A: FloatArray, y_V: FloatArray, hm_V: FloatArray, weights: FloatArray, a1: float,
    a2: float, theta: FloatArray, use_hysteresis: bool, use_offset: bool,
) -> float:  # fmt: skip
    """The reference: residual of the fixed model, the window-start branch voltages solved for
    by weighted least squares, the weighted RMSE of what is left."""
    pred = -theta[0] * current_A - theta[1] * rc_filter(current_A, a1)
    pred = pred - theta[2] * rc_filter(current_A, a2)
    if use_hysteresis:
        pred = pred + theta[3] * hm_V
    if use_offset:
        pred = pred + theta[4]
    r = y_V - pred
    k = np.arange(current_A.shape[0], dtype=np.float64)
    B = np.stack([a1**k, a2**k], axis=1)
    Bw = B * weights[:, None]
    c = np.linalg.solve(B.T @ Bw + RIDGE * np.eye(2), Bw.T @ r)
    res = r - B @ c
    sse = max(float(res @ (res * weights)), 0.0)
    return float(np.sqrt(sse / max(float(weights.sum()), 1e-300)))


def _fixed_rmse_source(
    current_A: FloatArray, y_V: FloatArray, hm_V: FloatArray, weights: FloatArray, a1: float,
    a2: float, theta: FloatArray, use_hysteresis: bool, use_offset: bool,
) -> float:  # fmt: skip
    """The same in two passes over the window (compiled by numba)."""
    n = current_A.shape[0]
    r = np.empty(n)
    s_h = theta[3] if use_hysteresis else 0.0
    off = theta[4] if use_offset else 0.0
    x1 = 0.0
    x2 = 0.0
    d1 = 1.0
    d2 = 1.0
    g11 = g12 = g22 = b1 = b2 = w_sum = 0.0
    for k in range(n):
        i = current_A[k]
        # the branch states before sample k's current (Eq. 8, ``rc_filter``)
        rk = y_V[k] - (-theta[0] * i - theta[1] * x1 - theta[2] * x2 + s_h * hm_V[k] + off)
        r[k] = rk
        w = weights[k]
        g11 += d1 * d1 * w
        g12 += d1 * d2 * w
        g22 += d2 * d2 * w
        b1 += d1 * w * rk
        b2 += d2 * w * rk
        w_sum += w
        x1 = a1 * x1 + (1.0 - a1) * i
        x2 = a2 * x2 + (1.0 - a2) * i
        d1 *= a1
        d2 *= a2
    g11 += RIDGE
    g22 += RIDGE
    det = g11 * g22 - g12 * g12
    c1 = (g22 * b1 - g12 * b2) / det
    c2 = (g11 * b2 - g12 * b1) / det
    sse = 0.0
    d1 = 1.0
    d2 = 1.0
    for k in range(n):
        res = r[k] - c1 * d1 - c2 * d2
        sse += res * res * weights[k]
        d1 *= a1
        d2 *= a2
    return math.sqrt(max(sse, 0.0) / max(w_sum, 1e-300))


def _warm(kernel: FixedRmse) -> object:
    one = np.ones(4)
    return kernel(one, one, one, one, 0.5, 0.9, np.ones(5), True, True)


KERNEL = jit.Kernel("fixed-parameter window RMSE", fixed_rmse_numpy, _fixed_rmse_source, _warm)
