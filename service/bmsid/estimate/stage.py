"""The protocol every estimation stage follows, and what the stages of one tick share.

A tick runs through the stages in order: the state stage (SOC and hysteresis; it owns z and h
and evaluates OCV(z) and M(z) into the :class:`TickContext`), then one parameter stage (the
AFFRLS on the ARX model, or the AFFRLS-LPSO fusion), which reads the state from the context. A
variant of the paper is a composition of stages (``bank.VARIANT_STAGES``), not a string the code
compares. Every stage keeps its state in plain per-cell arrays, so a checkpoint nests one
``state_dict`` per stage and a compiled kernel can later replace a stage's ``step`` unchanged.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from functools import lru_cache
from typing import Any, Protocol

import numpy as np
import numpy.typing as npt
from numpy._core.multiarray import count_nonzero as _count_nonzero

from bmsid.estimate.affrls import adaptive_lambda
from bmsid.estimate.cellmodel import CellModel
from bmsid.estimate.ticks import Tick
from bmsid.estimate.tuning import EstimatorTuning

FloatArray = npt.NDArray[np.float64]
BoolArray = npt.NDArray[np.bool_]


#: (e_floor_V, innovation_clip_sigmas, e_base_sigmas, forgetting_base) of the tuning: what the
#: innovation and forgetting step (Eq. 21) reads of it, as plain floats
InnovationConstants = tuple[float, float, float, float]

#: ``np.count_nonzero`` of a whole array without its Python dispatch layer (a quarter of the cost:
#: the per-tick code asks it of short masks several times a tick)
nnz = _count_nonzero

_EMPTY: FloatArray = np.zeros(0)
_EMPTY_BOOL: BoolArray = np.zeros(0, dtype=bool)


class TickContext:
    """One tick and what the state stage derived from it for the parameter stages.

    Attributes:
        tick: the assembled tick.
        soc_clamped: SOC clamped to the OCV curve's range, shape (n,).
        ocv_V: OCV(z) of Eq. 4, V.
        m_table_V: hysteresis half-gap M(z) of Eq. 32, V.
        h: hysteresis state h in [-1, 1] (Eq. 5-6).
        hm_V: hysteresis voltage h M(z), V (Eq. 9).
        v_safe_V: measured voltage, or OCV(z) where a cell has none (the update skips it), V.
        learn: cells whose parameters may learn from this tick (a valid voltage, SOC outside
            the OCV curve's knees: ``EstimatorTuning.knee_slope_factor``).
    """

    __slots__ = ("h", "hm_V", "learn", "m_table_V", "ocv_V", "soc_clamped", "tick", "v_safe_V")

    def __init__(self, tick: Tick) -> None:
        # Filled by the state stage; the shared empty placeholders cost nothing per tick (a
        # dataclass would need a factory, i.e. seven allocations per tick).
        self.tick = tick
        self.soc_clamped: FloatArray = _EMPTY
        self.ocv_V: FloatArray = _EMPTY
        self.m_table_V: FloatArray = _EMPTY
        self.h: FloatArray = _EMPTY
        self.hm_V: FloatArray = _EMPTY
        self.v_safe_V: FloatArray = _EMPTY
        self.learn: BoolArray = _EMPTY_BOOL


class Stage(Protocol):
    """A step of the estimator bank over per-cell state arrays."""

    #: key of the stage's state in a checkpoint
    name: str
    #: event counts, merged into the bank's counters (keys unique across stages)
    counters: dict[str, int]

    def step(self, ctx: TickContext) -> None:
        """Advance the stage's state by one tick (may fill ``ctx`` for later stages)."""

    def outputs(self) -> dict[str, FloatArray]:
        """Per-cell output fields (names of ``fields.CELL_FIELDS``) after the last step."""
        ...

    def reset(self, mask: BoolArray) -> None:
        """Re-initialise the masked cells to their start values."""

    def state_dict(self) -> dict[str, Any]:
        """Plain arrays and numbers (nested dicts allowed) that restore the stage exactly."""
        ...

    def load_state_dict(self, st: dict[str, Any]) -> None:
        """Restore ``state_dict`` output; ValueError/KeyError when it does not fit."""


class ParameterStage(Stage, Protocol):
    """A stage that identifies R0, R1, tau1, R2, tau2 (and reports the model voltage)."""

    @property
    def converged(self) -> BoolArray:
        """Cells whose estimate has converged once (quality CONVERGING until then)."""
        ...

    #: cells clamped to a bound at the last step (quality OUT_OF_BOUNDS)
    clamped: BoolArray

    def seed_branches(self, branch_V: FloatArray) -> bool:
        """Start the RC branches at the given voltages (V, (n_cells, 2): ``R1 x1``, ``R2 x2``
        of Eq. 9 with the start values' R1, R2), before the first tick; NaN leaves a branch
        empty. False: this stage keeps its branches empty."""
        ...


def per_cell_limit(share_C: float, model: CellModel) -> float | FloatArray:
    """``share_C`` x each cell's capacity, in A: one float when every cell has the same
    capacity (the usual pack), so the per-tick comparisons stay on Python scalars."""
    lim = share_C * model.capacity_Ah
    return float(lim[0]) if np.all(lim == lim[0]) else lim


def unit_branch_states(branch_V: FloatArray, r1_ohm: FloatArray, r2_ohm: FloatArray) -> tuple[
    FloatArray, FloatArray]:  # fmt: skip
    """The unit-gain branch states x1, x2 (A, Eq. 8) that hold ``branch_V`` (V, (n, 2)) across
    R1, R2 (ohm): 0 where a voltage is not finite or its resistance not positive."""
    out = []
    for j, r in enumerate((r1_ohm, r2_ohm)):
        u = branch_V[:, j]
        ok = np.isfinite(u) & (r > 0)
        out.append(np.where(ok, u / np.where(ok, r, 1.0), 0.0))
    return out[0], out[1]


def is_quiet(tick: Tick, rest_limit_A: float | FloatArray) -> bool | BoolArray:
    """Cells at rest with no current change this tick (|I| and |dI| below ``rest_limit_A``):
    no forgetting (lambda = 1), since a resting cell carries no new information about R0 and P
    must not grow."""
    i = tick.current_A
    return (abs(i) < rest_limit_A) & (abs(i - tick.i_prev_A) < rest_limit_A)


def is_excited(tick: Tick, excitation_limit_A: float | FloatArray) -> bool | BoolArray:
    """Cells whose current varies enough (RMS >= ``excitation_limit_A``) to identify."""
    return tick.current_std_A >= excitation_limit_A


@dataclass(frozen=True, slots=True)
class Forgetting:
    """Per-tick forgetting limits (Eq. 21 with per-second constants raised to the tick's data
    time) and the exponent that reports a per-tick lambda per second."""

    lam_lo: float
    lam_hi: float
    per_second_exp: float

    @classmethod
    def for_tick(cls, tick: Tick, tuning: EstimatorTuning) -> Forgetting:
        # Forgetting is per second of *data*: a gap carries none, so it forgets no more than a tick.
        dt_f = min(tick.dt_s, tick.period_s) if tick.dt_s > 0 else tuning.id_period_s
        if dt_f > 0:  # the usual tick: the same few steps again, their limits computed once
            return _forgetting(tuning.lambda_min, tuning.lambda_max, dt_f)
        return cls(tuning.lambda_min**dt_f, tuning.lambda_max**dt_f, 1.0 / dt_f)


@lru_cache(maxsize=64)
def _forgetting(lambda_min: float, lambda_max: float, dt_f: float) -> Forgetting:
    """:meth:`Forgetting.for_tick` of a data time ``dt_f`` > 0, s (equal keys, equal bits)."""
    return Forgetting(lambda_min**dt_f, lambda_max**dt_f, 1.0 / dt_f)


@lru_cache(maxsize=64)
def _innovation_gain(dt_s: float, scale_s: float) -> float:
    """The innovation RMS's EWMA gain over ``dt_s`` >= 1e-9 s (time constant ``scale_s``)."""
    return float(1.0 - np.exp(-dt_s / scale_s))


def innovation_constants(tuning: EstimatorTuning) -> InnovationConstants:
    """What Eq. 21's step reads of the tuning, as plain floats (a compiled kernel's argument)."""
    return (
        float(tuning.e_floor_V), float(tuning.innovation_clip_sigmas),
        float(tuning.e_base_sigmas), float(tuning.forgetting_base),
    )  # fmt: skip


def innovation_gain(dt_s: float, tuning: EstimatorTuning) -> float:
    """The innovation RMS's EWMA gain over a tick of ``dt_s`` s."""
    return _innovation_gain(max(dt_s, 1e-9), tuning.innovation_scale_s)


def adapt_innovation(
    e: FloatArray,
    sig_e: FloatArray,
    ok: BoolArray,
    quiet: bool | BoolArray,
    dt_s: float,
    forgetting: Forgetting,
    tuning: EstimatorTuning,
) -> tuple[FloatArray, FloatArray, FloatArray]:
    """Spike clipping, running innovation RMS and the forgetting factor (Eq. 21).

    Returns (clipped error V, new innovation RMS V, lambda per tick), each shape (n,).
    """
    g = innovation_gain(dt_s, tuning)
    lo, hi, consts = forgetting.lam_lo, forgetting.lam_hi, innovation_constants(tuning)
    return adapt_with_gain(e, sig_e, ok, quiet, g, lo, hi, consts)


def adapt_with_gain(
    e: FloatArray,
    sig_e: FloatArray,
    ok: BoolArray,
    quiet: bool | BoolArray,
    g: float,
    lam_lo: float,
    lam_hi: float,
    consts: InnovationConstants,
) -> tuple[FloatArray, FloatArray, FloatArray]:
    """:func:`adapt_innovation` with the RMS's EWMA gain ``g`` this tick, the forgetting limits
    (``Forgetting.lam_lo``, ``lam_hi``) and ``innovation_constants``."""
    if e.shape[0] == 1:
        return _adapt_one(e, sig_e, ok, quiet, g, lam_lo, lam_hi, consts)
    return _adapt_arrays(e, sig_e, ok, quiet, g, lam_lo, lam_hi, consts)


def _adapt_arrays(
    e: FloatArray,
    sig_e: FloatArray,
    ok: BoolArray,
    quiet: bool | BoolArray,
    g: float,
    lam_lo: float,
    lam_hi: float,
    consts: InnovationConstants,
) -> tuple[FloatArray, FloatArray, FloatArray]:
    """:func:`adapt_with_gain` over arrays."""
    floor, clip_sigmas, base_sigmas, base = consts
    sig = np.maximum(sig_e, floor)
    lim = clip_sigmas * sig
    e_c = np.minimum(np.maximum(e, -lim), lim)
    s2 = sig_e**2
    sig_new = np.sqrt(s2 + g * (e_c**2 - s2))
    if np.count_nonzero(ok) < ok.size:  # the masks only where some cell does not learn
        sig_new = np.where(ok, sig_new, sig_e)
    e_base = np.maximum(base_sigmas * sig, floor)
    lam = adaptive_lambda(e_c, e_base, lam_lo, lam_hi, base)
    if not isinstance(quiet, np.ndarray):  # one current for the pack: one answer, no mask
        return e_c, sig_new, np.ones(lam.shape) if quiet else lam
    return e_c, sig_new, np.asarray(np.where(quiet, 1.0, lam))


def _adapt_one(
    e: FloatArray,
    sig_e: FloatArray,
    ok: BoolArray,
    quiet: bool | BoolArray,
    g: float,
    lam_lo: float,
    lam_hi: float,
    consts: InnovationConstants,
) -> tuple[FloatArray, FloatArray, FloatArray]:
    """:func:`_adapt_arrays` of one cell in Python floats: the same IEEE operations in the same
    order (+ - * / and sqrt round alike; np.power kept: libm's pow differs in the last bit), the
    same bits (``tests/estimate/test_stage_paths.py``); a quarter of the numpy calls' time."""
    floor, clip_sigmas, base_sigmas, base = consts
    err, s = float(e[0]), float(sig_e[0])
    sig = _maximum(s, floor)
    lim = clip_sigmas * sig
    e_c = _minimum(_maximum(err, -lim), lim)
    if ok[0]:
        s2 = s * s  # what ndarray ** 2 computes
        v = s2 + g * (e_c * e_c - s2)
        s = math.sqrt(v) if v >= 0.0 else float(np.sqrt(v))  # numpy's NaN below 0 and for NaN
    e_base = _maximum(base_sigmas * sig, floor)
    # adaptive_lambda: eps = rint((e / e_base)^2 * 100) / 100 (round: half to even, as rint)
    q = e_c / e_base
    x = q * q * 100.0
    eps = _minimum((float(round(x)) if math.isfinite(x) else x) / 100.0, 1.0e3)
    lam = lam_lo + (lam_hi - lam_lo) * float(np.power(base, eps))
    if quiet[0] if isinstance(quiet, np.ndarray) else quiet:
        lam = 1.0
    return np.array([e_c]), np.array([s]), np.array([lam])


def _maximum(a: float, b: float) -> float:
    """np.maximum of two floats: NaN propagates (ties of equal values: either)."""
    return a if a >= b or math.isnan(a) else b


def _minimum(a: float, b: float) -> float:
    """np.minimum of two floats: NaN propagates (ties of equal values: either)."""
    return a if a <= b or math.isnan(a) else b
