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

import math
from collections.abc import Mapping
from typing import Any

import numpy as np
import numpy.typing as npt

from bmsid.estimate.cellmodel import CellModel
from bmsid.estimate.fields import FIELDS_BY_NAME
from bmsid.estimate.statedict import load_arrays
from bmsid.estimate.tuning import EstimatorTuning
from bmsid.estimate.types import Quality

FloatArray = npt.NDArray[np.float64]
IntArray = npt.NDArray[np.int64]
BoolArray = npt.NDArray[np.bool_]

#: The identified parameters, published together from one tick: the current one, or the last good.
HELD: tuple[str, ...] = (
    "R0_ohm", "R1_ohm", "C1_F", "R2_ohm", "C2_F", "tau1_s", "tau2_s", "ocv_offset_V",
)  # fmt: skip
#: Per :data:`HELD` row, the value a parameter must exceed: 0 where it must be > 0, else -inf
#: (finite only).
_LOWER = np.array([[0.0 if FIELDS_BY_NAME[k].positive else -np.inf] for k in HELD])

#: The bounded parameters the guard watches, in the bit order of :attr:`PublishGuard.bound_bits`
#: (1 R0, 2 R1, 4 R2, 8 tau1, 16 tau2).
WATCHED: tuple[str, ...] = ("R0_ohm", "R1_ohm", "R2_ohm", "tau1_s", "tau2_s")
_WATCHED_ROWS = np.array([HELD.index(k) for k in WATCHED])
_BIT_VALUES = (1 << np.arange(len(WATCHED), dtype=np.int64))[:, None]
#: Per :data:`HELD` row, its branch (0 R0, 1 R1 C1 tau1, 2 R2 C2 tau2; 3 none: the OCV offset
#: is held only with the whole cell).
_BRANCH_OF_HELD = np.array([0, 1, 1, 2, 2, 1, 2, 3])
_TAUS = [HELD.index("tau1_s"), HELD.index("tau2_s")]
_RC_ROWS = ((_BRANCH_OF_HELD == 1) | (_BRANCH_OF_HELD == 2))[:, None]
#: A parameter within this share of a bound counts as on it (a clamp leaves it exactly there;
#: the RLS map and the swarm can settle just inside).
ON_BOUND_REL = 0.01

#: Bits of :attr:`PublishGuard.cause`: why the cell's present episode started.
CAUSE_SOC = 1  #: SOC outside [-margin, 1 + margin] or not finite
CAUSE_ERROR = 2  #: model error in excess for ``divergence_hold_s``
CAUSE_PARAMS = 4  #: a parameter not finite (or not > 0 where it must be)

#: Quality codes as plain ints: numpy compares an array with an IntEnum member 5x slower.
_CONVERGING = int(Quality.CONVERGING)
_POORLY_EXCITED = int(Quality.POORLY_EXCITED)
_OUT_OF_BOUNDS = int(Quality.OUT_OF_BOUNDS)
_DIVERGED = int(Quality.DIVERGED)

_STATS = ("e2_fast", "fast_s", "e2_scale", "scale_s", "excess_s")
_ARRAYS = (*_STATS, "good", "good_soc", "episode", "cause")


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
        self.e2_fast = np.zeros(n_cells)
        self.fast_s = np.zeros(n_cells)
        self.e2_scale = np.zeros(n_cells)
        self.scale_s = np.zeros(n_cells)
        self.excess_s = np.zeros(n_cells)
        self.t_prev: float | None = None
        self.bound_bits = np.zeros(n_cells, dtype=np.int64)
        self._near: tuple[FloatArray, FloatArray] | None = None
        if bounds is not None:
            lo, hi = (
                np.stack([np.broadcast_to(np.asarray(bounds[k][i], dtype=np.float64), (n_cells,))
                          for k in WATCHED])
                for i in (0, 1)
            )  # fmt: skip
            self._near = (lo + ON_BOUND_REL * np.abs(lo), hi - ON_BOUND_REL * np.abs(hi))

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
        # ~40 us per tick when all is well (1 or 96 cells): branches skip what is not needed
        tun = self.tuning
        dt = self._data_dt(t_s)
        soc = np.asarray(cells["soc"], dtype=np.float64)
        # np.array of a list of equal rows: a fifth of np.stack's cost on rows this short
        params = np.array([cells[k] for k in HELD], dtype=np.float64)
        q = np.array(quality, dtype=np.int64)  # the copy returned
        converging = q == _CONVERGING

        # what is wrong now
        margin = tun.divergence_soc_margin
        soc_bad = ~((soc >= -margin) & (soc <= 1.0 + margin))  # NaN included
        params_bad = ~((params > _LOWER) & (params < np.inf)).all(axis=0)  # NaN included
        judged = ~converging if learn is None else ~converging & np.asarray(learn, dtype=bool)
        error_bad = self._error_step(
            np.asarray(cells["v_error_V"], dtype=np.float64), dt, judged,
            q != _POORLY_EXCITED,
        )  # fmt: skip
        diverged = soc_bad | error_bad | params_bad

        # episodes: one re-initialisation each; over once the cell converged again, unharmed
        reinit = diverged & ~self.episode
        # np.count_nonzero: a fifth of ndarray.any()'s cost on these short masks
        if np.count_nonzero(reinit) or np.count_nonzero(self.episode):
            over = self.episode & ~diverged & ~converging
            self.episode = (self.episode | reinit) & ~over
            cause = soc_bad * CAUSE_SOC | error_bad * CAUSE_ERROR | params_bad * CAUSE_PARAMS
            self.cause = np.where(reinit, cause, np.where(self.episode, self.cause, 0))
            self.counters["diverged"] += int(reinit.sum())
            if reinit.any():
                self.reset(reinit)
            q[self.episode] = _DIVERGED

        # hold the parameters (all of a cell's on a clamp or in an episode; on a parameter that
        # sits on a bound, its branch: R0, or R1 C1 tau1, or R2 C2 tau2, so C = tau / R stays
        # true and R0 still follows temperature while tau2 waits on its bound) and a bad SOC
        held = np.asarray(on_bound, dtype=bool) | self.episode
        clamped = np.count_nonzero(held) > 0
        mask: BoolArray | None = None
        if self._near is not None:
            w = params[_WATCHED_ROWS]
            # converging cells too: a value learnt on a bound before convergence would become
            # the "last good" one (the bank flags them after the average, bank._run_tick)
            sits = (w <= self._near[0]) | (w >= self._near[1])
            self.bound_bits = (sits * _BIT_VALUES).sum(axis=0)
            if np.count_nonzero(sits):
                none = np.zeros(self.n, dtype=bool)
                branch = np.array([sits[0], sits[1] | sits[3], sits[2] | sits[4], none])
                mask = branch[_BRANCH_OF_HELD] | held
                q[(self.bound_bits > 0) & ~self.episode & ~converging] = _OUT_OF_BOUNDS
        if mask is None and clamped:
            mask = np.broadcast_to(held, params.shape)
        # branch 1 stays the fast one: a branch held while the other moves can cross it (tau2
        # held by its lower bound, tau1 rising past it), so both RC branches are held then
        taus = params[_TAUS] if mask is None else np.where(mask, self.good, params)[_TAUS]
        crossed = ~(taus[0] < taus[1])  # NaN included
        if np.count_nonzero(crossed):
            mask = (held if mask is None else mask) | (crossed & _RC_ROWS)
        out = dict(cells)
        out["on_bound"] = self.bound_bits.astype(np.float64)
        if mask is not None:
            self.counters["held_on_bound"] += int((mask.any(axis=0) & ~self.episode).sum())
            published = np.where(mask, self.good, params)
            for j, k in enumerate(HELD):
                out[k] = published[j]
            self.good = published
        else:
            self.good = params
        # a count up to the margin past 0 or 1 is no divergence, but is published as 0 or 1
        good = np.where(soc_bad, self.good_soc, soc) if np.count_nonzero(soc_bad) else soc
        out["soc"] = self.good_soc = np.minimum(np.maximum(good, 0.0), 1.0)
        return out, q, reinit

    def _data_dt(self, t_s: float) -> float:
        """The tick's data time, s: the step since the previous tick, or ``id_period_s`` at the
        first tick, after a gap (longer than ``gap_s``) or a time jump back."""
        tun = self.tuning
        prev, self.t_prev = self.t_prev, float(t_s)
        step = float(t_s) - prev if prev is not None else 0.0
        return step if 0.0 < step <= tun.gap_s else tun.id_period_s

    def _error_step(
        self, err: FloatArray, dt: float, judged: BoolArray, excited: BoolArray
    ) -> BoolArray:
        """Advance F, S and T by one tick (module docstring) for the cells ``judged`` (not
        converging, may learn; S learns from the ``excited`` ones); the cells whose model error
        has been in excess for ``divergence_hold_s``."""
        if self.n == 1:
            return self._error_step_one(float(err[0]), dt, bool(judged[0]), bool(excited[0]))
        tun = self.tuning
        fin = np.isfinite(err)
        e2 = err * err  # NaN where not fin: every use below is masked by fin
        self.fast_s, self.e2_fast = _ewma(
            self.fast_s, self.e2_fast, e2, fin, dt, tun.divergence_fast_s
        )
        limit = tun.divergence_sigmas**2 * np.maximum(self.e2_scale, tun.divergence_floor_V**2)
        judged = fin & judged
        excess = judged & (self.scale_s >= tun.divergence_fast_s) & (self.e2_fast > limit)
        young = self.scale_s < tun.divergence_scale_s
        teach = judged & excited & ~self.episode & (young | (~excess & (e2 <= limit)))
        self.scale_s, self.e2_scale = _ewma(
            self.scale_s, self.e2_scale, e2, teach, dt, tun.divergence_scale_s
        )
        self.excess_s = np.where(excess, self.excess_s + dt, np.where(judged, 0.0, self.excess_s))
        return np.asarray(self.excess_s >= tun.divergence_hold_s)

    def _error_step_one(self, err: float, dt: float, judged: bool, excited: bool) -> BoolArray:
        """:meth:`_error_step` of a one-cell guard in Python floats: the same operations in the
        same order (np.expm1 as the arrays use it; a mask is a branch), the same bits
        (``tests/estimate/test_guard.py``); ~10 us instead of ~30 us of numpy calls a tick."""
        tun = self.tuning
        fin = math.isfinite(err)
        e2 = err * err
        fast_s, e2_fast = _ewma_one(
            float(self.fast_s[0]), float(self.e2_fast[0]), e2, fin, dt, tun.divergence_fast_s
        )
        scale_s, e2_scale = float(self.scale_s[0]), float(self.e2_scale[0])
        limit = tun.divergence_sigmas**2 * _maximum(e2_scale, tun.divergence_floor_V**2)
        judged = fin and judged
        excess = judged and scale_s >= tun.divergence_fast_s and e2_fast > limit
        young = scale_s < tun.divergence_scale_s
        teach = (
            judged and excited and not self.episode[0] and (young or (not excess and e2 <= limit))
        )
        scale_s, e2_scale = _ewma_one(scale_s, e2_scale, e2, teach, dt, tun.divergence_scale_s)
        excess_s = float(self.excess_s[0])
        excess_s = excess_s + dt if excess else (0.0 if judged else excess_s)
        self.fast_s, self.e2_fast = np.array([fast_s]), np.array([e2_fast])
        self.scale_s, self.e2_scale = np.array([scale_s]), np.array([e2_scale])
        self.excess_s = np.array([excess_s])
        return np.array([excess_s >= tun.divergence_hold_s])

    # ------------------------------------------------------------------ protocol
    def reset(self, mask: npt.ArrayLike) -> None:
        """Forget the masked cells' model-error statistics (learnt again once they converge).
        Their last good values and any running episode are kept: a re-initialised cell stays
        ``DIVERGED`` with its last good values until it has converged again."""
        m = np.broadcast_to(np.asarray(mask, dtype=bool), (self.n,))
        for k in _STATS:
            setattr(self, k, np.where(m, 0.0, getattr(self, k)))

    def state_dict(self) -> dict[str, Any]:
        """Plain arrays and numbers that restore the guard exactly."""
        st: dict[str, Any] = {k: np.array(getattr(self, k)) for k in _ARRAYS}
        st["t_prev"] = np.nan if self.t_prev is None else self.t_prev
        return st

    def load_state_dict(self, st: dict[str, Any]) -> None:
        """Restore :meth:`state_dict` output; ValueError/KeyError when it does not fit."""
        load_arrays(self, st, _ARRAYS, self.name)
        t = float(st["t_prev"])
        self.t_prev = t if np.isfinite(t) else None


def _ewma(
    seen_s: FloatArray, x: FloatArray, value: FloatArray, use: BoolArray, dt: float, tau_s: float
) -> tuple[FloatArray, FloatArray]:
    """Bias-corrected EWMA over time: ``x += g / w (value - x)`` where ``use``, with ``g = 1 -
    exp(-dt / tau)`` and ``w = 1 - exp(-seen / tau)`` (``seen`` counted with this tick): the
    weighted mean of what it saw, not a pull towards 0. Returns (seen s, x)."""
    every = np.count_nonzero(use) == use.size  # the usual tick: the same numbers, no masks
    seen = seen_s + dt if every else np.where(use, seen_s + dt, seen_s)
    g = -math.expm1(-dt / tau_s)
    w = np.maximum(-np.expm1(seen * (-1.0 / tau_s)), g)  # >= g > 0: no 0/0 where unused
    if every:
        return seen, x + (g / w) * (value - x)
    return seen, np.where(use, x + (g / w) * (value - x), x)


def _ewma_one(
    seen_s: float, x: float, value: float, use: bool, dt: float, tau_s: float
) -> tuple[float, float]:
    """:func:`_ewma` of one cell in Python floats (np.expm1 kept: libm's expm1 differs from
    numpy's in the last bit)."""
    seen = seen_s + dt if use else seen_s
    g = -math.expm1(-dt / tau_s)
    w = _maximum(float(-np.expm1(seen * (-1.0 / tau_s))), g)
    return seen, (x + (g / w) * (value - x) if use else x)


def _maximum(a: float, b: float) -> float:
    """np.maximum of two floats: NaN propagates, ties give ``a``."""
    return a if a >= b or math.isnan(a) else b
