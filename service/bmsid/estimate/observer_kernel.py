"""The state stage's and the SOC observer's per-tick step as a compiled kernel (issue 12); the
observer's measurement update is ``observer_update_kernel.py``'s.

The numpy reference is the stages' own code (``state.py``, ``observer.py``, ``model/ocv.py``),
unchanged; ``jit.select`` decides which one a stage runs (``state_jit.py`` calls the kernels,
the stages fall back to their own code for a tick with a cell to start). The kernels loop over
cells with the reference's operations in its order, so they agree to rounding (libm's exp/log
against numpy's SIMD ones, LAPACK's gesv and BLAS's sums against numba's):
``tests/estimate/test_state_kernel.py``.

The kernels call a few scalar helpers (numpy's interp, the hysteresis map's hat weights, the
pack's agreement test), plain Python marked ``@helper`` (``jit_helpers.py``), kept in this file
so that numba's cache sees a change to them (the update kernel names it in ``depends``); the
OCV curve and its slope are ``ocv_kernel.py``'s, which both kernels name for the same reason.
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
    docv_dz_at,  # noqa: F401 (re-exported)
    ocv_at,
)
from bmsid.estimate.rest_anchor import at_rest_reading, rest_draw
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


@helper
def h_step(h: float, i: float, dt: float, kappa: float, play: bool) -> float:
    """``ecm.hysteresis_step`` of one cell (Eq. 5-6, or the play law)."""
    if play:
        return _min(_max(h - 2.0 * kappa * i * dt, -1.0), 1.0)
    decay = math.exp(-abs(kappa * i) * dt)
    return decay * h - (1.0 - decay) * _sign(i)


# ------------------------------------------------------------------ the tick's state step
#: Rows of the per-cell constants ``cells``: the count's capacity (A s) and efficiency, the
#: hysteresis rates on discharge and charge (Eq. 6), the observer's capacity and efficiency.
CAP, EFF, KAPPA_D, KAPPA_C, Q_OBS, EFF_OBS, N_CELL_ROWS = 0, 1, 2, 3, 4, 5, 6
#: Rows of the step's output: SOC, h, clamped SOC, OCV, M, h M, the voltage or OCV.
N_OUT = 7
#: Layout of the step's tuning vector ``tun``: the learn range, the observer's rest limit (A),
#: current gain and SOC walk variances, 1 where h moves as a play operator (``ecm``), 1 where
#: h moves at rest with the pack's draw (``ObserverTuning.rest_draw``).
LEARN_LO, LEARN_HI, REST_LIMIT, GAIN2, WALK2, PLAY, DRAW, N_TUN = 0, 1, 2, 3, 4, 5, 6, 7


def _step_source(
    z: FloatArray, h: FloatArray, g: FloatArray, qz: FloatArray, thr: FloatArray,
    i_load: FloatArray, tau_load: FloatArray, gate: BoolArray, v: FloatArray, ok: BoolArray,
    steps: FloatArray, b: float, current_A: float, dt_s: float, p_bb: float, cells: FloatArray,
    tun: FloatArray, ocv: FloatArray, m_soc: FloatArray, m_V: FloatArray, knots: FloatArray,
    d: FloatArray, observer: bool, rest_i: float, log_decay: FloatArray,
) -> tuple[FloatArray, BoolArray, bool, bool]:  # fmt: skip
    """One tick of ``CoulombState.step`` (and with ``observer`` of ``ObserverState.step``)
    for cells none of which starts this tick: the coulomb steps (``steps`` (k, 2), measured,
    ``b`` the offset removed), h, OCV, M, h M, v or OCV, the learn mask. The observer's
    accumulators ``g``, ``qz``, ``thr`` (capacity throughput), ``i_load`` and ``log_decay``
    (h's, ``hysteresis_error.py``) are updated in place. Returns the ``N_OUT`` rows, the learn
    mask, whether every cell has a voltage, and whether the pack rests (observer)."""
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
    draw = rest_draw(rest_i, b, p_bb) if held and dt_s > 0 and tun[DRAW] > 0.0 else 0.0
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
                if tun[PLAY] > 0.0:
                    hc = h_step(hc, i, dt, kappa, True)
                else:
                    if kappa != kappa_prev or i != i_prev or dt != dt_prev or c == 0:
                        decay = math.exp(-abs(kappa * i) * dt)  # a pack of one rate: one exp
                        kappa_prev, i_prev, dt_prev = kappa, i, dt
                    hc = decay * hc - (1.0 - decay) * _sign(i)
                if observer:
                    log_decay[c] = log_decay[c] - abs(kappa * i) * dt
        if draw != 0.0:
            kappa = cells[KAPPA_C, c] if draw < 0 else cells[KAPPA_D, c]
            hc = h_step(hc, draw, dt_s, kappa, tun[PLAY] > 0.0)
            log_decay[c] = log_decay[c] - abs(kappa * draw) * dt_s
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
        np.array([0.0, 1.0, 0.1, 0.0, 0.0, 0.0, 0.0]), p, np.array([0.0, 1.0]), one * 0.01,
        np.array([0.0, 1.0]), one * 0.0, True, 0.0, one * 0.0,
    )  # fmt: skip


# ------------------------------------------------------------------ the pack's agreement
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


#: The reference in the registry is the kernel source run as plain Python (the stages' numpy
#: mode runs their own code: the reference the tests compare against).
_DEPENDS = (str(ocv_kernel.__file__), str(rest_anchor.__file__))
STEP = jit.Kernel("state step", _step_source, _step_source, _warm_step, depends=_DEPENDS)
