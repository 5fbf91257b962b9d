"""What an offline run produced and how well its model voltage tracks the cell (Eq. 31).

Every run is scored over the whole record (every tick), over its first
:data:`STARTUP_FRACTION` of the ticks on its own (the start-up, where the estimators converge from
their start values and can blow up), over the rest, and per 10 % SOC band, so a start-up
blow-up or an end of the SOC range the model cannot hold is seen rather than averaged away.
A user's evaluation window (:class:`EvalWindow`: a skipped share of the first ticks and a SOC
range) is scored as well; by default it is the whole record.

The SOC that decides the window and the bands is the estimator's own SOC, unless a
:class:`SocReference` is given: a coulomb count of the measured current from a known start
(e.g. "SOC 95..15 % counted from the full start"), independent of what the estimator believes.

Pure: arrays in, numbers and dicts out.
"""

from __future__ import annotations

import itertools
import math
from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import numpy.typing as npt

from bmsid.config.cell import CellConfig
from bmsid.estimate.startvalues import StartValues
from bmsid.estimate.tuning import EstimatorTuning, Variant
from bmsid.estimate.types import EstimateBlock
from bmsid.metrics import VoltageMetrics
from bmsid.model.simulator import coulomb_count
from bmsid.offline.accumulate import (
    CoulombCarry,
    ErrorSums,
    PartMasks,
    RunAccumulator,
)
from bmsid.offline.report import HeldShare

FloatArray = npt.NDArray[np.float64]
BoolArray = npt.NDArray[np.bool_]
IntArray = npt.NDArray[np.int64]

#: Share of the first ticks reported on their own as the start-up (and left out of
#: ``after_startup``): where the estimators converge from their start values.
STARTUP_FRACTION = 0.1
#: Inner edges of the SOC bands (fractions): 0-10 %, 10-20 %, ..., 90-100 % (100 % included).
SOC_BAND_EDGES: tuple[float, ...] = tuple(k / 10 for k in range(11))
#: The tick-interval limit of the default tuning, s: longer steps are gaps (no charge counted).
DEFAULT_GAP_S = EstimatorTuning().gap_s


# ----------------------------------------------------------------------------- reference SOC
def reference_soc(
    t_s: FloatArray,
    current_A: FloatArray,
    soc0: float,
    capacity_Ah: float,
    coulombic_efficiency: float = 1.0,
    gap_s: float = DEFAULT_GAP_S,
) -> FloatArray:
    """SOC (fraction) at each tick by a coulomb count of the tick currents from ``soc0`` at the
    first tick (Eq. 2, ``simulator.coulomb_count``): each tick's current (A, + = discharge) is
    held until the next tick, the efficiency applies on charge only, and steps back in time or
    longer than ``gap_s`` (s) count no charge, as the estimator assumes the pack rested over a
    gap. Not clamped: a count that leaves 0..1 says the capacity or the start is wrong."""
    t = np.asarray(t_s, dtype=np.float64)
    i = np.asarray(current_A, dtype=np.float64)
    if t.size == 0:
        return np.zeros(0)
    dt = np.diff(t, append=t[-1])  # the last tick's current acts on nothing scored
    dt = np.where((dt > 0) & (dt <= gap_s), dt, 0.0)
    return coulomb_count(i, dt, soc0, capacity_Ah, coulombic_efficiency)


@dataclass(frozen=True)
class SocReference:
    """The SOC windows and bands are decided by, when not the estimator's: a coulomb count of the
    measured current from ``soc0`` (fraction) at the first tick, with ``capacity_Ah`` (Ah), the
    ``coulombic_efficiency`` (on charge) and the gap limit ``gap_s`` (s) of :func:`reference_soc`.
    """

    soc0: float
    capacity_Ah: float
    coulombic_efficiency: float = 1.0
    gap_s: float = DEFAULT_GAP_S

    def __post_init__(self) -> None:
        if not (math.isfinite(self.soc0) and 0.0 <= self.soc0 <= 1.0):
            raise ValueError(f"the scoring SOC start is a fraction in [0, 1], got {self.soc0:g}")
        if not (self.capacity_Ah > 0 and self.coulombic_efficiency > 0 and self.gap_s > 0):
            raise ValueError("capacity, coulombic efficiency and gap limit must be positive")

    @classmethod
    def from_cell(cls, cell: CellConfig, soc0: float, gap_s: float = DEFAULT_GAP_S) -> SocReference:
        """A count from ``soc0`` with the cell config's capacity and coulombic efficiency."""
        return cls(soc0, cell.capacity_Ah, cell.coulombic_efficiency, gap_s)

    def soc(self, trace: EstimateBlock) -> FloatArray:
        """The counted SOC at each tick of ``trace``, shape (n_ticks,)."""
        return reference_soc(
            trace.t_s, trace.current_A, self.soc0, self.capacity_Ah,
            self.coulombic_efficiency, self.gap_s,
        )  # fmt: skip

    def describe(self) -> str:
        return (
            f"a coulomb count of the measured current from {100 * self.soc0:g} % at the first "
            f"sample ({self.capacity_Ah:g} Ah, coulombic efficiency {self.coulombic_efficiency:g})"
        )


def scoring_soc(trace: EstimateBlock, reference: SocReference | None) -> FloatArray:
    """The SOC that decides windows and bands, (n_ticks, n_cells): the estimator's ``soc``,
    or the reference count (the same for every cell of the pack: one current)."""
    if reference is None:
        return np.asarray(trace["soc"], dtype=np.float64)
    z = reference.soc(trace)
    return np.repeat(z[:, None], trace.n_cells, axis=1)


# ----------------------------------------------------------------------------- windows, bands
def startup_ticks(n_ticks: int, fraction: float = STARTUP_FRACTION) -> int:
    """Ticks in the start-up: the first ``floor(fraction n)``."""
    return int(np.floor(fraction * n_ticks))


@dataclass(frozen=True)
class EvalWindow:
    """Which ticks the top-level metrics score: SOC inside [soc_lo, soc_hi] (fractions), after
    skipping the first ``skip_fraction`` of the ticks. ``None`` bounds are open; the default is
    the whole record. ``soc_reference``: the SOC the range applies to (None: the estimator's)."""

    skip_fraction: float = 0.0
    soc_lo: float | None = None
    soc_hi: float | None = None
    soc_reference: SocReference | None = None

    def __post_init__(self) -> None:
        if not 0.0 <= self.skip_fraction < 1.0:
            raise ValueError(f"skip fraction must lie in [0, 1), got {self.skip_fraction}")
        lo = -np.inf if self.soc_lo is None else self.soc_lo
        hi = np.inf if self.soc_hi is None else self.soc_hi
        if lo >= hi:
            raise ValueError(f"SOC window needs lo < hi, got {self.soc_lo}, {self.soc_hi}")

    @property
    def is_whole_record(self) -> bool:
        """True when every tick is scored (no skip, no SOC range)."""
        return self.skip_fraction == 0 and self.soc_lo is None and self.soc_hi is None

    def mask(self, trace: EstimateBlock) -> BoolArray:
        """Boolean (n_ticks, n_cells): the scored ticks of each cell."""
        n = trace.n_ticks
        keep = np.arange(n) >= startup_ticks(n, self.skip_fraction)
        m = np.repeat(keep[:, None], trace.n_cells, axis=1)
        if self.soc_lo is None and self.soc_hi is None:
            return m
        soc = scoring_soc(trace, self.soc_reference)
        if self.soc_lo is not None:
            m &= soc >= self.soc_lo
        if self.soc_hi is not None:
            m &= soc <= self.soc_hi
        return m

    def describe(self) -> str:
        parts = []
        if self.skip_fraction > 0:
            parts.append(f"first {100 * self.skip_fraction:g} % of the ticks skipped")
        if self.soc_lo is not None or self.soc_hi is not None:
            lo = "0" if self.soc_lo is None else f"{100 * self.soc_lo:g}"
            hi = "100" if self.soc_hi is None else f"{100 * self.soc_hi:g}"
            which = "estimated SOC" if self.soc_reference is None else "SOC"
            parts.append(f"{which} within {lo}-{hi} %")
            if self.soc_reference is not None:
                parts.append(f"SOC: {self.soc_reference.describe()}")
        return "; ".join(parts) or "all ticks"

    def as_dict(self) -> dict[str, Any]:
        return {
            "skip_fraction": self.skip_fraction,
            "soc_lo": self.soc_lo,
            "soc_hi": self.soc_hi,
            "soc_source": "estimator" if self.soc_reference is None else "coulomb_count",
            "description": self.describe(),
        }


@dataclass(frozen=True)
class SocBand:
    """A SOC band: ``lo <= z < hi`` (fractions; ``None`` is open), the top in-range band also
    holding z = 1. Ticks outside 0..1 fall in the ``<0 %`` and ``>100 %`` bands."""

    label: str
    lo: float | None
    hi: float | None


def _band_label(lo: float, hi: float) -> str:
    return f"{100 * lo:g}-{100 * hi:g} %"


#: Every band, in SOC order: below 0, the ten 10 % bands, above 100 (indices of ``band_index``).
SOC_BANDS: tuple[SocBand, ...] = (
    SocBand("<0 %", None, 0.0),
    *(SocBand(_band_label(lo, hi), lo, hi) for lo, hi in itertools.pairwise(SOC_BAND_EDGES)),
    SocBand(">100 %", 1.0, None),
)


def band_index(soc: FloatArray) -> IntArray:
    """Index into ``SOC_BANDS`` of each SOC (fraction), -1 for a non-finite one."""
    z = np.asarray(soc, dtype=np.float64)
    edges = np.asarray(SOC_BAND_EDGES)
    idx = np.searchsorted(edges, z, side="right")  # 0 below 0, k in [edge k-1, edge k), 11 >= 1
    idx = np.where(z == edges[-1], len(edges) - 1, idx)  # a full cell belongs to 90-100 %
    return np.where(np.isfinite(z), idx, -1).astype(np.int64)


# ----------------------------------------------------------------------------- scores
@dataclass(frozen=True)
class BandScore:
    """Eq. 31 over the ticks whose scoring SOC lies in ``band``."""

    band: SocBand
    metrics: VoltageMetrics

    def as_dict(self) -> dict[str, Any]:
        return {
            "band": self.band.label,
            "soc_lo": self.band.lo,
            "soc_hi": self.band.hi,
            **self.metrics.as_dict(),
        }


@dataclass(frozen=True)
class ScoreSet:
    """Eq. 31 (errors in V, MAPE in %) over the parts of one record, for one cell or pooled:
    ``overall`` every tick, ``startup`` the first ``STARTUP_FRACTION`` of the ticks,
    ``after_startup`` the others, ``window`` the evaluation window, ``soc_bands`` the non-empty
    SOC bands in SOC order."""

    overall: VoltageMetrics
    startup: VoltageMetrics
    after_startup: VoltageMetrics
    window: VoltageMetrics
    soc_bands: tuple[BandScore, ...]


@dataclass(frozen=True)
class Scores:
    """Eq. 31 pooled over the cells (``pooled``) and per cell (``cells``); ``n_startup_ticks``
    ticks form the start-up."""

    pooled: ScoreSet
    cells: tuple[ScoreSet, ...]
    n_startup_ticks: int

    @property
    def window(self) -> VoltageMetrics:
        return self.pooled.window

    @property
    def overall(self) -> VoltageMetrics:
        return self.pooled.overall

    @property
    def per_cell_window(self) -> list[VoltageMetrics]:
        return [c.window for c in self.cells]

    @property
    def per_cell_overall(self) -> list[VoltageMetrics]:
        return [c.overall for c in self.cells]


def _score_set(sums: ErrorSums, cell: int | None) -> ScoreSet:
    """The parts of one cell (or pooled, None) from the run's Eq. 31 sums."""
    bands = (BandScore(b, sums.metrics(4 + k, cell)) for k, b in enumerate(SOC_BANDS))
    return ScoreSet(
        overall=sums.metrics(RunAccumulator.OVERALL, cell),
        startup=sums.metrics(RunAccumulator.STARTUP, cell),
        after_startup=sums.metrics(RunAccumulator.AFTER, cell),
        window=sums.metrics(RunAccumulator.WINDOW, cell),
        soc_bands=tuple(b for b in bands if b.metrics.n_samples > 0),
    )


class RunScorer:
    """Eq. 31 and the rest of metrics.json, scored block by block of estimates in tick order
    (:class:`~bmsid.offline.accumulate.RunAccumulator`): the start-up is the first
    ``startup_ticks(n_ticks)`` ticks, the window skips ``startup_ticks(n_ticks,
    window.skip_fraction)``, so the run's tick count is given up front. A whole trace is one
    ``add`` (:meth:`of_trace`).

    Parameters
    ----------
    n_ticks, n_cells : int
        Ticks the run produces, cells of each block.
    window : EvalWindow
        The evaluation window (and the SOC reference of the window and the bands).
    bounds : mapping or None
        Bounds (lo, hi) of each ``guard.WATCHED`` parameter, shape (n_cells,) each, for the
        bound findings; None: none counted (``bound_findings`` then reports nothing).
    """

    def __init__(
        self,
        n_ticks: int,
        n_cells: int,
        window: EvalWindow,
        bounds: Mapping[str, tuple[FloatArray, FloatArray]] | None = None,
    ) -> None:
        self.window = window
        self.n_ticks = n_ticks
        self.n_startup = startup_ticks(n_ticks)
        self._n_skip = startup_ticks(n_ticks, window.skip_fraction)
        self.acc = RunAccumulator(n_ticks, n_cells, len(SOC_BANDS), bounds)
        ref = window.soc_reference
        self._count = None if ref is None else CoulombCarry(
            ref.soc0, ref.capacity_Ah, ref.coulombic_efficiency, ref.gap_s
        )  # fmt: skip

    @classmethod
    def of_trace(
        cls,
        trace: EstimateBlock,
        window: EvalWindow,
        bounds: Mapping[str, tuple[FloatArray, FloatArray]] | None = None,
    ) -> RunScorer:
        """A whole trace scored at once."""
        scorer = cls(trace.n_ticks, trace.n_cells, window, bounds)
        scorer.add(trace)
        return scorer

    def add(self, block: EstimateBlock) -> None:
        """The next block of estimates (ticks after those already added)."""
        if block.n_ticks == 0:
            return
        k = self.acc.seen + np.arange(block.n_ticks)
        if self._count is None:
            soc = np.asarray(block["soc"], dtype=np.float64)
        else:
            z = self._count.soc(block.t_s, block.current_A)
            soc = np.repeat(z[:, None], block.n_cells, axis=1)
        win = np.repeat((k >= self._n_skip)[:, None], block.n_cells, axis=1)
        if self.window.soc_lo is not None:
            win &= soc >= self.window.soc_lo
        if self.window.soc_hi is not None:
            win &= soc <= self.window.soc_hi
        parts = PartMasks(startup=(k < self.n_startup)[:, None], window=win, band=band_index(soc))
        self.acc.add(block, parts, soc)

    def scores(self) -> Scores:
        """Eq. 31 pooled and per cell over the ticks added so far."""
        sums = self.acc.sums
        return Scores(
            pooled=_score_set(sums, None),
            cells=tuple(_score_set(sums, c) for c in range(self.acc.n_cells)),
            n_startup_ticks=self.n_startup,
        )


def score(trace: EstimateBlock, window: EvalWindow) -> Scores:
    """Eq. 31 on the model voltage, pooled over the cells and per cell: the whole record, the
    start-up and the rest, ``window``, and the SOC bands of ``window.soc_reference``'s SOC."""
    return RunScorer.of_trace(trace, window).scores()


# ----------------------------------------------------------------------------- metrics.json
@dataclass(frozen=True)
class IdentifyResult:
    """One bank run over a recording.

    Attributes
    ----------
    variant : str
        The estimator variant that ran.
    trace : EstimateBlock or None
        The bank's estimates at every identification tick; None for a streamed run, which kept
        only ``summary``.
    soc_init_method : str
        How the initial SOC was found (``given``, ``ocv_at_rest``,
        ``ocv_ir_corrected``, ``config``; ``pending`` when no cell had a valid voltage).
    counters : dict of str to int
        The bank's event counters at the end.
    runtime_s : float
        Wall time of the identification alone (reading and writing excluded), s.
    n_samples : int
        Input samples fed to the bank.
    cell_names : list of str
        Name of each cell column.
    start_values : StartValues or None
        Start values measured on the record for what the cell config left out (None: the
        config gave them, or the record had too few current steps).
    input_gates : dict
        What the plausibility gates refused, per reason and cell, and the cells that never
        carried a reading or never a valid one (``bmsid.gates.GateState.report``).
    summary : RunScorer or None
        The streamed scores, SOC range, bound findings and plot decimation of the run's
        evaluation window (a streamed run); None: computed from ``trace`` when needed.
    n_ticks : int
        Identification ticks of the run.
    start_branch_V : ndarray or None
        Per cell, the voltage the RC branches held at the first sample (V, their sum), fitted
        over the record's first minutes where it opened under load or relaxing
        (``offline/start_soc.py``); None: the branches started empty.
    start_fit_rmse_V : ndarray or None
        Per cell, the RMSE (V) of that start fit over its window (NaN where none held); None:
        no start was fitted.
    start_h : ndarray or None
        Per cell, the hysteresis state the bank started at, fitted where the record opened at
        rest after a charge or discharge (-1 after a discharge); None: 0, the engine's start.
    activation_energy_J_mol : ndarray or None
        Per cell, the temperature law's activation energy at the end, J/mol, and how many
        pairs of window fits taught it (``counters["arrhenius_pairs"]``; 0: the prior); None:
        the record's temperature did not move (or the variant has no such law).
    """

    variant: Variant
    trace: EstimateBlock | None
    soc_init_method: str
    counters: dict[str, int]
    runtime_s: float
    n_samples: int
    cell_names: list[str] = field(default_factory=list)
    start_values: StartValues | None = None
    input_gates: dict[str, Any] = field(default_factory=dict)
    summary: RunScorer | None = None
    start_branch_V: FloatArray | None = None
    start_fit_rmse_V: FloatArray | None = None
    start_h: FloatArray | None = None
    activation_energy_J_mol: FloatArray | None = None

    @property
    def n_ticks(self) -> int:
        if self.trace is not None:
            return self.trace.n_ticks
        return 0 if self.summary is None else self.summary.acc.seen

    def scorer(self, window: EvalWindow) -> RunScorer:
        """The run scored over ``window``: the streamed summary when it was made for this
        window, else the kept trace scored at once; ValueError for a streamed run asked for
        another window."""
        if self.summary is not None and self.summary.window == window:
            return self.summary
        if self.trace is None:
            raise ValueError("a streamed run is scored over its own evaluation window only")
        return RunScorer.of_trace(self.trace, window)

    def first_tick(self) -> EstimateBlock | None:
        """The run's first tick (None when it had none)."""
        if self.trace is not None:
            return self.trace.select(slice(0, 1)) if self.trace.n_ticks else None
        return None if self.summary is None else self.summary.acc.first

    def last_tick(self) -> EstimateBlock | None:
        """The run's last tick (None when it had none)."""
        if self.trace is not None:
            n = self.trace.n_ticks
            return self.trace.select(slice(n - 1, n)) if n else None
        return None if self.summary is None else self.summary.acc.last

    def soc_extremes(self) -> FloatArray:
        """The smallest and largest finite estimator SOC of the run (fractions; empty when
        none), for ``plausibility.check_soc_range``."""
        if self.trace is not None:
            z = np.asarray(self.trace["soc"], dtype=np.float64)
            z = z[np.isfinite(z)]
            return np.array([z.min(), z.max()]) if z.size else np.zeros(0)
        ext = np.zeros(0) if self.summary is None else self.summary.acc.est_soc
        return ext if np.isfinite(ext).all() else np.zeros(0)

    def kept_trace(self) -> EstimateBlock:
        """The whole trace; ValueError for a streamed run (``IdentifySpec.keep_trace``)."""
        if self.trace is None:
            raise ValueError("the run was streamed: no trace kept (IdentifySpec.keep_trace)")
        return self.trace


def _parts(s: ScoreSet, n_ticks: int, n_startup: int) -> dict[str, Any]:
    return {
        "overall": s.overall.as_dict(),
        "startup": {"n_ticks": n_startup, **s.startup.as_dict()},
        "after_startup": {"n_ticks": n_ticks - n_startup, **s.after_startup.as_dict()},
        "soc_bands": [b.as_dict() for b in s.soc_bands],
    }


def _no_data(overall: VoltageMetrics) -> dict[str, str]:
    """``status: no_data`` where no tick was scored (no valid reading of the cell: its quality
    ``no_data``, its errors null); nothing otherwise."""
    return {"status": "no_data"} if overall.n_samples == 0 else {}


def scoring_soc_document(scorer: RunScorer) -> dict[str, Any]:
    """The ``scoring_soc`` entry of metrics.json: which SOC decided the window and the bands, and
    the range it covered (fractions; first and last ticks averaged over the cells)."""
    reference = scorer.window.soc_reference
    head: dict[str, Any]
    if reference is None:
        head = {"source": "estimator", "description": "the estimator's SOC (coulomb count)"}
    else:
        head = {
            "source": "coulomb_count",
            "description": reference.describe(),
            "soc0": reference.soc0,
            "capacity_Ah": reference.capacity_Ah,
            "coulombic_efficiency": reference.coulombic_efficiency,
            "gap_s": reference.gap_s,
        }
    return {**head, **scorer.acc.soc_range()}


def held_warnings(result: IdentifyResult, window: EvalWindow) -> list[str]:
    """A line per cell whose published parameters were held on ``report.HELD_FLAG_SHARE`` or more of
    the window's ticks: its params.csv then shows where the estimate stopped, not the cell (a
    sweep of unseen cells held 36-92 % with fit-ocv configs, and nothing on the console said
    so)."""
    acc = result.scorer(window).acc
    lines = []
    for c, name in enumerate(result.cell_names):
        held = HeldShare(*acc.held(c))
        if held.flagged:
            lines.append(
                f"WARNING: {name}: {held.text()}: the model does not follow this cell within its "
                "bounds there (an OCV curve that misfits it, or dynamics outside them); "
                "params.csv's quality column says where"
            )
    return lines


#: A cell of a pack of 3 or more is warned about when its model error (RMSE over the window)
#: is this many times the cells' median and at least ``LONE_CELL_MIN_V`` above it.
LONE_CELL_RATIO = 4.0
LONE_CELL_MIN_V = 0.003


def lone_cell_warnings(result: IdentifyResult, window: EvalWindow) -> list[str]:
    """A line per cell of a pack (3 cells or more) whose model error is far beyond the other
    cells': one cell of a series string that the model follows that much worse than its
    siblings has its own fault (a loose or intermittent sense wire, a bad tap, a failing
    cell). Its parameters are then its sensing's, and the SOC observer has kept it from
    teaching the pack's offset (``ObserverTuning.agree_sigmas``); +50 mV on every tenth
    sample of one of 8 cells read 15.5 mV against 1.1-1.5 mV and held 34 % of the ticks, under
    ``held_warnings``' flag."""
    sums = result.scorer(window).acc.sums
    rmse = np.array([sums.metrics(RunAccumulator.WINDOW, c).rmse_V
                     for c in range(len(result.cell_names))])  # fmt: skip
    lone, med = lone_by_rmse(rmse)
    return [
        f"WARNING: {name}: model error {1e3 * rmse[c]:.2f} mV RMS, {rmse[c] / med:.1f}x the "
        f"pack's median ({1e3 * med:.2f} mV): a fault of this cell's own (a loose or "
        "intermittent sense wire, a bad tap, a failing cell) more than its dynamics; it did "
        "not teach the pack's current offset where its voltage disagreed with the others'"
        for c, name in enumerate(result.cell_names)
        if lone[c]
    ]


def lone_by_rmse(rmse_V: FloatArray) -> tuple[npt.NDArray[np.bool_], float]:
    """The cells (of 3 or more with a model error) whose RMSE (V) is ``LONE_CELL_RATIO`` times
    the cells' median and ``LONE_CELL_MIN_V`` above it, and that median (V; NaN with fewer
    than 3): offline over a record, live over a window (``daemon/lone_cell_watch.py``)."""
    scored = np.isfinite(rmse_V) & (rmse_V > 0)
    if np.count_nonzero(scored) < 3:
        return np.zeros(rmse_V.shape, dtype=bool), math.nan
    med = float(np.median(rmse_V[scored]))
    return scored & (rmse_V >= LONE_CELL_RATIO * med) & (rmse_V - med >= LONE_CELL_MIN_V), med


#: A cell whose mean model error (times the current's sign) differs by this much between two
#: |current| bands of at least ``CURRENT_BAND_MIN_TICKS`` window ticks is warned about, V.
CURRENT_DEPENDENCE_V = 0.015
CURRENT_BAND_MIN_TICKS = 60


def current_dependence_warnings(result: IdentifyResult, window: EvalWindow) -> list[str]:
    """A line per cell whose model error depends on the current's size: the linear 2RC has one
    resistance at every current, a cold cell's charge-transfer kinetics (Butler-Volmer) do
    not. A PyBaMM cell at -10 degC ran 41 mV RMS (+192 mV at the peaks, -15 mV at light load),
    quality ``converged`` and no line said so; its published R0 matched the large steps and
    lay 33 % under the small ones'."""
    acc = result.scorer(window).acc
    lines = []
    for c, name in enumerate(result.cell_names):
        bands = [b for b in acc.current_dependence(c) if b[2] >= CURRENT_BAND_MIN_TICKS]
        if len(bands) < 2:
            continue
        lo, hi = min(bands, key=lambda b: b[1]), max(bands, key=lambda b: b[1])
        if hi[1] - lo[1] < CURRENT_DEPENDENCE_V:
            continue
        said = ", ".join(f"{1e3 * m:+.0f} mV at {label}" for label, m, _ in bands)
        lines.append(
            f"WARNING: {name}: the model error depends on the current ({said}; the mean of "
            "measured - model voltage times the current's sign): the cell's resistance changes "
            "with the current (a cold cell's charge-transfer kinetics), which the linear 2RC "
            "model cannot follow; R0 and the RC parameters are a compromise between the "
            "current levels, and the SOC read through them carries the difference"
        )
    return lines


#: A discharge past the estimated empty is warned about from this share of the capacity in use.
PAST_EMPTY_SHARE = 0.005


def past_empty_warnings(result: IdentifyResult, window: EvalWindow) -> list[str]:
    """A line per cell that gave ``PAST_EMPTY_SHARE`` of its capacity or more while its SOC sat
    at 0 %: the whole record's RMSE is then mostly those ticks (CALCE DST 45 C from 80 % with
    the shipped 2.0 Ah config: 235 mV over 182 such ticks, 36.5 mV over the whole record and
    2.0 mV over SOC 95-15 %), and the cause is the capacity or the start, not the parameters."""
    acc = result.scorer(window).acc
    last = acc.last
    lines = []
    for c, name in enumerate(result.cell_names):
        past = acc.past_empty(c)
        q_Ah = float(last["capacity_Ah"][0, c]) if last is not None else math.nan
        if past is None or not past["charge_Ah"] >= PAST_EMPTY_SHARE * q_Ah:
            continue
        lines.append(
            f"WARNING: {name}: SOC at 0 % on {past['ticks']} ticks of discharge from t = "
            f"{past['from_t_s']:.0f} s, over which the cell gave {past['charge_Ah']:.3g} Ah "
            f"more: it holds more than the {q_Ah:.4g} Ah in use (or started fuller than "
            f"estimated), and the model cannot follow it past its empty (RMSE "
            f"{1e3 * past['rmse_V']:.1f} mV on those ticks); --capacity-ah or the cell "
            "config's capacity_Ah at this temperature"
        )
    return lines


def metrics_document(result: IdentifyResult, window: EvalWindow) -> dict[str, Any]:
    """The content of metrics.json.

    Top level: Eq. 31 over ``window`` (``n_samples``, ``max_abs_error_V``, ``rmse_V``,
    ``mape_pct``; the whole record by default), then ``overall`` (every tick), ``startup`` (the
    first ``STARTUP_FRACTION`` of the ticks) and ``after_startup`` (the rest), ``soc_bands``
    (non-empty 10 % SOC bands), ``evaluation_window`` and ``scoring_soc`` (the SOC that decided
    the window and bands); the same per cell under ``cells``; ``start_branch_V`` per cell (V,
    null for empty branches); ``start_fit_rmse_V`` per cell (V) where the start was fitted;
    ``start_h`` per cell (null: 0, the engine's start); ``activation_energy_J_mol`` per cell
    (J/mol; null where the record's temperature did not move).
    """
    scorer = result.scorer(window)
    s = scorer.scores()
    n, n0 = scorer.acc.seen, s.n_startup_ticks
    b = result.start_branch_V
    cells: dict[str, Any] = {}
    for c, name in enumerate(result.cell_names):
        held = HeldShare(*scorer.acc.held(c))
        cells[name] = {
            "algorithm": result.variant,
            **_no_data(s.cells[c].overall),
            **s.cells[c].window.as_dict(),
            "runtime_s": result.runtime_s,
            **_parts(s.cells[c], n, n0),
            "held_share": held.held,
            "most_on_bound": held.bound_param,
            "most_on_bound_share": held.bound,
            "past_empty": scorer.acc.past_empty(c),
        }
    return {
        "algorithm": result.variant,
        **_no_data(s.overall),
        **s.window.as_dict(),
        "runtime_s": result.runtime_s,
        "evaluation_window": window.as_dict(),
        **_parts(s.pooled, n, n0),
        "startup_fraction": STARTUP_FRACTION,
        "scoring_soc": scoring_soc_document(scorer),
        "n_input_samples": result.n_samples,
        "n_ticks": n,
        "soc_init_method": result.soc_init_method,
        "start_branch_V": None if b is None else [float(x) for x in b],
        "start_fit_rmse_V": _finite_list(result.start_fit_rmse_V),
        "start_h": _finite_list(result.start_h),
        "activation_energy_J_mol": _finite_list(result.activation_energy_J_mol),
        "counters": result.counters,
        "cells": cells,
    }


def _finite_list(x: FloatArray | None) -> list[float | None] | None:
    """JSON-ready: the values, NaN as null; None stays None."""
    return None if x is None else [float(v) if math.isfinite(v) else None for v in x]


#: Parameters summarised by ``parameter_medians`` and ``parameter_trajectories``.
SUMMARY_PARAMS = ("R0_ohm", "R1_ohm", "C1_F", "R2_ohm", "C2_F", "tau1_s", "tau2_s")


def parameter_trajectories(
    trace: EstimateBlock, window: EvalWindow, cell: int
) -> dict[str, FloatArray]:
    """Each parameter of ``SUMMARY_PARAMS`` at the scored ticks of one cell (SI units)."""
    m = window.mask(trace)[:, cell]
    return {name: trace[name][m, cell].copy() for name in SUMMARY_PARAMS}


def parameter_medians(trace: EstimateBlock, window: EvalWindow) -> dict[str, FloatArray]:
    """Median of each identified parameter (R0, R1, C1, R2, C2 and the taus) over the scored
    ticks, per cell (NaN for a cell with no scored tick). Units as in ``CELL_FIELDS``."""
    m = window.mask(trace)
    out: dict[str, FloatArray] = {}
    for name in SUMMARY_PARAMS:
        vals = trace[name]
        out[name] = np.array(
            [
                float(np.median(vals[m[:, c], c])) if m[:, c].any() else np.nan
                for c in range(trace.n_cells)
            ]
        )
    return out
