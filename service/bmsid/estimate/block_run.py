"""``EstimatorBank.update_block`` in compiled mode (issue 12): a block's ticks assembled at once
(``tick_block.py``), runs of ordinary ticks in one compiled loop (``fused_kernel.py``: the ARX
variants, and the fusion while its swarms run ahead), every other tick by the bank's own
``_run_tick``.

The loop returns here for a tick that needs the stages' Python code; this module checks, before
each call, what the loop cannot see (a cell to start, the start's relaxation watch, a re-anchor
or a widening due, a swarm stepped tick by tick), runs such a tick by ``_run_tick`` and hands
the rest back. A fusion's swarm runs to its end at its start (``FusionStage.ahead``: the same
fits and moves, so the same bits); the loop counts the ticks it would have taken, and a swarm due
or ending calls back into ``FusionStage._run_swarms`` from the loop (``_swarm_events``).

After calls that ran no tick (a long rest, where any tick may anchor) it leaves the next ticks
to ``_run_tick`` for a while (1, 2, 4 .. 64 ticks), so each call's packing is paid rarely. The
loop writes every output into preallocated (n_ticks, n_cells) arrays; ``_run_tick``'s outputs
are stored there per field at the end. Each tick's forgetting limits and innovation gain come
from the stages' own cached functions, once per distinct step (numpy's ``exp`` and Python's
``**`` round differently from compiled code in the last bit), as does ``lambda_``'s power.
"""

from __future__ import annotations

import math
from functools import partial
from typing import TYPE_CHECKING, Any

import numpy as np

from bmsid.estimate import fused_kernel as fk
from bmsid.estimate import (
    observer_kernel,
    observer_update_kernel,
    publish_kernel,
    rls_kernel,
    state_jit,
    swarms,
    tick_block,
)
from bmsid.estimate.arx_rls import ArxRlsStage
from bmsid.estimate.fields import FIELD_NAMES
from bmsid.estimate.fusion import FusionStage
from bmsid.estimate.observer import ObserverState
from bmsid.estimate.stage import Forgetting, innovation_gain, is_excited, nnz
from bmsid.estimate.state import CoulombState
from bmsid.estimate.tick_block import TickArrays
from bmsid.estimate.types import EstimateBlock
from bmsid.samples import SampleBlock

if TYPE_CHECKING:
    from bmsid.estimate.bank import EstimatorBank


def compiled() -> bool:
    """Whether the compiled block path is in use (``jit.select``)."""
    return tick_block.ASSEMBLE.kind == "compiled"


def fusable(bank: EstimatorBank) -> bool:
    """Whether the bank's ordinary ticks can run in the fused loop."""
    return (
        isinstance(bank.params, ArxRlsStage | FusionStage)
        and type(bank.state) in (CoulombState, ObserverState)
        and rls_kernel.FUSION_TICK.kind == "compiled"
        and fk.FUSED_TICKS.kind == "compiled" and observer_kernel.STEP.kind == "compiled"
        and observer_update_kernel.UPDATE.kind == "compiled"
        and rls_kernel.ARX_TICK.kind == "compiled"
        and publish_kernel.TAIL.kind == "compiled"
    )  # fmt: skip


def update_block(bank: EstimatorBank, block: SampleBlock) -> EstimateBlock:
    """``EstimatorBank.update_block`` (compiled mode): the same estimates, counters and state."""
    ta = tick_block.assemble(bank.ticks, block)
    n_t, n = ta.n, bank.n
    if n_t == 0:
        return EstimateBlock.empty(n)
    o = np.empty((len(FIELD_NAMES), n_t, n))
    oq = np.empty((n_t, n), dtype=np.int64)
    done: list[tuple[int, dict[str, Any], Any]] = []  # the ticks _run_tick ran, stored at the end
    if not fusable(bank):
        for k in range(n_t):
            _python_tick(bank, ta, k, done)
    else:  # a fusion's swarms run ahead at their start: the loop runs the ticks they take
        fusion = bank.params if isinstance(bank.params, FusionStage) else None
        try:
            if fusion is not None:
                fusion.ahead = True
                swarms.LOOP_EVENTS[id(fusion)] = partial(_swarm_events, fusion)
            _run_fused(bank, ta, o, oq, done)
        finally:
            if fusion is not None:
                fusion.ahead = False
                swarms.LOOP_EVENTS.pop(id(fusion), None)
    if done:  # per field, one array of the rows (a list of dicts would take a copy per row)
        rows = [k for k, _, _ in done]
        for j, name in enumerate(FIELD_NAMES):
            o[j, rows] = np.array([c[name] for _, c, _ in done])
        oq[rows] = np.array([q for _, _, q in done])
    return EstimateBlock(
        t_s=ta.tf[:, tick_block.T].copy(),
        current_A=ta.tf[:, tick_block.CUR].copy(),  # as measured: the observer corrects a copy
        cells={name: o[j] for j, name in enumerate(FIELD_NAMES)},
        quality=oq,
    )


def _swarm_events(
    pa: FusionStage, t_s: float, period_s: float, std_A: float, head_count: Any
) -> float:  # fmt: skip
    """``FusionStage._run_swarms`` in a tick of the loop (a swarm due or ending), with what it
    reads of the tick and the buffer set first; when the next swarm is due."""
    pa.buffer.head, pa.buffer.count = int(head_count[0]), int(head_count[1])
    pa._period_s = period_s
    pa._excited = is_excited(_Std(std_A), pa._excitation_limit_A)  # type: ignore[arg-type]
    pa._run_swarms(t_s)
    return float(pa.schedule._first_due_s)


def _python_tick(
    bank: EstimatorBank, ta: TickArrays, k: int, done: list[tuple[int, dict[str, Any], Any]]
) -> None:
    """Tick ``k`` by the stages' own code; its outputs kept in ``done``."""
    cells, q = bank._run_tick(ta.tick(k))
    done.append((k, cells, q))


class _DtPeriod:
    """What ``Forgetting.for_tick`` reads of a tick."""

    __slots__ = ("dt_s", "period_s")

    def __init__(self, dt_s: float, period_s: float) -> None:
        self.dt_s, self.period_s = dt_s, period_s


def _per_tick(bank: EstimatorBank, ta: TickArrays) -> tuple[Any, Any]:
    """Each tick's forgetting limits and innovation gain (the stage's own cached functions,
    once per distinct step), and the exponent that reports lambda per second."""
    tun = bank.tuning
    pairs = ta.tf[:, [tick_block.DT, tick_block.PERIOD]]
    keys, inv = np.unique(pairs, axis=0, return_inverse=True)
    table = np.empty((keys.shape[0], fk.N_PT))
    exps = np.empty(keys.shape[0])
    for r, (dt, period) in enumerate(keys.tolist()):
        f = Forgetting.for_tick(_DtPeriod(dt, period), tun)  # type: ignore[arg-type]
        table[r] = f.lam_lo, f.lam_hi, innovation_gain(dt, tun)
        exps[r] = f.per_second_exp
    inv = inv.reshape(-1)
    return np.ascontiguousarray(table[inv]), exps[inv]


def _python_needed(bank: EstimatorBank) -> bool:
    """A tick the loop cannot run: a cell to start or without a valid voltage yet, or the
    observer's watch or restart."""
    st, pa = bank.state, bank.params
    if nnz(st._pending) or not st._all_seen:
        return True
    if isinstance(pa, FusionStage):  # a swarm stepped tick by tick (not run ahead)
        rs = pa.swarms
        if nnz(rs.active) and nnz(rs.active & (rs.left == 0)):
            return True
    if isinstance(st, ObserverState):
        return bool(st._relax.active or st._widen or st._reanchor)
    return False


#: Ticks run by ``_run_tick`` at most before the loop is tried again, after calls that ran none.
_MAX_WAIT = 64


def _run_fused(
    bank: EstimatorBank, ta: TickArrays, o: Any, oq: Any,
    done: list[tuple[int, dict[str, Any], Any]],
) -> None:  # fmt: skip
    """The ticks of ``ta``: runs of them by the loop, the others by ``_run_tick``."""
    per_tick, lam_exp = _per_tick(bank, ta)
    n_t = ta.n
    o_lam = np.empty((n_t, bank.n))
    by_loop = np.zeros(n_t, dtype=bool)
    k, wait, backoff = 0, 0, 1
    while k < n_t:
        if wait or _python_needed(bank):
            _python_tick(bank, ta, k, done)
            k, wait = k + 1, max(wait - 1, 0)
            continue
        k_new, stop, reinit = _call(bank, ta, k, per_tick, lam_exp, o, oq, o_lam)
        by_loop[k:k_new] = True
        ran, k = k_new - k, k_new
        if stop == fk.STOP_REINIT:
            bank.reset(reinit)
        elif stop == fk.STOP_TICK:
            _python_tick(bank, ta, k, done)
            k += 1
            # A call that ran no tick (a long rest: each tick may anchor) costs the packing of
            # every stage's state: the next ticks go to _run_tick, the more the longer it lasts.
            wait, backoff = (backoff, min(2 * backoff, _MAX_WAIT)) if ran == 0 else (0, 1)
    # lambda per second: ArxRlsStage.outputs' power, per distinct exponent
    lam_out = o[fk.LAMF]
    for e in np.unique(lam_exp[by_loop]).tolist():
        rows = by_loop & (lam_exp == e)
        lam_out[rows] = o_lam[rows] ** e


def _call(
    bank: EstimatorBank, ta: TickArrays, k0: int, per_tick: Any, lam_exp: Any, o: Any, oq: Any,
    o_lam: Any,
) -> tuple[int, int, Any]:  # fmt: skip
    """One call of the fused loop from tick ``k0``, the stages' state packed from and written
    back to them. Returns (the next tick, why it stopped, the cells to re-initialise)."""
    st, gd, av = bank.state, bank.guard, bank.average
    pa = bank.params
    assert isinstance(pa, ArxRlsStage | FusionStage)  # (fusable)
    n = bank.n
    pk = state_jit.packed(st)
    obs = st if isinstance(st, ObserverState) else None
    f64 = np.ascontiguousarray
    if obs is not None:
        state_jit.offset_walk(obs, pk)
        ocv = obs.model.ocv
        tun = obs.tun
        so = np.array([obs.b, obs._qb, obs._since_s, obs._rest_s, obs._seen_s, pk.qb_coef,
                       tun.update_period_s, tun.anchor_min_rest_s, obs._b_max,
                       tun.unconverged_wait_s, obs._rest_i_A, obs._noise_sd_A, obs._i_prev_A,
                       obs._rest_base_A])  # fmt: skip
        obs_args = (
            True, st.z, st.h, obs._g, obs._qz, obs.capacity.throughput_Ah, obs._i_load_A,
            f64(obs._tau_load_s), obs._learn_gate, obs.P, obs.d, so, obs._anchored, pk.cells,
            pk.tun, pk.ocv, pk.m_soc, pk.m_V, pk.knots, f64(obs._d_walk, dtype=np.float64),
            f64(ocv._inv_v, dtype=np.float64), f64(ocv._inv_z, dtype=np.float64),
            f64(obs._m_knots, dtype=np.float64), state_jit.update_tuning(obs, pk),
            st._learn_everywhere, obs.capacity.q_Ah, obs.capacity.std_Ah,
        )  # fmt: skip
    else:
        f, b_ = np.zeros(n), np.zeros(n, dtype=bool)
        so = np.zeros(fk.N_SO)
        obs_args = (
            False, st.z, st.h, f, f, f, f, f, b_, np.zeros((n + 1, n + 1)), np.zeros(0), so, b_,
            pk.cells, pk.tun, pk.ocv, pk.m_soc, pk.m_V, pk.knots, np.zeros(0), np.zeros(2),
            np.zeros(2), np.zeros(0), np.zeros(observer_update_kernel.N_UTUN), st._learn_everywhere,
            f64(st.model.capacity_Ah, dtype=np.float64), f,
        )  # fmt: skip
    ex_lim = np.array(np.broadcast_to(bank._excitation_limit_A, (n,)), dtype=np.float64)
    counts = np.zeros(fk.N_C, dtype=np.int64)
    tun_b = bank.tuning
    arx_args, fusion_args = _param_args(pa, n)
    res = fk.FUSED_TICKS.impl(
        k0, ta.tf, ta.v, ta.ok, ta.off, ta.steps, per_tick, ex_lim, *obs_args, *arx_args,
        float(tun_b.trace_max), pa._consts, getattr(pa, "hysteresis", True), pa.arx_err,
        pa.v_model, f64(pa._m_table, dtype=np.float64), gd._stats, f64(gd.good, dtype=np.float64),
        gd.good_soc, gd.episode, gd.cause, gd.bound_bits, gd._near, gd._has_near, gd._consts,
        math.nan if gd.t_prev is None else gd.t_prev, float(gd.tuning.gap_s),
        float(gd.tuning.id_period_s), av.avg, av.restart, av.tau1_multiple, o, oq, o_lam, counts,
        *fusion_args, obs._lh if obs is not None else np.zeros(n),
    )  # fmt: skip
    (stop, k, z, h, tau_load, learn_gate, d, anchored, R0, R1, R2, tau1, tau2, arx_err, v_model,
     m_table, hist_n, good, good_soc, t_prev, restart, reinit, ms, off_v) = res  # fmt: skip
    if k == k0:
        return k, stop, reinit
    st.z, st.h = z, h
    if obs is not None:
        obs._tau_load_s, obs._learn_gate, obs.d, obs._anchored = tau_load, learn_gate, d, anchored
        obs.b, obs._qb, obs._since_s, obs._rest_s, obs._seen_s = (
            float(x) for x in so[: fk.QB_COEF]
        )
        obs._rest_i_A, obs._noise_sd_A, obs._i_prev_A = (
            float(x) for x in so[fk.REST_I : fk.REST_BASE]
        )
        obs._rest_limit_A = obs._h_rest_A = float(pk.tun[observer_kernel.REST_LIMIT])
        obs.counters["observer_updates"] += int(counts[fk.C_UPD])
        obs.counters["observer_gated"] += int(counts[fk.C_GATED])
    pa.R0, pa.R1, pa.R2 = R0, R1, R2
    pa.arx_err, pa.v_model, pa._m_table = arx_err, v_model, m_table
    pa.lam_exp = float(lam_exp[k - 1])
    if isinstance(pa, ArxRlsStage):
        pa.tau1, pa.tau2, pa.hist_n = tau1, tau2, int(hist_n)
        pa.counters["arx_rejected"] += int(counts[fk.C_REJ])
    else:  # the fusion: its taus are its own arrays (a swarm writes them in place)
        pa.Ms, pa.off = ms, off_v
        pa._period_s = float(ta.tf[k - 1, tick_block.PERIOD])
        pa._excited = is_excited(_Std(float(ta.tf[k - 1, tick_block.STD])),  # type: ignore[arg-type]
                                 pa._excitation_limit_A)  # fmt: skip
        pa.buffer.head, pa.buffer.count = (int(x) for x in fusion_args[8])
        pa.counters["clamped"] += int(counts[fk.C_CLAMP])
    gd.good, gd.good_soc = good, good_soc
    gd.t_prev = None if math.isnan(t_prev) else float(t_prev)
    gd.counters["diverged"] += int(counts[fk.C_DIV])
    gd.counters["held_on_bound"] += int(counts[fk.C_HELD])
    av.restart = restart
    return k, stop, reinit


class _Std:
    """What ``is_excited`` reads of a tick."""

    __slots__ = ("current_std_A",)

    def __init__(self, current_std_A: float) -> None:
        self.current_std_A = current_std_A


def _param_args(pa: ArxRlsStage | FusionStage, n: int) -> tuple[tuple[Any, ...], tuple[Any, ...]]:
    """The parameter stage's arguments of the loop: the ARX stage's (theta, P, histories; the
    fusion's own theta, P and scale in their place) and the fusion's (constants, window buffer,
    when the next swarm is due; placeholders for the ARX stage)."""
    f = np.zeros(n)
    if isinstance(pa, ArxRlsStage):
        arx = (
            pa.x1, pa.x2, pa.tau1, pa.tau2, pa.R0, pa.R1, pa.R2, pa.lam, pa.sig_e, pa.theta_arx,
            pa.P_arx, pa.ue_hist, pa.arx_scale, pa.i_hist, pa._bounds, pa._rest_A, pa.clamped,
            pa.arx_ok, float(pa.T_arx), int(pa.hist_n),
        )  # fmt: skip
        fusion = (
            False, np.zeros((5, n, 5)), False, False, np.zeros(1), np.zeros((n, 1)),
            np.zeros((n, 1)), np.zeros((n, 1), dtype=bool), np.zeros(2, dtype=np.int64), 0.0,
            f, f, np.zeros(n, dtype=bool), np.zeros(n, dtype=np.int64), -1,
        )  # fmt: skip
        return arx, fusion
    buf = pa.buffer
    arx = (
        pa.x1, pa.x2, pa.tau1, pa.tau2, pa.R0, pa.R1, pa.R2, pa.lam, pa.sig_e, pa.theta, pa.P,
        np.zeros((n, 2)), pa.scale, np.zeros(2), np.zeros((2, 5, n)), pa._rest_A, pa.clamped,
        pa.fused, 1.0, 0,
    )  # fmt: skip
    fusion = (
        True, pa._lin, bool(pa._fit_scale), bool(pa.tuning.identify_ocv_offset), buf.current_A,
        buf.y_V, buf.hm_V, buf.valid, np.array([buf.head, buf.count], dtype=np.int64),
        float(pa.schedule._first_due_s), pa.Ms, pa.off, pa.swarms.active, pa.swarms.left,
        id(pa) if id(pa) in swarms.LOOP_EVENTS else -1,
    )  # fmt: skip
    return arx, fusion
