"""The estimator bank: N cells that share one pack current, identified in one vectorised call.

A short coordinator over stages (``estimate/stage.py``)::

    SampleBlock --> TickAssembler --> tick --> state stage --> parameter stage --> guard
    (samples)       (ticks.py: bins,           (state.py,      (arx_rls.py or      (guard.py)
                     gaps, time jumps,          observer.py:    fusion.py +            |
                     coulomb steps)             SOC, h, OCV)    swarms.py)             v
                                                              EstimateBlock <-- average
                                                                          (publish_average.py)

Variants (the paper's three) are compositions of stages, :data:`VARIANT_STAGES`:

* ``non-hy-affrls`` - AFFRLS on the bilinear ARX model (Eq. 15-21) of ``U_E = V - OCV(z)``,
  mapped back to R0, R1, C1, R2, C2 by the corrected Eq. 22-23;
* ``hy-affrls`` - the same with the hysteresis voltage removed first: ``U_E = V - OCV - M(z) h``;
* ``hy-affrls-lpso`` - the AFFRLS-LPSO fusion: AFFRLS tracks the parameters the voltage is
  linear in every tick, LPSO re-fits the time constants over a window every ``swarm_period_s``
  per cell (amortised over ticks, cells staggered). Design and equations: ``fusion.py``.

Every published value is finite and inside the configured bounds. ``update_block`` is the
engine's entry point: with the compiled kernels (``jit.select``) it assembles a block's ticks at
once and runs the ordinary ones in one compiled loop (``block_run.py``, ``fused_kernel.py``),
each other tick by ``_run_tick``; the numpy mode keeps the per-sample loop below (the
reference). ``update`` (one sample, the daemon's path) runs ``_run_tick`` per tick.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np
import numpy.typing as npt

from bmsid.estimate import block_run, jit
from bmsid.estimate.arx_rls import ArxRlsStage
from bmsid.estimate.cellmodel import CellModel
from bmsid.estimate.fields import FIELD_NAMES
from bmsid.estimate.fusion import FusionStage
from bmsid.estimate.guard import PublishGuard
from bmsid.estimate.lost_readings import ReadingWatch
from bmsid.estimate.observer import ObserverState
from bmsid.estimate.publish_average import PublishAverage
from bmsid.estimate.publish_kernel import TAIL, publish
from bmsid.estimate.stage import ParameterStage, TickContext, is_excited, nnz, per_cell_limit
from bmsid.estimate.state import CoulombState, without_data
from bmsid.estimate.ticks import Tick, TickAssembler
from bmsid.estimate.tuning import EstimatorTuning, Variant
from bmsid.estimate.types import VARIANTS, EstimateBlock, Estimates, Quality
from bmsid.samples import SampleBlock

FloatArray = npt.NDArray[np.float64]
BoolArray = npt.NDArray[np.bool_]

#: Quality codes as plain ints: numpy assigns an IntEnum member into an array ~5x slower.
_CONVERGED, _CONVERGING = int(Quality.CONVERGED), int(Quality.CONVERGING)
_POORLY_EXCITED, _OUT_OF_BOUNDS = int(Quality.POORLY_EXCITED), int(Quality.OUT_OF_BOUNDS)

#: Version of ``EstimatorBank.state_dict``: 2 nests one state per stage (1 was flat).
STATE_FORMAT = 2


@dataclass(frozen=True)
class StageSetup:
    """What a parameter stage is built from (the bank's arguments)."""

    model: CellModel
    tuning: EstimatorTuning
    cell_ids: npt.NDArray[np.int64]
    n_stagger: int


#: Each variant's parameter stage (the state stage and tick assembly are common to all).
VARIANT_STAGES: dict[Variant, Callable[[StageSetup], ParameterStage]] = {
    "non-hy-affrls": lambda s: ArxRlsStage(s.model, s.tuning, hysteresis=False),
    "hy-affrls": lambda s: ArxRlsStage(s.model, s.tuning, hysteresis=True),
    "hy-affrls-lpso": lambda s: FusionStage(s.model, s.tuning, s.cell_ids, s.n_stagger),
}
assert tuple(VARIANT_STAGES) == VARIANTS


class EstimatorBank:
    """Online identification of the cells of ``model`` (see the module docstring).

    Args:
        model: per-cell numbers (``bmsid.config.engine.cell_model`` builds them from a config).
        variant: ``non-hy-affrls``, ``hy-affrls`` or ``hy-affrls-lpso``.
        tuning: estimator constants (defaults documented in ``EstimatorTuning``).
        soc0: initial SOC (fraction, scalar or per cell); None applies ``model.soc_start``.
        branch0_V: the RC branches' voltages at the first sample (V, (n_cells, 2), the drops
            ``R1 x1``, ``R2 x2`` of Eq. 9), as a start fit over the record's first minutes
            finds them under load (``offline/start_soc.py``); None: empty branches (a rest).
        h0: the hysteresis state (in [-1, 1], per cell) a start at ``soc0`` takes, as a start
            fit over a rested record's first minutes finds it; None (or no ``soc0``): 0.
        cell_ids: global index of each cell (seeds its swarm and staggers its schedule), default
            0..n_cells-1; ``n_stagger`` is the number of cells the schedule is spread over.
    """

    def __init__(
        self,
        model: CellModel,
        variant: Variant = "hy-affrls-lpso",
        tuning: EstimatorTuning | None = None,
        soc0: float | FloatArray | None = None,
        cell_ids: npt.ArrayLike | None = None,
        n_stagger: int | None = None,
        branch0_V: FloatArray | None = None,
        h0: FloatArray | None = None,
    ) -> None:
        if variant not in VARIANT_STAGES:
            raise ValueError(f"unknown variant {variant!r}; choose one of {', '.join(VARIANTS)}")
        jit.ensure()  # compile (or load) the kernels now, not in the middle of a run
        n = model.n_cells
        self.model = model
        self.n = n
        self.variant: Variant = variant
        self.tuning = tuning or EstimatorTuning()
        self.cell_ids = np.arange(n) if cell_ids is None else np.asarray(cell_ids, dtype=np.int64)
        setup = StageSetup(model, self.tuning, self.cell_ids, n_stagger or n)
        self.ticks = TickAssembler(n, self.tuning)
        tun = self.tuning
        self.state: CoulombState = (
            ObserverState(model, soc0, tun.knee_slope_factor, tun.observer, tun.rest_current_C)
            if tun.observer.enabled
            else CoulombState(model, soc0, tun.knee_slope_factor)
        )
        #: per cell, the hysteresis state a fitted start set (in [-1, 1]); None: 0
        self.start_h: FloatArray | None = None
        if h0 is not None and soc0 is not None:  # a fitted start's h pairs with its SOC
            self.state.h0 = np.clip(np.broadcast_to(np.nan_to_num(h0), (n,)), -1.0, 1.0)
            self.start_h = self.state.h0.copy() if np.any(self.state.h0) else None
        self.params: ParameterStage = VARIANT_STAGES[variant](setup)
        #: per cell, the voltage the RC branches started holding (V, their sum); None: empty
        self.start_branch_V: FloatArray | None = None
        if branch0_V is not None:
            u = np.asarray(branch0_V, dtype=np.float64).reshape(n, 2)
            if self.params.seed_branches(u):
                self.start_branch_V = np.nan_to_num(u).sum(axis=1)
        self._excitation_limit_A = per_cell_limit(self.tuning.excitation_C, model)
        self.guard = PublishGuard.for_model(model, self.tuning)
        self.average = PublishAverage(n, self.tuning.publish_average_tau1)
        self.readings = ReadingWatch(n, self.tuning.gap_s)
        # copied each tick: a seventh of np.full's cost
        self._q_converged = np.full(n, _CONVERGED, dtype=np.int64)
        self._q_poorly = np.full(n, _POORLY_EXCITED, dtype=np.int64)
        # ``excited`` as the compiled tail takes it, for one capacity: [not excited, excited]
        self._excited = (np.zeros(n, dtype=bool), np.ones(n, dtype=bool))

    # ------------------------------------------------------------------ public API
    @property
    def counters(self) -> dict[str, int]:
        """Event counts of every stage (samples, ticks, gaps, swarms, clamps, ...)."""
        return {
            **self.ticks.counters, **self.state.counters, **self.params.counters,
            **self.guard.counters, **self.readings.counters,
        }  # fmt: skip

    @property
    def activation_energy_J_mol(self) -> FloatArray | None:
        """Per cell, the temperature law's activation energy, J/mol (``estimate/arrhenius.py``:
        learnt from window fits, else its prior), where a moving temperature put the law to
        use; None otherwise (no temperature, a constant one, a variant without the law)."""
        if not isinstance(self.params, FusionStage) or not self.counters["arrhenius_carried"]:
            return None
        return self.params.arrhenius.activation_energy_J_mol()

    @property
    def soc_init_method(self) -> str:
        """How SOC started: ``given``, ``ocv_at_rest``, ``ocv_ir_corrected``, ``config``, or
        ``pending`` while no cell had a valid voltage (cells start at their own first one)."""
        return self.state.soc_init_method

    @property
    def last_sample_t_s(self) -> float | None:
        """Time of the newest accepted sample, s (None before the first): where a replay
        resumes after a restart from a checkpoint."""
        return self.ticks.t_raw

    def update_block(self, block: SampleBlock) -> EstimateBlock:
        """Feed a block of samples (s, A with + = discharge, V) in order; returns the estimates
        of every tick the block completes (possibly none). Never raises on bad numbers."""
        if block.n_cells != self.n:
            raise ValueError(f"block has {block.n_cells} cells, the bank {self.n}")
        est = self._update_block(block)
        if est.n_ticks == 0:
            return est
        cells, q = self.readings.apply(est.t_s, dict(est.cells), est.quality)
        return EstimateBlock(t_s=est.t_s, current_A=est.current_A, cells=cells, quality=q)

    def _update_block(self, block: SampleBlock) -> EstimateBlock:
        if block_run.compiled():  # the block's ticks at once, ordinary ones in one compiled loop
            return block_run.update_block(self, block)
        times: list[float] = []
        currents: list[float] = []
        ticks: list[dict[str, FloatArray]] = []
        quality: list[npt.NDArray[np.int64]] = []
        v = block.cell_voltages_V
        temps = (
            [math.nan] * len(block) if block.temperature_C is None else block.temperature_C.tolist()
        )
        push, run_tick = self.ticks.push, self._run_tick  # bound once: the loop runs per sample
        for k, (t, i) in enumerate(zip(block.t_s.tolist(), block.current_A.tolist(), strict=True)):
            tick = push(t, i, v[k], temps[k])
            if tick is None:
                continue
            currents.append(tick.current_A)  # as measured: the observer corrects a copy
            cells, q = run_tick(tick)
            times.append(tick.t_s)
            ticks.append(cells)
            quality.append(q)
        if not times:
            return EstimateBlock.empty(self.n)
        return EstimateBlock(
            t_s=np.array(times),
            current_A=np.array(currents),
            # np.array of a list of equal rows: a third of np.stack's cost on 8k small rows
            cells={name: np.array([c[name] for c in ticks]) for name in FIELD_NAMES},
            quality=np.array(quality),
        )

    def update(
        self,
        t_s: float,
        current_A: float,
        voltages_V: npt.ArrayLike,
        temperature_C: float = math.nan,
    ) -> Estimates | None:
        """Feed one raw sample (time s, pack current A, cell voltages V, pack temperature degC
        or NaN); returns the estimates when an identification tick completes, else None. Never
        raises on bad numbers."""
        v = np.asarray(voltages_V, dtype=np.float64).reshape(self.n)
        tick = self.ticks.push(t_s, current_A, v, temperature_C)
        if tick is None:
            return None
        i_meas = tick.current_A  # as measured: the observer removes its offset in the tick
        cells, q = self._run_tick(tick)
        rows, q2 = self.readings.apply(
            np.array([tick.t_s]), {k: v[None, :] for k, v in cells.items()}, q[None, :]
        )
        cells = {k: v[0] for k, v in rows.items()}
        return Estimates(t_s=tick.t_s, current_A=i_meas, cells=cells, quality=q2[0])

    def reset(self, mask: npt.ArrayLike) -> None:
        """Re-initialise the masked cells (SOC by the start policy at the next tick, parameters
        at their start values); the others are untouched."""
        m = np.broadcast_to(np.asarray(mask, dtype=bool), (self.n,))
        self.state.reset(m)
        self.params.reset(m)
        self.guard.reset(m)
        self.average.reset(m)

    # ------------------------------------------------------------------ one tick
    def _run_tick(self, tick: Tick) -> tuple[dict[str, FloatArray], npt.NDArray[np.int64]]:
        """The stages over one tick: every output field (n_cells,) and the quality codes."""
        ctx = TickContext(tick)
        state, params, guard = self.state, self.params, self.guard
        state.step(ctx)
        # Converged cells learn only while excited (a constant-current charge or a rest holds
        # nothing to learn R0 from, and a slow OCV error would drift into it) and while the
        # observer is sure enough of SOC (a SOC error would be learnt as R2), unless a
        # parameter sits on a bound: nothing there is worth protecting, and with no rest to
        # anchor SOC the gate may stay shut for hours (a start mid-drive froze tau2 on its
        # bound for the whole record: 20.7 mV instead of 1.3).
        excited = is_excited(tick, self._excitation_limit_A)
        gate = state.learn_gate
        if nnz(guard.bound_bits):
            gate = gate | (guard.bound_bits > 0)
        may_learn = gate if excited is True else gate & excited  # (x & True: x's values)
        # every cell may learn (the usual tick): the stage's learn mask as it is
        if may_learn is not True and nnz(may_learn) < self.n:
            ctx.learn = ctx.learn & (may_learn | ~params.converged)
        params.step(ctx)
        p_out = params.outputs()
        state.correct(ctx, p_out, params.converged)
        cells = state.outputs()
        cells.update(p_out)
        v_meas = cells["v_meas_V"] = np.asarray(tick.v_V, dtype=np.float64)
        cells["v_error_V"] = v_meas - cells["v_model_V"]
        if TAIL.kind == "compiled":  # the codes, guard, average and flag: one kernel call
            ex = excited if isinstance(excited, np.ndarray) else self._excited[bool(excited)]
            cells, q, reinit = publish(
                guard, self.average, tick.t_s, tick.dt_s, cells, ex, params.clamped,
                params.converged, ctx.learn,
            )  # fmt: skip
        else:
            cells, q, reinit = self._publish(tick, cells, excited, ctx.learn)
        if nnz(state.no_data):  # no valid reading since the (re)start
            cells, q = without_data(cells, q, state.no_data)
        if nnz(reinit):
            self.reset(reinit)
        return cells, q

    def _publish(
        self, tick: Tick, cells: dict[str, FloatArray], excited: bool | BoolArray,
        learn: BoolArray,
    ) -> tuple[dict[str, FloatArray], npt.NDArray[np.int64], BoolArray]:  # fmt: skip
        """The tick's quality codes, guard and average by the stages' own calls (the numpy
        mode; ``publish_kernel.TAIL`` compiled runs the same in one call)."""
        params, guard = self.params, self.guard
        if isinstance(excited, np.ndarray):
            q = self._q_converged.copy()
            q[~excited] = _POORLY_EXCITED
        else:  # one capacity for the pack: one comparison, no mask
            q = (self._q_converged if excited else self._q_poorly).copy()
        # the masks only where a cell is clamped or converging (most ticks: none)
        clamped = params.clamped
        if nnz(clamped):
            q[clamped] = _OUT_OF_BOUNDS
        converged = params.converged  # after the step: it marks the cells converged now
        n_conv = nnz(converged)
        if n_conv < self.n:
            q[~converged] = _CONVERGING
        cells, q, reinit = guard.apply(tick.t_s, cells, q, clamped, learn)
        cells = self.average.apply(cells, q, tick.dt_s)
        # A converging cell on a bound is a finding too (a bound never shows silently: quality
        # OUT_OF_BOUNDS where on_bound names it; its branch is held by the guard), flagged only
        # after the average, which publishes converging cells raw.
        if n_conv < self.n and nnz(guard.bound_bits):
            flag = (q == _CONVERGING) & (guard.bound_bits > 0)
            if nnz(flag):
                q[flag] = _OUT_OF_BOUNDS
        return cells, q, reinit

    # ------------------------------------------------------------------ checkpoints
    def state_dict(self) -> dict[str, Any]:
        """The whole estimator state: one nested ``state_dict`` per stage (format 2).

        Running swarms are not saved: after a restore they start again at their next period.
        """
        return {
            "format": STATE_FORMAT,
            "meta": {"n_cells": self.n, "variant": self.variant, "cell": self.model.name},
            "ticks": self.ticks.state_dict(),
            "state": self.state.state_dict(),
            "params": self.params.state_dict(),
            "guard": self.guard.state_dict(),
            "average": self.average.state_dict(),
            "readings": self.readings.state_dict(),
            "counters": self.counters,
        }

    def load_state_dict(self, st: dict[str, Any]) -> None:
        """Restore ``state_dict`` output (a format-1 state is migrated first); raises ValueError
        with one line that says why when it belongs to another setup or cannot be read."""
        from bmsid.estimate.migrate import upgrade_state  # noqa: PLC0415 (rarely needed)

        st = upgrade_state(st)
        meta = st.get("meta", {})
        if meta.get("n_cells") != self.n or meta.get("variant") != self.variant:
            raise ValueError(
                f"checkpoint is for {meta.get('n_cells')} cells / {meta.get('variant')}, "
                f"not {self.n} / {self.variant}"
            )
        self.ticks.load_state_dict(st["ticks"])
        self.state.load_state_dict(st["state"])
        self.params.load_state_dict(st["params"])
        if "guard" in st:  # checkpoints from before the guard start it fresh
            self.guard.load_state_dict(st["guard"])
        if "average" in st:  # from before the average: published raw at the next tick
            self.average.load_state_dict(st["average"])
        if "readings" in st:  # from before the watch: its clock starts at the next reading
            self.readings.load_state_dict(st["readings"])
        counters = st.get("counters", {})
        for stage in (self.ticks, self.state, self.params, self.guard, self.readings):
            for k in stage.counters:
                if k in counters:
                    stage.counters[k] = int(counters[k])
