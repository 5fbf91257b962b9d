"""Exact zero-order-hold simulator of the full hysteresis 2RC model (Eq. 2, 7-9), stepping
``model.ecm``.

States per parameter set: SOC z, branch voltages U1, U2 (V) and hysteresis h. The current i_k is
held over [t_k, t_k+1). The output at k is Eq. 9 with Plett's sign:
``U_L,k = OCV(z_k) + M(z_k) h_k - U1_k - U2_k - R0 i_k``.

Vectorised over P parameter sets (the swarm and the tests use this); every parameter may be a
scalar, shape (P,) or shape (P, n) for time-varying truth. The capacity may vary in time too
(shape (n,), one for all sets: the SOC depends on the current and the capacity only), for a
fading cell's known truth.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

from bmsid.model.ecm import hysteresis_kappa, hysteresis_step, rc_decay, rc_step, soc_delta
from bmsid.model.ocv import OcvModel

FloatArray = npt.NDArray[np.float64]
ArrayLike = float | FloatArray


@dataclass(frozen=True)
class SimResult:
    """Simulated trajectories, shape (P, n) (``soc`` is (n,): it depends on the current only)."""

    v_V: FloatArray
    soc: FloatArray
    soc_clamped: npt.NDArray[np.bool_]
    h: FloatArray
    U1_V: FloatArray
    U2_V: FloatArray


def coulomb_count(
    current_A: FloatArray, dt_s: FloatArray, soc0: float, capacity_Ah: ArrayLike, eta: float
) -> FloatArray:
    """SOC after each sample (Eq. 2): z_k+1 = z_k - eta_k i_k dt / Q_k, eta applied on charge
    only; ``capacity_Ah`` a constant or one value per sample (Q_k, a fading cell)."""
    dz = soc_delta(current_A, dt_s, capacity_Ah * 3600.0, eta)
    return np.asarray(soc0 + np.concatenate(([0.0], np.cumsum(dz[:-1]))), dtype=np.float64)


def _col(x: ArrayLike, p: int, n: int) -> FloatArray:
    a = np.asarray(x, dtype=np.float64)
    if a.ndim == 0:
        return np.full((p, n), float(a))
    if a.ndim == 1:
        return np.repeat(a[:, None], n, axis=1)
    return np.broadcast_to(a, (p, n))


def simulate(
    t_s: FloatArray,
    current_A: FloatArray,
    ocv: OcvModel,
    *,
    capacity_Ah: ArrayLike,
    R0_ohm: ArrayLike,
    R1_ohm: ArrayLike,
    tau1_s: ArrayLike,
    R2_ohm: ArrayLike,
    tau2_s: ArrayLike,
    M_scale: ArrayLike = 1.0,
    gamma: ArrayLike = 0.0,
    eta: float = 1.0,
    soc0: float = 1.0,
    h0: float = 0.0,
    n_sets: int = 1,
    play: bool = False,
) -> SimResult:
    """Simulate ``n_sets`` parameter sets over the current profile (exact ZOH, any time steps).

    ``gamma`` is the dimensionless hysteresis rate (kappa = eta gamma / Q); ``M_scale`` multiplies
    the cell's M(z) table; ``play`` moves h as a play operator (``ecm.hysteresis_step``) instead
    of Plett's exponential. ``t_s`` need not be uniform. ``capacity_Ah`` (Ah) is a constant or
    shape (n,): the capacity Q_k over step k, for SOC (Eq. 2) and kappa alike.
    """
    t = np.asarray(t_s, dtype=np.float64)
    i = np.asarray(current_A, dtype=np.float64)
    n, p = t.shape[0], n_sets
    dt = np.diff(t, append=t[-1] + (t[-1] - t[-2] if n > 1 else 1.0))
    q = np.asarray(capacity_Ah, dtype=np.float64)
    if q.ndim not in (0, 1) or (q.ndim == 1 and q.shape[0] != n):
        raise ValueError(f"capacity_Ah: a scalar or one value per sample ({n}), got {q.shape}")
    soc = coulomb_count(i, dt, soc0, q, eta)
    z, clamped = ocv.clamp(soc)
    r0, r1, r2 = _col(R0_ohm, p, n), _col(R1_ohm, p, n), _col(R2_ohm, p, n)
    a1 = rc_decay(dt[None, :], _col(tau1_s, p, n))
    a2 = rc_decay(dt[None, :], _col(tau2_s, p, n))
    kappa = hysteresis_kappa(_col(gamma, p, n), q * 3600.0, eta, i[None, :])
    u1 = np.zeros((p, n))
    u2 = np.zeros((p, n))
    h = np.zeros((p, n))
    hk = np.full(p, h0)
    u1k = np.zeros(p)
    u2k = np.zeros(p)
    for k in range(n):
        u1[:, k], u2[:, k], h[:, k] = u1k, u2k, hk
        u1k = rc_step(u1k, a1[:, k], i[k], gain=r1[:, k])
        u2k = rc_step(u2k, a2[:, k], i[k], gain=r2[:, k])
        hk = hysteresis_step(hk, i[k], dt[k], kappa[:, k], play)
    m = _col(M_scale, p, n) * ocv.hysteresis_M(z)[None, :]
    v = ocv.ocv(z)[None, :] + m * h - u1 - u2 - r0 * i[None, :]
    return SimResult(v_V=v, soc=soc, soc_clamped=clamped, h=h, U1_V=u1, U2_V=u2)
