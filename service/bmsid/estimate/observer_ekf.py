"""The SOC observer's measurement update (``observer.py``): one joint EKF step, pure numpy.

The state is ``x = [z_1 .. z_n, b, d_1 .. d_K]`` (SOC of each cell, the pack's current offset,
A, the half-gap corrections at the map's knots, V); the measurement of cell c is its voltage
(Eq. 9) with ``H_c = [dOCV/dz e_c | R0 + R1 + R2 | s h_c w(z_c)]``. H is sparse, so P H' and
H P H' are formed in O(N m) for m updated cells, not as dense products.
"""

from __future__ import annotations

from typing import Any, NamedTuple

import numpy as np

from bmsid.estimate.stage import BoolArray, FloatArray

IndexArray = np.ndarray[Any, np.dtype[np.intp]]


class EkfStep(NamedTuple):
    """What one update gives: the state change ``dx`` and the new covariance ``P`` (None:
    nothing updated: no cell inside the gate, a singular S, or a non-finite step), and how
    many cells the innovation gate held out."""

    dx: FloatArray | None
    P: FloatArray | None
    n_gated: int


def joint_update(
    P: FloatArray, n: int, idx: IndexArray, hz: FloatArray, hb: FloatArray, G: FloatArray,
    e: FloatArray, r: FloatArray, forced: BoolArray, gate_sigmas: float, consider_offset: bool,
    lone: BoolArray | None = None, teach: BoolArray | None = None, n_map: int | None = None,
) -> EkfStep:  # fmt: skip
    """Update the cells ``idx`` (of ``n``) with innovations ``e`` (V) of variance ``r`` (V^2).

    ``hz``: dOCV/dz (V); ``hb``: dv/db, the DC resistance (ohm); ``G``: dv/dd (n, K). Cells not
    ``forced`` (an anchor, a restart) are used only when ``e^2 <= gate_sigmas^2 S_cc``; a forced
    one beyond it (a SOC far off, or one cell's glitch) updates its own SOC only, as a ``lone``
    cell does: the pack's states (offset, map, hysteresis error) are not one cell's. With
    ``consider_offset`` the unforced cells leave the offset alone (Schmidt-Kalman: it stays in P
    but is not updated; under load it is confounded with the parameters' errors). A ``lone``
    cell (``observer_kernel.lone_cells``) updates its own SOC only. Where ``teach`` is given,
    the map's corrections (the first ``n_map`` columns of ``G``, all without it) are consider
    states for the cells it leaves out (their ``G`` rows count in S and in P, their gain on d
    is 0). The covariance is updated in Joseph form, P - K (PH')' - (PH') K' + K S K', true for
    any gain, symmetrised, its diagonal kept >= 0.
    """
    if idx.size == 0:
        return EkfStep(None, None, 0)
    Gi = G[idx]
    PHt = P[:, idx] * hz[idx] + np.outer(P[:, n], hb[idx]) + P[:, n + 1 :] @ Gi.T  # (N, m)
    S = hz[idx, None] * PHt[idx, :] + hb[idx, None] * PHt[n, :] + Gi @ PHt[n + 1 :, :]
    S[np.diag_indices_from(S)] += r[idx]
    within = e[idx] ** 2 <= gate_sigmas**2 * np.diag(S)
    inside = within | forced[idx]
    if not within.all():  # forced beyond the gate (a SOC far off): its own SOC only
        lone = np.zeros(n, dtype=bool) if lone is None else lone.copy()
        lone[idx[~within]] = True
    n_gated = int((~inside).sum())
    if not inside.all():
        idx, PHt, S = idx[inside], PHt[:, inside], S[np.ix_(inside, inside)]
    if idx.size == 0:
        return EkfStep(None, None, n_gated)
    try:
        K = np.linalg.solve(S, PHt.T).T  # (N, m)
    except np.linalg.LinAlgError:
        return EkfStep(None, None, n_gated)
    if consider_offset:
        K[n, ~forced[idx]] = 0.0
    if teach is not None:  # the map's corrections are consider states for cells not teaching
        m = G.shape[1] if n_map is None else n_map
        K[n + 1 : n + 1 + m, ~teach[idx]] = 0.0
    if lone is not None and lone[idx].any():
        q = np.flatnonzero(lone[idx])
        own = K[idx[q], q]
        K[:, q] = 0.0
        K[idx[q], q] = own
    dx = K @ e[idx]
    if not np.all(np.isfinite(dx)):
        return EkfStep(None, None, n_gated)
    KPHt = K @ PHt.T
    P = P - KPHt - KPHt.T + K @ S @ K.T
    P = 0.5 * (P + P.T)
    d = np.diag_indices_from(P)
    P[d] = np.maximum(P[d], 0.0)
    return EkfStep(dx, P, n_gated)
