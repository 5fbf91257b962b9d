"""The publish guard: never publish garbage, never let a value jump to a bound silently.

The last stage of a tick. It sees what the bank is about to publish and decides, per cell:

* **on a bound** (the parameter stage clamped the cell this tick, ``clamped``, or one of its
  R0, R1, R2, tau1, tau2 sits within :data:`ON_BOUND_REL` of a bound: a parameter can stay on
  its bound for hours after one clamp): the identified parameters published are the cell's
  last good ones, the quality is ``OUT_OF_BOUNDS``, and :attr:`PublishGuard.bound_bits` says
  which parameters sit on a bound (the finding ``identify`` reports); the
  estimators keep running (a bound says an estimate is implausible, not that the model fails:
  re-initialising would throw away the RLS memory, and would loop on a cell whose configured
  bounds are too tight). Counted in ``held_on_bound`` (cell-ticks).
* **diverged** -- the model error far beyond its running scale for ``divergence_hold_s`` of
  data (default an hour), SOC outside [-m, 1 + m] (m = ``divergence_soc_margin``) or not
  finite, or a parameter not finite or not > 0: the quality is ``DIVERGED``, the last good
  parameters are published, and the cell is returned in the re-initialisation mask once per
  episode (the bank resets its SOC from the observer's start policy and its parameters to the
  start values). The episode lasts until the cell is no longer diverged and no longer
  ``CONVERGING``: until then the last good values stay published under ``DIVERGED`` (start
  values are no better). Counted in ``diverged`` (episodes).

Held together, per cell (all or none, so C1 = tau1 / R1 stays true): :data:`HELD`, the identified
parameters. SOC is held only while it is itself bad (a re-initialised SOC is better than the
held one); the measured voltage, the model voltage and error (the evidence), lambda, h and the
observer's outputs always pass through.

Model error test, per cell, with ``e`` the tick's ``v_error_V`` (NaN: the tick does not count)
and ``dt`` the tick's data time (the step since the previous tick; ``id_period_s`` at the first
tick, after a gap or a time jump back)::

    F = EWMA_fast(e^2)   time constant divergence_fast_s   (the recent error power)
    S = EWMA_slow(e^2)   time constant divergence_scale_s  (the running scale)
    L = k^2 max(S, floor^2)                                 (k = divergence_sigmas)
    excess  = judged and S has >= divergence_fast_s of data and F > L
    T      += dt while in excess, T = 0 at a judged tick not in excess
    diverged (error) = T >= divergence_hold_s

A tick is judged when the cell is not ``CONVERGING`` and may learn (``learn``: outside the OCV
curve's knees, ``EstimatorTuning.knee_slope_factor``, where the model error is SOC's and the
curve's, tens of mV per point of SOC, not the parameters'); other ticks neither count towards T
nor clear it. S learns from judged ticks that are excited (quality not ``POORLY_EXCITED``: a
rest's sub-mV error would shrink it, and the next drive cycle would look like a divergence) and
not in an episode. For its first ``divergence_scale_s`` of data it learns every such tick (the
level is found, whatever it is); after that only ticks not in excess whose own e^2 <= L: a
divergence that jumps the error by more than k (a wrong SOC, a parameter gone) never teaches S
that large errors are normal, while a level that drifts (temperature, ageing, a harder drive
cycle) is followed. (Clipping those errors instead of dropping them was measured to fail: on
the A123 DYN50 record, S ~6 mV RMS, a 50 mV offset raised the limit faster than F rose, and
was never caught; dropped, it is caught one hold later. Numbers: ``divergence_sigmas``.)

Each EWMA is bias-corrected (``x += g / w (e^2 - x)``, ``g = 1 - exp(-dt / tau)``, ``w = 1 -
exp(-seconds seen / tau)``), so it starts at the mean of what it saw rather than at zero. A
re-initialised cell starts F, S and T again (its scale is learnt anew once it has converged).

The bank calls it last in a tick (``_run_tick``) and resets what it returns::

    self.guard = PublishGuard.for_model(model, self.tuning)          # __init__
    ...
    cells, q, reinit = self.guard.apply(tick.t_s, cells, q, self.params.clamped, ctx.learn)
    if reinit.any():
        self.reset(reinit)  # state and parameters; reset() also calls self.guard.reset(m)
    return cells, q

and nests ``self.guard.state_dict()`` under ``"guard"`` in its checkpoint (counters merged with
the other stages'). Pure numpy, no I/O, vectorised over cells.
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

import numpy as np
import numpy.typing as npt

from bmsid.estimate.cellmodel import CellModel
from bmsid.estimate.guard_kernel import (
    CAUSE_ERROR,
    CAUSE_PARAMS,
    CAUSE_SOC,
    HELD,
    KERNEL,
    WATCHED,
)
from bmsid.estimate.statedict import load_arrays
from bmsid.estimate.tuning import EstimatorTuning

FloatArray = npt.NDArray[np.float64]
IntArray = npt.NDArray[np.int64]
BoolArray = npt.NDArray[np.bool_]

__all__ = ["CAUSE_ERROR", "CAUSE_PARAMS", "CAUSE_SOC", "HELD", "ON_BOUND_REL", "WATCHED",
           "PublishGuard"]  # fmt: skip

#: A parameter within this share of a bound counts as on it (a clamp leaves it exactly there;
#: the RLS map and the swarm can settle just inside).
ON_BOUND_REL = 0.01

#: The model-error statistics, rows of ``PublishGuard._stats`` (each also an attribute).
_STATS = ("e2_fast", "fast_s", "e2_scale", "scale_s", "excess_s")
_ARRAYS = (*_STATS, "good", "good_soc", "episode", "cause")


class _StatRow:
    """One row of ``PublishGuard._stats`` as an attribute: read, a view of the live row (the
    tick kernel updates it in place); set, the row of a copy."""

    def __init__(self, row: int) -> None:
        self.row = row

    def __get__(self, guard: Any, owner: object = None) -> FloatArray:
        return guard._stats[self.row]  # type: ignore[no-any-return]

    def __set__(self, guard: Any, value: npt.ArrayLike) -> None:
        stats = guard._stats.copy()
        stats[self.row] = value
        guard._stats = stats


class PublishGuard:
    """Holds, flags and re-initialises what must not be published (module docstring).

    Args:
        n_cells: cells of the bank.
        tuning: the ``divergence_*`` constants, ``gap_s`` and ``id_period_s``.
        start: per :data:`HELD` name, the values published when a cell is held before it ever
            had a good tick (shape (n,) or scalar); a name left out holds NaN, which the MQTT
            schema refuses for a parameter: the bank builds its guard with :meth:`for_model`.
        bounds: per :data:`WATCHED` name, (lo, hi) (each shape (n,) or scalar); a parameter
            within :data:`ON_BOUND_REL` of one is held like a clamped one. None: only clamps.

    Attributes:
        counters: ``diverged`` (episodes started), ``held_on_bound`` (cell-ticks held at a bound).
        bound_bits: per cell, the :data:`WATCHED` parameters (bit ``1 << j``) the estimator had
            on a bound at the last tick (their last good values were published), shape (n,).
        episode: cells in a divergence episode (quality ``DIVERGED``), shape (n,).
        cause: ``CAUSE_*`` bits of each cell's present episode (0 outside one), shape (n,).
    """

    name = "guard"
    #: the model-error statistics F, its seconds seen, S, its seconds seen, T (module docstring)
    e2_fast, fast_s, e2_scale, scale_s, excess_s = (_StatRow(j) for j in range(len(_STATS)))

    def __init__(
        self,
        n_cells: int,
        tuning: EstimatorTuning | None = None,
        start: Mapping[str, npt.ArrayLike] | None = None,
        bounds: Mapping[str, tuple[npt.ArrayLike, npt.ArrayLike]] | None = None,
    ) -> None:
        self.n = n_cells
        self.tuning = tuning or EstimatorTuning()
        self.counters: dict[str, int] = {"diverged": 0, "held_on_bound": 0}
        start = start or {}
        self.good = np.stack(
            [np.broadcast_to(np.asarray(start.get(k, np.nan), dtype=np.float64), (n_cells,))
             for k in HELD]
        )  # fmt: skip
        self.good_soc = np.full(n_cells, np.nan)
        self.episode = np.zeros(n_cells, dtype=bool)
        self.cause = np.zeros(n_cells, dtype=np.int64)
        self._stats = np.zeros((len(_STATS), n_cells))  # e2_fast ... excess_s: one array
        self.t_prev: float | None = None
        self.bound_bits = np.zeros(n_cells, dtype=np.int64)
        # the kernel's arguments that never change: "on a bound" limits (lo, hi) per WATCHED
        # row (NaN and not read without bounds), the tuning's numbers, learn for all cells
        self._near = np.full((2, len(WATCHED), n_cells), np.nan)
        self._has_near = bounds is not None
        if bounds is not None:
            lo, hi = (
                np.stack([np.broadcast_to(np.asarray(bounds[k][i], dtype=np.float64), (n_cells,))
                          for k in WATCHED])
                for i in (0, 1)
            )  # fmt: skip
            self._near = np.array([lo + ON_BOUND_REL * np.abs(lo), hi - ON_BOUND_REL * np.abs(hi)])
        tun = self.tuning
        self._consts = np.array([
            tun.divergence_soc_margin, tun.divergence_fast_s, tun.divergence_scale_s,
            tun.divergence_hold_s, tun.divergence_sigmas**2, tun.divergence_floor_V**2,
        ])  # fmt: skip
        self._learn_all = np.ones(n_cells, dtype=bool)

    @classmethod
    def for_model(cls, model: CellModel, tuning: EstimatorTuning | None = None) -> PublishGuard:
        """A guard whose values before any good tick are ``model``'s start values (inside its
        bounds; C = tau / R, OCV offset 0): what a ``CONVERGING`` cell publishes anyway."""
        s = {k: np.clip(model.start(k), *model.bound(k)) for k in ("R0_ohm", "R1_ohm", "R2_ohm")}
        s |= {k: np.clip(model.start(k), *model.bound(k)) for k in ("tau1_s", "tau2_s")}
        s["C1_F"] = s["tau1_s"] / s["R1_ohm"]
        s["C2_F"] = s["tau2_s"] / s["R2_ohm"]
        s["ocv_offset_V"] = np.clip(np.zeros(model.n_cells), *model.bound("ocv_offset_V"))
        return cls(model.n_cells, tuning, s, {k: model.bound(k) for k in WATCHED})

    # ------------------------------------------------------------------ one tick
    def apply(
        self,
        t_s: float,
        cells: Mapping[str, FloatArray],
        quality: IntArray,
        on_bound: BoolArray,
        learn: BoolArray | None = None,
    ) -> tuple[dict[str, FloatArray], IntArray, BoolArray]:
        """Guard one tick's outputs.

        Args:
            t_s: the tick's time, s.
            cells: every output field, shape (n,) each (``soc`` and ``v_error_V`` are read
                from it, as are the :data:`HELD` parameters); never modified.
            quality: the bank's quality codes, shape (n,); never modified.
            on_bound: cells the parameter stage clamped to a bound this tick, shape (n,); cells
                whose parameters sit on a bound are added (``bounds``).
            learn: cells whose parameters may learn from this tick (``TickContext.learn``),
                shape (n,); None: all. The others' model error is not judged this tick.

        Returns:
            (what to publish: ``cells`` with held values where needed, the quality codes with
            ``DIVERGED`` where a cell is in an episode, the cells to re-initialise now).
        """
        # one kernel call (guard_kernel.py): the numpy reference or its compiled twin
        params = np.array([cells[k] for k in HELD], dtype=np.float64)
        learn_ = self._learn_all if learn is None else np.asarray(learn, dtype=bool)
        # (the statistics, episodes, causes and bound bits are updated in place)
        good, soc, q, reinit, n_reinit, n_held, masked = KERNEL.impl(
            self._data_dt(t_s), np.asarray(cells["soc"], dtype=np.float64), params,
            np.asarray(cells["v_error_V"], dtype=np.float64), np.asarray(quality, dtype=np.int64),
            np.asarray(on_bound, dtype=bool), learn_, self._stats, self.good, self.good_soc,
            self.episode, self.cause, self.bound_bits, self._near, self._has_near, self._consts,
        )  # fmt: skip
        if n_reinit:  # (both usually 0)
            self.counters["diverged"] += n_reinit
        if n_held:
            self.counters["held_on_bound"] += n_held
        out = dict(cells)
        out["on_bound"] = self.bound_bits.astype(np.float64)
        if masked:  # else the cells' own arrays are published
            for j, k in enumerate(HELD):
                out[k] = good[j]
        self.good = good
        out["soc"] = self.good_soc = soc
        return out, q, reinit

    def _data_dt(self, t_s: float) -> float:
        """The tick's data time, s: the step since the previous tick, or ``id_period_s`` at the
        first tick, after a gap (longer than ``gap_s``) or a time jump back."""
        tun = self.tuning
        prev, self.t_prev = self.t_prev, float(t_s)
        step = float(t_s) - prev if prev is not None else 0.0
        return step if 0.0 < step <= tun.gap_s else tun.id_period_s

    # ------------------------------------------------------------------ protocol
    def reset(self, mask: npt.ArrayLike) -> None:
        """Forget the masked cells' model-error statistics (learnt again once they converge).
        Their last good values and any running episode are kept: a re-initialised cell stays
        ``DIVERGED`` with its last good values until it has converged again."""
        m = np.broadcast_to(np.asarray(mask, dtype=bool), (self.n,))
        self._stats = np.where(m, 0.0, self._stats)

    def state_dict(self) -> dict[str, Any]:
        """Plain arrays and numbers that restore the guard exactly."""
        st: dict[str, Any] = {k: np.array(getattr(self, k)) for k in (*_ARRAYS, "bound_bits")}
        st["t_prev"] = np.nan if self.t_prev is None else self.t_prev
        return st

    def load_state_dict(self, st: dict[str, Any]) -> None:
        """Restore :meth:`state_dict` output; ValueError/KeyError when it does not fit."""
        load_arrays(self, st, _ARRAYS, self.name)
        # The bound findings open the next tick's learn gate (``bank._run_tick``). Checkpoints
        # written before they were saved restore none: their first tick learns as the fresh
        # findings of that tick say (a restored bank then differed for a tick or two).
        if "bound_bits" in st:
            load_arrays(self, st, ("bound_bits",), self.name)
        else:
            self.bound_bits = np.zeros(self.n, dtype=np.int64)
        t = float(st["t_prev"])
        self.t_prev = t if np.isfinite(t) else None
