"""Plausibility gates between the sample sources and the estimator bank.

A reading the gates refuse becomes NaN for its tick (a refused current drops its sample): the
bank already treats a NaN voltage as a missing channel (left out of the tick's bin, ``Tick.ok``
False: no learning, no observer update, no SOC start) and a NaN current as held from the
previous sample (``estimate/ticks.py``). So an implausible value is never fed to an estimator,
and nothing is invented in its place.

Per cell and sample, in this order (the first that fails is the reason counted):

* ``v_window``: the voltage lies outside ``[v_min_V, v_max_V]``, by default the cell's rested
  range (OCV at the curve's ends) widened by :attr:`GateConfig.v_low_factor` below and
  :attr:`GateConfig.v_high_factor` above: a dead sensor's 0 V or a half-alive channel's 1 V;
* ``v_step``: the voltage moved more than ``max_step_V`` (default the rested range itself) from
  the cell's last accepted reading, when that reading is at most ``step_max_age_s`` old (the
  engine's ``gap_s``): a jump no current step can make. Older than that, only the window applies,
  so a cell is never locked out by a stale reference;
* ``v_frozen``: the reading has not changed for ``frozen_min_s`` while the pack current moved
  enough to change it (``gates_frozen``): a front end that stopped converting.

Per sample: ``i_window``, the pack current beyond ``+-i_max_A`` (default
:attr:`GateConfig.i_max_C` x capacity), which drops the whole sample, as a decoder drops one
whose current is "not available" (a minute of them is a gap). Held instead, the last current
paired with the real voltages taught the estimator garbage: a 4-cell CALCE DST log with the
current at its DBC maximum for 60 s gave 19.3 mV (2.3 intact) and tau1 40-109 s against 11-12;
with the voltages dropped but the current held, 4.4 mV and 70 % of the later rows out of bounds;
the samples dropped, 4.7 mV and 0.4 % of the rows out of bounds, as the same log with the
current "not available". ``t_step``, a pack temperature further from the last accepted one
than ``TEMP_STEP_FLOOR_K + TEMP_MAX_RATE_K_S`` x the time since it: a cell's thermal mass does
not move tens of kelvin in a second (one -40 degC sample drove the Arrhenius law's R0 from 81
to 9 mOhm on a CALCE record). The refused reading is replaced by the last
accepted one (held, as the temperature a tick needs); two successive readings that agree with
each other but not with it replace it (a sensor wrong at its first reading is not held).

:func:`gate_block` is pure (a block and a :class:`GateState` in, the gated block and the next
state out), vectorised: a block whose cells all pass is checked in a handful of array
operations; only the cells with a refused reading are walked sample by sample from their first
refusal (the step check compares with the last *accepted* reading, which a refusal changes).
:class:`InputGate` holds the state for the daemon's worker and offline identification, and
says what it refused in thinned log lines.
"""

from __future__ import annotations

import logging
from collections.abc import Iterable
from dataclasses import dataclass, replace
from typing import TYPE_CHECKING, Any, Self

import numpy as np
import numpy.typing as npt
from pydantic import BaseModel, ConfigDict, Field, model_validator

from bmsid.gates_frozen import FrozenRuns, frozen_readings
from bmsid.samples import SampleBlock

if TYPE_CHECKING:  # attributes only: the daemon's parent process never loads the engine
    from bmsid.estimate.cellmodel import CellModel

log = logging.getLogger(__name__)

FloatArray = npt.NDArray[np.float64]
BoolArray = npt.NDArray[np.bool_]
IntArray = npt.NDArray[np.int64]

#: Why a cell's reading was refused (counted per cell).
VOLTAGE_REASONS = ("v_window", "v_step", "v_frozen")
#: The totals in the daemon's flat counters (:meth:`GateState.counters`).
GATE_COUNTERS = (
    "gated_v_window", "gated_v_step", "gated_v_frozen", "gated_i_window", "gated_t_step",
)  # fmt: skip
#: Readings this close to the top of the rested range, V, are never frozen: constant-voltage
#: charging holds them while the current tapers.
CV_MARGIN_V = 0.05
#: Fastest plausible change of a pack temperature reading, K/s: an 18650 (45 g, ~1 J/(g K))
#: dissipating I^2 R = 32 W at 20C (40 A, 20 mOhm) warms by 0.7 K/s; drive cycles stay far
#: below 0.05 K/s. A faster reading is a sensor fault, not the cell.
TEMP_MAX_RATE_K_S = 1.0
#: ... plus this much at any step, K: an NTC channel's quantisation and noise (0.5-1 K).
TEMP_STEP_FLOOR_K = 1.0


class GateConfig(BaseModel):
    """The gates' settings (``[gates]`` in the daemon's TOML); the defaults derive every limit
    from the cell config, so a pack of another chemistry needs no change here."""

    # strict: part of the daemon TOML, where a quoted number is refused, not coerced
    model_config = ConfigDict(
        extra="forbid", frozen=True, strict=True, use_attribute_docstrings=True
    )

    enabled: bool = True
    """Gate the readings (False: every finite reading reaches the estimators, as before)."""
    v_low_factor: float = Field(0.6, gt=0.0, lt=1.0)
    """Lowest plausible cell voltage as a fraction of the rested empty voltage (OCV at the
    curve's low end). Discharge cut-offs sit at 0.70-0.90 of it (measured: CALCE INR18650-20R
    at 0 degC under US06 2.46 V against 3.46 V, 0.71; A123 LFP 1.99 V against 2.21 V, 0.90);
    0.6 leaves room for a colder cell under a harder load and still refuses 0 V and 1 V on
    every shipped cell config (1.33 V for LFP, 1.87 V for the paper's NMC)."""
    v_high_factor: float = Field(1.15, gt=1.0)
    """Highest plausible cell voltage as a multiple of the rested full voltage (OCV at the
    curve's high end). Charging polarisation measured on the shipped data stays below 1.02 x
    (4.23 V against 4.16 V); 1.15 x (4.79 V for NMC) is over-charge no cell survives in
    service: a reading above is a sensor fault."""
    v_min_V: float | None = Field(None, gt=0.0)
    """Lowest plausible cell voltage, V; overrides ``v_low_factor``."""
    v_max_V: float | None = Field(None, gt=0.0)
    """Highest plausible cell voltage, V; overrides ``v_high_factor``."""
    max_step_V: float | None = Field(None, gt=0.0)
    """Largest plausible change of a cell's voltage between two readings, V; None = the cell's
    rested range (OCV full minus empty): no current step moves a series cell further than its
    whole range at once (largest measured one-sample step: 0.58 V, CALCE at 0 degC, 2C steps,
    against a 0.72 V range)."""
    step_max_age_s: float | None = Field(None, gt=0.0)
    """The step check compares with the last accepted reading only when it is at most this
    old, s; None = the estimator's ``gap_s`` (beyond it the engine starts a new segment too)."""
    i_max_C: float = Field(30.0, gt=0.0)
    """Largest plausible pack current magnitude as a C-rate of the cell capacity: power cells
    pulse at 10-30C, the shipped data stays within 2C; beyond it is a sensor fault."""
    i_max_A: float | None = Field(None, gt=0.0)
    """Largest plausible pack current magnitude, A; overrides ``i_max_C``."""
    frozen_min_s: float = Field(60.0, gt=0.0)
    """A cell's reading identical for this long, s, while the pack current moved enough to
    change it (``frozen_step_V``), is a front end that stopped converting (``gates_frozen``):
    refused until it changes. Longer than any CAN cycle of cell voltages (1-10 s)."""
    frozen_step_V: float = Field(0.01, gt=0.0)
    """... enough: a current change that moves a live cell's voltage by this much, V, through
    the smallest start R0 (10 mV: ten steps of a 1 mV reading)."""

    @model_validator(mode="after")
    def _check(self) -> Self:
        if self.v_min_V is not None and self.v_max_V is not None and self.v_min_V >= self.v_max_V:
            raise ValueError("v_min_V must be < v_max_V")
        return self

    def for_model(self, model: CellModel, gap_s: float) -> GateLimits:
        """The limits for the cells of an estimator bank's ``model`` (its OCV curve's ends and
        its smallest capacity: one current limit for the series string)."""
        ocv = model.ocv
        v_ends = ocv.ocv(np.array([ocv.soc_min, ocv.soc_max]))
        lim = self.limits(
            float(v_ends[0]), float(v_ends[1]), float(np.min(model.capacity_Ah)), gap_s
        )
        r0 = float(np.min(model.start("R0_ohm")))
        if not r0 > 0.0:
            return lim
        return replace(
            lim, frozen_min_s=self.frozen_min_s, frozen_dI_A=self.frozen_step_V / r0,
            frozen_top_V=float(v_ends[1]) - CV_MARGIN_V,
        )  # fmt: skip

    def limits(
        self, v_empty_V: float, v_full_V: float, capacity_Ah: float, gap_s: float
    ) -> GateLimits:
        """The limits for a cell whose rested voltage runs from ``v_empty_V`` to ``v_full_V``
        (V) with ``capacity_Ah`` (Ah), in a bank whose gap threshold is ``gap_s`` (s)."""
        if not (0.0 < v_empty_V < v_full_V):
            raise ValueError(f"rested range {v_empty_V!r}..{v_full_V!r} V is not a range")
        v_lo = self.v_min_V if self.v_min_V is not None else self.v_low_factor * v_empty_V
        v_hi = self.v_max_V if self.v_max_V is not None else self.v_high_factor * v_full_V
        if v_lo >= v_hi:
            raise ValueError(f"gates: v_min {v_lo:.3f} V >= v_max {v_hi:.3f} V")
        return GateLimits(
            enabled=self.enabled,
            v_min_V=float(v_lo),
            v_max_V=float(v_hi),
            max_step_V=float(self.max_step_V or (v_full_V - v_empty_V)),
            step_max_age_s=float(self.step_max_age_s or gap_s),
            i_max_A=float(self.i_max_A or self.i_max_C * capacity_Ah),
        )


@dataclass(frozen=True, slots=True)
class GateLimits:
    """The numbers :func:`gate_block` checks against (V, V, V, s, A)."""

    enabled: bool
    v_min_V: float
    v_max_V: float
    max_step_V: float
    step_max_age_s: float
    i_max_A: float
    #: the frozen-reading gate (``gates_frozen``; inf: off, as without a cell model's R0)
    frozen_min_s: float = float("inf")
    frozen_dI_A: float = float("inf")
    frozen_top_V: float = float("inf")

    def describe(self) -> str:
        if not self.enabled:
            return "input gates off"
        return (
            f"cell voltage {self.v_min_V:.3f}..{self.v_max_V:.3f} V, step <= "
            f"{self.max_step_V:.3f} V within {self.step_max_age_s:g} s, "
            f"|current| <= {self.i_max_A:g} A"
        )


@dataclass(frozen=True, slots=True)
class GateState:
    """What the gates remember between blocks, per cell (shape (n,)) unless said.

    Attributes:
        v_last_V: last accepted voltage, V (NaN: none yet).
        t_last_s: its sample time, s (NaN: none yet).
        seen: cells that ever carried a finite reading (accepted or not).
        valid: cells that ever carried an accepted reading.
        refused: per reason of :data:`VOLTAGE_REASONS`, readings refused per cell.
        i_refused: samples whose current was refused (the pack's one sensor).
        T_last_C, tT_last_s: last accepted pack temperature, degC, and its time, s (NaN: none).
        T_refused: samples whose temperature was refused (``t_step``, held instead).
        T_cand: the last refused temperature and its time (NaN: none since an accepted one).
        runs: each cell's run of identical readings (``gates_frozen``).
    """

    v_last_V: FloatArray
    t_last_s: FloatArray
    seen: BoolArray
    valid: BoolArray
    refused: dict[str, IntArray]
    runs: FrozenRuns
    i_refused: int = 0
    T_last_C: float = float("nan")
    tT_last_s: float = float("nan")
    T_refused: int = 0
    T_cand: tuple[float, float] = (float("nan"), float("nan"))

    @classmethod
    def fresh(cls, n_cells: int) -> GateState:
        return cls(
            v_last_V=np.full(n_cells, np.nan),
            t_last_s=np.full(n_cells, np.nan),
            seen=np.zeros(n_cells, dtype=bool),
            valid=np.zeros(n_cells, dtype=bool),
            refused={k: np.zeros(n_cells, dtype=np.int64) for k in VOLTAGE_REASONS},
            runs=FrozenRuns.fresh(n_cells),
        )

    @property
    def missing(self) -> list[int]:
        """Cells that never carried a reading (0-based)."""
        return [int(c) for c in np.flatnonzero(~self.seen)]

    @property
    def no_data(self) -> list[int]:
        """Cells that never carried an accepted reading (missing ones included)."""
        return [int(c) for c in np.flatnonzero(~self.valid)]

    def counters(self) -> dict[str, int]:
        """Totals over the cells, for the daemon's flat counters."""
        v_window, v_step, v_frozen, i_window, t_step = GATE_COUNTERS
        return {
            v_window: int(self.refused["v_window"].sum()),
            v_step: int(self.refused["v_step"].sum()),
            v_frozen: int(self.refused["v_frozen"].sum()),
            i_window: self.i_refused,
            t_step: self.T_refused,
        }

    def report(self) -> dict[str, Any]:
        """JSON-ready: refusals per reason and cell, missing and no-data cells."""
        return {
            "refused_per_cell": {k: v.tolist() for k, v in self.refused.items()},
            "current_refused": self.i_refused,
            "missing_cells": self.missing,
            "no_data_cells": self.no_data,
        }


def gate_block(
    block: SampleBlock, limits: GateLimits, state: GateState, drop_refused_current: bool = True
) -> tuple[SampleBlock, GateState]:
    """The block with refused readings as NaN and the samples of a refused current dropped
    (``drop_refused_current`` False: kept, their current NaN, for checks that need the rows
    aligned with their input), and the gates' next state (module docstring)."""
    v = block.cell_voltages_V
    t = block.t_s
    fin = np.isfinite(v)
    seen = state.seen | fin.any(axis=0)
    if not limits.enabled:
        valid = state.valid | fin.any(axis=0)
        return block, replace(state, seen=seen, valid=valid)
    i = block.current_A
    i_bad = np.abs(i) > limits.i_max_A  # NaN compares False: already missing, not refused
    n_i = int(i_bad.sum())
    current = np.where(i_bad, np.nan, i) if n_i else i

    with np.errstate(invalid="ignore"):
        in_win = fin & (v >= limits.v_min_V) & (v <= limits.v_max_V)
        # The fast path assumes every reading accepted: the reference is then the previous row.
        prev_v = np.vstack([state.v_last_V[None, :], v[:-1]])
        prev_t = np.concatenate([[np.nan], t[:-1]])[:, None]
        prev_t = np.where(np.arange(len(t))[:, None] == 0, state.t_last_s[None, :], prev_t)
        age = t[:, None] - prev_t
        checked = (age >= 0.0) & (age <= limits.step_max_age_s)  # NaN (no reference): False
        step_ok = ~checked | (np.abs(v - prev_v) <= limits.max_step_V)
    ok = in_win & step_ok
    clean = ok.all(axis=0)
    accepted = ok
    v_last, t_last = state.v_last_V.copy(), state.t_last_s.copy()
    if len(t):
        v_last[clean], t_last[clean] = v[-1, clean], t[-1]
    if not clean.all():
        accepted = ok.copy()
        for c in np.flatnonzero(~clean):
            first = int(np.argmin(ok[:, c]))  # rows before it are accepted, as assumed
            if first:
                v_last[c], t_last[c] = v[first - 1, c], t[first - 1]
            accepted[first:, c], v_last[c], t_last[c] = _walk(
                v[first:, c], t[first:], in_win[first:, c], v_last[c], t_last[c], limits
            )
    frozen, runs = frozen_readings(
        t, current, v, state.runs, limits.frozen_min_s, limits.frozen_dI_A, limits.frozen_top_V
    )
    n_frozen = (accepted & frozen).sum(axis=0)
    refused = {
        "v_window": state.refused["v_window"] + (fin & ~in_win).sum(axis=0),
        "v_step": state.refused["v_step"] + (in_win & ~accepted).sum(axis=0),
        "v_frozen": state.refused["v_frozen"] + n_frozen,
    }
    if n_frozen.any():  # after the step check, which still takes them as its reference
        accepted = accepted & ~frozen
        clean = clean & (n_frozen == 0)
    gated_v = v if clean.all() else np.where(accepted, v, np.nan)
    temp, T_last, tT_last, n_T, cand = gate_temperature(
        block.temperature_C, t, state.T_last_C, state.tT_last_s, state.T_cand
    )
    out = block
    if n_i or n_T or not clean.all():
        out = SampleBlock(t, current, gated_v, block.t_complete_mono, temp)
    if n_i and drop_refused_current:  # the sample goes with its current (module docstring)
        keep, m = ~i_bad, out.t_complete_mono
        out = SampleBlock(
            t[keep], current[keep], gated_v[keep], None if m is None else m[keep],
            None if temp is None else temp[keep],
        )  # fmt: skip
    return out, GateState(
        v_last_V=v_last,
        t_last_s=t_last,
        seen=seen,
        valid=state.valid | accepted.any(axis=0),
        refused=refused,
        i_refused=state.i_refused + n_i,
        T_last_C=T_last,
        tT_last_s=tT_last,
        T_refused=state.T_refused + n_T,
        T_cand=cand,
        runs=runs,
    )


def gate_temperature(
    temp_C: FloatArray | None,
    t_s: FloatArray,
    T_last_C: float,
    tT_last_s: float,
    cand: tuple[float, float] = (float("nan"), float("nan")),
) -> tuple[FloatArray | None, float, float, int, tuple[float, float]]:
    """A block's pack temperatures (degC, NaN: none) with each reading that moved faster than
    the slew limit (module docstring) from the last accepted one replaced by it; the new last
    accepted temperature and time, the readings refused and the last refused one (``cand``:
    reading degC, time s, carried between blocks). Vectorised while every reading
    passes; walked from the first refusal (the reference then changes)."""
    if temp_C is None or temp_C.size == 0:
        return temp_C, T_last_C, tT_last_s, 0, cand
    fin = np.isfinite(temp_C)
    if not fin.any():
        return temp_C, T_last_C, tT_last_s, 0, cand
    k_fin = np.flatnonzero(fin)
    ref_T = np.concatenate(([T_last_C], temp_C[k_fin[:-1]]))
    ref_t = np.concatenate(([tT_last_s], t_s[k_fin[:-1]]))
    with np.errstate(invalid="ignore"):
        allowed = TEMP_STEP_FLOOR_K + TEMP_MAX_RATE_K_S * np.abs(t_s[k_fin] - ref_t)
        bad = np.abs(temp_C[k_fin] - ref_T) > allowed  # NaN reference (none yet): False
    nan2 = (float("nan"), float("nan"))
    if not bad.any():
        return temp_C, float(temp_C[k_fin[-1]]), float(t_s[k_fin[-1]]), 0, nan2
    out = temp_C.copy()
    first = int(np.argmax(bad))
    cand_T, cand_t = cand  # the last refused reading
    if first:
        T_last_C, tT_last_s = float(temp_C[k_fin[first - 1]]), float(t_s[k_fin[first - 1]])
        cand_T, cand_t = nan2
    n = 0
    for k in k_fin[first:].tolist():
        T, tk = float(temp_C[k]), float(t_s[k])
        lim = TEMP_STEP_FLOOR_K + TEMP_MAX_RATE_K_S * abs(tk - tT_last_s)
        lim_cand = TEMP_STEP_FLOOR_K + TEMP_MAX_RATE_K_S * abs(tk - cand_t)
        # two successive readings that agree outvote the reference: it was the glitch (a
        # sensor wrong at its first reading would otherwise hold its value for a minute)
        if np.isnan(T_last_C) or abs(T - T_last_C) <= lim or abs(T - cand_T) <= lim_cand:
            T_last_C, tT_last_s = T, tk
            cand_T = cand_t = float("nan")
        else:
            out[k] = T_last_C
            cand_T, cand_t = T, tk
            n += 1
    return out, T_last_C, tT_last_s, n, (cand_T, cand_t)


def _walk(
    v: FloatArray, t: FloatArray, in_win: BoolArray, v_last: float, t_last: float, lim: GateLimits
) -> tuple[BoolArray, float, float]:
    """One cell's readings in order against its last accepted one: (accepted, new last V, its
    time s). Only cells with a refusal in the block come here."""
    acc = np.zeros(v.shape[0], dtype=bool)
    for k in np.flatnonzero(in_win).tolist():
        age = t[k] - t_last
        if not (0.0 <= age <= lim.step_max_age_s) or abs(v[k] - v_last) <= lim.max_step_V:
            acc[k] = True
            v_last, t_last = float(v[k]), float(t[k])
    return acc, v_last, t_last


class InputGate:
    """The gates with their state, for one stream of blocks (daemon worker, offline run), and
    the log lines a user reads: per cell and reason at the 1st, 10th, 100th, ... refusal, and
    once the cells that never appeared, ``step_max_age_s`` of data after the first sample.

    Args:
        limits: what is plausible (:meth:`GateConfig.limits`).
        n_cells: cells per sample.
        quiet: no log lines (a pass over a record's head that the run itself reads again:
            its refusals are told once, by the run's gate).
    """

    def __init__(self, limits: GateLimits, n_cells: int, quiet: bool = False) -> None:
        self.limits = limits
        self.state = GateState.fresh(n_cells)
        self._t_first: float | None = None
        self._missing_told = False
        self._quiet = quiet

    def apply(self, block: SampleBlock) -> SampleBlock:
        before = self.state
        out, self.state = gate_block(block, self.limits, before)
        if not self._quiet:
            self._tell(before, self.state, block)
        return out

    def _tell(self, before: GateState, after: GateState, block: SampleBlock) -> None:
        lim = self.limits
        what = {
            "v_window": f"outside the plausible {lim.v_min_V:.3f}..{lim.v_max_V:.3f} V",
            "v_step": f"more than {lim.max_step_V:.3f} V from its last accepted reading",
            "v_frozen": f"unchanged for {lim.frozen_min_s:g} s or more while the current moved "
            f"by {lim.frozen_dI_A:.3g} A (a front end that stopped converting?)",
        }
        for k in VOLTAGE_REASONS:
            for c in np.flatnonzero(_decade(before.refused[k], after.refused[k])).tolist():
                log.warning(
                    "cell %d: voltage reading %s refused (%d so far, %s): the cell is missing "
                    "for those samples, not estimated from them",
                    c, what[k], int(after.refused[k][c]), k,
                )  # fmt: skip
        if _decade(np.array([before.T_refused]), np.array([after.T_refused]))[0]:
            log.warning(
                "pack temperature moving faster than %g K/s (+%g K) refused (%d samples so "
                "far, t_step): the last accepted temperature is held for those samples",
                TEMP_MAX_RATE_K_S, TEMP_STEP_FLOOR_K, after.T_refused,
            )  # fmt: skip
        if _decade(np.array([before.i_refused]), np.array([after.i_refused]))[0]:
            log.warning(
                "pack current beyond +-%g A refused (%d samples so far, i_window): those "
                "samples are dropped (a voltage without its current is no evidence)",
                lim.i_max_A, after.i_refused,
            )  # fmt: skip
        if len(block) and not self._missing_told:
            if self._t_first is None:
                self._t_first = float(block.t_s[0])
            if float(block.t_s[-1]) - self._t_first >= lim.step_max_age_s and after.missing:
                self._missing_told = True
                log.warning(
                    "cells %s (0-based) configured but never on the bus: reported as "
                    "missing_cells, not published as cells (check can.n_cells)",
                    ", ".join(map(str, after.missing)),
                )


def gated_head(
    blocks: Iterable[SampleBlock], span_s: float, gate: InputGate | None = None
) -> SampleBlock | None:
    """The record's first ``span_s`` seconds (whole blocks, through ``gate`` when given: fresh
    gates, so that the run's own start from scratch), or None for a record without blocks."""
    head: list[SampleBlock] = []
    for block in blocks:
        head.append(block if gate is None else gate.apply(block))
        if len(block) and block.t_s[-1] - head[0].t_s[0] >= span_s:
            break
    return SampleBlock.concat(head) if head else None


def _decade(before: IntArray, after: IntArray) -> BoolArray:
    """Where a count crossed 1, 10, 100, ... (the thinning of repeated log lines)."""
    digits_before = np.where(before > 0, np.floor(np.log10(np.maximum(before, 1))) + 1, 0)
    return np.asarray(np.floor(np.log10(np.maximum(after, 1))) + 1 > digits_before) & (after > 0)
