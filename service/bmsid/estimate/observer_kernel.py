"""The state stage's and the SOC observer's per-tick work as compiled kernels (issue 12).

The numpy reference is the stages' own code (``state.py``, ``observer.py``,
``observer_ekf.py``, ``model/ocv.py``), unchanged; ``jit.select`` decides which one a stage
runs (``state_jit.py`` calls the kernels, the stages fall back to their own code for a tick
with a cell to start). The kernels here loop over cells with the reference's operations in its
order, so they agree to rounding (libm's exp/log against numpy's SIMD ones, LAPACK's gesv and
BLAS's sums against numba's): ``tests/estimate/test_state_kernel.py``.

The kernels call a few scalar helpers (numpy's interp, the hysteresis map's hat weights), plain
Python marked ``@helper`` (``jit_helpers.py``), kept in this file so that numba's cache sees a
change to them; the OCV curve and its slope are ``ocv_kernel.py``'s, which both kernels name in
``depends`` for the same reason.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from typing import Any

import numpy as np

from bmsid.estimate import jit, ocv_kernel, rest_anchor
from bmsid.estimate.jit_helpers import helper, register
from bmsid.estimate.ocv_kernel import (  # the OCV vector's layout and helpers, re-exported
    EQ4_MAX,
    EQ4_MIN,
    N_OCV,
    SOC_MAX,
    SOC_MIN,
    _max,
    _min,
    docv_dz_at,
    ocv_at,
)
from bmsid.estimate.rest_anchor import at_rest_reading
from bmsid.estimate.stage import BoolArray, FloatArray


@helper
def _sign(x: float) -> float:
    """np.sign of a float (0 at 0, NaN at NaN)."""
    return 1.0 if x > 0 else (-1.0 if x < 0 else (0.0 if x == 0 else x))


@helper
def interp_at(x: float, xp: FloatArray, fp: FloatArray) -> float:
    """``np.interp`` at one point (numpy's C code: ends held, NaN where x is NaN)."""
    n = xp.shape[0]
    if math.isnan(x):
        return x
    if x < xp[0]:
        return float(fp[0])
    if x > xp[n - 1]:
        return float(fp[n - 1])
    lo, hi = 0, n - 1  # the last j with xp[j] <= x
    while hi - lo > 1:
        mid = (lo + hi) // 2
        if xp[mid] <= x:
            lo = mid
        else:
            hi = mid
    j = hi if xp[hi] <= x else lo
    if j == n - 1 or xp[j] == x:
        return float(fp[j])
    slope = (fp[j + 1] - fp[j]) / (xp[j + 1] - xp[j])
    y = slope * (x - xp[j]) + fp[j]
    if math.isnan(y):
        y = slope * (x - xp[j + 1]) + fp[j + 1]
        if math.isnan(y) and fp[j] == fp[j + 1]:
            y = fp[j]
    return float(y)


@helper
def hat_at(knots: FloatArray, z: float) -> tuple[int, float]:
    """``hysteresis_map.hat_matrix`` of one SOC: its row is 1 - f at j and f at j + 1."""
    k = knots.shape[0]
    zc = _min(_max(z, knots[0]), knots[k - 1])
    j = 0
    while j < k - 1 and knots[j + 1] <= zc:  # searchsorted(side="right") - 1
        j += 1
    j = min(max(j, 0), k - 2)
    return j, (zc - knots[j]) / (knots[j + 1] - knots[j])


# ------------------------------------------------------------------ the tick's state step
#: Rows of the per-cell constants ``cells``: the count's capacity (A s) and efficiency, the
#: hysteresis rates on discharge and charge (Eq. 6), the observer's capacity and efficiency.
CAP, EFF, KAPPA_D, KAPPA_C, Q_OBS, EFF_OBS, N_CELL_ROWS = 0, 1, 2, 3, 4, 5, 6
#: Rows of the step's output: SOC, h, clamped SOC, OCV, M, h M, the voltage or OCV.
N_OUT = 7
#: Layout of the step's tuning vector ``tun``: the learn range, the observer's rest limit (A),
#: current gain and SOC walk variances.
LEARN_LO, LEARN_HI, REST_LIMIT, GAIN2, WALK2, N_TUN = 0, 1, 2, 3, 4, 5


def _step_source(
    z: FloatArray, h: FloatArray, g: FloatArray, qz: FloatArray, thr: FloatArray,
    i_load: FloatArray, tau_load: FloatArray, gate: BoolArray, v: FloatArray, ok: BoolArray,
    steps: FloatArray, b: float, current_A: float, dt_s: float, p_bb: float, cells: FloatArray,
    tun: FloatArray, ocv: FloatArray, m_soc: FloatArray, m_V: FloatArray, knots: FloatArray,
    d: FloatArray, observer: bool, rest_i: float,
) -> tuple[FloatArray, BoolArray, bool, bool]:  # fmt: skip
    """One tick of ``CoulombState.step`` (and with ``observer`` of ``ObserverState.step``)
    for cells none of which starts this tick: the coulomb steps (``steps`` (k, 2), measured,
    ``b`` the offset removed), h, OCV, M, h M, v or OCV, the learn mask. The observer's
    accumulators ``g``, ``qz``, ``thr`` (capacity throughput) and ``i_load`` are updated in
    place. Returns the ``N_OUT`` rows, the learn mask, whether every cell has a voltage, and
    whether the pack rests (observer)."""
    n = z.shape[0]
    out = np.empty((N_OUT, n))
    learn = np.empty(n, dtype=np.bool_)
    n_steps = steps.shape[0]
    use_map = False  # the observer's map: M corrected where any knot has learnt (d.any())
    for k in range(d.shape[0]):
        use_map = use_map or d[k] != 0.0
    all_ok = True
    any_gate = False
    kappa_prev = i_prev = dt_prev = decay = 0.0
    # the measured current at the rests' reading (rest_i, A), whatever b does: a rest
    cont = observer and at_rest_reading(current_A + b, rest_i, tun[REST_LIMIT])
    # h through the raw steps too (|i| does not average over a tick), unless the tick's mean
    # |i| is a rest's, after b or from the rests' reading (a raw sample's noise is no current)
    charge = off_reading = span = 0.0
    for k in range(n_steps):
        i = steps[k, 0] - b if observer and b != 0.0 else steps[k, 0]
        charge += abs(i) * steps[k, 1]
        off_reading += abs(steps[k, 0] - rest_i) * steps[k, 1]
        span += steps[k, 1]
    held = observer and span > 0 and off_reading / span < tun[REST_LIMIT]
    moves = dt_s > 0 and not held and span > 0 and charge / span >= tun[REST_LIMIT]
    for c in range(n):
        zc_ = z[c]
        hc = h[c]
        for k in range(n_steps):
            i = steps[k, 0] - b if observer and b != 0.0 else steps[k, 0]
            dt = steps[k, 1]
            if observer:  # _accumulate
                eta = cells[EFF_OBS, c] if i < 0 else 1.0
                dz = eta * dt / cells[Q_OBS, c]
                g[c] = g[c] + dz
                qz[c] = qz[c] + tun[GAIN2] * abs(i) * dz
                thr[c] = thr[c] + eta * i * dt / 3600.0
            ce = cells[EFF, c] if i < 0 else 1.0
            zc_ = zc_ + -ce * i * dt / cells[CAP, c]
            if moves and dt > 0:
                kappa = cells[KAPPA_C, c] if i < 0 else cells[KAPPA_D, c]
                if kappa != kappa_prev or i != i_prev or dt != dt_prev or c == 0:
                    decay = math.exp(-abs(kappa * i) * dt)  # a pack of one rate: one exp
                    kappa_prev, i_prev, dt_prev = kappa, i, dt
                hc = decay * hc - (1.0 - decay) * _sign(i)
        if observer:
            qz[c] = qz[c] + tun[WALK2] * dt_s / 3600.0
        out[0, c] = zc_
        out[1, c] = hc
        zcl = _min(_max(zc_, ocv[SOC_MIN]), ocv[SOC_MAX])
        out[2, c] = zcl
        u = ocv_at(ocv, zcl)
        out[3, c] = u
        m = interp_at(zcl, m_soc, m_V)
        if use_map:
            j, f = hat_at(knots, zcl)
            m = _max(m + ((1.0 - f) * d[j] + f * d[j + 1]), 0.0)
        out[4, c] = m
        out[5, c] = hc * m
        out[6, c] = v[c] if ok[c] else u
        all_ok = all_ok and ok[c]
        learn[c] = ok[c] and zcl >= tun[LEARN_LO] and zcl <= tun[LEARN_HI]
        any_gate = any_gate or gate[c]
    resting = False
    if observer:
        i_abs = abs(current_A)
        for c in range(n):
            a = math.exp(-dt_s / tau_load[c])
            i_load[c] = _max(i_abs, a * i_load[c] + (1 - a) * i_abs)
        limit = tun[REST_LIMIT]
        if not any_gate:
            limit += 2.0 * math.sqrt(max(p_bb, 0.0))
        resting = i_abs < limit or cont
    return out, learn, all_ok, resting


def _warm_step(kernel: Callable[..., Any]) -> object:
    register()
    one, yes = np.ones(2), np.ones(2, dtype=np.bool_)
    p = np.zeros(N_OCV)
    p[[0, EQ4_MIN, EQ4_MAX, SOC_MIN, SOC_MAX]] = 3.7, 0.01, 0.99, 0.01, 0.99
    return kernel(
        one * 0.5, one * 0.0, one * 0, one * 0, one * 0, one * 0, one * 100.0, yes, one * 3.7,
        yes, np.ones((1, 2)), 0.0, 1.0, 1.0, 0.0, np.ones((N_CELL_ROWS, 2)) * 1e4,
        np.array([0.0, 1.0, 0.1, 0.0, 0.0]), p, np.array([0.0, 1.0]), one * 0.01,
        np.array([0.0, 1.0]), one * 0.0, True, 0.0,
    )  # fmt: skip


# ------------------------------------------------------------------ the measurement update
#: Layout of the update's tuning vector ``utun``: v_sigma^2, r_dc_rel_sigma, v_sigma_floor^2,
#: gate_sigmas^2, learn_ocv_sigma, agree_sigmas^2 (``ObserverTuning``).
V_SIGMA2, R_DC_REL, FLOOR2, GATE2, LEARN_OCV, AGREE2, N_UTUN = 0, 1, 2, 3, 4, 5, 6


@helper
def lone_cells(e: FloatArray, floor2: float, valid: BoolArray, agree2: float) -> BoolArray:
    """The valid cells whose innovation ``e`` (V) disagrees with the pack's: further from the
    valid cells' median than ``sqrt(agree2)`` times their robust spread (1.4826 x the median
    absolute deviation), or times the rested voltage noise ``sqrt(floor2)`` (V) where the
    spread is smaller. None with fewer than 3 valid cells: two cannot tell which one is off.
    A current offset or a hysteresis error moves every cell's voltage alike; what one cell
    shows alone is its own (its SOC, its model, its sensing). Such a cell teaches only its own
    SOC (``ObserverTuning.agree_sigmas``)."""
    lone = np.zeros(e.shape[0], dtype=np.bool_)
    idx = np.flatnonzero(valid)
    if idx.size < 3:
        return lone
    ev = e[idx]
    med = np.median(ev)
    spread = 1.4826 * np.median(np.abs(ev - med))
    for c in idx:
        dev = e[c] - med
        lone[c] = dev * dev > agree2 * _max(spread * spread, floor2)
    return lone


def _update_source(
    P: FloatArray, g: FloatArray, qz: FloatArray, qb: float, since_s: float, d_walk: FloatArray,
    z: FloatArray, zc: FloatArray, ocv_V: FloatArray, h: FloatArray, m_table: FloatArray,
    v: FloatArray, ok: BoolArray, R0: FloatArray, R1: FloatArray, R2: FloatArray,
    v_model: FloatArray, M_V: FloatArray, converged: BoolArray, anchor: BoolArray,
    i_load: FloatArray, reanchor: bool, current_A: float, consider_offset: bool, b: float,
    b_max: float, ocv: FloatArray, inv_v: FloatArray, inv_z: FloatArray, knots: FloatArray,
    d: FloatArray, m_knots: FloatArray, utun: FloatArray,
) -> tuple[FloatArray, FloatArray, BoolArray, BoolArray, FloatArray, FloatArray, float, int,
           bool]:  # fmt: skip
    """``ObserverState.correct`` from ``_predict`` to ``_gate_learning`` (with
    ``observer_ekf.joint_update``): P updated in place, ``g`` and ``qz`` zeroed. Returns the
    new z, d, learn gate, the anchored cells, the OCV's SOC and its variance there, the new
    offset, the cells gated out and whether the state was updated."""
    n, N, K = z.shape[0], P.shape[0], d.shape[0]
    pb = P[:n, n].copy()  # _predict: P <- F P F' + Q
    pbb = P[n, n]
    for i in range(n):
        for j in range(n):
            P[i, j] = P[i, j] + (g[i] * pb[j] + pb[i] * g[j] + pbb * (g[i] * g[j]))
    for i in range(n):
        P[i, n] = P[n, i] = pb[i] + g[i] * pbb
        P[i, i] = P[i, i] + qz[i]
        g[i] = qz[i] = 0.0
    P[n, n] = P[n, n] + qb
    for k in range(K):
        P[n + 1 + k, n + 1 + k] = P[n + 1 + k, n + 1 + k] + d_walk[k] * since_s
    hz, hb, e, r = np.empty(n), np.empty(n), np.empty(n), np.empty(n)
    z_ocv, z_var = np.full(n, np.nan), np.empty(n)
    G = np.zeros((n, K))
    teaches = np.zeros(n, dtype=np.bool_)
    valid = np.empty(n, dtype=np.bool_)
    jump = reanchor
    for c in range(n):
        jump = jump or anchor[c]
    for c in range(n):
        hz[c] = docv_dz_at(ocv, zc[c])
        hb[c] = R0[c] + R1[c] + R2[c]
        e[c] = v[c] - v_model[c]
        if jump:  # SOC may move far: the OCV's secant (OcvModel.secant_slope)
            z_to = interp_at(ocv_V[c] + e[c], inv_v, inv_z)
            z_ocv[c] = z_to
            dz = z_to - zc[c]
            sec = ((ocv_at(ocv, z_to) - ocv_at(ocv, zc[c])) / dz if abs(dz) > 1e-3
                   else docv_dz_at(ocv, zc[c]))  # fmt: skip
            if (anchor[c] or reanchor) and math.isfinite(sec):
                hz[c] = sec
        if reanchor:
            r_rc = abs(current_A) * (R1[c] + R2[c])
            r[c] = utun[V_SIGMA2] + r_rc * r_rc
        else:
            r_load = i_load[c] * utun[R_DC_REL] * hb[c]
            r[c] = utun[V_SIGMA2] + r_load * r_load
        if K:
            r_anchor = utun[FLOOR2]
            mt = m_table[c]
            scale = M_V[c] / _max(mt, 1e-12) if mt > 0 else 1.0
            scale = scale if math.isfinite(scale) else 1.0
            j, f = hat_at(knots, zc[c])
            var_c = _max(P[c, c], 0.0)
            var_m = (1.0 - f) * _max(P[n + 1 + j, n + 1 + j], 0.0) + f * _max(
                P[n + 2 + j, n + 2 + j], 0.0)  # fmt: skip
            teaches[c] = anchor[c] and abs(hz[c]) * math.sqrt(var_c) <= math.sqrt(var_m)
            coef = scale * h[c]
            G[c, j] = coef * (1.0 - f)
            G[c, j + 1] = coef * f
        else:
            r_anchor = utun[FLOOR2] + (0.25 * m_table[c]) * (0.25 * m_table[c])
        if anchor[c]:
            r[c] = r_anchor
        forced = anchor[c] or reanchor
        valid[c] = (ok[c] and math.isfinite(e[c]) and math.isfinite(hz[c])
                    and math.isfinite(hb[c]) and (converged[c] or forced))  # fmt: skip
        z_var[c] = r[c] / _max(hz[c] * hz[c], 1e-12)
    lone = lone_cells(e, utun[FLOOR2], valid, utun[AGREE2])
    idx = np.flatnonzero(valid)
    n_gated, updated = 0, False
    z_new, b_new, d_new = z, b, d
    if idx.size:  # observer_ekf.joint_update
        m = idx.size
        PHt = np.empty((N, m))
        for a in range(N):
            for q in range(m):
                c = idx[q]
                acc = 0.0
                for k in range(K):
                    acc += P[a, n + 1 + k] * G[c, k]
                PHt[a, q] = P[a, c] * hz[c] + P[a, n] * hb[c] + acc
        S = np.empty((m, m))
        for p_ in range(m):
            c = idx[p_]
            for q in range(m):
                acc = 0.0
                for k in range(K):
                    acc += G[c, k] * PHt[n + 1 + k, q]
                S[p_, q] = hz[c] * PHt[c, q] + hb[c] * PHt[n, q] + acc
            S[p_, p_] += r[c]
        inside = np.empty(m, dtype=np.bool_)
        for p_ in range(m):
            c = idx[p_]
            inside[p_] = e[c] * e[c] <= utun[GATE2] * S[p_, p_] or anchor[c] or reanchor
        keep = np.flatnonzero(inside)
        n_gated = m - keep.size
        if keep.size:
            idx = idx[keep]
            PHt = np.ascontiguousarray(PHt[:, keep])
            S = np.ascontiguousarray(S[keep][:, keep])
            solved = True
            try:
                X = np.linalg.solve(S, np.ascontiguousarray(PHt.T))
            except Exception:  # a singular S: nothing updated
                solved = False
                X = np.zeros((idx.size, N))
            Kg = np.ascontiguousarray(X.T)
            if consider_offset:
                for q in range(idx.size):
                    if not (anchor[idx[q]] or reanchor):
                        Kg[n, q] = 0.0
            for q in range(idx.size):  # the map: consider states where a cell does not teach
                if not teaches[idx[q]]:
                    for k in range(K):
                        Kg[n + 1 + k, q] = 0.0
            for q in range(idx.size):  # a lone cell teaches its own SOC only
                if lone[idx[q]]:
                    for a in range(N):
                        if a != idx[q]:
                            Kg[a, q] = 0.0
            dx = Kg @ np.ascontiguousarray(e[idx])
            if solved and np.all(np.isfinite(dx)):
                KPHt = Kg @ np.ascontiguousarray(PHt.T)
                Pn = P - KPHt - KPHt.T + (Kg @ S) @ np.ascontiguousarray(Kg.T)
                for a in range(N):
                    for q in range(a, N):
                        P[a, q] = P[q, a] = 0.5 * (Pn[a, q] + Pn[q, a])
                    P[a, a] = _max(P[a, a], 0.0)
                z_new = np.empty(n)
                for c in range(n):
                    z_new[c] = _min(_max(z[c] + dx[c], 0.0), 1.0)
                b_new = _min(_max(b + float(dx[n]), -b_max), b_max)
                d_new = np.empty(K)
                for k in range(K):
                    d_new[k] = _max(d[k] + dx[n + 1 + k], -m_knots[k])
                updated = True
    gate = np.empty(n, dtype=np.bool_)  # _gate_learning
    anchored = np.empty(n, dtype=np.bool_)
    for c in range(n):
        zz = _min(_max(z_new[c], ocv[SOC_MIN]), ocv[SOC_MAX])
        gate[c] = abs(docv_dz_at(ocv, zz)) * math.sqrt(_max(P[c, c], 0.0)) <= utun[LEARN_OCV]
        anchored[c] = anchor[c] and valid[c]
    return z_new, d_new, gate, anchored, z_ocv, z_var, b_new, n_gated, updated


def _warm_update(kernel: Callable[..., Any]) -> object:
    register()
    one, yes = np.ones(2), np.ones(2, dtype=np.bool_)
    p = np.zeros(N_OCV)
    p[[0, 1, EQ4_MIN, EQ4_MAX, SOC_MIN, SOC_MAX]] = 3.5, 0.5, 0.01, 0.99, 0.01, 0.99
    return kernel(
        np.eye(5) * 1e-4, one * 0, one * 0, 0.0, 0.0, one * 0, one * 0.5, one * 0.5, one * 3.7,
        one * 0, one * 0.01, one * 3.7, yes, one * 1e-3, one * 1e-3, one * 1e-3, one * 3.7,
        one * 0.01, yes, yes, one * 0, True, 0.0, True, 0.0, 1.0, p, np.array([3.0, 4.0]),
        np.array([0.0, 1.0]), np.array([0.0, 1.0]), one * 0, one * 0.01, np.ones(N_UTUN) * 1e-4,
    )  # fmt: skip


#: The reference in the registry is the kernel source run as plain Python (the stages' numpy
#: mode runs their own code: the reference the tests compare against).
_DEPENDS = (str(ocv_kernel.__file__), str(rest_anchor.__file__))
STEP = jit.Kernel("state step", _step_source, _step_source, _warm_step, depends=_DEPENDS)
UPDATE = jit.Kernel(
    "observer update", _update_source, _update_source, _warm_update, depends=_DEPENDS
)
