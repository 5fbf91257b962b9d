"""Is a recording what it claims to be? Checks run on the arrays before they are identified.

Each check is a pure function over columns (time s, current A with + = discharge, cell voltages
V) and plain numbers, returning :class:`Finding` values (level, a stable code, one line of
text). Nothing here reads files or prints: ``bmsid identify`` prints the findings and turns the
first error into a ``UserError``; the daemon can run the same checks on its sample blocks.

Levels: ``error`` where identifying would give garbage (time in milliseconds, a flipped current
sign), ``warning`` where the result is only doubtful (a capacity that does not fit the record,
too little excitation for the capacity, an assumed cell).

Evidence used:

- **time unit**: a record logged in ms has a median step of 10-1000 "s" with a current that
  changes at most steps (no tester logs a drive cycle every 1000 s), and a coulomb count in
  seconds that moves many times the capacity while in ms it moves a plausible share of it;
- **current sign**: at a current step the voltage answers at once through R0, against the step
  when positive = discharge (U = OCV - R0 I - ...); so voltage steps correlate negatively with
  current steps, and a strong positive correlation means the sign is flipped;
- **capacity**: no cell moves more than its capacity (within ageing and efficiency, 25 %) in
  one direction; the engine's excitation threshold is ``excitation_C`` times the capacity, so a
  capacity far too large leaves every tick "poorly excited" and the swarm never runs;
- **capacity from the record**: a discharge from full (at rest) to empty (at a cut-off) moves
  the capacity (a lower bound: a cut-off under load leaves some charge in the cell).
"""

from __future__ import annotations

import math
from collections.abc import Callable, Iterable, Sequence
from dataclasses import dataclass
from typing import Literal

import numpy as np
import numpy.typing as npt

from bmsid.estimate.observer_tuning import ObserverTuning
from bmsid.estimate.rest_anchor import noise_std_A
from bmsid.estimate.start_relaxation import NOISE_FLOOR_V, slope_from_sums
from bmsid.estimate.startvalues import median_step_resistance
from bmsid.gates import GateConfig

FloatArray = npt.NDArray[np.float64]
Level = Literal["error", "warning"]

#: The engine's gap threshold (``EstimatorTuning.gap_s``), s: the coulomb count assumes rest
#: over longer steps, as the engine does.
GAP_S = 30.0

# Time unit: a median step this long (in the file's unit) with a current that changes at
# DYNAMIC_SHARE of the steps or more (a drive cycle's steps, not a constant-current OCV test) is a
# record in ms; so is a coulomb count that in seconds moves more than MS_CAPACITY_RATIO
# capacities and in ms a plausible share of one (MS_PLAUSIBLE_LO..HI).
MS_MEDIAN_STEP = 100.0
MS_MEDIAN_STEP_WITH_CAPACITY = 10.0
DYNAMIC_SHARE = 0.02
MS_CAPACITY_RATIO = 3.0
MS_PLAUSIBLE_LO, MS_PLAUSIBLE_HI = 0.05, 1.5

# Current sign: steps of at least STEP_SHARE of the peak current, within SIGN_MAX_DT_S of each
# other (the R0 response is immediate; OCV drift over long steps would blur it).
STEP_SHARE = 0.05
SIGN_MAX_DT_S = 60.0
SIGN_ERROR_CORR, SIGN_ERROR_MIN_STEPS = 0.5, 10
SIGN_WARN_CORR, SIGN_WARN_MIN_STEPS = 0.2, 5

# Capacity: one-direction charge beyond this many capacities (a configured capacity; an assumed
# one is checked at 1x), and below TINY_SHARE of an assumed capacity with peaks below
# TINY_PEAK_C (a short record of the right cell moves little but still peaks at its C-rate).
CAPACITY_SLACK = 1.25
#: A current-sensor offset the capacity check allows for, C-rate (the SOC observer's prior,
#: ``ObserverTuning.offset_prior_C``: 1 % of 1C, a plain Hall sensor).
OFFSET_C = float(ObserverTuning.model_fields["offset_prior_C"].default)
TINY_SHARE = 0.05
TINY_PEAK_C = 0.5
EXCITED_SHARE_MIN = 0.05

# SOC by coulomb count further than this outside [0, 1] (fraction).
SOC_SLACK = 0.1

# Full and empty, for a capacity read off the record: rested voltages of a full Li-ion cell
# (NMC/NCA/LCO >= 4.1 V; LFP on its flat plateau, 3.40-3.65 V) and cut-offs under load.
FULL_NMC_V, EMPTY_NMC_V = 4.1, 3.0
FULL_LFP_V, LFP_MAX_V, EMPTY_LFP_V = 3.40, 3.65, 2.7
LFP_PLATEAU_SPAN_V = 0.15
REST_SHARE = 0.05
# A capacity read off a discharge from part-charged: its start SOC at least this (the charge is
# divided by it), the start under at most this share of the peak current.
PARTIAL_START_SOC_MIN = 0.3
#: A loaded start is IR-corrected (v + R0 I) when the correction moves the SOC the OCV reads by
#: at most this (fraction): R0 is measured within a few tens of percent, so the start SOC stays
#: within a few points (a CALCE DST record opening at C/4 corrects by 3 points).
LOADED_START_SOC_SHIFT = 0.1
# Capacity from the SOC change (no cut-off in the record): at least SOC_CHANGE_MIN_POINTS rest
# ends spanning SOC_CHANGE_MIN_SPAN of SOC (fraction) on the assumed OCV, each read off strictly
# inside the curve's range (a voltage beyond its ends is clamped to them and tells no SOC).
SOC_CHANGE_MIN_POINTS = 3
SOC_CHANGE_MIN_SPAN = 0.3


@dataclass(frozen=True)
class Finding:
    """One result of a check: ``level``, a stable ``code`` (for metrics.json) and one line."""

    level: Level
    code: str
    message: str

    def line(self) -> str:
        """The line to print: ``WARNING: ...`` or ``ERROR: ...``."""
        return f"{self.level.upper()}: {self.message}"

    def as_dict(self) -> dict[str, str]:
        return {"level": self.level, "code": self.code, "message": self.message}


def first_error(findings: Iterable[Finding]) -> Finding | None:
    """The first finding of level ``error``, if any."""
    return next((f for f in findings if f.level == "error"), None)


#: The checks before a run look at the record's first samples only, so that their memory does
#: not grow with the record: two days at 1 s, fewer for packs of more than 20 cells (at most
#: 4 M values of time, current and voltages). A shorter record is checked whole.
CHECK_HEAD_SAMPLES = 172_800
CHECK_HEAD_VALUES = 4_000_000


def check_head_samples(n_cells: int) -> int:
    """Samples of a record of ``n_cells`` cells that the checks before a run look at."""
    return min(CHECK_HEAD_SAMPLES, CHECK_HEAD_VALUES // (n_cells + 2))


# ----------------------------------------------------------------------------- time base
@dataclass(frozen=True)
class SamplePeriod:
    """The time base of a record: median step (s) and steps longer than ``gap_s`` (gaps)."""

    median_dt_s: float
    n_gaps: int
    gap_s: float = GAP_S

    def text(self) -> str:
        """``median dt 1 s, 0 gaps > 30 s``."""
        dt = "n/a" if math.isnan(self.median_dt_s) else f"{self.median_dt_s:.4g} s"
        return f"median dt {dt}, {self.n_gaps} gap(s) > {self.gap_s:g} s"


def sample_period(t_s: FloatArray, gap_s: float = GAP_S) -> SamplePeriod:
    """Median forward step (s; NaN with fewer than 2 samples) and the number of gaps."""
    dt = np.diff(np.asarray(t_s, dtype=np.float64))
    fwd = dt[dt > 0]
    med = float(np.median(fwd)) if fwd.size else math.nan
    return SamplePeriod(median_dt_s=med, n_gaps=int(np.count_nonzero(dt > gap_s)), gap_s=gap_s)


def coulomb_Ah(t_s: FloatArray, current_A: FloatArray, gap_s: float | None = GAP_S) -> FloatArray:
    """Discharged charge since the first sample, Ah (+ = discharge), shape (n,).

    Each sample's current is held until the next sample (as the engine counts); over a step
    longer than ``gap_s`` the cell is taken to rest (None: no gap rule).
    """
    t = np.asarray(t_s, dtype=np.float64)
    i = held(np.asarray(current_A, dtype=np.float64), 0.0)
    dt = np.clip(np.diff(t), 0.0, None)
    if gap_s is not None:
        dt = np.where(dt > gap_s, 0.0, dt)
    return np.concatenate([[0.0], np.cumsum(i[:-1] * dt)]) / 3600.0


def held(x: FloatArray, before: float = math.nan) -> FloatArray:
    """``x`` (n,) with each NaN replaced by the last finite value before it (``before`` ahead
    of the first): a refused or missing current is held, as the engine holds it (``ticks.py``;
    it starts from 0 A), and a refused voltage stays the last accepted one."""
    x = np.asarray(x, dtype=np.float64)
    ok = np.isfinite(x)
    if ok.all():
        return x
    last = np.maximum.accumulate(np.where(ok, np.arange(x.shape[0]), -1))
    return np.where(last >= 0, x[np.maximum(last, 0)], before)


def cell_mean_min(voltages_V: FloatArray) -> tuple[FloatArray, FloatArray]:
    """Per sample the mean and the minimum (V) over the cells with a finite reading (a refused
    or dead channel, NaN, is left out, never read as a cut-off); a sample without any holds the
    previous sample's values (NaN before the first)."""
    v = np.asarray(voltages_V, dtype=np.float64)
    v = v[:, None] if v.ndim == 1 else v
    fin = np.isfinite(v)
    n = fin.sum(axis=1)
    mean = np.where(n > 0, np.where(fin, v, 0.0).sum(axis=1) / np.maximum(n, 1), np.nan)
    low = np.where(fin, v, np.inf).min(axis=1)
    return held(mean), held(np.where(n > 0, low, np.nan))


@dataclass(frozen=True)
class Excursion:
    """The largest one-direction charge movement: ``charge_Ah`` (> 0) from sample ``start`` to
    ``end``; ``direction`` is ``discharge`` or ``charge``."""

    charge_Ah: float
    start: int
    end: int
    direction: Literal["discharge", "charge"]


def widest_excursion(t_s: FloatArray, current_A: FloatArray, gap_s: float) -> Excursion:
    """:func:`max_excursion` of the coulomb count within each stretch between gaps longer than
    ``gap_s`` (what the pack did in a gap is unknown: a recharge there is not in the count), the
    widest of them (indices into the whole record)."""
    t = np.asarray(t_s, dtype=np.float64)
    q = coulomb_Ah(t, current_A, gap_s)
    cuts = np.flatnonzero(np.diff(t) > gap_s) + 1
    best = Excursion(0.0, 0, 0, "discharge")
    for a, b in zip([0, *cuts.tolist()], [*cuts.tolist(), t.size], strict=True):
        ex = max_excursion(q[a:b])
        if ex.charge_Ah > best.charge_Ah:
            best = Excursion(ex.charge_Ah, a + ex.start, a + ex.end, ex.direction)
    return best


def max_excursion(q_Ah: FloatArray) -> Excursion:
    """The widest swing of a cumulative charge (Ah): max over a <= b of |q[b] - q[a]|."""
    q = np.asarray(q_Ah, dtype=np.float64)
    lo = np.minimum.accumulate(q)
    hi = np.maximum.accumulate(q)
    b_dis = int(np.argmax(q - lo))
    b_chg = int(np.argmax(hi - q))
    dis = float(q[b_dis] - lo[b_dis])
    chg = float(hi[b_chg] - q[b_chg])
    if dis >= chg:
        a = int(np.argmin(q[: b_dis + 1]))
        return Excursion(dis, a, b_dis, "discharge")
    a = int(np.argmax(q[: b_chg + 1]))
    return Excursion(chg, a, b_chg, "charge")


#: A typical current (95th percentile of |I|) beyond this many C is no cell's (the input gates'
#: ``GateConfig.i_max_C``); within it in milliamps, the column is in milliamps.
I_MAX_C = float(GateConfig.model_fields["i_max_C"].default)


def _current_in_milliamps(current_A: FloatArray, capacity_Ah: float | None) -> Finding | None:
    """An error when the current reads as no cell's in A but as a plausible one in mA (a
    2 Ah cell's 0.2 C in mA read as 37 C: the run refused every sample, and the time-unit
    check took the 1000x coulomb count for milliseconds)."""
    fin = np.abs(current_A[np.isfinite(current_A)])
    if not (capacity_Ah and capacity_Ah > 0) or fin.size == 0:
        return None
    c_rate = float(np.percentile(fin, 95)) / capacity_Ah
    if not (c_rate > I_MAX_C and 1e-3 * c_rate <= I_MAX_C):
        return None
    return Finding(
        "error",
        "current_unit_mA",
        f"current_A looks like milliamps: its 95th percentile, {c_rate * capacity_Ah:.4g}, "
        f"would be {c_rate:.0f} C of a {capacity_Ah:g} Ah cell, beyond the {I_MAX_C:g} C any "
        "cell sustains: give it in amperes, e.g. --columns current_A=NAME*0.001 (NAME: its "
        "column), or check the capacity",
    )


def current_change_share(current_A: FloatArray) -> float:
    """Share of the steps at which the current moves by more than 2 % of its span."""
    i = np.asarray(current_A, dtype=np.float64)
    span = float(np.ptp(i)) if i.size else 0.0
    return float(np.mean(np.abs(np.diff(i)) > 0.02 * span)) if span > 0 and i.size > 1 else 0.0


#: A record sampled slower than this many identification periods whose current moves at
#: COARSE_CHANGE_SHARE of the steps or more changes between its samples too.
COARSE_PERIODS = 2.0
COARSE_CHANGE_SHARE = 0.5


def check_sample_period(
    t_s: FloatArray, current_A: FloatArray, id_period_s: float
) -> list[Finding]:
    """A warning when the samples are coarser than the current's changes: a median step over
    ``COARSE_PERIODS`` identification periods (``id_period_s``) with the current moving at most
    steps. What the current did between two samples is not seen (each is held until the next,
    Eq. 2 and 8), so the step responses the resistances are read from are not the cell's: the
    paper cell's DST sampled at 10 s read R0 +7.5 % and R0+R1+R2 +26 to +36 % (1 s: within 1 %),
    and nothing was said. A constant-current or pulse test logged slowly moves at few steps."""
    t = np.asarray(t_s, dtype=np.float64)
    if t.size < 10:
        return []
    med = sample_period(t).median_dt_s
    share = current_change_share(current_A)
    if not (med > COARSE_PERIODS * id_period_s and share >= COARSE_CHANGE_SHARE):
        return []
    return [
        Finding(
            "warning",
            "coarse_sampling",
            f"samples every {med:.3g} s, and the current changes at {100 * share:.0f} % of them: "
            "what it did between samples is not seen (each value is held until the next), so "
            "the resistances are read off step responses the cell did not make (a DST sampled "
            "at 10 s: R0 +7.5 %, R0+R1+R2 +30 %); log at 1 s or faster for a drive cycle",
        )
    ]


def check_time_unit(
    t_s: FloatArray,
    current_A: FloatArray,
    capacity_Ah: float | None,
    fix: str = "--columns t_s=t_s*0.001",
    gap_s: float = GAP_S,
) -> list[Finding]:
    """An error when ``t_s`` looks like milliseconds, or its steps are longer than ``gap_s``.

    Refused rather than converted: the evidence is a heuristic, a silently rescaled time axis
    changes every time constant, and the fix (``fix``, shown in the message) is one option.
    A median step beyond the engine's gap threshold is an error in any unit: the engine would
    take nearly every step for a gap and assume rest over it (``--tuning gap_s`` says otherwise).
    """
    t = np.asarray(t_s, dtype=np.float64)
    i = np.asarray(current_A, dtype=np.float64)
    if t.size < 3:
        return []
    if (ma := _current_in_milliamps(i, capacity_Ah)) is not None:
        return [ma]  # a count 1000x the capacity is then no evidence of milliseconds
    period = sample_period(t, gap_s)
    med = period.median_dt_s
    if not med >= MS_MEDIAN_STEP_WITH_CAPACITY:
        return []
    changes = current_change_share(i)
    evidence: list[str] = []
    if med >= MS_MEDIAN_STEP and changes >= DYNAMIC_SHARE:
        evidence.append(f"a current that changes at {100 * changes:.0f} % of the steps")
    if capacity_Ah is not None and capacity_Ah > 0:
        moved = max_excursion(coulomb_Ah(t, i, gap_s=None)).charge_Ah
        ratio = moved / capacity_Ah
        if ratio > MS_CAPACITY_RATIO and MS_PLAUSIBLE_LO <= ratio / 1000 <= MS_PLAUSIBLE_HI:
            evidence.append(
                f"a coulomb count in seconds that moves {moved:.4g} Ah of a {capacity_Ah:g} Ah "
                f"cell ({moved / 1000:.3g} Ah in ms)"
            )
    gaps = f"{period.n_gaps} of {t.size - 1} steps are gaps > {gap_s:g} s"
    if evidence:
        return [
            Finding(
                "error",
                "time_unit_ms",
                f"t_s looks like milliseconds (median step {med:g} with "
                f"{' and '.join(evidence)}; {gaps}): give t_s in seconds, e.g. {fix}",
            )
        ]
    if med > gap_s:
        return [
            Finding(
                "error",
                "time_steps_too_long",
                f"the median step of t_s is {med:g} s, longer than the engine's gap threshold "
                f"({gaps}, over which it assumes rest): if t_s is in milliseconds give it in "
                f"seconds (e.g. {fix}), else raise --tuning gap_s",
            )
        ]
    return []


#: Time in minutes or hours: the capacity a record implies (the charge it moves over the SOC
#: change its voltages read) makes its currents (95th percentile of |I|, robust to glitches)
#: exceed this many C, the input gates' plausible C-rate (``GateConfig.i_max_C``); the factors
#: tried are minutes and hours, the smaller one that brings the currents within it is named.
SLOW_UNIT_FACTORS = ((60.0, "minutes"), (3600.0, "hours"))


#: A given capacity this many times above or below the one the record's own voltages imply
#: (a cut-off reached, or the SOC change its rests read) is worth a warning: a cell of another
#: size, or mAh typed as Ah (1000x); closer than this, the reading (a cut-off under load, an OCV
#: curve that is not the cell's) cannot tell.
CAPACITY_MISMATCH = 3.0


def mismatch_ratio(given: float, measured: float, factor: float) -> float | None:
    """``given / measured`` where it lies more than ``factor`` times off 1 either way; None
    where it does not, or where either is not positive (nothing to compare)."""
    if not (given > 0 and measured > 0):
        return None
    ratio = given / measured
    return None if 1.0 / factor <= ratio <= factor else ratio


def check_capacity_given(
    est: CapacityEstimate | None, capacity_Ah: float, source: str
) -> list[Finding]:
    """A warning when ``capacity_Ah`` (from ``source``: the cell config, --capacity-ah) is
    :data:`CAPACITY_MISMATCH` times off the capacity the record implies (``est``)."""
    if est is None:
        return []
    ratio = mismatch_ratio(capacity_Ah, est.capacity_Ah, CAPACITY_MISMATCH)
    if ratio is None:
        return []
    how = (
        f"it moves {est.capacity_Ah * est.start_soc:.3g} Ah from {100 * est.start_soc:.0f} % "
        f"SOC to the cut-off ({est.v_empty_V:.3g} V)"
        if est.n_rests == 0
        else f"it moves charge over {100 * est.soc_span:.0f} % of SOC between its rests"
    )
    return [
        Finding(
            "warning",
            "capacity_mismatch",
            f"the capacity {capacity_Ah:g} Ah ({source}) is {ratio:.3g}x what the record implies "
            f"({est.capacity_Ah:.3g} Ah: {how}): SOC and every parameter fitted with it will be "
            "wrong; check the capacity (Ah, not mAh) and the current's unit",
        )
    ]


def check_cell_fit(est: CapacityEstimate | None, chemistry: str, name: str) -> list[Finding]:
    """A warning when the record's discharge to the cut-off reads as another chemistry than the
    cell config's (an LFP record run on an NMC config gave 129 mV and a 61.7 % consistency error
    in ``compare`` without a word). A capacity from the SOC change names no chemistry of its
    own (it is read on the config's curve)."""
    if est is None or est.n_rests or chemistry not in ("NMC", "LFP") or est.chemistry == chemistry:
        return []
    return [
        Finding(
            "warning",
            "cell_mismatch",
            f"the record does not fit the cell config {name!r} ({chemistry}): {est.text()}; "
            f"an {chemistry} OCV cannot follow it: give this cell's config",
        )
    ]


def check_time_compressed(
    t_s: FloatArray,
    current_A: FloatArray,
    est: CapacityEstimate | None,
    i_max_C: float,
    fix: Callable[[float], str],
) -> list[Finding]:
    """An error when ``t_s`` looks like minutes or hours: the capacity read off the record in
    the file's unit (``est``; ``derive_capacity`` or ``capacity_from_soc_change``, which scale
    with the time unit) puts its typical current beyond ``i_max_C`` C. A median step cannot tell
    it (60 Hz CAN logs step by 17 ms, a minute record in minutes by 0.017); a cell that moves
    80 % of its charge in three "seconds" can. Refused like milliseconds (a silently rescaled
    time axis changes every time constant); ``fix(factor)`` is the option that converts."""
    t = np.asarray(t_s, dtype=np.float64)
    if est is None or t.size < 3 or not est.capacity_Ah > 0:
        return []
    i_typ = float(np.percentile(np.abs(np.asarray(current_A, dtype=np.float64)), 95))
    c_rate = i_typ / est.capacity_Ah
    if not c_rate > i_max_C:
        return []
    factor, unit = next(
        ((f, u) for f, u in SLOW_UNIT_FACTORS if c_rate / f <= i_max_C), SLOW_UNIT_FACTORS[-1]
    )
    med = sample_period(t).median_dt_s
    return [
        Finding(
            "error",
            f"time_unit_{unit}",
            f"t_s looks like {unit} (median step {med:.4g}): the record moves "
            f"{est.capacity_Ah * est.start_soc:.3g} Ah over the SOC its voltages read in "
            f"{float(np.ptp(t)):.4g} time units, a {est.capacity_Ah:.3g} Ah cell whose current "
            f"(95th percentile {i_typ:.3g} A) would be {c_rate:.0f} C, beyond the {i_max_C:g} C "
            f"any cell sustains: give t_s in seconds, e.g. {fix(factor)}",
        )
    ]


# ----------------------------------------------------------------------------- current sign
@dataclass(frozen=True)
class SignEvidence:
    """Correlation of voltage steps with current steps (median over cells) and the steps used."""

    corr: float
    n_steps: int


def current_sign_evidence(
    t_s: FloatArray, current_A: FloatArray, voltages_V: FloatArray
) -> SignEvidence:
    """corr(dV, dI) over the record's current steps (see the module docstring); NaN when the
    record has fewer than 3 usable steps. ``voltages_V`` has shape (n,) or (n, cells)."""
    t = np.asarray(t_s, dtype=np.float64)
    i = np.asarray(current_A, dtype=np.float64)
    v = np.asarray(voltages_V, dtype=np.float64)
    v = v[:, None] if v.ndim == 1 else v
    if t.size < 4:
        return SignEvidence(math.nan, 0)
    di = np.diff(i)
    dt = np.diff(t)
    peak = float(np.max(np.abs(i)))
    steps = (np.abs(di) >= STEP_SHARE * peak) & (dt > 0) & (dt <= SIGN_MAX_DT_S) & (peak > 0)
    corrs: list[float] = []
    n_used = 0
    for c in range(v.shape[1]):
        dv = np.diff(v[:, c])
        use = steps & np.isfinite(dv) & np.isfinite(di)
        n = int(np.count_nonzero(use))
        if n < 3 or np.std(dv[use]) == 0 or np.std(di[use]) == 0:
            continue
        corrs.append(float(np.corrcoef(dv[use], di[use])[0, 1]))
        n_used = max(n_used, n)
    if not corrs:
        return SignEvidence(math.nan, 0)
    return SignEvidence(float(np.median(corrs)), n_used)


#: The trend evidence of the sign (a record without current steps: a constant-current test):
#: the voltage must move this much (V, median over cells) ...
SIGN_TREND_MIN_V = 0.2
#: ... and rise with the discharged charge this strongly (correlation) to call the sign flipped.
SIGN_TREND_CORR = 0.8


def current_trend_evidence(t_s: FloatArray, current_A: FloatArray, voltages_V: FloatArray) -> float:
    """Rank corr(V, discharged charge) over the record (median over cells): near -1 when
    positive = discharge (a cell's voltage falls as it is emptied, steps or none), NaN where
    the voltage moves less than ``SIGN_TREND_MIN_V`` or the charge does not move."""
    t = np.asarray(t_s, dtype=np.float64)
    i = np.asarray(current_A, dtype=np.float64)
    v = np.asarray(voltages_V, dtype=np.float64)
    v = v[:, None] if v.ndim == 1 else v
    if t.size < 4:
        return math.nan
    dt = np.diff(t, prepend=t[0])
    q = np.cumsum(np.where(np.isfinite(i), i, 0.0) * dt)
    corrs = []
    for c in range(v.shape[1]):
        ok = np.isfinite(v[:, c])
        if np.count_nonzero(ok) < 4 or np.ptp(v[ok, c]) < SIGN_TREND_MIN_V or np.ptp(q[ok]) == 0:
            continue
        # ranks: the curve is monotonic, not linear (an LFP plateau, then its knee)
        rq, rv = np.argsort(np.argsort(q[ok])), np.argsort(np.argsort(v[ok, c]))
        corrs.append(float(np.corrcoef(rq, rv)[0, 1]))
    return float(np.median(corrs)) if corrs else math.nan


def check_current_sign(
    t_s: FloatArray, current_A: FloatArray, voltages_V: FloatArray, charge_positive: bool = False
) -> list[Finding]:
    """An error (strong evidence) or warning (weak) when voltage steps follow current steps;
    in a record without steps, an error when the voltage rises as the cell is discharged.

    ``charge_positive``: the user already flipped the sign, so the hint is to drop the flag.
    """
    ev = current_sign_evidence(t_s, current_A, voltages_V)
    fix = "drop --charge-positive" if charge_positive else "pass --charge-positive"
    if math.isnan(ev.corr):
        trend = current_trend_evidence(t_s, current_A, voltages_V)
        if not trend >= SIGN_TREND_CORR:
            return []
        return [
            Finding(
                "error",
                "current_sign",
                "current sign looks flipped (the voltage rises as the count says the cell is "
                f"discharged: rank corr(V, discharged charge) = {trend:+.2f}, no current steps to "
                f"tell otherwise): {fix}",
            )
        ]
    stat = f"corr(dV, dI) = {ev.corr:+.2f} over {ev.n_steps} current steps"
    if ev.corr >= SIGN_ERROR_CORR and ev.n_steps >= SIGN_ERROR_MIN_STEPS:
        return [
            Finding(
                "error",
                "current_sign",
                f"current sign looks flipped (voltage rises when the current rises: {stat}): {fix}",
            )
        ]
    if ev.corr >= SIGN_WARN_CORR and ev.n_steps >= SIGN_WARN_MIN_STEPS:
        return [
            Finding(
                "warning",
                "current_sign",
                f"current sign may be flipped ({stat}; with positive = discharge it is "
                f"negative): check it; {fix} if it is",
            )
        ]
    return []


# ----------------------------------------------------------------------------- capacity
def check_capacity(
    t_s: FloatArray,
    current_A: FloatArray,
    capacity_Ah: float,
    *,
    assumed: bool = False,
    gap_s: float = GAP_S,
) -> list[Finding]:
    """Warnings when the record's one-direction charge does not fit ``capacity_Ah``.

    ``assumed``: the capacity is not the user's (no cell config, no ``--capacity-ah``); then a
    record moving more than 1x, or less than ``TINY_SHARE`` of it at low C-rates, is worth a
    line.
    """
    t = np.asarray(t_s, dtype=np.float64)
    i = np.asarray(current_A, dtype=np.float64)
    if t.size < 2 or not capacity_Ah > 0:
        return []
    ex = widest_excursion(t, i, gap_s)
    ratio = ex.charge_Ah / capacity_Ah
    what = "the assumed capacity" if assumed else "the capacity"
    fix = "give --capacity-ah or --cell-config" if assumed else "check the capacity"
    where = f"t = {t[ex.start]:g}..{t[ex.end]:g} s"
    # what a current-sensor offset of OFFSET_C moves over the excursion (2 days at 1 % of C:
    # 0.48 x the capacity), which the SOC observer estimates and removes
    drift = OFFSET_C * (t[ex.end] - t[ex.start]) / 3600.0
    if ratio > (1.0 if assumed else CAPACITY_SLACK) + drift:
        return [
            Finding(
                "warning",
                "capacity_exceeded",
                f"the record moves {ex.charge_Ah:.4g} Ah in one direction ({ex.direction}, "
                f"{where}), {ratio:.2g}x {what} {capacity_Ah:g} Ah: {fix}, the current unit "
                "and the time unit",
            )
        ]
    peak_C = float(np.max(np.abs(i))) / capacity_Ah
    if assumed and ratio < TINY_SHARE and peak_C < TINY_PEAK_C:  # a short record peaks higher
        return [
            Finding(
                "warning",
                "capacity_tiny",
                f"the record moves only {ex.charge_Ah:.3g} Ah ({100 * ratio:.1f} % of the "
                f"assumed {capacity_Ah:g} Ah) with peaks of {peak_C:.2g} C: a smaller cell? "
                f"{fix}",
            )
        ]
    return []


def excited_share(
    t_s: FloatArray,
    current_A: FloatArray,
    capacity_Ah: float,
    excitation_C: float = 0.02,
    window_s: float = 300.0,
) -> tuple[float, float]:
    """Share of samples the engine would call excited, and the peak RMS current variation (A).

    Mirrors the tick assembler's running variance of the current (time constant ``window_s``)
    at the raw rate; a tick is excited when that RMS is at least ``excitation_C x capacity``.
    """
    t = np.asarray(t_s, dtype=np.float64)
    i = np.asarray(current_A, dtype=np.float64)
    n = t.size
    if n == 0:
        return 0.0, 0.0
    g = np.concatenate([[0.0], 1.0 - np.exp(-np.clip(np.diff(t), 0.0, None) / window_s)])
    mean = var = 0.0
    std = np.empty(n)
    # A recursion (the mean enters the variance): ~0.3 us per sample in plain floats.
    for k, (gk, ik) in enumerate(zip(g.tolist(), i.tolist(), strict=True)):
        mean += gk * (ik - mean)
        var += gk * ((ik - mean) ** 2 - var)
        std[k] = math.sqrt(max(var, 0.0))
    threshold = excitation_C * capacity_Ah
    return float(np.mean(std >= threshold)), float(np.max(std))


def check_excitation(
    t_s: FloatArray,
    current_A: FloatArray,
    capacity_Ah: float,
    *,
    excitation_C: float = 0.02,
    window_s: float = 300.0,
    assumed: bool = False,
) -> list[Finding]:
    """A warning when almost no sample passes the engine's excitation threshold, which is
    relative to the capacity (so a capacity far too large starves the estimator)."""
    share, peak = excited_share(t_s, current_A, capacity_Ah, excitation_C, window_s)
    if len(t_s) < 2 or share >= EXCITED_SHARE_MIN:
        return []
    what = "assumed " if assumed else ""
    hint = "; give the cell's capacity (--capacity-ah or --cell-config)" if assumed else ""
    return [
        Finding(
            "warning",
            "poorly_excited",
            f"only {100 * share:.1f} % of the record is excited enough to identify: the "
            f"current's running RMS variation peaks at {peak:.3g} A against a threshold of "
            f"excitation_C {excitation_C:g} x the {what}capacity {capacity_Ah:g} Ah = "
            f"{excitation_C * capacity_Ah:.3g} A (the threshold is relative to the capacity); "
            f"parameters stay near their start values and the swarm may never run, and the "
            f"SOC observer corrects SOC through those start values only after an hour without "
            f"identified parameters (observer.unconverged_wait_s), at rests long enough to "
            f"anchor it before that{hint}",
        )
    ]


#: The leading rest's voltage counts as still relaxing when it moves at least this fast (V/s),
#: by at least ``RELAX_MIN_V`` over the rest, and its fitted rate is ``RELAX_T_MIN`` standard
#: errors from 0 (the residual noise floored at ``RELAX_NOISE_FLOOR_V``, a 1 mV resolution's
#: quantisation: 1 mV / sqrt(12)): a relaxed cell drifts by well under 1 mV a minute.
RELAX_MIN_RATE_V_S = 1e-4
RELAX_MIN_V = 1e-3
RELAX_T_MIN = 5.0
RELAX_NOISE_FLOOR_V = NOISE_FLOOR_V
#: The leading rest is looked at over at most this long, s.
RELAX_LOOK_S = 120.0
#: A first rested voltage this far (V) from the median of the next ``GLITCH_NEXT`` (and 5 of
#: their robust scatter) is a glitch, not the OCV: one reading +50 mV off at the start of an
#: 8-cell record set its cell's SOC 4.8 points high for hours.
GLITCH_MIN_V = 5e-3
GLITCH_NEXT = 10


def _first_glitch(vv: FloatArray) -> FloatArray:
    """Per cell, how far (V) the first voltage of a rest ``vv`` (samples, cells) lies from the
    median of the next ``GLITCH_NEXT``, where that is a glitch; 0 elsewhere."""
    nxt = vv[1 : GLITCH_NEXT + 1]
    if nxt.shape[0] < 3:
        return np.zeros(vv.shape[1])
    med = np.median(nxt, axis=0)
    scatter = np.maximum(1.4826 * np.median(np.abs(nxt - med), axis=0), RELAX_NOISE_FLOOR_V)
    off = vv[0] - med
    return np.where(np.abs(off) > np.maximum(GLITCH_MIN_V, 5.0 * scatter), off, 0.0)


def check_start_relaxation(
    t_s: FloatArray,
    current_A: FloatArray,
    voltages_V: FloatArray,
    capacity_Ah: float,
    r0_ohm: float,
    rest_current_C: float = 0.01,
) -> list[Finding]:
    """A warning when SOC will be read from a first voltage that is still relaxing: the record
    opens at rest but the voltage still moves, so the cell came off a current step moments
    before and the OCV lies beyond it by the relaxation still to come (what the engine cannot
    know from one voltage); or when that first voltage is a glitch (``GLITCH_MIN_V``).
    ``voltages_V`` (samples, cells).

    The rest is the leading run of samples within the engine's rest limit (``rest_current_C``
    x capacity) whose current moves the voltage by at most half of ``RELAX_MIN_V`` through
    ``r0_ohm`` (the cell's start R0): a small current ramping up is not relaxation."""
    t = np.asarray(t_s, dtype=np.float64)
    v = np.asarray(voltages_V, dtype=np.float64).reshape(t.shape[0], -1)
    rest_limit_A = min(rest_current_C * capacity_Ah, 0.5 * RELAX_MIN_V / max(r0_ohm, 1e-9))
    i = np.asarray(current_A, dtype=np.float64)
    rest_limit_A += 3.0 * noise_std_A(i, rest_limit_A)  # the sensor's noise is no load
    busy = np.flatnonzero(~(np.abs(i) <= rest_limit_A))
    n_rest = int(busy[0]) if busy.size else t.shape[0]
    if n_rest < 3:
        return []  # no rest at the start: the engine IR-corrects the first voltage instead
    k = np.flatnonzero(t[:n_rest] - t[0] <= RELAX_LOOK_S)
    tt, vv = t[k], v[k]
    ok = np.isfinite(tt) & np.isfinite(vv).all(axis=1)
    if np.count_nonzero(ok) < 3 or not np.ptp(tt[ok]) > 0:
        return []
    glitch = _first_glitch(vv[ok])
    if np.count_nonzero(glitch):
        c = int(np.argmax(np.abs(glitch)))
        return [
            Finding(
                "warning",
                "start_glitch",
                f"the record's first voltage (cell {c + 1}) lies {1e3 * glitch[c]:+.1f} mV off "
                "the next seconds' at rest, a glitch rather than the OCV: the start SOC and the "
                "RC branches are fitted over the first 20 min instead; give --soc0 when the "
                "start is known",
            )
        ]
    tc = (tt[ok] - tt[ok][0])[:, None]
    dv = vv[ok] - vv[ok][0]
    rate, se = slope_from_sums(  # V/s per cell, least squares, as the engine's start watch
        np.full(dv.shape[1], float(tc.shape[0])), np.full(dv.shape[1], float(tc.sum())),
        dv.sum(axis=0), np.full(dv.shape[1], float((tc**2).sum())), (tc * dv).sum(axis=0),
        (dv**2).sum(axis=0), RELAX_NOISE_FLOOR_V,
    )  # fmt: skip
    t_stat = np.abs(rate) / se
    span_s = float(np.ptp(tt[ok]))
    relaxing = (
        (np.abs(rate) >= RELAX_MIN_RATE_V_S)
        & (np.abs(rate) * span_s >= RELAX_MIN_V)
        & (t_stat >= RELAX_T_MIN)
    )
    if not np.count_nonzero(relaxing):
        return []
    worst = int(np.argmax(np.where(relaxing, np.abs(rate), -1.0)))
    way = "rising: a discharge" if rate[worst] > 0 else "falling: a charge"
    return [
        Finding(
            "warning",
            "start_not_relaxed",
            f"the record opens with {span_s:.0f} s at rest while the voltage still moves "
            f"{1e3 * rate[worst]:+.2f} mV/s ({way} ended just before): the first voltage is "
            "no OCV yet, so the start SOC and the RC branches are fitted over the first 20 min "
            "instead (a CALCE US06 test that opened 3 s after a step at +1.2 mV/s read 77.9 % "
            "for 80 % from its first voltage, 81.8 % fitted); give --soc0 when the start is "
            "known",
        )
    ]


#: A record more than this (K) from the temperature its cell config's OCV was measured at is
#: warned about: NMC's entropic coefficient (0.1-0.4 mV/K) moves the OCV 1-4 mV per 10 K.
OCV_TEMPERATURE_MAX_K = 10.0


def check_ocv_temperature(
    temperature_C: FloatArray | None, ocv_temperature_C: float | None
) -> list[Finding]:
    """A warning when the record's median temperature (degC) lies more than
    ``OCV_TEMPERATURE_MAX_K`` from the OCV test's (the cell config's ``ocv.temperature_C``);
    nothing when either is unknown."""
    if temperature_C is None or ocv_temperature_C is None:
        return []
    temp = np.asarray(temperature_C, dtype=np.float64)
    temp = temp[np.isfinite(temp)]
    if not temp.size:
        return []
    med = float(np.median(temp))
    if abs(med - ocv_temperature_C) <= OCV_TEMPERATURE_MAX_K:
        return []
    return [
        Finding(
            "warning",
            "ocv_temperature",
            f"the record runs at {med:.0f} degC (median of its first samples) and the cell "
            f"config's OCV was measured at {ocv_temperature_C:.0f} degC: the OCV moves with "
            "temperature, so SOC read through it may be points off and its published std too "
            "small (a PyBaMM NMC cell through its 25 degC curve: 2-5 points at -10 and 50 "
            "degC); use a config from an OCV test at this temperature (fit-ocv, one per "
            "temperature)",
        )
    ]


def coulomb_soc(
    t_s: FloatArray,
    current_A: FloatArray,
    capacity_Ah: float,
    soc0: float,
    gap_s: float = GAP_S,
) -> FloatArray:
    """SOC (fraction) by coulomb count from ``soc0``, efficiency 1, unclamped."""
    return soc0 - coulomb_Ah(t_s, current_A, gap_s) / capacity_Ah


def check_soc_range(soc: FloatArray, capacity_Ah: float, start: str) -> list[Finding]:
    """A warning when a coulomb-counted SOC (fraction, any shape) leaves [0, 1] by more than
    ``SOC_SLACK``: a hint at a flipped sign, a wrong capacity or a wrong start (``start`` says
    where the start SOC came from, e.g. ``--soc0``)."""
    z = np.asarray(soc, dtype=np.float64)
    z = z[np.isfinite(z)]
    if z.size == 0:
        return []
    lo, hi = float(np.min(z)), float(np.max(z))
    if lo >= -SOC_SLACK and hi <= 1.0 + SOC_SLACK:
        return []
    return [
        Finding(
            "warning",
            "soc_out_of_range",
            f"SOC by coulomb count from {start} spans {100 * lo:.0f}..{100 * hi:.0f} %: the "
            f"current sign (--charge-positive), the capacity ({capacity_Ah:g} Ah) or the start "
            "SOC is off",
        )
    ]


@dataclass(frozen=True)
class CapacityEstimate:
    """A capacity read off a discharge to the cut-off in the record (Ah, a lower bound: the
    cut-off comes under load). ``start_soc``: the SOC the discharge started from (fraction; 1
    from full, else read off the assumed OCV at the rest it started from, or at ``v_full_V``
    IR-corrected from under a small load of ``start_load_A``)."""

    capacity_Ah: float
    v_full_V: float
    v_empty_V: float
    chemistry: Literal["NMC", "LFP"]
    start_soc: float = 1.0
    start_load_A: float = 0.0
    #: A capacity from the SOC change (:func:`capacity_from_soc_change`): the rest ends used,
    #: the SOC span they cover (fraction) and the polarisation fitted at them (V); 0: none.
    n_rests: int = 0
    soc_span: float = 0.0
    polarisation_V: float = 0.0

    def text(self) -> str:
        if self.n_rests:
            at = (
                f"IR-corrected from under {self.start_load_A:.3g} A"
                if self.start_load_A
                else "at rest"
            )
            return (
                f"no cut-off in the record: the charge moved over the SOC change on the assumed "
                f"OCV, from {100 * self.start_soc:.0f} % ({self.v_full_V:.3f} V {at}) through "
                f"{self.n_rests} rests spanning {100 * self.soc_span:.0f} % of SOC (their "
                f"voltages {1e3 * self.polarisation_V:+.0f} mV of polarisation fitted): an "
                "estimate, give --capacity-ah when the capacity is known"
            )
        if self.start_soc < 1.0:
            at = (
                f"from {self.v_full_V:.3f} V (IR-corrected from under {self.start_load_A:.3g} A)"
                if self.start_load_A
                else f"from a rest at {self.v_full_V:.3f} V"
            )
            return (
                f"a discharge in the record {at} "
                f"({100 * self.start_soc:.0f} % on the assumed OCV) to the cut-off "
                f"({self.v_empty_V:.3f} V, {self.chemistry}-like) moves "
                f"{self.capacity_Ah * self.start_soc:.3g} Ah"
            )
        return (
            f"a full-to-empty discharge in the record ({self.v_full_V:.3f} V at rest to "
            f"{self.v_empty_V:.3f} V, {self.chemistry}-like) moves {self.capacity_Ah:.3g} Ah"
        )


def derive_capacity(
    t_s: FloatArray,
    current_A: FloatArray,
    voltages_V: FloatArray,
    gap_s: float = GAP_S,
    soc_at_rest: Callable[[float], float] | None = None,
) -> CapacityEstimate | None:
    """The capacity (Ah) when the record discharges a cell from full, or from a rest that
    ``soc_at_rest`` (the assumed OCV curve's inverse, V -> fraction) puts at >= 30 % SOC, to
    empty; else None.

    Full: at rest (|I| below ``REST_SHARE`` of the peak) at >= 4.1 V, or on an LFP-like flat
    plateau (3.40-3.65 V at rest, the whole record below 3.7 V, the resting voltage in the middle
    of the discharge within 0.15 V). A partial start: at rest above 3.65 V (NMC-like: an LFP
    plateau tells no SOC), the charge divided by its SOC. Empty: the weakest cell at or below
    the cut-off (3.0 V; LFP 2.7 V) at the end of the discharge. Packs use the cell mean (full)
    and minimum (empty) over the cells with a reading: NaN (a reading the input gates refused,
    ``record_cell.accepted_readings``) is left out, and a NaN current is held (``held``).
    """
    t = np.asarray(t_s, dtype=np.float64)
    i = held(np.asarray(current_A, dtype=np.float64), 0.0)
    v_mean, v_min = cell_mean_min(voltages_V)
    if t.size < 10 or not np.isfinite(v_mean).any():
        return None
    q = coulomb_Ah(t, i, gap_s)
    ex = max_excursion(q)
    if ex.direction != "discharge" or ex.charge_Ah <= 0:
        return None
    peak = float(np.max(np.abs(i)))
    a, b = ex.start, ex.end
    v_full = float(v_mean[a])
    v_empty = float(v_min[b])
    if abs(i[a]) > REST_SHARE * peak:
        return _partial_start(t, i, v_mean, v_min, ex, soc_at_rest, peak)
    if v_full >= FULL_NMC_V and v_empty <= EMPTY_NMC_V:
        return CapacityEstimate(ex.charge_Ah, v_full, v_empty, "NMC")
    if LFP_MAX_V < v_full < FULL_NMC_V:
        return _partial_start(t, i, v_mean, v_min, ex, soc_at_rest, peak)
    v_top = float(np.nanmax(np.asarray(voltages_V, dtype=np.float64)))
    if not (FULL_LFP_V <= v_full <= LFP_MAX_V and v_top <= LFP_MAX_V + 0.05):
        return None
    if v_empty > EMPTY_LFP_V:
        return None
    seg = slice(a, b + 1)
    qs, vs, rest = q[seg] - q[a], v_mean[seg], np.abs(i[seg]) <= REST_SHARE * peak
    middle = rest & (qs >= 0.2 * ex.charge_Ah) & (qs <= 0.8 * ex.charge_Ah)
    if np.count_nonzero(middle) < 3:
        return None
    lo, hi = np.percentile(vs[middle], [5, 95])
    if hi - lo > LFP_PLATEAU_SPAN_V:
        return None
    return CapacityEstimate(ex.charge_Ah, v_full, v_empty, "LFP")


def _partial_start(
    t: FloatArray,
    i: FloatArray,
    v_mean: FloatArray,
    v_min: FloatArray,
    ex: Excursion,
    soc_at_rest: Callable[[float], float] | None,
    peak_A: float,
) -> CapacityEstimate | None:
    """:func:`derive_capacity` for a discharge to the cut-off that starts part-charged (NMC-like),
    at rest or under a load whose IR correction moves the start SOC by at most
    ``LOADED_START_SOC_SHIFT`` (its voltage IR-corrected with the median -dV/dI of the record's
    current steps, ``startvalues.median_step_resistance``)."""
    a, b = ex.start, ex.end
    v_start, v_empty = float(v_mean[a]), float(v_min[b])
    if soc_at_rest is None or v_empty > EMPTY_NMC_V:
        return None
    load_A = 0.0
    if abs(i[a]) > REST_SHARE * peak_A:
        load_A = float(i[a])
        r_ohm = median_step_resistance(t[a:b], i[a:b], v_mean[a:b])
        if r_ohm is None:
            return None
        v_loaded = v_start
        v_start += r_ohm * load_A
        if not abs(float(soc_at_rest(v_start)) - float(soc_at_rest(v_loaded))) <= (
            LOADED_START_SOC_SHIFT
        ):
            return None
    if not LFP_MAX_V < v_start < FULL_NMC_V:
        return None
    z = float(soc_at_rest(v_start))
    if not (math.isfinite(z) and z >= PARTIAL_START_SOC_MIN):
        return None
    return CapacityEstimate(ex.charge_Ah / z, v_start, v_empty, "NMC", z, load_A)


def capacity_from_soc_change(
    t_s: FloatArray,
    current_A: FloatArray,
    voltages_V: FloatArray,
    soc_of: Callable[[FloatArray], FloatArray],
    soc_range: tuple[float, float],
    gap_s: float = GAP_S,
) -> CapacityEstimate | None:
    """The capacity (Ah) of a record that reaches no cut-off, from the charge it moves over the
    SOC change the assumed OCV (``soc_of``, V -> fraction, valid inside ``soc_range``) reads;
    None without the evidence (NMC-like only: an LFP plateau tells no SOC).

    The start is read at rest (the first voltage; under load IR-corrected as in
    :func:`_partial_start`); the later points are the rest ends (the last sample of each rest,
    |I| <= ``REST_SHARE`` of the peak). A short rest inside a cycle is not relaxed: its voltage
    sits a polarisation ``d`` off the OCV (below it after a discharge), which read as it is
    takes the capacity 10-15 % low on a DST record. So ``z(v_k + d) = z0 - q_k / C`` is fitted
    over the rest ends for C and one ``d``, within 2 R0 x the peak current (R1 + R2 at most
    about 2 R0), on a 1 mV grid. Needs ``SOC_CHANGE_MIN_POINTS`` rest ends read inside the curve
    spanning ``SOC_CHANGE_MIN_SPAN`` of SOC from the start."""
    t = np.asarray(t_s, dtype=np.float64)
    i = held(np.asarray(current_A, dtype=np.float64), 0.0)
    v, _ = cell_mean_min(voltages_V)
    if t.size < 10 or not np.isfinite(v[0]):
        return None
    peak = float(np.max(np.abs(i)))
    rest = np.abs(i) <= REST_SHARE * peak
    loaded = np.flatnonzero(~rest)
    if peak <= 0 or loaded.size == 0:
        return None
    r_ohm = median_step_resistance(t, i, v)
    lo, hi = soc_range
    v0, load_A = float(v[0]), 0.0
    if not rest[0]:
        if r_ohm is None:
            return None
        load_A = float(i[0])
        v0 += r_ohm * load_A
        if not abs(float(soc_of(np.array(v0))) - float(soc_of(np.array(v[0])))) <= (
            LOADED_START_SOC_SHIFT
        ):
            return None
    z0 = float(soc_of(np.array(v0)))
    if not (v0 > LFP_MAX_V and lo < z0 < hi):
        return None
    ends = np.flatnonzero(rest[:-1] & ~rest[1:])
    if rest[-1]:
        ends = np.append(ends, t.size - 1)
    ends = ends[(ends > loaded[0]) & np.isfinite(v[ends])]
    gaps = np.flatnonzero(np.diff(t) > gap_s)
    if gaps.size:  # what moved across a gap is unknown (a current lost mid-drive, downtime)
        ends = ends[ends <= gaps[0]]
    q = coulomb_Ah(t, i, gap_s)[ends]
    if ends.size < SOC_CHANGE_MIN_POINTS or not np.any(q):
        return None
    sign = 1.0 if q[np.argmax(np.abs(q))] > 0 else -1.0  # discharge: rest voltages below OCV
    d_max = 2.0 * r_ohm * peak if r_ohm is not None else 0.0
    best: tuple[float, float, float, int, float] | None = None  # rms, d, 1/C, n, span
    for d in sign * np.arange(0.0, d_max + 1e-3, 1e-3)[:1000]:
        z = soc_of(v[ends] + d)
        ok = (z > lo) & (z < hi)
        n = int(np.count_nonzero(ok))
        if n < SOC_CHANGE_MIN_POINTS:
            continue
        y, x = z0 - z[ok], q[ok]
        inv_c = float(x @ y) / float(x @ x)
        rms = float(np.sqrt(np.mean((y - inv_c * x) ** 2)))
        if best is None or rms < best[0]:
            best = (rms, float(d), inv_c, n, float(np.max(np.abs(y))))
    if best is None or not best[2] > 0 or best[4] < SOC_CHANGE_MIN_SPAN:
        return None
    _, d, inv_c, n, span = best
    return CapacityEstimate(
        1.0 / inv_c, v0, float(v[ends[-1]]), "NMC", z0, load_A, n_rests=n, soc_span=span,
        polarisation_V=-d,
    )  # fmt: skip


def capacity_not_read(capacity_Ah: float) -> Finding:
    """The loud line for a run without a cell config or ``--capacity-ah`` whose record tells
    no capacity (:func:`derive_capacity`, :func:`capacity_from_soc_change`)."""
    return Finding(
        "warning",
        "capacity_not_read",
        "the capacity could not be read off the record (no discharge to a cut-off, no rests "
        f"spanning {100 * SOC_CHANGE_MIN_SPAN:.0f} % of SOC on the assumed OCV): the assumed "
        f"cell's {capacity_Ah:g} Ah is used, and the SOC, the current-offset estimate and the "
        "capacity-relative thresholds all follow it; give --capacity-ah",
    )


def assumed_cell(
    name: str,
    capacity_Ah: float,
    *,
    capacity_from: Literal["cell", "option", "record"] = "cell",
    chemistry: str = "NMC",
    record_chemistry: str | None = None,
    ocv_from_record: str | None = None,
) -> Finding:
    """The loud line for a run without a cell config: which cell and capacity are assumed.

    ``capacity_from``: the assumed cell's own capacity, ``--capacity-ah``, or the record (a
    full-to-empty discharge, :func:`derive_capacity`, whose ``record_chemistry`` is named when
    it differs from the assumed cell's ``chemistry``: its OCV cannot fit). ``ocv_from_record``:
    the description of a pseudo-OCV read off the record in its place (``pseudo_ocv.py``; the
    first line prints it, the warning names it).
    """
    source = {
        "cell": f"its {capacity_Ah:g} Ah",
        "option": f"{capacity_Ah:g} Ah from --capacity-ah",
        "record": f"{capacity_Ah:.3g} Ah read off the record",
    }[capacity_from]
    mismatch = ""
    if record_chemistry is not None and record_chemistry != chemistry:
        mismatch = f" (the record looks {record_chemistry}-like: the {chemistry} OCV cannot fit it)"
    if ocv_from_record is not None:
        return Finding(
            "warning",
            "no_cell_config",
            f"no --cell-config and the record looks {record_chemistry}-like, which the paper's "
            f"{chemistry} cell cannot fit: a pseudo-OCV read off the record (first line) with "
            f"{source}; it carries the record's polarisation: a config from the cell's OCV test "
            "(bmsid fit-ocv) gives a true OCV",
        )
    return Finding(
        "warning",
        "no_cell_config",
        f"no --cell-config: assuming the paper's cell {name!r} (Table 1 OCV, 15 mV hysteresis) "
        f"with {source}{mismatch}; SOC and the capacity follow that cell's OCV, and another "
        "cell's differs (tens of SOC points off on other chemistries, --capacity-ah alone "
        "included): give the cell's own config (bmsid fit-ocv on its OCV test)",
    )


def check_consistency(
    t_s: FloatArray,
    current_A: FloatArray,
    voltages_V: FloatArray,
    *,
    capacity_Ah: float,
    capacity_assumed: bool = False,
    soc0: float | None = None,
    charge_positive: bool = False,
    excitation_C: float = 0.02,
    excitation_window_s: float = 300.0,
    gap_s: float = GAP_S,
) -> list[Finding]:
    """The checks that need a right time axis: current sign, capacity, excitation and (with a
    known start ``soc0``) the coulomb-counted SOC range."""
    out = check_current_sign(t_s, current_A, voltages_V, charge_positive)
    out += check_capacity(t_s, current_A, capacity_Ah, assumed=capacity_assumed, gap_s=gap_s)
    out += check_excitation(
        t_s, current_A, capacity_Ah, excitation_C=excitation_C,
        window_s=excitation_window_s, assumed=capacity_assumed,
    )  # fmt: skip
    if soc0 is not None:
        z = coulomb_soc(t_s, current_A, capacity_Ah, soc0, gap_s)
        out += check_soc_range(z, capacity_Ah, f"--soc0 {100 * soc0:g} %")
    return out


def check_record(
    t_s: FloatArray,
    current_A: FloatArray,
    voltages_V: FloatArray,
    *,
    capacity_Ah: float,
    capacity_assumed: bool = False,
    soc0: float | None = None,
    charge_positive: bool = False,
    excitation_C: float = 0.02,
    excitation_window_s: float = 300.0,
    gap_s: float = GAP_S,
    time_fix: str = "--columns t_s=t_s*0.001",
) -> list[Finding]:
    """:func:`check_time_unit`, then (unless it found an error: every other number would be
    computed on a wrong time axis) :func:`check_consistency`."""
    out = check_time_unit(t_s, current_A, capacity_Ah, time_fix, gap_s)
    if first_error(out):
        return out
    return out + check_consistency(
        t_s, current_A, voltages_V, capacity_Ah=capacity_Ah, capacity_assumed=capacity_assumed,
        soc0=soc0, charge_positive=charge_positive, excitation_C=excitation_C,
        excitation_window_s=excitation_window_s, gap_s=gap_s,
    )  # fmt: skip


def lines(findings: Sequence[Finding]) -> list[str]:
    """The printable lines of ``findings``, in order."""
    return [f.line() for f in findings]
