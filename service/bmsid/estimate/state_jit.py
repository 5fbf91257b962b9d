"""The state stages' compiled per-tick path (``observer_kernel.py``): what a stage hands its
kernels and takes back, so that ``state.py`` and ``observer.py`` only ask whether it ran.

The kernels' per-cell constants and the OCV curve's numbers are packed once and again only when
the stage rebinds one of them (a capacity measured at an anchor, a checkpoint loaded). State
arrays the stages publish or hand on (z, h, the context's fields) are new arrays every tick, as
in the numpy code; the observer's private accumulators (dz/db, process noise, throughput, load
current) and P are updated in place. One difference a later stage could see: the observer
removes its current offset from the tick's current and held current as the numpy code does,
but leaves ``tick.coulomb_steps`` as measured (the kernel removes it; nothing after the state
stage reads them).
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Any

import numpy as np

from bmsid.estimate import observer_kernel as ok_
from bmsid.estimate import observer_update_kernel as ou_
from bmsid.estimate import ocv_kernel as oc_
from bmsid.estimate.stage import BoolArray, FloatArray, TickContext, nnz
from bmsid.model.ocv import OcvModel

if TYPE_CHECKING:
    from bmsid.estimate.observer import ObserverState
    from bmsid.estimate.state import CoulombState

_EMPTY = np.zeros(0)
_NO_STEPS = np.zeros((0, 2))


def ocv_params(ocv: OcvModel) -> FloatArray:
    """The curve's numbers in the kernels' layout (``ocv_kernel.EQ4_MIN`` ..), the correction
    table (when the curve has one) appended."""
    p = np.zeros(oc_.N_OCV)
    p[:6] = ocv.coeffs
    p[[oc_.EQ4_MIN, oc_.EQ4_MAX]] = ocv.eq4_min, ocv.eq4_max
    p[[oc_.SOC_MIN, oc_.SOC_MAX]] = ocv.soc_min, ocv.soc_max
    for flag, at, dat, poly in ((oc_.HAS_LOW, oc_.LOW, oc_.DLOW, ocv._low),
                                (oc_.HAS_HIGH, oc_.HIGH, oc_.DHIGH, ocv._high)):  # fmt: skip
        if poly is not None:
            p[flag] = 1.0
            c = np.asarray(poly, dtype=np.float64)
            p[at + 4 - c.shape[0] : at + 4] = c
            dc = np.asarray(np.polyder(c), dtype=np.float64)  # what OcvModel._ends evaluates
            p[dat + 3 - dc.shape[0] : dat + 3] = dc
    if ocv.corr_soc is None or ocv.corr_V is None or ocv._corr_d is None:
        return p
    p[oc_.CORR_N] = ocv.corr_soc.shape[0]
    return np.concatenate([p, ocv.corr_soc, ocv.corr_V, ocv._corr_d])


class Packed:
    """A stage's constants in the kernels' layout, and what they were packed from."""

    __slots__ = (
        "cells", "key", "knots", "m_V", "m_soc", "ocv", "one_step", "q_key", "qb_coef", "tun",
        "utun",
    )  # fmt: skip

    def __init__(self, st: CoulombState) -> None:
        ocv = st.model.ocv
        self.ocv = ocv_params(ocv)
        self.m_soc = np.ascontiguousarray(ocv.m_soc, dtype=np.float64)
        self.m_V = np.ascontiguousarray(ocv.m_V, dtype=np.float64)
        self.knots: FloatArray = getattr(st, "_knots", _EMPTY)
        self.tun = np.zeros(ok_.N_TUN)
        self.tun[[ok_.LEARN_LO, ok_.LEARN_HI]] = st._learn_lo, st._learn_hi
        self.tun[ok_.PLAY] = float(st.model.hysteresis_play)
        tun = getattr(st, "tun", None)
        if tun is not None:  # the observer
            self.tun[ok_.REST_LIMIT] = st._rest_limit_A  # type: ignore[attr-defined]
            self.tun[ok_.GAIN2] = tun.current_gain_sigma**2
            self.tun[ok_.WALK2] = tun.soc_walk_per_sqrt_h**2
            self.tun[ok_.DRAW] = float(tun.rest_draw)
        self.key: tuple[Any, ...] = ()
        self.cells = np.zeros((ok_.N_CELL_ROWS, st.n))
        self.q_key: Any = None
        self.qb_coef = 0.0
        self.utun: FloatArray | None = None
        self.one_step = np.zeros((1, 2))  # a tick's one coulomb step (read by the kernel only)


def _cell_sources(st: CoulombState) -> tuple[Any, ...]:
    d = st.__dict__  # instance attributes: a dict lookup each, cheaper than getattr every tick
    cap, eff = d["_capacity_As"], d["_efficiency"]
    return (
        cap, eff, d["_kappa_discharge"], d["_kappa_charge"], d.get("_q_As", cap),
        d.get("_eff", eff),
    )  # fmt: skip


def packed(st: CoulombState) -> Packed:
    """The stage's constants in the kernels' layout, packed again where a source was rebound."""
    pk: Packed | None = st.__dict__.get("_packed")
    if pk is None:
        pk = st.__dict__["_packed"] = Packed(st)
    src, key = _cell_sources(st), pk.key
    if not key or not (
        src[0] is key[0] and src[1] is key[1] and src[2] is key[2] and src[3] is key[3]
        and src[4] is key[4] and src[5] is key[5]
    ):  # fmt: skip
        for row, x in zip((ok_.CAP, ok_.EFF, ok_.KAPPA_D, ok_.KAPPA_C, ok_.Q_OBS, ok_.EFF_OBS),
                          src, strict=True):  # fmt: skip
            pk.cells[row] = x
        pk.key = src
    return pk


def offset_walk(obs: ObserverState, pk: Packed) -> None:
    """The offset's process noise per second of data, ``pk.qb_coef``, for the capacity now."""
    q_Ah = obs.capacity.q_Ah
    if q_Ah is not pk.q_key:
        q_mean_Ah = float(q_Ah.sum() / q_Ah.size)
        pk.qb_coef = (obs.tun.offset_walk_C_per_sqrt_day * q_mean_Ah) ** 2
        pk.q_key = q_Ah


def update_tuning(obs: ObserverState, pk: Packed) -> FloatArray:
    """The update kernel's tuning vector (``observer_kernel.V_SIGMA2`` ..), packed once."""
    if pk.utun is None:
        tun = obs.tun
        pk.utun = np.array([tun.v_sigma_V**2, tun.r_dc_rel_sigma, tun.v_sigma_floor_V**2,
                            tun.gate_sigmas**2, tun.learn_ocv_sigma_V,
                            tun.agree_sigmas**2, float(tun.hysteresis_error),
                            obs._h_floor])  # fmt: skip
    return pk.utun


def step(st: CoulombState, ctx: TickContext, observer: bool) -> bool:
    """The tick's state step by the compiled kernel (``jit.select``); False (nothing done)
    where the stage runs its own code: the numpy mode, a cell that starts this tick or one that
    has not read a valid voltage yet."""
    if ok_.STEP.kind != "compiled" or nnz(st._pending) or not st._all_seen:
        return False
    tick = ctx.tick
    pk = packed(st)
    cs = tick.coulomb_steps
    if len(cs) == 1:  # the usual tick: one raw step, into the stage's buffer (no array built)
        steps = pk.one_step
        steps[0, 0], steps[0, 1] = cs[0]
    else:
        steps = np.array(cs, dtype=np.float64).reshape(-1, 2) if cs else _NO_STEPS
    if observer:
        obs: ObserverState = st  # type: ignore[assignment]
        b = obs.b
        if b != 0.0:  # Tick.remove_offset, less the coulomb steps: the kernel removes b from those
            tick.current_A -= b
            if not (tick.new_segment and not tick.first):
                tick.i_prev_A -= b
        offset_walk(obs, pk)
        pk.tun[ok_.REST_LIMIT] = obs._rest_limit_A  # with the sensor's noise (observer.step)
        tau_load = np.ascontiguousarray(obs._tau_load_s)  # params' tau2: a view would compile
        out, learn, all_ok, resting = ok_.STEP.impl(
            st.z, st.h, obs._g, obs._qz, obs.capacity.throughput_Ah, obs._i_load_A, tau_load,
            obs._learn_gate, tick.v_V, tick.ok, steps, b, tick.current_A,
            tick.dt_s, float(obs.P[obs.n, obs.n]), pk.cells, pk.tun, pk.ocv, pk.m_soc, pk.m_V,
            pk.knots, obs.d, True, obs._rest_i_A, obs._lh,
        )  # fmt: skip
        obs._qb += pk.qb_coef * tick.dt_s / 86400.0
        obs._since_s += tick.dt_s
        obs._seen_s += tick.dt_s
    else:
        out, learn, all_ok, resting = ok_.STEP.impl(
            st.z, st.h, _EMPTY, _EMPTY, _EMPTY, _EMPTY, _EMPTY, tick.ok, tick.v_V,
            tick.ok, steps, 0.0, tick.current_A, tick.dt_s, 0.0, pk.cells, pk.tun,
            pk.ocv, pk.m_soc, pk.m_V, pk.knots, _EMPTY, False, 0.0, _EMPTY,
        )  # fmt: skip
    z, h, ctx.soc_clamped, ctx.ocv_V, ctx.m_table_V, ctx.hm_V, v_safe = out
    st.z = z
    st.h = ctx.h = h
    ctx.v_safe_V = tick.v_V if all_ok else v_safe
    ctx.learn = tick.ok if st._learn_everywhere else learn
    if observer:
        obs._after_step(tick, resting)
    return True


def update(
    obs: ObserverState, ctx: TickContext, params: dict[str, FloatArray], converged: BoolArray,
    anchor: BoolArray,
) -> bool:  # fmt: skip
    """The observer's measurement update that is due by the compiled kernel; False (nothing
    done) in the numpy mode."""
    if ou_.UPDATE.kind != "compiled":
        return False
    tick, n, pk = ctx.tick, obs.n, packed(obs)
    utun = update_tuning(obs, pk)
    ocv = obs.model.ocv
    # C-contiguous float64 as the kernel was compiled for (a view would compile anew mid-run)
    p = {k: np.ascontiguousarray(params[k], dtype=np.float64)
         for k in ("R0_ohm", "R1_ohm", "R2_ohm", "v_model_V", "M_V") if k in params}  # fmt: skip
    z, d, gate, anchored, z_ocv, z_var, b, n_gated, updated, h = ou_.UPDATE.impl(
        obs.P, obs._g, obs._qz, obs._qb, obs._since_s, obs._d_walk, obs.z, ctx.soc_clamped,
        ctx.ocv_V, ctx.h, ctx.m_table_V, tick.v_V, tick.ok, p["R0_ohm"], p["R1_ohm"],
        p["R2_ohm"], p["v_model_V"], p["M_V"],
        converged, anchor, obs._i_load_A, obs._reanchor, tick.current_A, obs._rest_s <= 0.0,
        obs.b, obs._b_max, pk.ocv, ocv._inv_v, ocv._inv_z, pk.knots, obs.d, obs._m_knots,
        utun, obs._lh,
    )  # fmt: skip
    obs._qb = 0.0
    obs._since_s = 0.0
    obs.counters["observer_gated"] += n_gated
    if updated:
        obs.z, obs.b, obs.h = z, b, h
        if obs.d.shape[0]:
            obs.d = d
        obs.counters["observer_updates"] += 1
    if anchored.any():
        obs.capacity.anchor(tick.t_s, z_ocv, z_var, float(obs.P[n, n]), anchored)
        obs._use_capacity()
        obs._anchored = obs._anchored | anchored
        obs.counters["anchors"] += int(anchored.sum())
    if obs._reanchor:
        obs.counters["reanchors"] += 1
        obs._reanchor = False
    obs._learn_gate = gate
    return True
