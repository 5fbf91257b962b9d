"""Start values and bounds of the parameters from the record itself, not from a rule of thumb.

A capacity rule (R0 ~ 0.1 ohm Ah / Q) is off by 5x on real cells (48 mOhm for a 2 Ah LFP cell
whose R0 is 10 mOhm) and the estimators start their first minutes far away; bounds set around
such a guess are either too tight for the real cell or so wide (0.5 ohm) that the first
transient runs to them. What the record says is better:

* R0 (Eq. 9): the instantaneous voltage response to a current step, ``-dV/dI`` over one sample
  (the RC branches cannot move in dt << tau1); the median over every step of the record's
  first hours (robust to the few steps that coincide with a voltage glitch);
* R1, R2: half of R0 each (a DC resistance of about twice R0 over tens of minutes, typical of
  Li-ion cells at room temperature), refined by the estimators within seconds to minutes;
* bounds relative to the measured R0: R0 within 4x either way (0 C doubles it, ageing adds
  50-100 %), R1 and R2 from 1 % of R0 up to 2x and 3x R0; the fast time constant at least two
  tick periods (a faster branch is indistinguishable from R0 at that rate) and the slow one at
  most the swarm window (a slower one is collinear with an OCV offset there).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

FloatArray = npt.NDArray[np.float64]

#: A step is a current change of at least this share of the record's 95th-percentile |I|.
STEP_SHARE = 0.1
#: ... and at least this many amperes (sensor noise of a few mA must not count as a step).
MIN_STEP_A = 0.05
#: Steps over a longer sample interval are not instantaneous: the RC branches move.
MAX_STEP_DT_S = 2.0
#: Samples closer than this are thinned to about this spacing before differencing: at 100 Hz a
#: current step ramps over several samples, none of whose differences reaches the threshold.
STEP_SPACING_S = 0.5
#: Fewer steps than this: no estimate (the caller falls back and says so).
MIN_STEPS = 3
#: Only the record's first part is used: start values are needed at the start.
PROBE_S = 4 * 3600.0

#: Bound factors around the measured R0 (see the module docstring).
R0_FACTOR = 4.0
RC_LO_SHARE = 0.01
R1_HI_SHARE = 2.0
R2_HI_SHARE = 3.0
TAU1_MIN_TICKS = 2.0


@dataclass(frozen=True)
class StartValues:
    """Start values (ohm, s) and how they were found."""

    R0_ohm: float
    R1_ohm: float
    tau1_s: float
    R2_ohm: float
    tau2_s: float
    n_steps: int
    source: str

    def bounds(
        self, tick_period_s: float, window_s: float, defaults: dict[str, tuple[float, float]]
    ) -> dict[str, tuple[float, float]]:
        """Bounds (lo, hi) per parameter around these values; ``defaults`` gives the time
        constants' outer limits and the non-resistive entries (M scale, OCV offset)."""
        r0 = self.R0_ohm
        t1_lo, t1_hi = defaults["tau1_s"]
        t2_lo, t2_hi = defaults["tau2_s"]
        t1_lo = max(t1_lo, TAU1_MIN_TICKS * tick_period_s)
        t2_hi = max(min(t2_hi, window_s), 4.0 * t2_lo)
        return {
            **defaults,
            "R0_ohm": (r0 / R0_FACTOR, r0 * R0_FACTOR),
            "R1_ohm": (r0 * RC_LO_SHARE, r0 * R1_HI_SHARE),
            "R2_ohm": (r0 * RC_LO_SHARE, r0 * R2_HI_SHARE),
            "tau1_s": (t1_lo, max(t1_hi, 2.0 * t1_lo)),
            "tau2_s": (t2_lo, t2_hi),
        }

    def describe(self) -> str:
        return (
            f"R0 {1e3 * self.R0_ohm:.2f} mOhm ({self.source}), R1 = R2 = R0/2, "
            f"tau1 {self.tau1_s:g} s, tau2 {self.tau2_s:g} s"
        )


def _step_lag(t_s: FloatArray) -> int:
    """Samples per ``STEP_SPACING_S`` at the median interval (<= 1: difference every sample)."""
    dt = np.diff(t_s)
    dt = dt[dt > 0]
    if dt.size == 0:
        return 1
    return round(STEP_SPACING_S / float(np.median(dt)))


def step_resistances(
    t_s: FloatArray, current_A: FloatArray, voltage_V: FloatArray, max_dt_s: float = MAX_STEP_DT_S,
    min_step_A: float = MIN_STEP_A,
) -> FloatArray:  # fmt: skip
    """``-dV/dI`` (ohm) at every current step of one cell's record (Eq. 9 with the branches
    frozen over one sample, or, where that finds too few on samples faster than
    ``STEP_SPACING_S``, over about ``STEP_SPACING_S``); NaN samples and steps over long
    intervals are left out. A step moves the current by ``STEP_SHARE`` of its 95th percentile
    and at least ``min_step_A`` (A)."""
    t, i, v = (np.asarray(x, dtype=np.float64) for x in (t_s, current_A, voltage_V))
    ok = np.isfinite(t) & np.isfinite(i) & np.isfinite(v)
    t, i, v = t[ok], i[ok], v[ok]
    if t.shape[0] < 2:
        return np.zeros(0)
    keep = t - t[0] <= PROBE_S
    t, i, v = t[keep], i[keep], v[keep]
    big = max(STEP_SHARE * float(np.percentile(np.abs(i), 95)), min_step_A)
    r = _steps(t, i, v, big, max_dt_s)
    k = _step_lag(t)
    if r.shape[0] < MIN_STEPS and k > 1:
        # fast samples whose steps ramp over several (100 Hz): every k-th, so a step lies
        # within one difference. Only then: a record whose time unit is not seconds yet
        # (hours read as seconds, for the time-unit check) keeps its one-sample steps.
        r = _steps(t[::k], i[::k], v[::k], big, max_dt_s)
    return r


def _steps(t: FloatArray, i: FloatArray, v: FloatArray, big: float, max_dt_s: float) -> FloatArray:
    """``-dV/dI`` (ohm) where the current moves by ``big`` (A) or more between samples."""
    di, dv, dt = np.diff(i), np.diff(v), np.diff(t)
    step = (np.abs(di) >= big) & (dt > 0) & (dt <= max_dt_s)
    r = -dv[step] / di[step]
    return np.asarray(r[np.isfinite(r) & (r > 0)], dtype=np.float64)


def median_step_resistance(
    t_s: FloatArray, current_A: FloatArray, voltage_V: FloatArray
) -> float | None:
    """R0 (ohm) as the start values measure it: the median of :func:`step_resistances` over one
    voltage series (a cell, or a pack's mean); None when the series holds no current step."""
    r = step_resistances(t_s, current_A, voltage_V)
    return float(np.median(r)) if r.size else None


def start_values_from_record(
    t_s: FloatArray, current_A: FloatArray, voltages_V: FloatArray,
    min_step_A: float = MIN_STEP_A,
) -> StartValues | None:  # fmt: skip
    """Start values from a record (time s, current A + = discharge, voltages V of shape (n,)
    or (n, n_cells), pooled over the cells that read a voltage: a cell absent from the bus
    must not hold every other's start back); None when it holds fewer than ``MIN_STEPS``
    current steps of at least ``min_step_A`` (A; ``min_step_for``)."""
    v = np.asarray(voltages_V, dtype=np.float64)
    v = v[:, None] if v.ndim == 1 else v
    present = [c for c in range(v.shape[1]) if np.isfinite(v[:, c]).any()]
    rs = [step_resistances(t_s, current_A, v[:, c], min_step_A=min_step_A) for c in present]
    r = np.concatenate(rs) if rs else np.zeros(0)
    n = min((x.shape[0] for x in rs), default=0)
    if n < MIN_STEPS:
        return None
    r0 = float(np.median(r))
    return StartValues(
        R0_ohm=r0,
        R1_ohm=0.5 * r0,
        tau1_s=10.0,
        R2_ohm=0.5 * r0,
        tau2_s=300.0,
        n_steps=n,
        source=f"median -dV/dI over {n} current steps of the record",
    )


def min_step_for(capacity_Ah: float, excitation_C: float) -> float:
    """The smallest current step (A) that measures R0: the excitation threshold (C-rate x
    capacity), at least ``MIN_STEP_A``. Below it a step is sensor noise, which through a
    rested head's own 95th percentile counted: a gateway started at rest took 0.05 A of
    noise against 1 mV of voltage noise as steps of 17 mOhm (truth 0.8) and published R0 at
    5-8x the truth for the whole run."""
    return max(MIN_STEP_A, excitation_C * capacity_Ah)


#: Measured and configured R0 this many times apart: the config is not the pack's cells' (a
#: 2 Ah cell under the 70 Ah default: 60x); temperature alone moves R0 by 2-5x.
R0_MISFIT_FACTOR = 10.0


def r0_misfit(found: StartValues, config_r0_ohm: float) -> str | None:
    """Why a cell config does not fit the cells measured (``found``: their step resistance)
    when that R0 and the config's start R0 are ``R0_MISFIT_FACTOR`` or more apart, else None.
    A pack of 2 Ah cells run with the default 70 Ah cell (R0 73 against 1.2 mOhm) published
    wrong SOC and parameters for hours, and nothing said why (a sweep)."""
    ratio = found.R0_ohm / config_r0_ohm if config_r0_ohm > 0 else math.inf
    if 1.0 / R0_MISFIT_FACTOR < ratio < R0_MISFIT_FACTOR:
        return None
    return (
        f"the cells measure R0 {1e3 * found.R0_ohm:.4g} mOhm over {found.n_steps} current "
        f"steps, {ratio:.3g}x the cell config's start value {1e3 * config_r0_ohm:.4g} mOhm: is "
        "the cell config this pack's? (its capacity, OCV and bounds drive SOC and every "
        "parameter; bmsid fit-ocv makes one)"
    )
