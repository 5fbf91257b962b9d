"""Tick assembly: raw samples -> identification ticks (the first stage of the bank).

Samples are averaged into ``id_period_s`` bins; a tick is emitted at the sample that completes a
bin and carries everything later stages need about the time base, so none of them looks at raw
samples:

* a time step longer than ``gap_s`` is a gap: a tick with ``new_segment`` whose propagation
  current ``i_prev_A`` is 0 (the pack is assumed to have rested; histories restart);
* a step back by more than ``gap_s`` is a restarted time base (a replay from its start, a clock
  set back): a new segment with nothing propagated across it (``dt_s`` = 0);
* any other non-increasing time is dropped and counted;
* a NaN current holds the previous current; a NaN voltage is left out of its cell's bin mean
  (``ok`` False when a cell has no valid voltage in the bin);
* SOC is coulomb-counted at the raw rate: the tick lists the raw (current, interval) steps since
  the previous tick, which the state stage applies in order (Eq. 2).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from functools import lru_cache
from typing import Any

import numpy as np
import numpy.typing as npt
from numpy._core.multiarray import count_nonzero as nnz  # np.count_nonzero less its dispatch

from bmsid.estimate.statedict import load_arrays
from bmsid.estimate.tuning import EstimatorTuning

FloatArray = npt.NDArray[np.float64]
BoolArray = npt.NDArray[np.bool_]


@dataclass(slots=True)  # not frozen: built every tick, and frozen init costs ~3 us here
class Tick:
    """One identification tick (times s, currents A with + = discharge, voltages V).

    Attributes:
        t_s: time of the sample that completed the tick.
        current_A: mean pack current over the bin.
        i_prev_A: current held since the previous tick (what the ZOH propagation uses; 0 over
            a gap).
        dt_s: time since the previous tick (0 at the first sample and after a time jump back).
        period_s: nominal tick period (running mean of the tick steps, >= ``id_period_s``).
        v_V: per-cell mean voltage over the bin, NaN where no valid voltage, shape (n,).
        ok: cells with a valid voltage in the bin, shape (n,).
        coulomb_steps: the raw (held current A, interval s) steps since the previous tick, in
            order (plain floats: usually one or a few, cheaper than arrays).
        current_std_A: running RMS variation of the current (time constant
            ``excitation_window_s``): the excitation measure.
        temperature_C: mean pack temperature over the bin, degC (NaN: none measured).
        first: the first sample of the run (SOC starts here).
        new_segment: histories restart here (first sample, gap, time jump).
    """

    t_s: float
    current_A: float
    i_prev_A: float
    dt_s: float
    period_s: float
    v_V: FloatArray
    ok: BoolArray
    coulomb_steps: tuple[tuple[float, float], ...]
    current_std_A: float
    temperature_C: float
    first: bool
    new_segment: bool

    def remove_offset(self, b_A: float) -> None:
        """Measured current -> true current, ``b_A`` the sensor's offset (A); in place (the
        tick is rebuilt every tick). Over a gap the pack is assumed at rest: ``i_prev_A`` 0."""
        if b_A == 0.0:
            return
        self.current_A -= b_A
        if not (self.new_segment and not self.first):
            self.i_prev_A -= b_A
        self.coulomb_steps = tuple((i - b_A, dt) for i, dt in self.coulomb_steps)


class TickAssembler:
    """Bins raw samples into ticks; owns the raw and tick clocks and the excitation measure."""

    name = "ticks"

    def __init__(self, n_cells: int, tuning: EstimatorTuning) -> None:
        self.n = n_cells
        self.tuning = tuning
        self.counters: dict[str, int] = {
            "samples": 0,
            "ticks": 0,
            "non_increasing_time": 0,
            "time_jumps_back": 0,
            "nan_current": 0,
            "nan_voltage": 0,
            "gaps": 0,
        }
        self.t_raw: float | None = None
        self.i_raw = 0.0
        self.t_tick = 0.0
        self.i_tick = 0.0
        self.bin_i = 0.0
        self.bin_n = 0
        self.bin_v = np.zeros(n_cells)
        self.bin_vn = np.zeros(n_cells, dtype=np.int64)
        self.i_mean = 0.0
        self.i_var = 0.0
        self.dt_nom = 0.0
        self.bin_T = 0.0
        self.bin_Tn = 0
        self._steps: list[tuple[float, float]] = []  # the raw (current, interval) steps

    @property
    def period_s(self) -> float:
        """Nominal time between ticks, s (ticks are ``id_period_s`` apart or more)."""
        return max(self.dt_nom, self.tuning.id_period_s)

    def push(
        self, t_s: float, current_A: float, v: FloatArray, temperature_C: float = math.nan
    ) -> Tick | None:
        """One raw sample (s, A, V of shape (n,), pack temperature degC or NaN); the tick it
        completes, else None."""
        tun = self.tuning
        self.counters["samples"] += 1
        if not math.isfinite(t_s):
            self.counters["non_increasing_time"] += 1
            return None
        if not math.isfinite(current_A):
            self.counters["nan_current"] += 1
            current_A = self.i_raw
        good = np.isfinite(v)  # the cells with a voltage: each tick's own new array
        n_bad = self.n - int(nnz(good))
        v_raw = v
        if n_bad:
            self.counters["nan_voltage"] += n_bad
            v = np.where(good, v, 0.0)  # summed into the bin, excluded by the count
        if self.t_raw is None:
            self.t_raw = t_s
            self.i_raw = current_A
            self.t_tick = t_s
            self.i_tick = current_A
            return self._tick(
                t_s, current_A, v_raw, good, 0.0, first=True, new_segment=True,
                temperature_C=temperature_C,
            )  # fmt: skip
        dt = t_s - self.t_raw
        if dt < -tun.gap_s:
            self.counters["time_jumps_back"] += 1
            return self._gap(t_s, current_A, v_raw, good, 0.0, temperature_C)
        if dt <= 0:
            self.counters["non_increasing_time"] += 1
            return None
        if dt > tun.gap_s:
            return self._gap(t_s, current_A, v_raw, good, t_s - self.t_tick, temperature_C)
        self._steps.append((self.i_raw, dt))
        self.t_raw = t_s
        self.i_raw = current_A
        self.bin_i += current_A
        self.bin_n += 1
        if not math.isnan(temperature_C):
            self.bin_T += temperature_C
            self.bin_Tn += 1
        if t_s - self.t_tick < tun.id_period_s - 0.5 * dt:
            self.bin_v += v
            self.bin_vn += good
            return None
        if self.bin_n == 1 and not n_bad:
            # A bin of one sample with every voltage (the usual 1 s record): the mean below is
            # (0 + v) / 1, i.e. v + 0.0, without the bin arrays (they stay zero)
            has_v = good
            v_avg = v + 0.0
        else:
            self.bin_v += v
            self.bin_vn += good
            has_v = self.bin_vn > 0
            v_avg = np.where(has_v, self.bin_v / np.maximum(self.bin_vn, 1), np.nan)
            self.bin_v[:] = 0.0
            self.bin_vn[:] = 0
        i_avg = self.bin_i / self.bin_n
        dt_tick = t_s - self.t_tick
        temp = self.bin_T / self.bin_Tn if self.bin_Tn else math.nan
        self.bin_i = 0.0
        self.bin_n = 0
        self.bin_T = 0.0
        self.bin_Tn = 0
        return self._tick(
            t_s, i_avg, v_avg, has_v, dt_tick, first=False, new_segment=False, temperature_C=temp
        )

    def _clear_bin(self) -> None:
        self.bin_i = 0.0
        self.bin_n = 0
        self.bin_T = 0.0
        self.bin_Tn = 0
        self.bin_v[:] = 0.0
        self.bin_vn[:] = 0

    def _gap(
        self,
        t_s: float,
        current_A: float,
        v: FloatArray,
        ok: BoolArray,
        elapsed_s: float,
        temperature_C: float,
    ) -> Tick:
        """A new segment after ``elapsed_s`` of unknown current (assumed rest)."""
        self.counters["gaps"] += 1
        self._clear_bin()  # the raw steps before the gap still count: they go with this tick
        self.t_raw = t_s
        self.i_raw = current_A
        self.i_tick = 0.0  # unknown current during the gap: assume the pack rested
        return self._tick(
            t_s, current_A, v, ok, elapsed_s, first=False, new_segment=True,
            temperature_C=temperature_C,
        )  # fmt: skip

    def _tick(
        self,
        t: float,
        i: float,
        v: FloatArray,
        ok: BoolArray,
        dt: float,
        *,
        first: bool,
        new_segment: bool,
        temperature_C: float,
    ) -> Tick:
        tun = self.tuning
        self.counters["ticks"] += 1
        if 0 < dt <= tun.gap_s:
            self.dt_nom = dt if self.dt_nom == 0.0 else self.dt_nom + 0.05 * (dt - self.dt_nom)
        # Excitation: running variance of the current (time constant excitation_window_s).
        g = _excitation_gain(dt, tun.excitation_window_s) if dt > 0 else 0.0
        self.i_mean += g * (i - self.i_mean)
        self.i_var += g * ((i - self.i_mean) ** 2 - self.i_var)
        steps = tuple(self._steps)
        self._steps.clear()
        tick = Tick(
            t_s=t,
            current_A=i,
            i_prev_A=self.i_tick,
            dt_s=dt,
            period_s=self.period_s,
            v_V=v,
            ok=ok,
            coulomb_steps=steps,
            current_std_A=math.sqrt(self.i_var) if self.i_var >= 0 else math.nan,
            temperature_C=temperature_C,
            first=first,
            new_segment=new_segment,
        )
        self.t_tick = t
        self.i_tick = i
        return tick

    # ------------------------------------------------------------------ checkpoints
    _ARRAYS = ("bin_v", "bin_vn")
    _SCALARS = (
        "t_raw", "i_raw", "t_tick", "i_tick", "bin_i", "bin_n", "i_mean", "i_var", "dt_nom",
        "bin_T", "bin_Tn",
    )  # fmt: skip

    def state_dict(self) -> dict[str, Any]:
        st: dict[str, Any] = {k: getattr(self, k).copy() for k in self._ARRAYS}
        st.update({k: getattr(self, k) for k in self._SCALARS})
        st["steps_i"] = np.array([i for i, _ in self._steps])
        st["steps_dt"] = np.array([dt for _, dt in self._steps])
        return st

    def load_state_dict(self, st: dict[str, Any]) -> None:
        load_arrays(self, st, self._ARRAYS, self.name)
        for k in self._SCALARS:
            if k != "t_raw":  # the temperature bin came later: 0 in older checkpoints
                setattr(self, k, float(st.get(k, 0.0) if k in ("bin_T", "bin_Tn") else st[k]))
        self.t_raw = None if st["t_raw"] is None else float(st["t_raw"])
        self.bin_n = int(st["bin_n"])
        self.bin_Tn = int(self.bin_Tn)
        steps_i = [float(x) for x in np.asarray(st.get("steps_i", []), dtype=float)]
        steps_dt = [float(x) for x in np.asarray(st.get("steps_dt", []), dtype=float)]
        self._steps = list(zip(steps_i, steps_dt, strict=True))


@lru_cache(maxsize=64)
def _excitation_gain(dt_s: float, window_s: float) -> float:
    """The excitation EWMA's gain over a tick of ``dt_s`` > 0 s (the same few steps again: once
    each; numpy's exp, as the running moments always had, as a Python float: the moments' few
    operations a tick then cost a fifth, the same IEEE operations, the same bits)."""
    return float(1.0 - np.exp(-dt_s / window_s))
