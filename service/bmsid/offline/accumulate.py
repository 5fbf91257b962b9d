"""Streamed summaries of a run: everything metrics.json and the plots need, accumulated block by
block of estimates with memory that does not grow with the record (issue 12).

:class:`RunAccumulator` eats :class:`~bmsid.estimate.types.EstimateBlock` after block, in tick
order, and keeps

- exact running sums of Eq. 31 (count, sum of squared errors, sum of relative errors, largest
  error) per cell for every part of the record :mod:`bmsid.offline.scoring` reports: every tick,
  the start-up (the first ``STARTUP_FRACTION`` of the ticks), the rest, the evaluation window and
  each SOC band. The start-up and a skipped share of the window are counted in ticks, so the
  accumulator is told the run's tick count up front (``n_ticks``; the streamed run counts its
  ticks in a first pass over the input, :func:`bmsid.offline.identify.count_ticks`);
- the scoring SOC's range (a coulomb count carried from block to block when the SOC is a
  reference count), the estimator SOC's extremes, the bound findings (ticks on a bound, per
  parameter), and the first and last tick;
- each cell's median R0 over the evaluation window's ticks not held (:class:`StreamedMedian`,
  a histogram in 0.2 % wide bins: what the fleet summary ranks cells on);
- per cell, the ticks of discharge at which the estimator's SOC sat at 0 % (the capacity in
  use spent while the cell still gave charge), their squared errors and the charge they moved
  (:meth:`RunAccumulator.past_empty`);
- a min-max decimation for the plots: per bin of ``ceil(n_ticks / PLOT_BINS)`` ticks the smallest
  and largest value of each plotted series with their times, so a one-tick spike stays visible;
  a record of at most ``PLOT_BINS`` ticks keeps every tick.

Pure numpy: blocks in, numbers out. The in-memory path (a whole trace) is one ``add`` of the
whole trace, so a streamed run and a whole-file run give the same numbers to float rounding.
"""

from __future__ import annotations

import itertools
import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

from bmsid.estimate.guard import ON_BOUND_REL, WATCHED
from bmsid.estimate.types import EstimateBlock, Quality
from bmsid.metrics import VoltageMetrics
from bmsid.model.ecm import soc_delta

FloatArray = npt.NDArray[np.float64]
BoolArray = npt.NDArray[np.bool_]
IntArray = npt.NDArray[np.int64]

#: Bins of the plots' min-max decimation (two points per bin and series).
PLOT_BINS = 4000
#: A published SOC at or below this (fraction) is at empty: the guard publishes a count that
#: passed 0 as 0, and the observer's SOC stops there.
EMPTY_SOC = 1e-4
#: Steps between ticks longer than this (s) move no charge in the past-empty count (a gap).
EMPTY_MAX_DT_S = 60.0
#: Lower edges of the |current| bands (C-rate) over which the model error's dependence on the
#: current is told (``RunAccumulator.current_dependence``): light load, a drive's mean, peaks.
CRATE_EDGES = (0.05, 0.6, 1.3)
#: The series the plots draw, per cell: parameters (Fig. 10) and voltages with their error (11).
PLOT_SERIES = ("R0_ohm", "R1_ohm", "C1_F", "R2_ohm", "C2_F", "lambda_", "v_meas_V", "v_model_V",
               "error_V")  # fmt: skip


# ----------------------------------------------------------------------------- Eq. 31 sums
@dataclass
class ErrorSums:
    """Running Eq. 31 sums, shape (parts, cells): finite samples ``n``, sum of squared errors
    ``sq`` (V^2), sum of |error / measured| ``rel`` and the largest |error| ``peak`` (V)."""

    n: IntArray
    sq: FloatArray
    rel: FloatArray
    peak: FloatArray

    @classmethod
    def zeros(cls, n_parts: int, n_cells: int) -> ErrorSums:
        shape = (n_parts, n_cells)
        return cls(np.zeros(shape, np.int64), np.zeros(shape), np.zeros(shape), np.zeros(shape))

    def add(self, part: int, mask: BoolArray, err: FloatArray, rel: FloatArray) -> None:
        """Add the ticks of ``mask`` (ticks, cells) of errors ``err`` (V) and ``rel`` (|e/v|),
        which are 0 where a tick does not count (see :meth:`RunAccumulator.add`)."""
        self.n[part] += mask.sum(axis=0)
        self.sq[part] += np.where(mask, err * err, 0.0).sum(axis=0)
        self.rel[part] += np.where(mask, rel, 0.0).sum(axis=0)
        if mask.shape[0]:
            self.peak[part] = np.maximum(self.peak[part], np.where(mask, np.abs(err), 0.0).max(0))

    def metrics(self, part: int, cell: int | None = None) -> VoltageMetrics:
        """Eq. 31 of one part, for one cell or pooled over the cells (None); zeros when empty,
        as :func:`~bmsid.metrics.voltage_metrics`."""
        sel = slice(None) if cell is None else slice(cell, cell + 1)
        n = int(self.n[part, sel].sum())
        if n == 0:
            return VoltageMetrics(0, 0.0, 0.0, 0.0)
        return VoltageMetrics(
            n_samples=n,
            max_abs_error_V=float(self.peak[part, sel].max()),
            rmse_V=math.sqrt(float(self.sq[part, sel].sum()) / n),
            mape_pct=100.0 * float(self.rel[part, sel].sum()) / n,
        )


# ----------------------------------------------------------------------------- SOC count
@dataclass
class CoulombCarry:
    """A coulomb count of the tick currents carried across blocks (``scoring.reference_soc``
    cut into pieces): SOC (fraction) from ``soc0`` at the first tick, capacity Ah, efficiency on
    charge, steps longer than ``gap_s`` (s) or back in time count nothing. The running sum of
    the SOC steps is carried as the whole record's cumulative sum builds it (sequentially), so
    the pieces give the same numbers bit for bit."""

    soc0: float
    capacity_Ah: float
    coulombic_efficiency: float
    gap_s: float
    _t: float = math.nan  # the last tick counted so far; its own step waits for the next tick
    _i: float = 0.0
    _sum: float = 0.0  # SOC steps up to that tick

    def soc(self, t_s: FloatArray, current_A: FloatArray) -> FloatArray:
        """The counted SOC at each of these ticks (the ones after those already counted)."""
        if t_s.size == 0:
            return np.zeros(0)
        t = np.concatenate(([self._t], t_s))
        i = np.concatenate(([self._i], current_A))
        dt = np.diff(t)
        dt = np.where((dt > 0) & (dt <= self.gap_s), dt, 0.0)  # the first tick's NaN step too
        dz = soc_delta(i[:-1], dt, self.capacity_Ah * 3600.0, self.coulombic_efficiency)
        sums = np.cumsum(np.concatenate(([self._sum], dz)))[1:]
        self._t, self._i, self._sum = float(t[-1]), float(i[-1]), float(sums[-1])
        return np.asarray(self.soc0 + sums, dtype=np.float64)


# ----------------------------------------------------------------------------- plots
@dataclass
class MinMaxDecimator:
    """Per bin of ``width`` consecutive ticks, the smallest and largest value of each series
    (series, cells) and the times (s) they occurred; NaN values are left out."""

    width: int
    lo: FloatArray  # (bins, series, cells)
    hi: FloatArray
    t_lo: FloatArray
    t_hi: FloatArray
    seen: int = 0

    @classmethod
    def for_ticks(cls, n_ticks: int, n_series: int, n_cells: int,
                  n_bins: int = PLOT_BINS) -> MinMaxDecimator:  # fmt: skip
        width = max(1, -(-n_ticks // n_bins))
        shape = (max(1, -(-n_ticks // width)), n_series, n_cells)
        return cls(width, np.full(shape, np.inf), np.full(shape, -np.inf),
                   np.full(shape, np.nan), np.full(shape, np.nan))  # fmt: skip

    def add(self, t_s: FloatArray, values: FloatArray) -> None:
        """Ticks at times ``t_s`` (T,) with ``values`` (T, series, cells), next in order."""
        n = t_s.shape[0]
        if n == 0:
            return
        bins = np.minimum((self.seen + np.arange(n)) // self.width, self.lo.shape[0] - 1)
        self.seen += n
        starts = np.flatnonzero(np.diff(bins, prepend=-1))
        which = bins[starts]
        counts = np.diff(np.append(starts, n))
        for vals, sign, best, when in ((values, 1.0, self.lo, self.t_lo),
                                       (-values, -1.0, self.hi, self.t_hi)):  # fmt: skip
            v = np.where(np.isnan(vals), np.inf, vals)
            seg = np.minimum.reduceat(v, starts, axis=0)
            at = v == np.repeat(seg, counts, axis=0)
            tt = np.where(at, t_s[:, None, None], np.inf)
            t_seg = np.minimum.reduceat(tt, starts, axis=0)
            old = sign * best[which]
            better = seg < old
            best[which] = np.where(better, sign * seg, best[which])
            when[which] = np.where(better & np.isfinite(seg), t_seg, when[which])

    def series(self, k: int, cell: int) -> tuple[FloatArray, FloatArray]:
        """Times (s) and values of series ``k`` of one cell: each bin's minimum and maximum in
        time order (one point when they are the same tick)."""
        t = np.stack([self.t_lo[:, k, cell], self.t_hi[:, k, cell]], axis=1)
        y = np.stack([self.lo[:, k, cell], self.hi[:, k, cell]], axis=1)
        swap = t[:, 1] < t[:, 0]
        t[swap] = t[swap][:, ::-1]
        y[swap] = y[swap][:, ::-1]
        t, y = t.ravel(), y.ravel()
        keep = np.isfinite(t) & np.append(True, np.diff(t) != 0)
        return t[keep], y[keep]


# ----------------------------------------------------------------------------- medians
class StreamedMedian:
    """Per cell, the median of a positive series streamed block by block, in flat memory: counts
    in log-spaced bins of ``rel_width`` relative width over [``lo``, ``hi``] (values outside
    counted in the end bins), the median read as its bin's geometric centre, so within
    ``rel_width / 2`` of the exact (lower) median. Last-tick values rank cells on noise (three
    copies of one cell's column read 72.8 / 85.2 / 82.4 mOhm at a record's end: a sweep); a
    median over the record does not."""

    def __init__(
        self, n_cells: int, lo: float = 1e-6, hi: float = 10.0, rel_width: float = 2e-3
    ) -> None:
        self._log_lo = math.log(lo)
        self._step = math.log1p(rel_width)
        self.n_bins = math.ceil(math.log(hi / lo) / self._step)
        self.counts = np.zeros((n_cells, self.n_bins), np.int32)

    def add(self, values: FloatArray, mask: BoolArray) -> None:
        """Count ``values`` (ticks, cells) where ``mask`` and they are finite and positive."""
        with np.errstate(invalid="ignore", divide="ignore"):
            ok = mask & np.isfinite(values) & (values > 0)
            k = (np.log(np.where(ok, values, 1.0)) - self._log_lo) / self._step
        cells = np.broadcast_to(np.arange(values.shape[1]), values.shape)[ok]
        bins = np.clip(k[ok].astype(np.int64), 0, self.n_bins - 1)
        np.add.at(self.counts, (cells, bins), 1)

    def median(self) -> FloatArray:
        """Each cell's median (NaN for a cell with nothing counted)."""
        n = self.counts.sum(axis=1)
        cum = np.cumsum(self.counts, axis=1)
        k = np.argmax(cum >= ((n + 1) // 2)[:, None], axis=1)
        centre = np.exp(self._log_lo + (k + 0.5) * self._step)
        return np.where(n > 0, centre, np.nan)


#: Published values a median over the record takes: the estimator's own (converging ones too:
#: a short record may never leave that code), not values held on a bound or after a divergence.
IDENTIFIED = (Quality.CONVERGING, Quality.CONVERGED, Quality.POORLY_EXCITED)


# ----------------------------------------------------------------------------- the run
@dataclass(frozen=True)
class PartMasks:
    """Where the parts of a block lie: ``startup`` (ticks, 1), ``window`` and ``band`` (index
    into the SOC bands, -1 for none), both (ticks, cells)."""

    startup: BoolArray
    window: BoolArray
    band: IntArray


class RunAccumulator:
    """Everything metrics.json and the plots need from a run's estimates, block by block.

    Parameters
    ----------
    n_ticks : int
        Ticks the run will produce (decides the start-up, the skipped share and the plot bins).
    n_cells : int
        Cells of every block.
    n_bands : int
        SOC bands scored.
    bounds : mapping of name to (lo, hi), or None
        Per watched parameter (``guard.WATCHED``) its bounds, each shape (n_cells,), for the
        published-on-a-bound share; None: not counted.
    """

    #: Parts before the bands: every tick, the start-up, the rest, the window.
    OVERALL, STARTUP, AFTER, WINDOW = range(4)

    def __init__(
        self,
        n_ticks: int,
        n_cells: int,
        n_bands: int,
        bounds: Mapping[str, tuple[FloatArray, FloatArray]] | None = None,
    ) -> None:
        self.n_ticks = n_ticks
        self.n_cells = n_cells
        self.n_bands = n_bands
        self.bounds = None if bounds is None else dict(bounds)
        self.seen = 0
        self.sums = ErrorSums.zeros(4 + n_bands, n_cells)
        self.on_bound = np.zeros(len(WATCHED), np.int64)
        self.published_on_bound = np.zeros(len(WATCHED), np.int64)
        self.plot = MinMaxDecimator.for_ticks(n_ticks, len(PLOT_SERIES), n_cells)
        self.first: EstimateBlock | None = None
        self.last: EstimateBlock | None = None
        self.score_soc = np.array([np.inf, -np.inf])
        self.score_soc_first = math.nan
        self.score_soc_last = math.nan
        self.est_soc = np.array([np.inf, -np.inf])
        self.r0_median = StreamedMedian(n_cells)
        #: per cell: window ticks, those whose published values were held (not ``IDENTIFIED``),
        #: and per ``WATCHED`` parameter those on a bound
        self.window_ticks = np.zeros(n_cells, np.int64)
        self.window_held = np.zeros(n_cells, np.int64)
        self.window_on_bound = np.zeros((len(WATCHED), n_cells), np.int64)
        #: per cell: discharge ticks at SOC 0 with a model error, their squared errors (V^2),
        #: the charge over them (Ah), the first one's time (s)
        self.empty_ticks = np.zeros(n_cells, np.int64)
        self.empty_sse = np.zeros(n_cells)
        self.empty_Ah = np.zeros(n_cells)
        self.empty_from_s = np.full(n_cells, np.nan)
        self._t_prev = math.nan
        #: per |current| band (``CRATE_EDGES``) and cell over the window's converged ticks
        #: (not a start's, whose error is the start values', nor a held cell's): the model
        #: error times the current's sign summed (V), and the ticks
        self.crate_sum = np.zeros((len(CRATE_EDGES), n_cells))
        self.crate_n = np.zeros((len(CRATE_EDGES), n_cells), np.int64)

    def add(self, block: EstimateBlock, parts: PartMasks, score_soc: FloatArray) -> None:
        """The next block of estimates, where its parts lie and its scoring SOC (ticks, cells)."""
        if block.n_ticks == 0:
            return
        if self.first is None:
            self.first = block.select(slice(0, 1))
            self.score_soc_first = _mean_finite(score_soc[0])
        self.last = block.select(slice(block.n_ticks - 1, block.n_ticks))
        self.score_soc_last = _mean_finite(score_soc[-1])
        self.seen += block.n_ticks
        meas = np.asarray(block["v_meas_V"], dtype=np.float64)
        model = np.asarray(block["v_model_V"], dtype=np.float64)
        with np.errstate(invalid="ignore", divide="ignore"):
            ok = np.isfinite(meas) & np.isfinite(model) & (np.abs(meas) > 0)
            err = np.where(ok, meas - model, 0.0)
            rel = np.where(ok, np.abs(err / np.where(ok, meas, 1.0)), 0.0)
        startup = np.broadcast_to(parts.startup, ok.shape)
        self.sums.add(self.OVERALL, ok, err, rel)
        self.sums.add(self.STARTUP, ok & startup, err, rel)
        self.sums.add(self.AFTER, ok & ~startup, err, rel)
        self.sums.add(self.WINDOW, ok & parts.window, err, rel)
        for k in range(self.n_bands):
            self.sums.add(4 + k, ok & (parts.band == k), err, rel)
        _extend(self.score_soc, score_soc)
        identified = np.isin(block.quality, IDENTIFIED)
        self.r0_median.add(np.asarray(block["R0_ohm"], np.float64), parts.window & identified)
        _extend(self.est_soc, np.asarray(block["soc"], dtype=np.float64))
        bits = _bits(block["on_bound"])
        self.window_ticks += np.count_nonzero(parts.window, axis=0)
        self.window_held += np.count_nonzero(parts.window & ~identified, axis=0)
        for j, name in enumerate(WATCHED):
            on = (bits >> j) & 1 > 0
            self.on_bound[j] += int(np.count_nonzero(on))
            self.window_on_bound[j] += np.count_nonzero(parts.window & on, axis=0)
            if self.bounds is None:
                continue
            lo, hi = self.bounds[name]
            x = block[name]
            pub = (x <= lo * (1 + ON_BOUND_REL)) | (x >= hi * (1 - ON_BOUND_REL))
            self.published_on_bound[j] += int(np.count_nonzero(pub))
        self._count_empty(block, ok, err)
        self._count_crate(block, ok & parts.window & (block.quality == Quality.CONVERGED), err)
        vals = [meas if k == "v_meas_V" else meas - model if k == "error_V" else block[k]
                for k in PLOT_SERIES]  # fmt: skip
        self.plot.add(block.t_s, np.stack(vals, axis=1))

    def bound_findings(self, cell_names: Sequence[str]) -> dict[str, object]:
        """The ``bounds`` entry of metrics.json (see ``identify.bound_findings``)."""
        size = self.seen * self.n_cells
        share = {n: (float(self.on_bound[j]) / size if size else 0.0)
                 for j, n in enumerate(WATCHED)}  # fmt: skip
        at_end: dict[str, list[str]] = {}
        if self.last is not None:
            bits = _bits(self.last["on_bound"])[0]
            for j, name in enumerate(WATCHED):
                ended = [cell_names[int(c)] for c in np.flatnonzero((bits >> j) & 1)]
                if ended:
                    at_end[name] = ended
        published = {n: float(self.published_on_bound[j]) / size
                     for j, n in enumerate(WATCHED) if self.published_on_bound[j]}  # fmt: skip
        return {
            "share_of_ticks_on_a_bound": share,
            "ends_on_a_bound": at_end,
            "published_on_a_bound": published,
        }

    def _count_empty(self, block: EstimateBlock, ok: BoolArray, err: FloatArray) -> None:
        """The discharge ticks whose published SOC sits at 0 (``past_empty``)."""
        t = block.t_s
        dt = np.diff(t, prepend=self._t_prev)
        self._t_prev = float(t[-1])
        dt = np.where(np.isfinite(dt) & (dt > 0) & (dt <= EMPTY_MAX_DT_S), dt, 0.0)
        i = np.asarray(block.current_A, dtype=np.float64)
        soc = np.asarray(block["soc"], dtype=np.float64)
        at = (soc <= EMPTY_SOC) & (i > 0)[:, None] & ok
        if not np.count_nonzero(at):
            return
        self.empty_ticks += np.count_nonzero(at, axis=0)
        self.empty_sse += np.sum(np.where(at, err * err, 0.0), axis=0)
        self.empty_Ah += np.sum(np.where(at, (i * dt)[:, None], 0.0), axis=0) / 3600.0
        first = np.where(at.any(axis=0), t[np.argmax(at, axis=0)], np.nan)
        self.empty_from_s = np.where(np.isnan(self.empty_from_s), first, self.empty_from_s)

    def _count_crate(self, block: EstimateBlock, ok: BoolArray, err: FloatArray) -> None:
        """The window's model error per |current| band (``current_dependence``)."""
        i = np.asarray(block.current_A, dtype=np.float64)[:, None]
        with np.errstate(invalid="ignore", divide="ignore"):
            c_rate = np.abs(i) / np.asarray(block["capacity_Ah"], dtype=np.float64)
        band = np.searchsorted(CRATE_EDGES, c_rate, side="right") - 1  # -1: below the first
        signed = err * np.sign(i)
        for k in range(len(CRATE_EDGES)):
            m = ok & (band == k)
            self.crate_sum[k] += np.sum(np.where(m, signed, 0.0), axis=0)
            self.crate_n[k] += np.count_nonzero(m, axis=0)

    def current_dependence(self, cell: int) -> list[tuple[str, float, int]]:
        """One cell's mean model error (V) times the current's sign per |current| band
        (``CRATE_EDGES``) over the window's converged ticks, with the band's label and
        ticks: under a resistance
        that falls as the current grows (a cold cell's charge-transfer kinetics), the fitted
        linear one overstates the drop at high currents (positive there) and understates it
        at low ones."""
        labels = [f"{a:g}-{b:g}C" for a, b in itertools.pairwise(CRATE_EDGES)]
        labels.append(f"> {CRATE_EDGES[-1]:g}C")
        return [
            (labels[k], float(self.crate_sum[k, cell]) / int(self.crate_n[k, cell]),
             int(self.crate_n[k, cell]))
            for k in range(len(CRATE_EDGES)) if self.crate_n[k, cell]
        ]  # fmt: skip

    def past_empty(self, cell: int) -> dict[str, float] | None:
        """One cell's discharge past its estimated empty: ticks, the charge moved there (Ah),
        the model's RMSE over them (V) and the first one's time (s); None where it never
        discharged at SOC 0. A 2RC model cannot follow the voltage collapse there, and a
        cell that still gives charge holds more than the capacity in use (or started higher)."""
        n = int(self.empty_ticks[cell])
        if n == 0:
            return None
        return {
            "ticks": n,
            "charge_Ah": float(self.empty_Ah[cell]),
            "rmse_V": math.sqrt(float(self.empty_sse[cell]) / n),
            "from_t_s": float(self.empty_from_s[cell]),
        }

    def held(self, cell: int) -> tuple[float, str | None, float]:
        """Over one cell's window ticks: the share whose published values were held (on a bound
        or after a divergence), the parameter most often on a bound (None: none) and its share."""
        n = int(self.window_ticks[cell])
        if n == 0:
            return 0.0, None, 0.0
        shares = self.window_on_bound[:, cell] / n
        j = int(np.argmax(shares))
        name = WATCHED[j] if shares[j] > 0 else None
        return int(self.window_held[cell]) / n, name, float(shares[j]) if name else 0.0

    def soc_range(self) -> dict[str, float | None]:
        """First and last scoring SOC (mean over the cells) and its extremes (fractions)."""
        if not np.isfinite(self.score_soc).all():
            return {"soc_first": None, "soc_last": None, "soc_min": None, "soc_max": None}
        return {
            "soc_first": None if math.isnan(self.score_soc_first) else self.score_soc_first,
            "soc_last": None if math.isnan(self.score_soc_last) else self.score_soc_last,
            "soc_min": float(self.score_soc[0]),
            "soc_max": float(self.score_soc[1]),
        }


def _bits(on_bound: FloatArray) -> npt.NDArray[np.int64]:
    """The ``on_bound`` codes as integers, a ``no_data`` cell's NaN as no bit (a NaN cast to
    int64 is undefined)."""
    x = np.asarray(on_bound, dtype=np.float64)
    return np.where(np.isfinite(x), x, 0.0).astype(np.int64)


def _mean_finite(x: FloatArray) -> float:
    ok = x[np.isfinite(x)]
    return float(ok.mean()) if ok.size else math.nan


def _extend(extremes: FloatArray, x: FloatArray) -> None:
    """Widen ``[min, max]`` by the finite values of ``x``."""
    ok = x[np.isfinite(x)]
    if ok.size:
        extremes[0] = min(extremes[0], float(ok.min()))
        extremes[1] = max(extremes[1], float(ok.max()))
