"""The parameter stages' per-tick recursion, compiled: one kernel call per tick and stage.

``ARX_TICK`` runs ``ArxRlsStage.step`` (branch states, a-priori error, Eq. 21's forgetting, the
AFFRLS update with its trace cap and active mask, the map theta -> R0, R1, R2, tau2, tau1 and
its accept/clamp rule), ``FUSION_TICK`` the per-tick AFFRLS of ``FusionStage.step`` (the same
recursion on the linear parameters, then their projection onto the bounds and the clamp). Their
numpy references are ``rls_reference``'s functions (the code the stages ran before), whose
arguments and results they share; ``jit.select`` chooses for all kernels at once.

Each kernel loops over the cells and, per cell, calls the helpers below the two stages share
(``_branch``, ``_adapt_cell``, ``_rls_row``), in the same formulas and order as the reference:
equal to it to rounding (``tests/estimate/test_rls_kernel.py``: the map ``_map_row`` gives the
same bits as ``model.arx``'s; libm's exp and pow and the RLS's plain sums differ from numpy's
vectorised exp, pow and BLAS products in the last bits, 1e-15 relative a tick, ~1e-12 over a
run, and the same accept/reject decisions and quality codes on the reference DST).

The helpers are plain Python marked ``@helper`` (``jit_helpers.py``: they run uncompiled too,
and are compiled into the kernels that call them when a kernel's ``warm`` first runs, so numba
is imported only where a kernel is compiled). Helpers and kernels stay in this one file:
numba's cache of a kernel is invalidated by changes to the kernel's own file only, not to the
files it calls into.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np

from bmsid.estimate import jit
from bmsid.estimate.jit_helpers import helper, register
from bmsid.estimate.rls_reference import arx_tick_numpy, fusion_tick_numpy

# ------------------------------------------------------------------ helpers (shared)


@helper
def _maximum(a: float, b: float) -> float:
    """np.maximum of two floats: NaN propagates."""
    return a if a >= b or math.isnan(a) else b


@helper
def _minimum(a: float, b: float) -> float:
    """np.minimum of two floats: NaN propagates."""
    return a if a <= b or math.isnan(a) else b


@helper
def _branch(x: float, tau: float, i: float, dt: float) -> float:
    """A unit-gain RC branch state over ``dt`` > 0 at the held current ``i`` (Eq. 8)."""
    a = np.exp(-dt / tau)
    return a * x + (1.0 - a) * i  # type: ignore[no-any-return]


@helper
def _adapt_cell(
    e: float, s: float, ok: bool, quiet: bool, g: float, lam_lo: float, lam_hi: float,
    consts: tuple[float, float, float, float],
) -> tuple[float, float, float]:  # fmt: skip
    """``stage._adapt_one``: (clipped error, new innovation RMS, lambda) of one cell."""
    floor, clip_sigmas, base_sigmas, base = consts
    sig = _maximum(s, floor)
    lim = clip_sigmas * sig
    e_c = _minimum(_maximum(e, -lim), lim)
    if ok:
        s2 = s * s
        s = np.sqrt(s2 + g * (e_c * e_c - s2))
    e_base = _maximum(base_sigmas * sig, floor)
    q = e_c / e_base
    eps = _minimum(np.rint(q * q * 100.0) / 100.0, 1.0e3)
    lam = 1.0 if quiet else lam_lo + (lam_hi - lam_lo) * base**eps
    return e_c, s, lam


@helper
def _rls_row(
    theta: Any, P: Any, phi: Any, e: float, lam: float, theta_out: Any, P_out: Any, pphi: Any
) -> float:
    """``affrls.rls_update`` of one row (theta (m,), P (m, m), regressor phi (m,), a-priori
    error e) into ``theta_out``, ``P_out`` (``pphi``: scratch (m,)); returns trace(P_out)."""
    m = phi.shape[0]
    for r in range(m):
        acc = 0.0
        for q in range(m):
            acc += P[r, q] * phi[q]
        pphi[r] = acc
    acc = 0.0
    for r in range(m):
        acc += phi[r] * pphi[r]
    denom = lam + acc
    for r in range(m):
        k = pphi[r] / denom
        theta_out[r] = theta[r] + k * e
        for q in range(m):
            P_out[r, q] = (P[r, q] - k * pphi[q]) / lam
    tr = 0.0
    for r in range(m):
        for q in range(r, m):
            sym = 0.5 * (P_out[r, q] + P_out[q, r])
            P_out[r, q] = sym
            P_out[q, r] = sym
        tr += P_out[r, r]
    return tr


@helper
def _cap_and_mask(
    theta: Any, P: Any, theta_new: Any, P_new: Any, tr: Any, active: Any, trace_max: float
) -> None:
    """The rest of ``rls_update`` over all rows: trace(P) capped at ``trace_max`` (when the
    largest trace, NaN propagating, exceeds it), inactive rows back to ``theta``, ``P``."""
    n = tr.shape[0]
    top = tr[0]
    for c in range(1, n):
        top = _maximum(top, tr[c])
    cap = top > trace_max
    for c in range(n):
        if not active[c]:
            theta_new[c, :] = theta[c, :]
            P_new[c, :, :] = P[c, :, :]
        elif cap:
            f = _minimum(trace_max / tr[c], 1.0)
            for r in range(P_new.shape[1]):
                for q in range(P_new.shape[2]):
                    P_new[c, r, q] *= f


@helper
def _map_row(
    t1: float, t2: float, t3: float, t4: float, t5: float, T: float
) -> tuple[float, float, float, float, float, float]:
    """``model.arx._map_one``: (status, R0, R1, R2, tau2, tau1) of one theta (Eq. 22-23)."""
    if not (math.isfinite(t1) and math.isfinite(t2) and math.isfinite(t3)
            and math.isfinite(t4) and math.isfinite(t5)):  # fmt: skip
        return 1.0, 0.0, 0.0, 0.0, 0.0, 0.0  # NOT_FINITE
    dm = 1.0 - t1 - t2
    dp = 1.0 + t1 - t2
    if not (dm > 0 and dp > 0):
        return 2.0, 0.0, 0.0, 0.0, 0.0, 0.0  # UNSTABLE
    m1 = (t4 - t3 - t5) / dp
    m2 = dp * T * T / (4.0 * dm)
    m3 = (1.0 + t2) * T / dm
    m4 = (-t3 - t4 - t5) / dm
    m5 = (t5 - t3) * T / dm
    disc = m3 * m3 - 4.0 * m2
    if disc <= 0:
        return 3.0, 0.0, 0.0, 0.0, 0.0, 0.0  # COMPLEX_POLES
    root = np.sqrt(disc) if disc > 0 else 0.0  # NaN: 0, as the array path
    tau_f = 0.5 * (m3 - root)
    tau_s = 0.5 * (m3 + root)
    spread = tau_s - tau_f
    gap = spread if spread > 0 else 1.0
    r_slow = (tau_s * (m4 - m1) + m1 * m3 - m5) / gap
    r_fast = m4 - m1 - r_slow
    if tau_f <= 0 or tau_s <= 0:
        return 4.0, 0.0, 0.0, 0.0, 0.0, 0.0  # NONPOS_TAU
    if m1 <= 0 or r_fast <= 0 or r_slow <= 0:
        return 5.0, 0.0, 0.0, 0.0, 0.0, 0.0  # NONPOS_R
    if not (math.isfinite(m1) and math.isfinite(r_fast) and math.isfinite(r_slow)
            and math.isfinite(tau_s)):  # fmt: skip
        return 1.0, 0.0, 0.0, 0.0, 0.0, 0.0
    return 0.0, m1, r_fast, r_slow, tau_s, tau_f


# ------------------------------------------------------------------ the stages' kernels


def _arx_source(
    x1: Any, x2: Any, tau1: Any, tau2: Any, R0: Any, R1: Any, R2: Any, lam: Any, sig_e: Any,
    theta: Any, P: Any, ue_hist: Any, scale: Any, i_hist: Any, bounds: Any, rest_A: Any,
    v: Any, ocv: Any, hm: Any, ok: Any, learn: Any, clamped: Any, arx_ok: Any, i: float,
    ip: float, dt: float, T: float, lam_lo: float, lam_hi: float, g: float,
    consts: tuple[float, float, float, float], trace_max: float, use_h: bool, do_rls: bool,
) -> Any:  # fmt: skip
    """``rls_reference.arx_tick_numpy`` cell by cell (compiled by numba)."""
    n, m = theta.shape
    out = np.empty((7, n))  # R0, R1, R2, tau1, tau2, a-priori error, model voltage
    theta_n, P_n, tr = np.empty((n, m)), np.empty((n, m, m)), np.zeros(n)
    phi, pphi = np.empty(m), np.empty(m)
    for c in range(n):
        if dt > 0:
            x1[c] = _branch(x1[c], tau1[c], ip, dt)
            x2[c] = _branch(x2[c], tau2[c], ip, dt)
        clamped[c] = False
        h = hm[c] if use_h else 0.0
        vm = ocv[c] + h - R0[c] * i - R1[c] * x1[c] - R2[c] * x2[c]
        out[6, c] = vm
        ue = v[c] - ocv[c] - h
        if do_rls:
            phi[0], phi[1], phi[2] = ue_hist[c, 0], ue_hist[c, 1], i
            phi[3], phi[4] = i_hist[0], i_hist[1]
            acc = 0.0
            for k in range(m):
                acc += phi[k] * (theta[c, k] * scale[c, k])
            e = ue - acc
            out[5, c] = e if ok[c] else 0.0
            quiet = abs(i) < rest_A[c] and abs(i - ip) < rest_A[c]
            e_c, sig_e[c], lam[c] = _adapt_cell(
                e, sig_e[c], learn[c], quiet, g, lam_lo, lam_hi, consts
            )
            for k in range(m):
                phi[k] *= scale[c, k]
            tr[c] = _rls_row(theta[c], P[c], phi, e_c, lam[c], theta_n[c], P_n[c], pphi)
        else:
            out[5, c] = v[c] - vm if ok[c] else 0.0
        ue_hist[c, 1] = ue_hist[c, 0]
        ue_hist[c, 0] = ue
        out[0, c], out[1, c], out[2, c] = R0[c], R1[c], R2[c]  # held unless the map is taken
        out[3, c], out[4, c] = tau1[c], tau2[c]
    i_hist[1] = i_hist[0]
    i_hist[0] = i
    rejected = 0
    if do_rls:
        _cap_and_mask(theta, P, theta_n, P_n, tr, learn, trace_max)
        theta[:, :] = theta_n
        P[:, :, :] = P_n
        lo, hi = bounds[0], bounds[1]
        raw = np.empty(5)
        for c in range(n):
            status, raw[0], raw[1], raw[2], raw[3], raw[4] = _map_row(
                theta[c, 0] * scale[c, 0], theta[c, 1] * scale[c, 1], theta[c, 2] * scale[c, 2],
                theta[c, 3] * scale[c, 3], theta[c, 4] * scale[c, 4], T,
            )  # fmt: skip
            if not (learn[c] and status == 0.0):
                rejected += 1 if learn[c] else 0
                continue
            inside = True
            for k in range(5):  # rows R0, R1, R2, tau2, tau1 into out's R0, R1, R2, tau2, tau1
                r = _minimum(_maximum(raw[k], lo[k, c]), hi[k, c])
                inside = inside and r == raw[k]
                out[k if k < 3 else 7 - k, c] = r
            clamped[c] = not inside
            arx_ok[c] = True
    return out, rejected


def _fusion_source(
    x1: Any, x2: Any, tau1: Any, tau2: Any, theta: Any, P: Any, sig_e: Any, lam: Any, lin: Any,
    rest_A: Any, v: Any, ocv: Any, hm: Any, ok: Any, learn: Any, clamped: Any, i: float,
    ip: float, dt: float, lam_lo: float, lam_hi: float, g: float,
    consts: tuple[float, float, float, float], trace_max: float, fit_scale: bool,
    fit_offset: bool,
) -> Any:  # fmt: skip
    """``rls_reference.fusion_tick_numpy`` cell by cell (compiled by numba)."""
    sc, phi_sc, lo, hi, tol = lin[0], lin[1], lin[2], lin[3], lin[4]
    n, m = theta.shape
    out = np.empty((3, n))  # a-priori error, model voltage, V - OCV
    theta_n, P_n, tr = np.empty((n, m)), np.empty((n, m, m)), np.empty(n)
    phi, pphi = np.empty(m), np.empty(m)
    for c in range(n):
        if dt > 0:
            x1[c] = _branch(x1[c], tau1[c], ip, dt)
            x2[c] = _branch(x2[c], tau2[c], ip, dt)
        clamped[c] = False
        phi[0], phi[1], phi[2], phi[3], phi[4] = -i, -x1[c], -x2[c], hm[c], 1.0
        acc = 0.0
        for k in range(m):
            acc += phi[k] * (theta[c, k] * sc[c, k])
        vm = ocv[c] + acc
        out[1, c] = vm
        out[2, c] = v[c] - ocv[c]
        e = v[c] - vm
        out[0, c] = e if ok[c] else 0.0
        quiet = abs(i) < rest_A[c] and abs(i - ip) < rest_A[c]
        e_c, sig_e[c], lam[c] = _adapt_cell(e, sig_e[c], learn[c], quiet, g, lam_lo, lam_hi, consts)
        for k in range(m):
            phi[k] *= phi_sc[c, k]
        tr[c] = _rls_row(theta[c], P[c], phi, e_c, lam[c], theta_n[c], P_n[c], pphi)
    _cap_and_mask(theta, P, theta_n, P_n, tr, learn, trace_max)
    P[:, :, :] = P_n
    out_of_bounds = False
    for c in range(n):
        for k in range(m):
            th = theta_n[c, k] * sc[c, k]
            out_of_bounds = out_of_bounds or th < lo[c, k] or th > hi[c, k]
    # project_linear: every cell, coordinates in a fixed order, when any left its bounds
    for j in range(m if out_of_bounds else 0):
        for c in range(n):
            th_j = theta_n[c, j] * sc[c, j]
            d_n = (_minimum(_maximum(th_j, lo[c, j]), hi[c, j]) - th_j) / sc[c, j]
            pjj = P[c, j, j]
            for k in range(m):
                theta_n[c, k] += (P[c, k, j] / pjj if pjj > 0 else 0.0) * d_n
    # clamp_linear
    n_moved = 0
    for c in range(n):
        moved = False
        for k in range(m):
            th = theta_n[c, k] * sc[c, k]
            cl = _minimum(_maximum(th, lo[c, k]), hi[c, k])
            if k == 3 and not fit_scale:
                cl = 1.0
            elif k == 4 and not fit_offset:
                cl = 0.0
            moved = moved or abs(cl - th) > tol[c, k]
            theta[c, k] = cl / sc[c, k]
        if moved:
            clamped[c] = True
            n_moved += 1
    return out, n_moved


def _f() -> Any:
    """A fresh one-cell float array (the warm-up calls write some arguments in place)."""
    return np.ones(1)


def _warm_arx(kernel: Any) -> object:
    """One cell, every argument of the type the stage passes."""
    register()
    th, P, flag = np.ones((1, 5)), np.eye(5)[None], np.ones(1, bool)
    bounds = np.stack([np.zeros((5, 1)), np.full((5, 1), 1e9)])
    return kernel(
        _f(), _f(), _f(), _f(), _f(), _f(), _f(), _f(), _f(), th * 0.1, P, np.zeros((1, 2)), th,
        np.zeros(2), bounds, _f(), _f(), _f(), _f(), flag, flag, flag.copy(), flag.copy(), 1.0,
        1.0, 1.0, 1.0, 0.99, 1.0, 0.01, (1e-3, 6.0, 3.0, 0.5), 1e5, True, True,
    )  # fmt: skip


def _warm_fusion(kernel: Any) -> object:
    register()
    th, P, flag = np.ones((1, 5)), np.eye(5)[None], np.ones(1, bool)
    lin = np.stack([th, th, th * 0.0, th * 2.0, th * 1e-12])
    return kernel(
        _f(), _f(), _f(), _f(), th, P, _f(), _f(), lin, _f(), _f(), _f(), _f(), flag, flag,
        flag.copy(), 1.0, 1.0, 1.0, 0.99, 1.0, 0.01, (1e-3, 6.0, 3.0, 0.5), 1e5, True, False,
    )  # fmt: skip


ARX_TICK = jit.Kernel("ARX tick", arx_tick_numpy, _arx_source, _warm_arx)
FUSION_TICK = jit.Kernel("fusion tick", fusion_tick_numpy, _fusion_source, _warm_fusion)
