"""The engine's ordinary ticks in one compiled loop (issue 12): ``bank._run_tick``, compiled.

``FUSED_TICKS`` runs ``EstimatorBank._run_tick`` (the state stage with or without the observer,
the learn gate, the parameter stage, the observer's periodic update, the tail of codes, guard
and average) over ticks ``k0 ..`` of a block's tick arrays (``tick_block.py``), writing every
published field into preallocated arrays. The parameter stage is the AFFRLS on the ARX model
(``non-hy-affrls``, ``hy-affrls``) or the fusion's per-tick AFFRLS and window buffer
(``hy-affrls-lpso``, while swarms run ahead). It calls the stages' own compiled kernels (same
bits) and does between them, in loops, what the Python glue does (``state_jit``, the observer's
rest clock and noise, the parameter stage's ``step`` and ``outputs``, ``publish``).

It stops before a tick that needs the stages' Python code (``STOP_TICK``): a new segment (the
first sample, a gap, a time jump), the first tick with a step (the ARX period is seeded), a
rest long enough for an anchor, a temperature to carry or a swarm stepped tick by tick (the
fusion); the caller checks the rest (a cell to start, the start's relaxation watch, a re-anchor).
A fusion's swarm events (one due, or one run ahead ending: ``FusionStage._run_ahead``) call back
into its Python at their place in the tick (``swarms.loop_events``, numba's object mode); in
between, a swarm run ahead only counts its ticks. It stops after a tick whose guard asks for a
re-initialisation (``STOP_REINIT``: the caller resets those cells). ``lambda_`` is left to the
caller (``lam`` per tick: numpy's power, as the stages' ``outputs``). Its cache entry is named
after the files whose compiled code it embeds (``jit.Kernel.depends``).
"""

from __future__ import annotations

import contextlib
import math
import warnings
from collections.abc import Callable
from typing import Any

import numpy as np

from bmsid.estimate import (
    guard_kernel,
    hysteresis_error,
    jit,
    observer_kernel,
    observer_update_kernel,
    ocv_kernel,
    publish_average,
    publish_kernel,
    rest_anchor,
    rls_kernel,
    rls_reference,
    tick_block,
)
from bmsid.estimate.fields import FIELD_NAMES
from bmsid.estimate.jit_helpers import helper, register
from bmsid.estimate.observer_kernel import REST_LIMIT
from bmsid.estimate.publish_kernel import AVG_ROW, BITS_ROW, SOC_ROW
from bmsid.estimate.rest_anchor import at_rest_reading, next_rest_reading, offset_within_rest
from bmsid.estimate.swarms import loop_events

next_noise, rest_limit = rest_anchor.next_noise, rest_anchor.rest_limit  # (import: 400 lines)
#: Field rows of the output ``o`` (``fields.FIELD_NAMES`` order), literals checked below.
R0F, R1F, C1F, R2F, C2F, TAU1F, TAU2F, LAMF, HF, SOCF, SOCSTDF = 0, 1, 2, 3, 4, 5, 6, 7, 8, 9, 10
CAPF, CAPSTDF, OFFF, VMODF, VMEASF, VERRF, MF, OCVOFFF, ONBF, ARXF = range(11, 21)
#: Published HELD rows (R0, R1, C1, R2, C2, tau1, tau2, ocv_offset) and PUBLISHED rows (R1,
#: R2, tau1, tau2, C1, C2) as field rows.
HELD_F = (R0F, R1F, C1F, R2F, C2F, TAU1F, TAU2F, OCVOFFF)
PUB_F = (R1F, R2F, TAU1F, TAU2F, C1F, C2F)
#: Per-tick floats of ``per_tick``: forgetting limits, the innovation RMS's gain.
LAM_LO, LAM_HI, GAIN, N_PT = 0, 1, 2, 3
#: The observer's scalars ``so`` (in place): b, qb, clocks, constants, reading, sensor noise.
B, QB, SINCE, REST, SEEN, QB_COEF, UPD_PERIOD, MIN_REST, B_MAX, WAIT, REST_I = range(11)
NOISE, I_PREV, REST_BASE, N_SO = 11, 12, 13, 14
#: The counters ``counts`` (in place).
C_REJ, C_UPD, C_GATED, C_DIV, C_HELD, C_CLAMP, N_C = range(7)
#: Why the loop stopped: the end, a tick for the Python path, a re-initialisation after a tick.
STOP_END, STOP_TICK, STOP_REINIT = 0, 1, 2


def _check_literals() -> None:
    from bmsid.estimate.guard_kernel import HELD  # noqa: PLC0415
    from bmsid.estimate.publish_average import PUBLISHED  # noqa: PLC0415

    f = FIELD_NAMES.index
    ok = (
        tuple(f(k) for k in HELD) == HELD_F and tuple(f(k) for k in PUBLISHED) == PUB_F
        and (f("lambda_"), f("h"), f("soc"), f("soc_std"), f("capacity_Ah")) == (LAMF, HF, SOCF,
                                                                                 SOCSTDF, CAPF)
        and (f("capacity_std_Ah"), f("current_offset_A"), f("v_model_V"), f("v_meas_V"))
        == (CAPSTDF, OFFF, VMODF, VMEASF)
        and (f("v_error_V"), f("M_V"), f("on_bound"), f("arx_error_V")) == (VERRF, MF, ONBF, ARXF)
        and len(FIELD_NAMES) == 21
    )  # fmt: skip
    if not ok:
        raise RuntimeError("fused_kernel: the field rows no longer match fields.FIELD_NAMES")


_check_literals()

#: The compiled kernels called (bound by the warm-up, before this kernel compiles).
_STEP: Any = None
_UPDATE: Any = None
_ARX: Any = None
_TAIL: Any = None
_FUSION: Any = None
_TF_T, _TF_I, _TF_IP, _TF_DT, _TF_STD, _TF_NEWSEG, _TF_TEMP, _TF_PERIOD = (
    tick_block.T, tick_block.CUR, tick_block.IP, tick_block.DT, tick_block.STD, tick_block.NEWSEG,
    tick_block.TEMP, tick_block.PERIOD,
)  # fmt: skip
objmode: Any = None  # the swarm events call back into Python (numba's, where it imports)
with contextlib.suppress(ImportError):
    from numba import objmode
# numba compiles the callback at its first call, and says that it takes the GIL (as it must)
warnings.filterwarnings("ignore", "Code running in object mode won't allow parallel execution")


def _fused_source(
    k0: int, tf: Any, v_all: Any, ok_all: Any, off: Any, steps: Any, per_tick: Any, ex_lim: Any,
    observer: bool, z: Any, h: Any, g: Any, qz: Any, thr: Any, i_load: Any, tau_load: Any,
    learn_gate: Any, P: Any, d: Any, so: Any, anchored: Any, cells_c: Any, tun: Any, ocv: Any,
    m_soc: Any, m_V: Any, knots: Any, d_walk: Any, inv_v: Any, inv_z: Any, m_knots: Any,
    utun: Any, learn_everywhere: bool, cap: Any, cap_std: Any,
    x1: Any, x2: Any, tau1: Any, tau2: Any, R0: Any, R1: Any, R2: Any, lam: Any, sig_e: Any,
    theta: Any, P_arx: Any, ue_hist: Any, scale: Any, i_hist: Any, bounds: Any, rest_A: Any,
    clamped: Any, arx_ok: Any, T_arx: float, hist_n: int, trace_max: float,
    consts: tuple[float, float, float, float], use_h: bool, arx_err: Any, v_model: Any,
    m_table: Any, stats: Any, good: Any, good_soc: Any, episode: Any, cause: Any,
    bound_bits: Any, near: Any, has_near: bool, gconsts: Any, t_prev: float, gap_s: float,
    id_period_s: float, avg: Any, restart: Any, tau1_multiple: float, o: Any, oq: Any,
    o_lam: Any, counts: Any, fusion: bool, lin: Any, fit_scale: bool, fit_offset: bool,
    buf_i: Any, buf_y: Any, buf_hm: Any, buf_valid: Any, buf_hc: Any, first_due: float, ms: Any,
    off_v: Any, sw_active: Any, sw_left: Any, sw_key: int, lh: Any,
) -> Any:  # fmt: skip
    """The ticks ``k0 ..`` (module docstring); per-cell state arrays that the Python code
    updates in place are updated in place, those it rebinds are returned."""
    n_t, n = tf.shape[0], z.shape[0]
    zeros, empty = np.zeros(n), np.zeros(0)
    m_out = zeros  # the published M (the fusion's scaled M)
    no_anchor, reinit = np.zeros(n, dtype=np.bool_), np.zeros(n, dtype=np.bool_)
    ex, (stop, k) = np.empty(n, dtype=np.bool_), (STOP_END, k0)
    while k < n_t:
        if tf[k, _TF_NEWSEG] != 0.0:
            stop = STOP_TICK
            break
        t, i_meas, dt = tf[k, _TF_T], tf[k, _TF_I], tf[k, _TF_DT]
        cur, ip = i_meas, tf[k, _TF_IP]
        events = False  # the fusion: a swarm due or ending (run ahead); a temperature, a swarm
        if fusion:  # stepped tick by tick: the stage's own code
            stepped = False
            for c in range(n):
                events = events or (sw_active[c] and sw_left[c] == 1)
                stepped = stepped or (sw_active[c] and sw_left[c] == 0)
            events = events or t >= first_due
            if stepped or not math.isnan(tf[k, _TF_TEMP]) or (events and sw_key < 0):
                stop = STOP_TICK
                break
        elif T_arx == 0.0 and dt > 0:  # the ARX period is seeded: the stage's own code
            stop = STOP_TICK
            break
        if observer:  # ObserverState.step: the rest limit with the sensor's noise (kept below)
            nv = next_noise(so[NOISE], cur, so[I_PREV], so[REST_BASE], dt)
            tun[REST_LIMIT] = rest_limit(so[REST_BASE], nv)
        if observer and at_rest_reading(cur, so[REST_I], tun[REST_LIMIT]):
            so[B] = offset_within_rest(so[B], so[REST_I], so[REST_BASE])  # a draw, not noise
        b, cont = so[B], False
        if observer:
            if b != 0.0:  # Tick.remove_offset (the kernel removes it from the coulomb steps)
                cur -= b
                ip -= b
            any_gate = False
            all_anchored = True
            for c in range(n):
                any_gate = any_gate or learn_gate[c]
                all_anchored = all_anchored and anchored[c]
            limit = tun[REST_LIMIT]  # the step's rest test, ahead of it: an anchor is near?
            if not any_gate:
                limit += 2.0 * math.sqrt(max(P[n, n], 0.0))
            cont = at_rest_reading(cur + b, so[REST_I], tun[REST_LIMIT])
            rest_after = so[REST] + dt if abs(cur) < limit or cont else 0.0
            if rest_after >= so[MIN_REST] and not all_anchored:
                stop = STOP_TICK
                break
        v, ok = v_all[k], ok_all[k]
        st = steps[off[k] : off[k + 1]]
        if observer:
            out, learn, all_ok, resting = _STEP(
                z, h, g, qz, thr, i_load, tau_load, learn_gate, v, ok, st, b, cur, dt,
                P[n, n], cells_c, tun, ocv, m_soc, m_V, knots, d, True, so[REST_I], lh,
            )  # fmt: skip
            so[QB] += so[QB_COEF] * dt / 86400.0
            so[SINCE] += dt
            so[SEEN] += dt
            so[NOISE], so[I_PREV] = nv, i_meas  # past the stops: a stopped tick is Python's
        else:
            out, learn, all_ok, resting = _STEP(
                z, h, empty, empty, empty, empty, empty, ok, v, ok, st, 0.0, cur, dt, 0.0,
                cells_c, tun, ocv, m_soc, m_V, knots, empty, False, 0.0, empty,
            )  # fmt: skip
        z, h = out[0], out[1]
        v_safe = v if all_ok else out[6]
        if learn_everywhere:
            learn = ok
        if observer:  # _after_step: the rest clock (no watch open, no restart here)
            if resting:
                so[REST] += dt
                if abs(cur) < tun[REST_LIMIT] or cont:  # at the reading: the test above
                    so[REST_I] = next_rest_reading(so[REST_I], cur + b, dt)
            elif so[REST] != 0.0:
                so[REST], anchored = 0.0, np.zeros(n, dtype=np.bool_)
        # the learn gate (bank._run_tick)
        any_bits = False
        for c in range(n):
            ex[c] = tf[k, _TF_STD] >= ex_lim[c]
            any_bits = any_bits or bound_bits[c] != 0
        n_may = 0
        may = np.empty(n, dtype=np.bool_)
        for c in range(n):
            gate = learn_gate[c] if observer else True
            if any_bits:
                gate = gate or bound_bits[c] > 0
            may[c] = gate and ex[c]
            n_may += 1 if may[c] else 0
        if n_may < n:
            learn2 = np.empty(n, dtype=np.bool_)
            for c in range(n):
                learn2[c] = learn[c] and (may[c] or not arx_ok[c])
            learn = learn2
        m_table = out[4]
        if fusion:  # FusionStage.step (no swarm due, ending or stepped: see above)
            fo, n_moved = _FUSION(
                x1, x2, tau1, tau2, theta, P_arx, sig_e, lam, lin, rest_A, v_safe, out[3],
                out[5], ok, learn, clamped, cur, ip, dt, per_tick[k, LAM_LO],
                per_tick[k, LAM_HI], per_tick[k, GAIN], consts, trace_max, fit_scale, fit_offset,
            )  # fmt: skip
            arx_err, v_model = fo[0], fo[1]
            counts[C_CLAMP] += n_moved
            j, size = buf_hc[0], buf_i.shape[0]  # WindowBuffer.push
            buf_i[j] = cur
            for c in range(n):
                buf_y[c, j], buf_hm[c, j], buf_valid[c, j] = fo[2, c], out[5, c], learn[c]
            buf_hc[0] = (j + 1) % size
            buf_hc[1] = min(buf_hc[1] + 1, size)
            if events:  # FusionStage._run_swarms, in Python (swarms.loop_events)
                period, std = tf[k, _TF_PERIOD], tf[k, _TF_STD]
                with objmode(first_due="float64"):
                    first_due = loop_events(sw_key, t, period, std, buf_hc)
            for c in range(n):  # else FusionStage._step_swarms: a swarm run ahead counts a tick
                if sw_active[c] and sw_left[c] > 0 and not events:
                    sw_left[c] -= 1
            R0, R1, R2 = np.empty(n), np.empty(n), np.empty(n)  # _publish_linear
            ms, off_v, m_out = np.empty(n), np.empty(n), np.empty(n)
            for c in range(n):
                R0[c], R1[c] = theta[c, 0] * scale[c, 0], theta[c, 1] * scale[c, 1]
                R2[c], ms[c] = theta[c, 2] * scale[c, 2], theta[c, 3] * scale[c, 3]
                off_v[c] = theta[c, 4] * scale[c, 4]
                m_out[c] = ms[c] * m_table[c] * 1.0
        else:
            R0, R1, R2, tau1, tau2, arx_err, v_model, hist_n = _arx_step(
                x1, x2, tau1, tau2, R0, R1, R2, lam, sig_e, theta, P_arx, ue_hist, scale,
                i_hist, bounds, rest_A, v_safe, out, ok, learn, clamped, arx_ok, cur, ip, dt,
                T_arx, per_tick, k, consts, trace_max, use_h, hist_n, counts,
            )  # fmt: skip
            m_out = m_table if use_h else zeros
        # ObserverState.correct: the periodic update (anchors and re-anchors: the Python path)
        if observer:
            tau_load = tau2.copy() if so[REST] <= 0.0 else tau_load  # rest: the one before
            if so[SINCE] >= so[UPD_PERIOD]:
                u1 = (P, g, qz, so[QB], so[SINCE], d_walk, z, out[2], out[3], h, m_table, v,
                      ok, R0, R1, R2, v_model, m_out, np.logical_or(arx_ok, so[SEEN] >= so[WAIT]),
                      no_anchor)  # fmt: skip
                u2 = (i_load, False, cur, so[REST] <= 0.0, b, so[B_MAX], ocv, inv_v, inv_z,
                      knots, d, m_knots, utun, lh)  # fmt: skip
                z_n, d_n, gate_n, _anch, _zo, _zv, b_n, n_gated, updated, h_n = _UPDATE(*u1, *u2)
                so[QB], so[SINCE] = 0.0, 0.0
                counts[C_GATED] += n_gated
                if updated:
                    z, h, so[B] = z_n, h_n, b_n
                    if d.shape[0]:
                        d = d_n
                    counts[C_UPD] += 1
                learn_gate = gate_n
        # the published fields before the tail (state.outputs, params.outputs)
        for c in range(n):
            o[R0F, k, c], o[R1F, k, c], o[R2F, k, c] = R0[c], R1[c], R2[c]
            o[C1F, k, c], o[C2F, k, c] = tau1[c] / R1[c], tau2[c] / R2[c]
            o[TAU1F, k, c], o[TAU2F, k, c] = tau1[c], tau2[c]
            o[OCVOFFF, k, c] = off_v[c] if fusion else 0.0
            o_lam[k, c] = lam[c]
            o[HF, k, c] = h[c] if use_h or fusion else 0.0
            o[MF, k, c] = m_out[c]
            o[ARXF, k, c], o[VMODF, k, c], o[VMEASF, k, c] = arx_err[c], v_model[c], v[c]
            o[VERRF, k, c] = v[c] - v_model[c]
            o[CAPF, k, c] = cap[c]
            if observer:
                o[SOCSTDF, k, c] = math.sqrt(max(P[c, c], 0.0))
                o[CAPSTDF, k, c], o[OFFF, k, c] = cap_std[c], so[B]
            else:
                o[SOCSTDF, k, c], o[CAPSTDF, k, c], o[OFFF, k, c] = np.nan, 0.0, 0.0
        # publish_kernel.publish: guard._data_dt, the tail, what publish stores
        step = t - t_prev  # NaN before the first tick: no step
        t_prev = t
        dtg = step if 0.0 < step <= gap_s else id_period_s
        offset = off_v if fusion else zeros
        floats, q, reinit, n_reinit, n_held, masked = _TAIL(
            dtg, z, o[R0F, k], o[R1F, k], o[C1F, k], o[R2F, k], o[C2F, k], o[TAU1F, k],
            o[TAU2F, k], offset, o[VERRF, k], ex, clamped, arx_ok, learn, stats, good, good_soc,
            episode, cause, bound_bits, near, has_near, gconsts, avg, restart, dt, tau1_multiple,
        )  # fmt: skip
        counts[C_DIV] += n_reinit
        counts[C_HELD] += n_held
        any_restart = False
        for c in range(n):
            any_restart = any_restart or restart[c]
        if tau1_multiple > 0.0 and any_restart:
            restart = np.zeros(n, dtype=np.bool_)
        for c in range(n):
            o[ONBF, k, c] = floats[BITS_ROW, c]
            if masked:
                for j in range(len(HELD_F)):
                    o[HELD_F[j], k, c] = floats[j, c]
            o[SOCF, k, c] = floats[SOC_ROW, c]
            if tau1_multiple > 0.0:
                for j in range(len(PUB_F)):
                    o[PUB_F[j], k, c] = floats[AVG_ROW + j, c]
            oq[k, c] = q[c]
        good = np.ascontiguousarray(floats[: len(HELD_F)])
        good_soc = floats[SOC_ROW].copy()
        k += 1
        any_reinit = False
        for c in range(n):
            any_reinit = any_reinit or reinit[c]
        if any_reinit:
            stop = STOP_REINIT
            break
    return (
        stop, k, z, h, tau_load, learn_gate, d, anchored, R0, R1, R2, tau1, tau2, arx_err,
        v_model, m_table, hist_n, good, good_soc, t_prev, restart, reinit, ms, off_v,
    )  # fmt: skip


@helper
def _arx_step(
    x1: Any, x2: Any, tau1: Any, tau2: Any, R0: Any, R1: Any, R2: Any, lam: Any, sig_e: Any,
    theta: Any, P_arx: Any, ue_hist: Any, scale: Any, i_hist: Any, bounds: Any, rest_A: Any,
    v_safe: Any, out: Any, ok: Any, learn: Any, clamped: Any, arx_ok: Any, cur: float,
    ip: float, dt: float, T_arx: float, per_tick: Any, k: int,
    consts: tuple[float, float, float, float], trace_max: float, use_h: bool, hist_n: int,
    counts: Any,
) -> Any:  # fmt: skip
    """``ArxRlsStage.step``: the tick kernel and its counts; the rebound arrays returned."""
    # (two tuples: Python 3.11 passes a call of more than 30 arguments as one tuple, which
    # numba reads only as star-args)
    a1 = (x1, x2, tau1, tau2, R0, R1, R2, lam, sig_e, theta, P_arx, ue_hist, scale, i_hist,
          bounds, rest_A, v_safe, out[3], out[5], ok)  # fmt: skip
    a2 = (learn, clamped, arx_ok, cur, ip, dt, T_arx, per_tick[k, LAM_LO], per_tick[k, LAM_HI],
          per_tick[k, GAIN], consts, trace_max, use_h, hist_n >= 2 and T_arx > 0)  # fmt: skip
    aout, rejected = _ARX(*a1, *a2)
    counts[C_REJ] += rejected
    return aout[0], aout[1], aout[2], aout[3], aout[4], aout[5], aout[6], hist_n + 1


def warm_args(n: int) -> tuple[Any, ...]:
    """Arguments of every type the bank passes, for ``n`` cells and no tick."""
    f, b_, i_ = np.zeros(n), np.zeros(n, dtype=np.bool_), np.zeros(n, dtype=np.int64)
    return (
        0, np.zeros((0, tick_block.N_TF)), np.zeros((0, n)), np.zeros((0, n), dtype=np.bool_),
        np.zeros(1, dtype=np.int64), np.zeros((0, 2)), np.zeros((0, N_PT)), f, True, f, f, f,
        f, f, f, f, b_, np.zeros((n + 1, n + 1)), np.zeros(0), np.zeros(N_SO), b_,
        np.zeros((observer_kernel.N_CELL_ROWS, n)), np.zeros(observer_kernel.N_TUN),
        np.zeros(ocv_kernel.N_OCV), np.zeros(2), np.zeros(2), np.zeros(0), np.zeros(0),
        np.zeros(2), np.zeros(2), np.zeros(0), np.zeros(observer_update_kernel.N_UTUN), True, f, f,
        f, f, f, f, f, f, f, f, f, np.zeros((n, 5)), np.zeros((n, 5, 5)), np.zeros((n, 2)),
        np.zeros((n, 5)), np.zeros(2), np.zeros((2, 5, n)), f, b_, b_, 1.0, 0, 1e5,
        (1e-3, 6.0, 3.0, 0.5), True, f, f, f, np.zeros((5, n)), np.zeros((8, n)), f, b_, i_,
        i_, np.zeros((2, 5, n)), True, np.zeros(6), math.nan, 30.0, 1.0, np.zeros((4, n)), b_,
        1.0, np.zeros((len(FIELD_NAMES), 0, n)), np.zeros((0, n), dtype=np.int64),
        np.zeros((0, n)), np.zeros(N_C, dtype=np.int64), True, np.zeros((5, n, 5)), True, False,
        np.zeros(3), np.zeros((n, 3)), np.zeros((n, 3)), np.zeros((n, 3), dtype=np.bool_),
        np.zeros(2, dtype=np.int64), 0.0, f, f, b_, i_, -1, f,
    )  # fmt: skip


def _warm(kernel: Callable[..., Any]) -> object:
    # the compiled callees, bound before this kernel compiles
    global _STEP, _UPDATE, _ARX, _TAIL, _FUSION  # noqa: PLW0603
    register()  # the helpers (_arx_step) callable from compiled code
    _STEP, _UPDATE = observer_kernel.STEP.compiled(), observer_update_kernel.UPDATE.compiled()
    _ARX, _TAIL = rls_kernel.ARX_TICK.compiled(), publish_kernel.TAIL.compiled()
    _FUSION = rls_kernel.FUSION_TICK.compiled()
    if _STEP is None or _UPDATE is None or _ARX is None or _TAIL is None or _FUSION is None:
        raise RuntimeError("a kernel the fused loop calls did not compile")
    for n in (1, 2):
        kernel(*warm_args(n))
    return None


def _reference(*args: Any) -> Any:
    raise RuntimeError("the fused loop has no numpy reference: the bank's per-tick path is it")


#: The files whose compiled code the loop embeds (its cache entry is named after them).
_EMBEDS = (observer_kernel, observer_update_kernel, ocv_kernel, rls_kernel, rls_reference,
           publish_kernel, guard_kernel, publish_average, tick_block, rest_anchor,
           hysteresis_error)  # fmt: skip
FUSED_TICKS = jit.Kernel("fused ticks", _reference, _fused_source, _warm,
                         depends=tuple(str(m.__file__) for m in _EMBEDS))  # fmt: skip
