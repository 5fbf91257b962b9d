"""The parameter stages' per-tick recursion in numpy: the reference of ``rls_kernel``'s kernels.

One function per stage, the code its ``step`` ran before the kernels (moved, the same operations
in the same order, so the numpy path gives the same bits as before), over plain arrays and
floats so that a compiled kernel can take the same arguments:

* :func:`arx_tick_numpy` (``arx_rls.ArxRlsStage``): branch states, a-priori error, Eq. 21's
  forgetting, the AFFRLS update (Eq. 18-20), the map to R0, R1, tau1, R2, tau2 (Eq. 22-23) and
  its accept/clamp rule;
* :func:`fusion_tick_numpy` (``fusion.FusionStage``): branch states, model voltage, Eq. 21, the
  AFFRLS update of the linear parameters, their projection onto the bounds and the clamp.

Both update the stage's internal state in place (branch states, lambda, innovation RMS, theta,
P, histories, the flags) and return what the stage publishes without a copy, new every tick, as
the rows of one array: a compiled kernel returns one array rather than ten (turning each into a
Python object costs about half a microsecond). The argument order is the kernels'.
"""

from __future__ import annotations

import numpy as np
import numpy.typing as npt

from bmsid.estimate.affrls import rls_update
from bmsid.estimate.stage import InnovationConstants, adapt_with_gain
from bmsid.model.arx import MapStatus, theta_to_rows
from bmsid.model.ecm import branches_step

FloatArray = npt.NDArray[np.float64]
BoolArray = npt.NDArray[np.bool_]

_MAP_OK = int(MapStatus.OK)  # numpy compares an array with an IntEnum member ~5x slower

#: (rows R0, R1, R2, tau1, tau2, a-priori error, model voltage (7, n); sets the map rejected)
ArxTick = tuple[FloatArray, int]

#: (rows a-priori error, model voltage, V - OCV (the window buffer's y) (3, n); cells clamped)
FusionTick = tuple[FloatArray, int]


def arx_tick_numpy(
    x1: FloatArray, x2: FloatArray, tau1: FloatArray, tau2: FloatArray, R0: FloatArray,
    R1: FloatArray, R2: FloatArray, lam: FloatArray, sig_e: FloatArray, theta: FloatArray,
    P: FloatArray, ue_hist: FloatArray, scale: FloatArray, i_hist: FloatArray,
    bounds: FloatArray, rest_A: FloatArray, v: FloatArray, ocv: FloatArray, hm: FloatArray,
    ok: BoolArray, learn: BoolArray, clamped: BoolArray, arx_ok: BoolArray, i: float, ip: float,
    dt: float, T: float, lam_lo: float, lam_hi: float, g: float, consts: InnovationConstants,
    trace_max: float, use_h: bool, do_rls: bool,
) -> ArxTick:  # fmt: skip
    """One tick of the AFFRLS on the ARX model (``ArxRlsStage.step``).

    Per cell (n,): branch states, parameters, lambda, innovation RMS, the voltage ``v`` (V, OCV
    where none), OCV and h M (V), the masks ``ok`` (a voltage) and ``learn``; theta (n, 5) and
    P (n, 5, 5) normalised by ``scale`` (n, 5); ``ue_hist`` (n, 2) and ``i_hist`` (2,) the
    last two U_E and currents; ``bounds`` (2, 5, n) the lower and upper bounds of the map's rows
    R0, R1, R2, tau2, tau1; ``rest_A`` (n,) the rest limit. The tick: current ``i`` and the one
    held before it ``ip`` (A), its step ``dt`` and the ARX period ``T`` (s), the forgetting
    limits, the innovation gain ``g``; ``use_h`` removes h M from U_E; ``do_rls`` (two past
    samples and a period) updates theta, else only the states move. In place: x1, x2, lam,
    sig_e, theta, P, ue_hist, i_hist and the flags ``clamped``, ``arx_ok``.
    """
    n = x1.shape[0]
    x1[:], x2[:] = branches_step(x1, x2, tau1, tau2, ip, dt)
    clamped[:] = False
    h_term = hm if use_h else np.zeros(n)
    v_model = ocv + h_term - R0 * i - R1 * x1 - R2 * x2
    ue = v - ocv - h_term
    n_rejected = 0
    if do_rls:
        phi = np.empty((n, 5))
        phi[:, :2] = ue_hist
        phi[:, 2] = i
        phi[:, 3:] = i_hist
        e = ue - np.einsum("nk,nk->n", phi, theta * scale)
        arx_err = np.where(ok, e, 0.0)
        quiet = _quiet(i, ip, rest_A)
        e_c, sig_e[:], lam[:] = adapt_with_gain(e, sig_e, learn, quiet, g, lam_lo, lam_hi, consts)
        theta[:], P[:] = rls_update(theta, P, phi * scale, e_c, lam, learn, trace_max)
        R0, R1, R2, tau2, tau1, n_rejected = _accept(
            theta * scale, T, learn, bounds, (R0, R1, R2, tau2, tau1), clamped, arx_ok
        )
    else:
        arx_err = np.where(ok, v - v_model, 0.0)
    ue_hist[:, 1] = ue_hist[:, 0]
    ue_hist[:, 0] = ue
    i_hist[1] = i_hist[0]
    i_hist[0] = i
    return np.array([R0, R1, R2, tau1, tau2, arx_err, v_model]), n_rejected


def _accept(
    theta: FloatArray, T: float, ok: BoolArray, bounds: FloatArray,
    held: tuple[FloatArray, FloatArray, FloatArray, FloatArray, FloatArray], clamped: BoolArray,
    arx_ok: BoolArray,
) -> tuple[FloatArray, FloatArray, FloatArray, FloatArray, FloatArray, int]:  # fmt: skip
    """The rows R0, R1, R2, tau2, tau1 that theta maps to where the map is valid and ``ok``
    (clamped to ``bounds``, flagged in ``clamped``), the ``held`` ones elsewhere; and the number
    of sets the map rejected."""
    raw, status = theta_to_rows(theta, T)
    good = ok & (status == _MAP_OK)
    lo, hi = bounds[0], bounds[1]
    clipped = np.minimum(np.maximum(raw, lo), hi)  # rows R0, R1, R2, tau2, tau1
    inside = np.logical_and.reduce(clipped == raw)  # ufunc reduce: no .all() dispatch
    if np.count_nonzero(good) == good.size:  # the usual tick: every row taken
        clamped |= ~inside
        arx_ok |= good
        r0, r1, r2, t2, t1 = clipped
        return r0, r1, r2, t2, t1, 0
    n_rejected = int(np.count_nonzero(ok & ~good))
    clamped |= good & ~inside
    r0, r1, r2, t2, t1 = np.where(good, clipped, np.array(held))
    arx_ok |= good
    return r0, r1, r2, t2, t1, n_rejected


def fusion_tick_numpy(
    x1: FloatArray, x2: FloatArray, tau1: FloatArray, tau2: FloatArray, theta: FloatArray,
    P: FloatArray, sig_e: FloatArray, lam: FloatArray, lin: FloatArray, rest_A: FloatArray,
    v: FloatArray,
    ocv: FloatArray, hm: FloatArray, ok: BoolArray, learn: BoolArray, clamped: BoolArray,
    i: float, ip: float, dt: float, lam_lo: float, lam_hi: float, g: float,
    consts: InnovationConstants, trace_max: float, fit_scale: bool, fit_offset: bool,
) -> FusionTick:  # fmt: skip
    """One tick of the fusion's AFFRLS (``FusionStage.step`` up to the temperature carry).

    theta (n, 5): R0, R1, R2, M scale, OCV offset normalised; ``lin`` (5, n, 5) holds per cell
    their scale, the regressor's scale, lower and upper bounds and the clamp tolerance; the
    rest as in :func:`arx_tick_numpy`. ``fit_scale``/``fit_offset``: the M scale/the offset are
    identified (else held at 1/0). In place: x1, x2, theta, P, lam, sig_e and ``clamped``.
    """
    scale, phi_scale, lo, hi, tol = lin
    n = x1.shape[0]
    x1[:], x2[:] = branches_step(x1, x2, tau1, tau2, ip, dt)
    clamped[:] = False
    phi = np.ones((n, 5))  # column 4: the offset's 1
    phi[:, 0] = -i
    phi[:, 1] = -x1
    phi[:, 2] = -x2
    phi[:, 3] = hm
    v_model = ocv + (phi * (theta * scale)).sum(axis=1)
    e = v - v_model
    arx_err = e if np.count_nonzero(ok) == n else np.where(ok, e, 0.0)
    quiet = _quiet(i, ip, rest_A)
    e_c, sig_e[:], lam[:] = adapt_with_gain(e, sig_e, learn, quiet, g, lam_lo, lam_hi, consts)
    theta_n, P[:] = rls_update(theta, P, phi * phi_scale, e_c, lam, learn, trace_max)
    theta_n, th = project_linear(theta_n, P, scale, lo, hi)
    theta[:], moved = clamp_linear(theta_n, th, scale, lo, hi, tol, fit_scale, fit_offset)
    n_moved = int(np.count_nonzero(moved))  # usually 0: the flags stay as they are
    if n_moved:
        clamped |= moved
    return np.array([arx_err, v_model, v - ocv]), n_moved


def _quiet(i: float, ip: float, rest_A: FloatArray) -> bool | BoolArray:
    """``stage.is_quiet``: cells at rest with no current change (|I|, |dI| < ``rest_A``); one
    cell's answer as one bool (no array operations: the innovation step takes either)."""
    lim = rest_A if rest_A.shape[0] > 1 else float(rest_A[0])
    return (abs(i) < lim) & (abs(i - ip) < lim)


def project_linear(
    theta_n: FloatArray, P: FloatArray, sc: FloatArray, lo: FloatArray, hi: FloatArray
) -> tuple[FloatArray, FloatArray]:
    """Project an estimate that left the bounds back onto them in the metric of P.

    Clipping one coordinate alone leaves the coordinates correlated with it carrying a step
    that assumed it had moved; the error then grows and the next updates push further the
    wrong way. Moving coordinate j onto its bound by d shifts the others by P[:, j] d /
    P[j, j] (the least-squares estimate conditioned on theta_j at the bound). P is kept, so
    the parameter can leave the bound again when the data say so. Coordinates are taken one
    at a time, in a fixed order; the final clip removes what is left. Returns it and it x sc.
    """
    th = theta_n * sc
    if not ((th < lo) | (th > hi)).any():
        return theta_n, th
    theta_n = theta_n.copy()
    for j in range(5):  # fixed order, whatever the other cells do (bank == single)
        th_j = theta_n[:, j] * sc[:, j]
        d_n = (np.minimum(np.maximum(th_j, lo[:, j]), hi[:, j]) - th_j) / sc[:, j]
        pjj = P[:, j, j]
        gain = np.where(pjj[:, None] > 0, P[:, :, j] / np.where(pjj > 0, pjj, 1.0)[:, None], 0.0)
        theta_n += gain * d_n[:, None]
    return theta_n, theta_n * sc


def clamp_linear(
    theta_n: FloatArray, th: FloatArray, sc: FloatArray, lo: FloatArray, hi: FloatArray,
    tol: FloatArray, fit_scale: bool, fit_offset: bool,
) -> tuple[FloatArray, BoolArray]:  # fmt: skip
    """theta_n (normalised; ``th``: x ``sc``) clipped to [lo, hi], the M scale held at 1 unless
    ``fit_scale``, the offset at 0 unless ``fit_offset``; and the rows it moved by more than
    ``tol``."""
    cl = np.minimum(np.maximum(th, lo), hi)
    if not fit_scale:
        cl[:, 3] = 1.0
    if not fit_offset:
        cl[:, 4] = 0.0
    moved = (np.abs(cl - th) > tol).any(axis=1)
    return np.asarray(cl / sc), np.asarray(moved)
