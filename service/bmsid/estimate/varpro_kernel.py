"""The normal equations of the swarm's window fit (``varpro.fit_linear``), for many pole pairs.

For each candidate (a1, a2) = ZOH poles of the two branches (Eq. 7) the window's regressor rows
are ``[-i_k, -x1_k, -x2_k, (h M)_k, 1, a1^k, a2^k]`` (scaled, inactive columns left out), with
x_j the unit-gain branch states of Eq. 8 (``model.ecm.rc_filter``); the fit needs only
``G = A' W A``, ``b = A' W y`` and the branch states at the last tick. This is where the fused
estimator spends most of its time (two thirds of a 96-cell bank's with swarms running), so it
comes twice:

* ``normal_equations_numpy``: the reference, whole-window numpy (scipy's ``lfilter`` for the
  recursions, batched matrix products);
* a compiled kernel (numba, ``cache=True``; ``fastmath`` lets the window sums vectorise, which
  reorders their additions; its source is ``varpro_sums.py``): the recursions of four
  candidates at once, then each candidate's sums in a few vectorised passes over the window, no
  (candidates x window x columns) array. It agrees with the reference to rounding
  (``tests/estimate/test_varpro_kernel.py``).

``normal_equations`` runs the implementation ``jit.select`` chose: the compiled one where numba
imports and compiles (seconds once, then ~0.1 s per process from numba's cache), else the
reference.
"""

from __future__ import annotations

import math
from collections.abc import Callable

import numpy as np
import numpy.typing as npt

from bmsid.estimate import jit, varpro_sums
from bmsid.estimate.jit_helpers import register
from bmsid.estimate.varpro_sums import normal_equations_source
from bmsid.model.ecm import rc_filter

FloatArray = npt.NDArray[np.float64]

#: (current A, y V, h M V, weights, a1, a2, column scales, use h M, use offset) ->
#: (G (P, n, n), b (P, n), branch states at the last tick (P, 2))
NormalEquations = Callable[
    [FloatArray, FloatArray, FloatArray, FloatArray, FloatArray, FloatArray, FloatArray, bool,
     bool],
    tuple[FloatArray, FloatArray, FloatArray],
]  # fmt: skip


def normal_equations_numpy(
    current_A: FloatArray, y_V: FloatArray, hm_V: FloatArray, weights: FloatArray,
    a1: FloatArray, a2: FloatArray, s_cols: FloatArray, use_hysteresis: bool, use_offset: bool,
) -> tuple[FloatArray, FloatArray, FloatArray]:  # fmt: skip
    """The reference: ``s_cols`` scales the active columns in order (R0, R1, R2, [M scale],
    [offset], c1, c2); returns G, b and the unit-gain branch states x1, x2 at the last tick."""
    n_w, p, n_a = current_A.shape[0], a1.shape[0], s_cols.shape[0]
    k = np.arange(n_w, dtype=np.float64)
    A = np.empty((p, n_w, n_a))
    A[:, :, 0] = -current_A * s_cols[0]
    last = np.empty((p, 2))
    for j in range(p):
        x1 = rc_filter(current_A, float(a1[j]))
        x2 = rc_filter(current_A, float(a2[j]))
        A[j, :, 1] = x1 * -s_cols[1]
        A[j, :, 2] = x2 * -s_cols[2]
        last[j] = x1[-1], x2[-1]
    col = 3
    if use_hysteresis:
        A[:, :, col] = hm_V * s_cols[col]
        col += 1
    if use_offset:
        A[:, :, col] = s_cols[col]
        col += 1
    A[:, :, col] = np.exp(np.log(a1)[:, None] * k)
    A[:, :, col + 1] = np.exp(np.log(a2)[:, None] * k)
    Aw = A * weights[None, :, None]
    G = np.swapaxes(Aw, 1, 2) @ A
    b = np.swapaxes(Aw, 1, 2) @ y_V
    return G, b, last


def _warm(kernel: NormalEquations) -> object:
    register()  # the source's helpers (varpro_sums.py) callable from compiled code
    one = np.ones(3)
    return kernel(one, one, one, one, one[:1] * 0.5, one[:1] * 0.9, one[:2].repeat(2), False, False)


#: ``fastmath`` lets the window sums vectorise (it reorders their additions)
KERNEL = jit.Kernel(
    "window fits", normal_equations_numpy, normal_equations_source, _warm, fastmath=True
)


def normal_equations(
    current_A: FloatArray, y_V: FloatArray, hm_V: FloatArray, weights: FloatArray,
    a1: FloatArray, a2: FloatArray, s_cols: FloatArray, use_hysteresis: bool, use_offset: bool,
) -> tuple[FloatArray, FloatArray, FloatArray]:  # fmt: skip
    """G, b and the last branch states (see ``normal_equations_numpy``) by the implementation
    in use (``jit.select``: the compiled one where it works)."""
    return KERNEL.impl(current_A, y_V, hm_V, weights, a1, a2, s_cols, use_hysteresis, use_offset)


#: (G, b, last branch states, y V, weights, a1, a2, column scales, active column indices,
#: offset ridge, its column, with covariance) -> (theta (P, 5), RMSE V (P,), branch states at
#: the last tick (P, 2), covariance (P, 5, 5))
Solve = Callable[
    [FloatArray, FloatArray, FloatArray, FloatArray, FloatArray, FloatArray, FloatArray,
     FloatArray, npt.NDArray[np.int64], float, int, bool],
    tuple[FloatArray, FloatArray, FloatArray, FloatArray],
]  # fmt: skip


def solve_numpy(
    G: FloatArray, b: FloatArray, x_last: FloatArray, y_V: FloatArray, wts: FloatArray,
    a1: FloatArray, a2: FloatArray, s_full: FloatArray, idx: npt.NDArray[np.int64],
    offset_prior: float, j_off: int, with_cov: bool,
) -> tuple[FloatArray, FloatArray, FloatArray, FloatArray]:  # fmt: skip
    """The reference: each candidate's equilibrated normal equations solved (the offset's
    ridge added to G in place), its weighted RMSE, the linear parameters in the order R0, R1,
    R2, M scale, offset (inactive ones 0), the covariance in normalised units, and the branch
    states at the last tick with the window-start voltages folded in (``varpro.fit_linear``)."""
    p, n_a = b.shape
    if j_off >= 0 and offset_prior > 0:
        G[:, j_off, j_off] += offset_prior
    d = np.sqrt(np.maximum(np.diagonal(G, axis1=1, axis2=2), 1e-300))
    Gs = G / (d[:, :, None] * d[:, None, :]) + 1e-10 * np.eye(n_a)
    th_s = np.linalg.solve(Gs, (b / d)[..., None])[..., 0]
    th_n = th_s / d
    yy = float(y_V @ (y_V * wts))
    sse = yy - 2.0 * np.einsum("pk,pk->p", th_n, b) + np.einsum("pk,pkl,pl->p", th_n, G, th_n)
    rmse = np.sqrt(np.maximum(sse, 0.0) / max(float(wts.sum()), 1e-300))
    theta_full = np.zeros((p, 7))
    theta_full[:, idx] = th_n * s_full
    cov5 = np.zeros((p, 5, 5))
    if with_cov:
        with np.errstate(all="ignore"):  # degenerate windows: the caller checks finiteness
            cov_n = np.linalg.inv(Gs) / (d[:, :, None] * d[:, None, :])
        cov_full = np.zeros((p, 7, 7))
        cov_full[:, idx[:, None], idx[None, :]] = cov_n
        cov5 = cov_full[:, :5, :5]
    decay_last = np.stack([a1, a2], axis=1) ** (y_V.shape[0] - 1)
    r = theta_full[:, 1:3]
    ic = np.where(r > 0, -theta_full[:, 5:7] / np.where(r > 0, r, 1.0), 0.0)
    return theta_full[:, :5].copy(), rmse, x_last + ic * decay_last, cov5


def _solve_source(
    G: FloatArray, b: FloatArray, x_last: FloatArray, y_V: FloatArray, wts: FloatArray,
    a1: FloatArray, a2: FloatArray, s_full: FloatArray, idx: npt.NDArray[np.int64],
    offset_prior: float, j_off: int, with_cov: bool,
) -> tuple[FloatArray, FloatArray, FloatArray, FloatArray]:  # fmt: skip
    """The same per candidate, in loops (compiled by numba): no Python between the small
    solves, which were most of a swarm fit's time after the normal equations compiled."""
    p, n_a = b.shape
    n_w = y_V.shape[0]
    theta = np.zeros((p, 5))
    rmse = np.zeros(p)
    x_out = np.empty((p, 2))
    cov5 = np.zeros((p, 5, 5))
    yy = 0.0
    w_sum = 0.0
    for k in range(n_w):
        yy += y_V[k] * (y_V[k] * wts[k])
        w_sum += wts[k]
    full = np.zeros(7)
    for j in range(p):
        if j_off >= 0 and offset_prior > 0:
            G[j, j_off, j_off] += offset_prior
        d = np.empty(n_a)
        for r in range(n_a):
            d[r] = np.sqrt(max(G[j, r, r], 1e-300))
        Gs = np.empty((n_a, n_a))
        for r in range(n_a):
            for q in range(n_a):
                Gs[r, q] = G[j, r, q] / (d[r] * d[q]) + (1e-10 if r == q else 0.0)
        th = np.linalg.solve(Gs, b[j] / d) / d
        sse = yy
        for r in range(n_a):
            sse -= 2.0 * th[r] * b[j, r]
        for r in range(n_a):
            acc = 0.0
            for q in range(n_a):
                acc += G[j, r, q] * th[q]
            sse += th[r] * acc
        rmse[j] = np.sqrt(max(sse, 0.0) / max(w_sum, 1e-300))
        full[:] = 0.0
        for r in range(n_a):
            full[idx[r]] = th[r] * s_full[r]
        theta[j] = full[:5]
        if with_cov:
            inv = np.linalg.solve(Gs, np.eye(n_a))  # as numpy's inv: LU with identity
            for r in range(n_a):
                for q in range(n_a):
                    if idx[r] < 5 and idx[q] < 5:
                        cov5[j, idx[r], idx[q]] = inv[r, q] / (d[r] * d[q])
        for br in range(2):
            r_br = full[1 + br]
            ic = -full[5 + br] / r_br if r_br > 0 else 0.0
            a = a1[j] if br == 0 else a2[j]
            x_out[j, br] = x_last[j, br] + ic * a ** (n_w - 1)
    return theta, rmse, x_out, cov5


def _warm_solve(kernel: Solve) -> object:
    G = np.eye(5)[None, :, :].repeat(2, axis=0) + 0.1
    one = np.ones(2)
    idx = np.array([0, 1, 2, 5, 6], dtype=np.int64)
    return kernel(G, np.ones((2, 5)), np.ones((2, 2)), one, one, one * 0.5, one * 0.9,
                  np.ones(5), idx, 0.0, -1, True)  # fmt: skip


SOLVE = jit.Kernel("window solves", solve_numpy, _solve_source, _warm_solve)


# ------------------------------------------------------------------ one swarm fitness call


def fitness_numpy(
    current_A: FloatArray, y_V: FloatArray, hm_V: FloatArray, wts: FloatArray, a1: FloatArray,
    a2: FloatArray, s_full: FloatArray, idx: npt.NDArray[np.int64], use_hysteresis: bool,
    use_offset: bool, offset_prior: float, j_off: int, lin_lo: FloatArray, lin_hi: FloatArray,
    abs_scale: FloatArray, t_lo: FloatArray, t_hi: FloatArray, tau_ratio_min: float,
) -> FloatArray:  # fmt: skip
    """The reference of a swarm fitness (``swarm_kernel.py``) after the poles: the window fit
    (normal equations and solves, references) of each candidate, its RMSE penalised by 10x the
    linear parameters' bound violations (in units of ``abs_scale``) and the taus' ratio
    shortfall."""
    G, b, last = normal_equations_numpy(
        current_A, y_V, hm_V, wts, a1, a2, s_full, use_hysteresis, use_offset
    )
    theta, rmse, _, _ = solve_numpy(
        G, b, last, y_V, wts, a1, a2, s_full, idx, offset_prior, j_off, False
    )
    viol = (np.maximum(lin_lo - theta, 0.0) + np.maximum(theta - lin_hi, 0.0)) / abs_scale
    viol_r = np.maximum(tau_ratio_min / (t_hi / t_lo) - 1.0, 0.0)
    return np.asarray(rmse * (1.0 + 10.0 * (viol.sum(axis=1) + viol_r)))


#: The compiled normal equations and solves, called by the compiled fitness (set by its warm-up,
#: before it compiles: the same compiled code, and its fastmath flags, as when called alone).
_NORMAL: Callable[..., tuple[FloatArray, FloatArray, FloatArray]] | None = None
_SOLVE: Callable[..., tuple[FloatArray, FloatArray, FloatArray, FloatArray]] | None = None


def _fitness_source(
    current_A: FloatArray, y_V: FloatArray, hm_V: FloatArray, wts: FloatArray, a1: FloatArray,
    a2: FloatArray, s_full: FloatArray, idx: npt.NDArray[np.int64], use_hysteresis: bool,
    use_offset: bool, offset_prior: float, j_off: int, lin_lo: FloatArray, lin_hi: FloatArray,
    abs_scale: FloatArray, t_lo: FloatArray, t_hi: FloatArray, tau_ratio_min: float,
) -> FloatArray:  # fmt: skip
    """The same in one call (compiled by numba): the two compiled kernels, then the penalty per
    candidate in the reference's operations and order (its row sums add left to right, as
    numpy's over five columns), so the same bits as the kernels called one by one."""
    G, b, last = _NORMAL(current_A, y_V, hm_V, wts, a1, a2, s_full, use_hysteresis, use_offset)  # type: ignore[misc]
    theta, rmse, _, _ = _SOLVE(  # type: ignore[misc]
        G, b, last, y_V, wts, a1, a2, s_full, idx, offset_prior, j_off, False
    )
    p, m = theta.shape
    out = np.empty(p)
    for j in range(p):
        total = 0.0
        for k in range(m):
            lo = lin_lo[k] - theta[j, k]
            hi = theta[j, k] - lin_hi[k]
            # np.maximum(x, 0.0): NaN propagates
            lo = lo if lo >= 0.0 or math.isnan(lo) else 0.0
            hi = hi if hi >= 0.0 or math.isnan(hi) else 0.0
            v = (lo + hi) / abs_scale[k]
            total = v if k == 0 else total + v
        r = tau_ratio_min / (t_hi[j] / t_lo[j]) - 1.0
        r = r if r >= 0.0 or math.isnan(r) else 0.0
        out[j] = rmse[j] * (1.0 + 10.0 * (total + r))
    return out


def _warm_fitness(kernel: Callable[..., FloatArray]) -> object:
    global _NORMAL, _SOLVE  # the compiled callees, bound before this kernel compiles
    _NORMAL, _SOLVE = KERNEL.compiled(), SOLVE.compiled()
    if _NORMAL is None or _SOLVE is None:
        raise RuntimeError("the window kernels did not compile")
    one = np.ones(4)
    idx = np.array([0, 1, 2, 5, 6], dtype=np.int64)
    return kernel(one, one, one, one, one[:2] * 0.5, one[:2] * 0.9, np.ones(5), idx, False,
                  False, 0.0, -1, one[:5] * 0.0, one[:5] * 2.0, np.ones(5), one[:2], one[:2] * 2,
                  1.5)  # fmt: skip


#: One swarm fitness evaluation (``swarm_kernel.STEP``): the window fit and its penalty. It
#: embeds the compiled normal equations, whose source is another file.
FITNESS = jit.Kernel(
    "swarm fitness", fitness_numpy, _fitness_source, _warm_fitness,
    depends=(str(varpro_sums.__file__),),
)  # fmt: skip
