"""The compiled normal equations of the swarm's window fits (``varpro_kernel.KERNEL``, issue 12).

numba vectorises innermost loops only, so every window sum runs with the window innermost, in
passes of at most 12 accumulators (more spill to memory), and what is sequential in the window
is done before, once per candidate:

* the unit-gain branch states x1, x2 of four candidates advance together: eight independent
  chains hide the multiply-add's latency, which one candidate's two chains waited on each tick
  (the loop is bound by its stores instead);
* the decays a^k, as a recurrence 64 ticks apart (``_decay``), which vectorises;
* the columns the candidates share (current A, h M V, the offset's ones, y V) are weighted once
  per call, and their own sums taken once, not per candidate.

Per candidate (1800-tick window, 4 or 12 candidates, 5-7 columns) this is 2.1-2.8x faster than
one dot product over the window per entry of G, each of ~26 reading its rows again. The sums are
reordered (``fastmath``): equal to the reference (``varpro_kernel.normal_equations_numpy``) to
rounding (``tests/estimate/test_varpro_kernel.py``).
"""

from __future__ import annotations

import numpy as np
import numpy.typing as npt

from bmsid.estimate.jit_helpers import helper

FloatArray = npt.NDArray[np.float64]

#: Sums matrix ``m`` (8 x 8, upper triangle) index of each column kind: the shared columns
#: current, h M, offset (ones), y; the candidate's x1, x2, a1^k, a2^k.
I_, H_, ONE, Y_, X1, X2, D1, D2 = range(8)


@helper
def _states(rows: FloatArray, current_A: FloatArray, pq: FloatArray) -> None:
    """x_(k+1) = a x_k + (1 - a) i_k from x_0 = 0 (Eq. 8) for the eight poles ``pq[0]``
    (``pq[1]`` = 1 - a) at once, written to ``rows[c, branch, k]``."""
    p0, p1, p2, p3 = pq[0, 0], pq[0, 1], pq[0, 2], pq[0, 3]
    p4, p5, p6, p7 = pq[0, 4], pq[0, 5], pq[0, 6], pq[0, 7]
    q0, q1, q2, q3 = pq[1, 0], pq[1, 1], pq[1, 2], pq[1, 3]
    q4, q5, q6, q7 = pq[1, 4], pq[1, 5], pq[1, 6], pq[1, 7]
    x0 = x1 = x2 = x3 = x4 = x5 = x6 = x7 = 0.0
    for k in range(current_A.shape[0]):
        rows[0, 0, k], rows[0, 1, k], rows[1, 0, k], rows[1, 1, k] = x0, x1, x2, x3
        rows[2, 0, k], rows[2, 1, k], rows[3, 0, k], rows[3, 1, k] = x4, x5, x6, x7
        i = current_A[k]
        x0 = p0 * x0 + q0 * i
        x1 = p1 * x1 + q1 * i
        x2 = p2 * x2 + q2 * i
        x3 = p3 * x3 + q3 * i
        x4 = p4 * x4 + q4 * i
        x5 = p5 * x5 + q5 * i
        x6 = p6 * x6 + q6 * i
        x7 = p7 * x7 + q7 * i


@helper
def _decay(out: FloatArray, a: float) -> None:
    """``out[k] = a^k``: 64 by repeated products, then 64 ticks apart: vectorised, 16 vectors
    in flight (a shorter step waits on each vector's store and reload)."""
    n = out.shape[0]
    d = 1.0
    for k in range(min(n, 64)):
        out[k] = d
        d *= a
    for k in range(n - 64):  # (k from 0: a negative index would cost numba a check)
        out[k + 64] = out[k] * d


@helper
def _sums(
    m: FloatArray, r: FloatArray, d: FloatArray, w: FloatArray, wi: FloatArray,
    wh: FloatArray, wy: FloatArray, use_h: bool, use_off: bool,
) -> None:  # fmt: skip
    """One candidate's window sums into ``m``: its columns (x1, x2 in ``r``, decays in ``d``)
    against each other and the shared ones (weighted: ``wi`` = w i etc.)."""
    x1x1 = x1x2 = x1d1 = x1d2 = x2x2 = x2d1 = x2d2 = d1d1 = d1d2 = d2d2 = 0.0
    for k in range(w.shape[0]):
        x1, x2, d1, d2, wk = r[0, k], r[1, k], d[0, k], d[1, k], w[k]
        wx1, wx2, wd1 = wk * x1, wk * x2, wk * d1
        x1x1 += wx1 * x1
        x1x2 += wx1 * x2
        x1d1 += wx1 * d1
        x1d2 += wx1 * d2
        x2x2 += wx2 * x2
        x2d1 += wx2 * d1
        x2d2 += wx2 * d2
        d1d1 += wd1 * d1
        d1d2 += wd1 * d2
        d2d2 += wk * d2 * d2
    m[X1, X1], m[X1, X2], m[X1, D1], m[X1, D2] = x1x1, x1x2, x1d1, x1d2
    m[X2, X2], m[X2, D1], m[X2, D2] = x2x2, x2d1, x2d2
    m[D1, D1], m[D1, D2], m[D2, D2] = d1d1, d1d2, d2d2
    x1i = x1y = x2i = x2y = d1i = d1y = d2i = d2y = 0.0
    x1h = x2h = d1h = d2h = 0.0
    if use_h:  # one pass of 12 sums, not 8 then 4 (each waits on its own latency)
        for k in range(w.shape[0]):
            x1, x2, d1, d2, vi, vy, vh = r[0, k], r[1, k], d[0, k], d[1, k], wi[k], wy[k], wh[k]
            x1i += x1 * vi
            x1y += x1 * vy
            x1h += x1 * vh
            x2i += x2 * vi
            x2y += x2 * vy
            x2h += x2 * vh
            d1i += d1 * vi
            d1y += d1 * vy
            d1h += d1 * vh
            d2i += d2 * vi
            d2y += d2 * vy
            d2h += d2 * vh
    else:
        for k in range(w.shape[0]):
            x1, x2, d1, d2, vi, vy = r[0, k], r[1, k], d[0, k], d[1, k], wi[k], wy[k]
            x1i += x1 * vi
            x1y += x1 * vy
            x2i += x2 * vi
            x2y += x2 * vy
            d1i += d1 * vi
            d1y += d1 * vy
            d2i += d2 * vi
            d2y += d2 * vy
    m[I_, X1], m[I_, X2], m[I_, D1], m[I_, D2] = x1i, x2i, d1i, d2i
    m[Y_, X1], m[Y_, X2], m[Y_, D1], m[Y_, D2] = x1y, x2y, d1y, d2y
    m[H_, X1], m[H_, X2], m[H_, D1], m[H_, D2] = x1h, x2h, d1h, d2h
    if use_off:
        x1w = x2w = d1w = d2w = 0.0
        for k in range(w.shape[0]):
            wk = w[k]
            x1w += r[0, k] * wk
            x2w += r[1, k] * wk
            d1w += d[0, k] * wk
            d2w += d[1, k] * wk
        m[ONE, X1], m[ONE, X2], m[ONE, D1], m[ONE, D2] = x1w, x2w, d1w, d2w


def normal_equations_source(
    current_A: FloatArray, y_V: FloatArray, hm_V: FloatArray, weights: FloatArray,
    a1: FloatArray, a2: FloatArray, s_cols: FloatArray, use_hysteresis: bool, use_offset: bool,
) -> tuple[FloatArray, FloatArray, FloatArray]:  # fmt: skip
    """``varpro_kernel.normal_equations_numpy``'s G, b and last branch states (compiled by
    numba): the sums of every column kind in ``m``, then G, b as its entries times the columns'
    scales (the reference's columns: -s0 i, -s1 x1, -s2 x2, [s h M], [s], a1^k, a2^k)."""
    n_w, p, n_a = current_A.shape[0], a1.shape[0], s_cols.shape[0]
    G = np.empty((p, n_a, n_a))
    b = np.empty((p, n_a))
    last = np.empty((p, 2))
    kind = np.empty(n_a, dtype=np.int64)  # each active column's kind in m, and its scale
    scale = np.ones(n_a)
    kind[0], kind[1], kind[2] = I_, X1, X2
    scale[0], scale[1], scale[2] = -s_cols[0], -s_cols[1], -s_cols[2]
    col = 3
    if use_hysteresis:
        kind[col], scale[col] = H_, s_cols[col]
        col += 1
    if use_offset:
        kind[col], scale[col] = ONE, s_cols[col]
        col += 1
    kind[col], kind[col + 1] = D1, D2
    wi, wh, wy = weights * current_A, weights * hm_V, weights * y_V
    ii = ih = i1 = iy = hh = h1 = hy = w1 = wy1 = 0.0
    for k in range(n_w):  # the shared columns' sums, once (in registers: they vectorise)
        i, h = current_A[k], hm_V[k]
        ii += wi[k] * i
        ih += wi[k] * h
        i1 += wi[k]
        iy += wy[k] * i
        hh += wh[k] * h
        h1 += wh[k]
        hy += wy[k] * h
        w1 += weights[k]
        wy1 += wy[k]
    m = np.zeros((8, 8))
    m[I_, I_], m[I_, H_], m[I_, ONE], m[I_, Y_] = ii, ih, i1, iy
    m[H_, H_], m[H_, ONE], m[H_, Y_], m[ONE, ONE], m[ONE, Y_] = hh, h1, hy, w1, wy1
    rows = np.empty((4, 2, n_w))
    decays = np.empty((4, 2, n_w))
    pq = np.empty((2, 8))
    for j0 in range(0, p, 4):  # four candidates at a time (a short group repeats its last)
        n_c = min(4, p - j0)
        for c in range(4):
            j = j0 + min(c, n_c - 1)
            pq[0, 2 * c], pq[0, 2 * c + 1] = a1[j], a2[j]
            pq[1, 2 * c], pq[1, 2 * c + 1] = 1.0 - a1[j], 1.0 - a2[j]
        _states(rows, current_A, pq)
        for c in range(n_c):
            j = j0 + c
            last[j, 0], last[j, 1] = rows[c, 0, n_w - 1], rows[c, 1, n_w - 1]
            _decay(decays[c, 0], a1[j])
            _decay(decays[c, 1], a2[j])
            _sums(m, rows[c], decays[c], weights, wi, wh, wy, use_hysteresis, use_offset)
            for r in range(n_a):
                kr = kind[r]
                b[j, r] = scale[r] * (m[kr, Y_] if kr < Y_ else m[Y_, kr])
                for q in range(r, n_a):
                    kq = kind[q]
                    g = scale[r] * scale[q] * (m[kr, kq] if kr <= kq else m[kq, kr])
                    G[j, r, q] = g
                    G[j, q, r] = g
    return G, b, last
