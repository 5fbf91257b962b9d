"""The state stage: SOC by coulomb counting (Eq. 2) and the hysteresis state (Eq. 5-6).

It runs first in every tick, owns z and h, and leaves OCV(z), M(z) and h M(z) in the tick
context for the parameter stages. (A SOC observer that corrects z from the voltage through the
identified model replaces this stage behind the same protocol.)
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import numpy as np

from bmsid.estimate import state_jit
from bmsid.estimate.cellmodel import CellModel
from bmsid.estimate.stage import BoolArray, FloatArray, TickContext
from bmsid.estimate.statedict import load_arrays
from bmsid.estimate.ticks import Tick
from bmsid.estimate.types import IntArray, Quality
from bmsid.model.ecm import hysteresis_kappa, hysteresis_step, soc_step
from bmsid.model.ocv import OcvModel

_NO_DATA = int(Quality.NO_DATA)


def without_data(
    cells: dict[str, FloatArray], quality: IntArray, no_data: BoolArray
) -> tuple[dict[str, FloatArray], IntArray]:
    """``cells`` with every field NaN and ``quality`` ``NO_DATA`` for the ``no_data`` cells:
    what is published for a cell whose state came from no reading (new arrays: the fields
    may be a stage's live state)."""
    out = {k: np.where(no_data, np.nan, v) for k, v in cells.items()}
    return out, np.where(no_data, _NO_DATA, quality)


def mean_abs_current(steps: Sequence[tuple[float, float]]) -> float:
    """Time-weighted mean |i| of a tick's raw (current A, interval s) steps, A (0 if none)."""
    charge = span = 0.0
    for i, dt in steps:
        charge += abs(i) * dt
        span += dt
    return charge / span if span > 0 else 0.0


def _uniform(x: FloatArray) -> float | FloatArray:
    return float(x[0]) if np.all(x == x[0]) else x


#: Start SOC uncertainty sources, V: what the first voltage cannot tell beyond hysteresis
#: and the IR drop (relaxation left from before the start, sensor offset).
START_V_SIGMA_V = 0.01


def starts_at_rest(current_A: float, model: CellModel) -> bool:
    """A start at rest: the first tick's current (A) within ``soc_start.rest_current_C`` x
    each cell's capacity; a start under load (or without a current) IR-corrects its first
    voltage."""
    return bool(np.all(abs(current_A) <= model.soc_start.rest_current_C * model.capacity_Ah))


def start_soc_sigma(
    model: CellModel, z: FloatArray, i_abs_A: float, sigma_max: float
) -> FloatArray:
    """Std (fraction) of a SOC read from the first voltage at ``z`` under ``i_abs_A``: the
    voltage's uncertainty (hysteresis M(z), the start values' IR drop of R1 + R2, relaxation
    and offset) through the OCV slope, at most ``sigma_max`` (a flat LFP plateau)."""
    ocv = model.ocv
    slope = np.abs(ocv.docv_dz(np.clip(z, ocv.soc_min, ocv.soc_max)))
    r_rc = model.start("R1_ohm") + model.start("R2_ohm")
    sigma_v = ocv.hysteresis_M(z) + i_abs_A * r_rc + START_V_SIGMA_V
    return np.asarray(np.minimum(sigma_v / np.maximum(slope, 1e-9), sigma_max), dtype=np.float64)


def learnable_soc_range(ocv: OcvModel, knee_slope_factor: float) -> tuple[float, float]:
    """The SOC range (fractions) around mid-SOC where |dOCV/dz| stays within
    ``knee_slope_factor`` x its median over 20-80 %: outside it lie the OCV curve's knees."""
    grid = np.linspace(ocv.soc_min, ocv.soc_max, 2001)
    slope = np.abs(ocv.docv_dz(grid))
    limit = knee_slope_factor * float(np.median(np.abs(ocv.docv_dz(np.linspace(0.2, 0.8, 61)))))
    ok = slope <= limit
    mid = int(np.argmin(np.abs(grid - 0.5)))
    if not ok[mid]:
        return float(grid[0]), float(grid[-1])  # no flat middle: learn everywhere
    lo = mid
    while lo > 0 and ok[lo - 1]:
        lo -= 1
    hi = mid
    while hi < grid.shape[0] - 1 and ok[hi + 1]:
        hi += 1
    return float(grid[lo]), float(grid[hi])


class CoulombState:
    """SOC z (fraction) and hysteresis h in [-1, 1] of every cell; no correction from voltage.

    Args:
        model: per-cell capacity (Ah), coulombic efficiency, hysteresis rate, OCV curve.
        soc0: start SOC (fraction, scalar or per cell); None applies ``model.soc_start``.
    """

    name = "state"

    def __init__(
        self,
        model: CellModel,
        soc0: float | FloatArray | None = None,
        knee_slope_factor: float = np.inf,
    ) -> None:
        self.model = model
        self.n = model.n_cells
        self.soc0 = soc0
        self.counters: dict[str, int] = {}
        self.z = np.full(self.n, 0.5)
        self.h = np.zeros(self.n)
        #: per cell, the hysteresis state a start at ``soc0`` takes (a start fit's, which
        #: pairs with its SOC: ``offline/start_soc.py``); 0 else, what a voltage cannot tell
        self.h0 = np.zeros(self.n)
        self.soc_init_method = "pending"
        # One float per constant when every cell shares it (the usual pack): the per-tick
        # arithmetic then stays on Python scalars, as cheap as before per-cell arrays existed.
        self._capacity_As = _uniform(model.capacity_As)
        self._efficiency = _uniform(model.efficiency)
        self._pending = np.ones(self.n, dtype=bool)  # cells whose SOC starts at the next tick
        # Cells with a valid voltage since the start: a given or configured soc0 starts every
        # cell at once, a dead voltage tap too, which must still publish nothing (no_data).
        self._seen = np.zeros(self.n, dtype=bool)
        self._all_seen = False
        self._learn_lo, self._learn_hi = learnable_soc_range(model.ocv, knee_slope_factor)
        self._learn_everywhere = (
            self._learn_lo <= model.ocv.soc_min and self._learn_hi >= model.ocv.soc_max
        )
        # kappa (Eq. 6) depends on the current's sign only: both once, not every tick.
        gamma = _uniform(model.gamma)
        self._kappa_discharge = hysteresis_kappa(gamma, self._capacity_As, self._efficiency, 1.0)
        self._kappa_charge = hysteresis_kappa(gamma, self._capacity_As, self._efficiency, -1.0)
        #: |current| (A) below which the hysteresis holds (the observer's rest limit; 0 here)
        self._h_rest_A = 0.0
        self._h_hold = False  # set by the observer for the tick: a rest goes on

    def step(self, ctx: TickContext) -> None:
        if state_jit.step(self, ctx, observer=False):  # the compiled kernel (jit.select)
            return
        tick = ctx.tick
        m = self.model
        if not self._all_seen:  # until every cell has read a valid voltage (never compiled)
            self._seen = self._seen | tick.ok
            self._all_seen = bool(self._seen.all())
        # h through the raw steps too (|i| does not average over a tick), unless the tick's
        # mean |i| is a rest's (a raw sample's noise is no current)
        moves = (tick.dt_s > 0 and not self._h_hold
                 and mean_abs_current(tick.coulomb_steps) >= self._h_rest_A)  # fmt: skip
        for i, dt in tick.coulomb_steps:
            self.z = soc_step(self.z, i, dt, self._capacity_As, self._efficiency)
            if moves and dt > 0:
                kappa = self._kappa_charge if i < 0 else self._kappa_discharge
                self.h = hysteresis_step(self.h, i, dt, kappa, m.hysteresis_play)
                self._h_decayed(-np.abs(kappa * i) * dt)
        held = (tick.dt_s > 0 and self._h_hold  # at the rests' reading, over some time
                and any(dt > 0 for _, dt in tick.coulomb_steps))  # fmt: skip
        draw = self._rest_draw_A() if held else 0.0
        if draw:  # at rest h moves with what the pack draws (rest_anchor.rest_draw)
            kappa = self._kappa_charge if draw < 0 else self._kappa_discharge
            self.h = hysteresis_step(self.h, draw, tick.dt_s, kappa, m.hysteresis_play)
            self._h_decayed(-np.abs(kappa * draw) * tick.dt_s)
        if np.count_nonzero(self._pending):  # after the count: SOC is that of the start sample
            self._start(tick, self._pending)
        ocv = m.ocv
        zc = np.minimum(np.maximum(self.z, ocv.soc_min), ocv.soc_max)
        ctx.soc_clamped = zc
        ctx.ocv_V = ocv.ocv(zc)
        ctx.m_table_V = self.hysteresis_m(zc)
        ctx.h = self.h
        ctx.hm_V = self.h * ctx.m_table_V
        all_ok = np.count_nonzero(tick.ok) == self.n  # the usual tick: no mask to apply
        ctx.v_safe_V = tick.v_V if all_ok else np.where(tick.ok, tick.v_V, ctx.ocv_V)
        if self._learn_everywhere:
            ctx.learn = tick.ok
        else:
            ctx.learn = tick.ok & (zc >= self._learn_lo) & (zc <= self._learn_hi)

    def _rest_draw_A(self) -> float:
        """Hook: the current the pack draws at rest, A (the observer knows it; a count: 0)."""
        return 0.0

    def _h_decayed(self, log_decay: FloatArray) -> None:
        """Hook: h moved with ``-kappa |i| dt`` of a raw step (the observer keeps its sum)."""

    def hysteresis_m(self, zc: FloatArray) -> FloatArray:
        """The half-gap M (V) at the (clamped) SOC ``zc``: the configured table (Eq. 32)."""
        return self.model.ocv.hysteresis_M(zc)

    def _start(self, tick: Tick, cells: BoolArray) -> BoolArray:
        """SOC of ``cells`` from the caller's soc0 or a fixed policy's config value, else from
        each cell's first valid voltage through the OCV (IR-corrected with the start R0 when a
        current flows: a gateway that restarts under the 12 V converter's load, or mid-drive).
        A cell without a valid voltage this tick stays pending: it starts at its own first
        valid reading, never from a fallback (its coulomb count starts there too). Returns the
        cells started."""
        si = self.model.soc_start
        if self.soc0 is not None:
            z = np.broadcast_to(np.asarray(self.soc0, dtype=float), (self.n,)).copy()
            method = "given"
        elif si.policy == "fixed" and si.soc0 is not None:
            z = np.full(self.n, si.soc0)
            method = "config"
        else:
            v_eq = tick.v_V + self.model.start("R0_ohm") * tick.current_A
            z = self.model.ocv.soc_from_ocv(np.where(tick.ok & np.isfinite(v_eq), v_eq, np.nan))
            cells = cells & np.isfinite(z)
            if not cells.any():
                return cells
            rest = starts_at_rest(tick.current_A, self.model)
            method = "ocv_at_rest" if rest else "ocv_ir_corrected"
        self.z = np.where(cells, z, self.z)
        self.h = np.where(cells, self.h0 if method == "given" else 0.0, self.h)
        if cells.all() or self.soc_init_method == "pending":
            self.soc_init_method = method
        self._pending = self._pending & ~cells
        self.start_variance(tick, method, z)
        return cells

    @property
    def no_data(self) -> BoolArray:
        """Cells without a valid reading since their (re)start: their SOC is not known, so
        nothing of theirs is published (quality ``NO_DATA``, fields NaN)."""
        return self._pending if self._all_seen else self._pending | ~self._seen

    def start_variance(self, tick: Tick, method: str, z: FloatArray) -> None:
        """Hook for a stage that keeps SOC uncertainty (the observer); none here."""

    @property
    def learn_gate(self) -> bool | BoolArray:
        """Cells whose SOC is certain enough for their parameters to learn: a plain count
        does not know its uncertainty, so every cell."""
        return True

    def correct(
        self, ctx: TickContext, params: dict[str, FloatArray], converged: BoolArray
    ) -> None:
        """The voltage correction of the state after the parameter stage: none in a count."""

    def outputs(self) -> dict[str, FloatArray]:
        # Rebound every step, never written in place. A plain count knows no uncertainty,
        # capacity beyond the config, nor offset: NaN (null) and the configured values.
        n = self.n
        return {
            "soc": self.z,
            "h": self.h,
            "soc_std": np.full(n, np.nan),
            "capacity_Ah": self.model.capacity_Ah,
            "capacity_std_Ah": np.zeros(n),
            "current_offset_A": np.zeros(n),
        }

    def reset(self, mask: BoolArray) -> None:
        """The masked cells start again at the next tick (SOC by the start policy, h = 0)."""
        self._pending = self._pending | np.asarray(mask, dtype=bool)

    def state_dict(self) -> dict[str, Any]:
        return {
            "z": self.z.copy(),
            "h": self.h.copy(),
            "pending": self._pending.copy(),
            "soc_init_method": self.soc_init_method,
        }

    def load_state_dict(self, st: dict[str, Any]) -> None:
        load_arrays(self, st, ("z", "h"), self.name)
        pend = np.asarray(st.get("pending", np.zeros(self.n, dtype=bool)), dtype=bool)
        if pend.shape != (self.n,):
            raise ValueError(f"checkpoint field state/pending has shape {pend.shape}")
        self._pending = pend.copy()
        self._seen = ~pend  # a started cell had read a voltage when the checkpoint was taken
        self._all_seen = bool(self._seen.all())
        self.soc_init_method = str(st["soc_init_method"])
