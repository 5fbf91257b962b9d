"""The SOC observer's measurement update as a compiled kernel (issue 12): ``ObserverState.correct``
from its prediction to its learn gate, with ``observer_ekf.joint_update`` and the hysteresis
error's prediction and fold (``hysteresis_error.py``).

The numpy reference is the stage's own code (``observer.py``, ``observer_ekf.py``,
``hysteresis_map.py``); the kernel loops over cells with its operations in its order, so they
agree to rounding: ``tests/estimate/test_state_kernel.py``. Its scalar helpers are
``observer_kernel.py``'s, ``ocv_kernel.py``'s and ``hysteresis_error.py``'s, all named in
``depends`` (numba's cache sees a change to them).

The filter's state: ``[z_1 .. z_n, b, d_1 .. d_K, dh]`` (SOC per cell, the pack's current
offset, the hysteresis map's corrections, the pack's hysteresis error).
"""

from __future__ import annotations

import math
from collections.abc import Callable
from typing import Any

import numpy as np

from bmsid.estimate import hysteresis_error, jit, observer_kernel, ocv_kernel
from bmsid.estimate.hysteresis_error import fold, target_variance
from bmsid.estimate.hysteresis_error import predict as predict_h
from bmsid.estimate.jit_helpers import register
from bmsid.estimate.observer_kernel import hat_at, interp_at, lone_cells
from bmsid.estimate.ocv_kernel import (
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
from bmsid.estimate.stage import BoolArray, FloatArray

#: Layout of the update's tuning vector ``utun``: v_sigma^2, r_dc_rel_sigma, v_sigma_floor^2,
#: gate_sigmas^2, learn_ocv_sigma, agree_sigmas^2, 1 where the hysteresis error is estimated
#: (``ObserverTuning``), its variance's floor (``ObserverState._h_floor``).
V_SIGMA2, R_DC_REL, FLOOR2, GATE2, LEARN_OCV, AGREE2, H_ERROR, H_FLOOR, N_UTUN = range(9)


def _update_source(
    P: FloatArray, g: FloatArray, qz: FloatArray, qb: float, since_s: float, d_walk: FloatArray,
    z: FloatArray, zc: FloatArray, ocv_V: FloatArray, h: FloatArray, m_table: FloatArray,
    v: FloatArray, ok: BoolArray, R0: FloatArray, R1: FloatArray, R2: FloatArray,
    v_model: FloatArray, M_V: FloatArray, converged: BoolArray, anchor: BoolArray,
    i_load: FloatArray, reanchor: bool, current_A: float, consider_offset: bool, b: float,
    b_max: float, ocv: FloatArray, inv_v: FloatArray, inv_z: FloatArray, knots: FloatArray,
    d: FloatArray, m_knots: FloatArray, utun: FloatArray, log_decay: FloatArray,
) -> tuple[FloatArray, FloatArray, BoolArray, BoolArray, FloatArray, FloatArray, float, int,
           bool, FloatArray]:  # fmt: skip
    """``ObserverState.correct`` from ``_predict`` to ``_gate_learning`` (with
    ``observer_ekf.joint_update``): P updated in place, ``g``, ``qz`` and ``log_decay`` zeroed.
    ``M_V``: the half-gap the model voltage uses (V). Returns the new z, d, learn gate, the
    anchored cells, the OCV's SOC and its variance there, the new offset, the cells gated out,
    whether the state was updated and the new h."""
    n, N, K = z.shape[0], P.shape[0], d.shape[0]
    Kt = N - n - 1  # the map's K and the hysteresis error
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
    predict_h(P, log_decay, target_variance(h, utun[H_FLOOR]) if utun[H_ERROR] > 0.0 else 0.0)
    hz, hb, e, r = np.empty(n), np.empty(n), np.empty(n), np.empty(n)
    z_ocv, z_var = np.full(n, np.nan), np.empty(n)
    G = np.zeros((n, Kt))
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
        G[c, K] = M_V[c]  # dv / d dh
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
                    and math.isfinite(hb[c]) and math.isfinite(M_V[c])
                    and (converged[c] or forced))  # fmt: skip
        z_var[c] = r[c] / _max(hz[c] * hz[c], 1e-12)
    lone = lone_cells(e, utun[FLOOR2], valid, utun[AGREE2])
    idx = np.flatnonzero(valid)
    n_gated, updated = 0, False
    z_new, b_new, d_new, h_new = z, b, d, h
    if idx.size:  # observer_ekf.joint_update
        m = idx.size
        PHt = np.empty((N, m))
        for a in range(N):
            for q in range(m):
                c = idx[q]
                acc = 0.0
                for k in range(Kt):
                    acc += P[a, n + 1 + k] * G[c, k]
                PHt[a, q] = P[a, c] * hz[c] + P[a, n] * hb[c] + acc
        S = np.empty((m, m))
        for p_ in range(m):
            c = idx[p_]
            for q in range(m):
                acc = 0.0
                for k in range(Kt):
                    acc += G[c, k] * PHt[n + 1 + k, q]
                S[p_, q] = hz[c] * PHt[c, q] + hb[c] * PHt[n, q] + acc
            S[p_, p_] += r[c]
        inside = np.empty(m, dtype=np.bool_)
        for p_ in range(m):
            c = idx[p_]
            within = e[c] * e[c] <= utun[GATE2] * S[p_, p_]
            inside[p_] = within or anchor[c] or reanchor
            if not within:  # forced beyond the gate: its own SOC only (observer_ekf)
                lone[c] = True
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
                h_new = fold(h, float(dx[N - 1]))
                updated = True
    gate = np.empty(n, dtype=np.bool_)  # _gate_learning
    anchored = np.empty(n, dtype=np.bool_)
    for c in range(n):
        zz = _min(_max(z_new[c], ocv[SOC_MIN]), ocv[SOC_MAX])
        gate[c] = abs(docv_dz_at(ocv, zz)) * math.sqrt(_max(P[c, c], 0.0)) <= utun[LEARN_OCV]
        anchored[c] = anchor[c] and valid[c]
    return z_new, d_new, gate, anchored, z_ocv, z_var, b_new, n_gated, updated, h_new


def _warm_update(kernel: Callable[..., Any]) -> object:
    register()
    one, yes = np.ones(2), np.ones(2, dtype=np.bool_)
    p = np.zeros(N_OCV)
    p[[0, 1, EQ4_MIN, EQ4_MAX, SOC_MIN, SOC_MAX]] = 3.5, 0.5, 0.01, 0.99, 0.01, 0.99
    return kernel(
        np.eye(6) * 1e-4, one * 0, one * 0, 0.0, 0.0, one * 0, one * 0.5, one * 0.5, one * 3.7,
        one * 0, one * 0.01, one * 3.7, yes, one * 1e-3, one * 1e-3, one * 1e-3, one * 3.7,
        one * 0.01, yes, yes, one * 0, True, 0.0, True, 0.0, 1.0, p, np.array([3.0, 4.0]),
        np.array([0.0, 1.0]), np.array([0.0, 1.0]), one * 0, one * 0.01, np.ones(N_UTUN) * 1e-4,
        one * 0,
    )  # fmt: skip


#: The reference in the registry is the kernel source run as plain Python (the stage's numpy
#: mode runs its own code: the reference the tests compare against).
_DEPENDS = tuple(str(m.__file__) for m in (observer_kernel, ocv_kernel, hysteresis_error))
UPDATE = jit.Kernel(
    "observer update", _update_source, _update_source, _warm_update, depends=_DEPENDS
)
