"""One tick of the publish guard (``guard.py``) in one call: numpy reference, compiled kernel.

``PublishGuard.apply`` gathers the tick's arrays and its own state, calls ``KERNEL.impl`` (the
implementation ``jit.select`` chose) once, and stores what comes back. Both implementations
take and return the same arrays and make the same decisions:

* ``guard_step_numpy``: the reference, the guard's vectorised numpy code as it was (the one-cell
  model-error test in Python floats included), moved here unchanged but for the state, passed
  in and returned instead of read from and written to ``self``;
* ``_guard_source``: the same rules per cell in plain loops, compiled by numba. Its helpers (the
  NaN-propagating max/min, the bias-corrected EWMA step) are inner functions of the source:
  numba compiles and inlines them with it (and caches them with it), and the module imports
  no numba, so the reference runs where numba is missing. Arithmetic in the same order as the
  reference; the one difference is ``expm1`` (libm's here; the reference's is numpy's own SIMD
  one, a last-bit different for a few percent of arguments), so the statistics agree to
  rounding and the decisions are the same (``tests/estimate/test_guard_kernel.py``).

Constants the compiled kernel reads from this module (the row layout, the quality codes, each
parameter's lower limit) are literals here, checked against their sources at import: numba's
cache recompiles when this file changes, not when another module's constants do.

Arguments (n cells; the guard's own state ``stats``, ``episode``, ``cause`` and ``bound_bits`` is
updated in place, which spares the compiled call boxing four more arrays, ~0.7 us each; the
others are never written)::

    dt         the tick's data time, s
    soc, err   SOC and the model error v_error_V, (n,)
    params     the HELD parameters, (8, n)
    quality    the bank's quality codes, (n,) int64
    on_bound   cells the parameter stage clamped, (n,) bool
    learn      cells that may learn this tick, (n,) bool
    stats      e2_fast, fast_s, e2_scale, scale_s, excess_s (rows), (5, n)
    good       the last published parameters, (8, n); good_soc the last published SOC, (n,)
    episode    (n,) bool; cause (n,) int64; bound_bits (n,) int64 (kept as is without bounds)
    near       the bounds' "on a bound" limits (lo, hi) per WATCHED row, (2, 5, n)
    has_near   whether the guard has bounds (else ``near`` is not read)
    consts     divergence_soc_margin, _fast_s, _scale_s, _hold_s, divergence_sigmas^2,
               divergence_floor_V^2

Returns new arrays, which the caller may hand out: ``(published (8, n), soc published (n,),
quality (n,), reinit (n,), n_reinit, n_held, masked)``: ``published`` is the new last-good
array (the parameters when ``masked`` is False: nothing held, publish the cells' own arrays),
the counts are the counters' increments (episodes started, cell-ticks held outside one).
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np
import numpy.typing as npt

from bmsid.estimate import jit
from bmsid.estimate.fields import FIELDS_BY_NAME
from bmsid.estimate.types import Quality

FloatArray = npt.NDArray[np.float64]
BoolArray = npt.NDArray[np.bool_]

#: The identified parameters, published together from one tick: the current one, or the last good.
HELD: tuple[str, ...] = (
    "R0_ohm", "R1_ohm", "C1_F", "R2_ohm", "C2_F", "tau1_s", "tau2_s", "ocv_offset_V",
)  # fmt: skip
#: The bounded parameters the guard watches, in the bit order of ``PublishGuard.bound_bits``
#: (1 R0, 2 R1, 4 R2, 8 tau1, 16 tau2).
WATCHED: tuple[str, ...] = ("R0_ohm", "R1_ohm", "R2_ohm", "tau1_s", "tau2_s")
#: Per HELD row, the value a parameter must exceed: 0 where it must be > 0, else -inf.
LOWER = (0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, -math.inf)
_LOWER = np.array(LOWER)[:, None]
WATCHED_ROWS = (0, 1, 3, 5, 6)
_WATCHED_ROWS = np.array(WATCHED_ROWS)
_BIT_VALUES = (1 << np.arange(len(WATCHED), dtype=np.int64))[:, None]
#: Per HELD row, its branch (0 R0, 1 R1 C1 tau1, 2 R2 C2 tau2; 3 none: the OCV offset is held
#: only with the whole cell).
BRANCH_OF_HELD = (0, 1, 1, 2, 2, 1, 2, 3)
_BRANCH_OF_HELD = np.array(BRANCH_OF_HELD)
TAU1, TAU2 = 5, 6
_TAUS = [TAU1, TAU2]
_RC_ROWS = ((_BRANCH_OF_HELD == 1) | (_BRANCH_OF_HELD == 2))[:, None]

#: Bits of ``PublishGuard.cause``: why the cell's present episode started.
CAUSE_SOC = 1  #: SOC outside [-margin, 1 + margin] or not finite
CAUSE_ERROR = 2  #: model error in excess for ``divergence_hold_s``
CAUSE_PARAMS = 4  #: a parameter not finite (or not > 0 where it must be)

#: Quality codes as plain ints (numpy compares an array with an IntEnum member 5x slower).
CONVERGING, POORLY_EXCITED, OUT_OF_BOUNDS, DIVERGED = 0, 2, 3, 4


def _check_literals() -> None:
    """The literals above against their sources (a change there must edit this file)."""
    codes = (Quality.CONVERGING, Quality.POORLY_EXCITED, Quality.OUT_OF_BOUNDS, Quality.DIVERGED)
    lower = tuple(0.0 if FIELDS_BY_NAME[k].positive else -math.inf for k in HELD)
    rows = tuple(HELD.index(k) for k in (*WATCHED, "tau1_s", "tau2_s"))
    if (
        codes != (CONVERGING, POORLY_EXCITED, OUT_OF_BOUNDS, DIVERGED)
        or lower != LOWER
        or rows != (*WATCHED_ROWS, TAU1, TAU2)
    ):
        raise RuntimeError("guard_kernel: a literal constant no longer matches its source")


_check_literals()


# ---------------------------------------------------------------------- the numpy reference
def guard_step_numpy(
    dt: float, soc: FloatArray, params: FloatArray, err: FloatArray, quality: Any,
    on_bound: BoolArray, learn: BoolArray, stats: FloatArray, good: FloatArray,
    good_soc: FloatArray, episode: BoolArray, cause: Any, bound_bits: Any, near: FloatArray,
    has_near: bool, consts: FloatArray,
) -> tuple[Any, ...]:  # fmt: skip
    """The reference (module docstring); ~40 us per tick when all is well (1 or 96 cells):
    branches skip what is not needed."""
    margin, fast_tau, scale_tau, hold_s, sig2, floor2 = consts.tolist()
    n = soc.shape[0]
    state = (stats, episode, cause, bound_bits)  # written in place at the end
    q = np.array(quality, dtype=np.int64)  # the copy returned
    converging = q == CONVERGING

    # what is wrong now
    soc_bad = ~((soc >= -margin) & (soc <= 1.0 + margin))  # NaN included
    params_bad = ~((params > _LOWER) & (params < np.inf)).all(axis=0)  # NaN included
    judged = ~converging & learn
    excited = q != POORLY_EXCITED
    if n == 1:
        error_bad, stats = _error_step_one(
            stats, float(err[0]), dt, bool(judged[0]), bool(excited[0]),
            bool(episode[0]), fast_tau, scale_tau, hold_s, sig2, floor2,
        )  # fmt: skip
    else:
        error_bad, stats = _error_step(
            stats, err, dt, judged, excited, episode, fast_tau, scale_tau, hold_s, sig2, floor2
        )
    diverged = soc_bad | error_bad | params_bad

    # episodes: one re-initialisation each; over once the cell converged again, unharmed
    reinit = diverged & ~episode
    n_reinit = 0
    # np.count_nonzero: a fifth of ndarray.any()'s cost on these short masks
    if np.count_nonzero(reinit) or np.count_nonzero(episode):
        over = episode & ~diverged & ~converging
        episode = (episode | reinit) & ~over
        now = soc_bad * CAUSE_SOC | error_bad * CAUSE_ERROR | params_bad * CAUSE_PARAMS
        cause = np.where(reinit, now, np.where(episode, cause, 0))
        n_reinit = int(reinit.sum())
        if reinit.any():  # their statistics start again (PublishGuard.reset)
            stats = np.where(reinit, 0.0, stats)
        q[episode] = DIVERGED

    # hold the parameters (all of a cell's on a clamp or in an episode; on a parameter that
    # sits on a bound, its branch: R0, or R1 C1 tau1, or R2 C2 tau2, so C = tau / R stays
    # true and R0 still follows temperature while tau2 waits on its bound) and a bad SOC
    held = on_bound | episode
    clamped = np.count_nonzero(held) > 0
    mask: BoolArray | None = None
    if has_near:
        w = params[_WATCHED_ROWS]
        # converging cells too: a value learnt on a bound before convergence would become
        # the "last good" one (the bank flags them after the average, bank._run_tick)
        sits = (w <= near[0]) | (w >= near[1])
        bound_bits = (sits * _BIT_VALUES).sum(axis=0)
        if np.count_nonzero(sits):
            none = np.zeros(n, dtype=bool)
            branch = np.array([sits[0], sits[1] | sits[3], sits[2] | sits[4], none])
            mask = branch[_BRANCH_OF_HELD] | held
            q[(bound_bits > 0) & ~episode & ~converging] = OUT_OF_BOUNDS
    if mask is None and clamped:
        mask = np.broadcast_to(held, params.shape)
    # branch 1 stays the fast one: a branch held while the other moves can cross it (tau2
    # held by its lower bound, tau1 rising past it), so both RC branches are held then
    taus = params[_TAUS] if mask is None else np.where(mask, good, params)[_TAUS]
    crossed = ~(taus[0] < taus[1])  # NaN included
    if np.count_nonzero(crossed):
        mask = (held if mask is None else mask) | (crossed & _RC_ROWS)
    n_held = 0
    if mask is not None:
        n_held = int((mask.any(axis=0) & ~episode).sum())
        published = np.where(mask, good, params)
    else:
        published = params
    # a count up to the margin past 0 or 1 is no divergence, but is published as 0 or 1
    s = np.where(soc_bad, good_soc, soc) if np.count_nonzero(soc_bad) else soc
    soc_out = np.minimum(np.maximum(s, 0.0), 1.0)
    for old, new in zip(state, (stats, episode, cause, bound_bits), strict=True):
        if new is not old:
            old[...] = new
    return published, soc_out, q, reinit, n_reinit, n_held, mask is not None


def _error_step(
    stats: FloatArray, err: FloatArray, dt: float, judged: BoolArray, excited: BoolArray,
    episode: BoolArray, fast_tau: float, scale_tau: float, hold_s: float, sig2: float,
    floor2: float,
) -> tuple[BoolArray, FloatArray]:  # fmt: skip
    """Advance F, S and T by one tick (``guard.py``) for the cells ``judged`` (not converging,
    may learn; S learns from the ``excited`` ones); (the cells whose model error has been in
    excess for ``divergence_hold_s``, the new statistics)."""
    e2_fast, fast_s, e2_scale, scale_s, excess_s = stats
    fin = np.isfinite(err)
    e2 = err * err  # NaN where not fin: every use below is masked by fin
    fast_s, e2_fast = _ewma(fast_s, e2_fast, e2, fin, dt, fast_tau)
    limit = sig2 * np.maximum(e2_scale, floor2)
    judged = fin & judged
    excess = judged & (scale_s >= fast_tau) & (e2_fast > limit)
    young = scale_s < scale_tau
    teach = judged & excited & ~episode & (young | (~excess & (e2 <= limit)))
    scale_s, e2_scale = _ewma(scale_s, e2_scale, e2, teach, dt, scale_tau)
    excess_s = np.where(excess, excess_s + dt, np.where(judged, 0.0, excess_s))
    return excess_s >= hold_s, np.array([e2_fast, fast_s, e2_scale, scale_s, excess_s])


def _error_step_one(
    stats: FloatArray, err: float, dt: float, judged: bool, excited: bool, episode: bool,
    fast_tau: float, scale_tau: float, hold_s: float, sig2: float, floor2: float,
) -> tuple[BoolArray, FloatArray]:  # fmt: skip
    """:func:`_error_step` of one cell in Python floats: the same operations in the same order
    (np.expm1 as the arrays use it; a mask is a branch), the same bits
    (``tests/estimate/test_guard.py``); ~10 us instead of ~30 us of numpy calls a tick.
    ``stats`` (5, 1) is updated in place and returned."""
    e2_fast, fast_s, e2_scale, scale_s, excess_s = stats[:, 0].tolist()
    fin = math.isfinite(err)
    e2 = err * err
    fast_s, e2_fast = _ewma_one(fast_s, e2_fast, e2, fin, dt, fast_tau)
    limit = sig2 * _maximum(e2_scale, floor2)
    judged = fin and judged
    excess = judged and scale_s >= fast_tau and e2_fast > limit
    young = scale_s < scale_tau
    teach = judged and excited and not episode and (young or (not excess and e2 <= limit))
    scale_s, e2_scale = _ewma_one(scale_s, e2_scale, e2, teach, dt, scale_tau)
    excess_s = excess_s + dt if excess else (0.0 if judged else excess_s)
    stats[:, 0] = e2_fast, fast_s, e2_scale, scale_s, excess_s
    return np.array([excess_s >= hold_s]), stats


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


# ---------------------------------------------------------------------- the compiled kernel
def _guard_source(
    dt: float, soc: FloatArray, params: FloatArray, err: FloatArray, quality: Any,
    on_bound: BoolArray, learn: BoolArray, stats: FloatArray, good: FloatArray,
    good_soc: FloatArray, episode: BoolArray, cause: Any, bound_bits: Any, near: FloatArray,
    has_near: bool, consts: FloatArray,
) -> tuple[Any, ...]:  # fmt: skip
    """The same tick per cell (compiled by numba; inner functions are compiled with it)."""

    def mx(a: float, b: float) -> float:  # np.maximum: NaN propagates, ties give a
        return a if a >= b or math.isnan(a) else b

    def mn(a: float, b: float) -> float:  # np.minimum
        return a if a <= b or math.isnan(a) else b

    def ewma(seen: float, x: float, value: float, use: bool, tau: float) -> tuple[float, float]:
        g = -math.expm1(-dt / tau)
        if use:
            seen = seen + dt
        w = mx(-math.expm1(seen * (-1.0 / tau)), g)
        # np.true_divide: numpy's x / 0 (inf, NaN), where numba's "/" raises
        return seen, (x + np.true_divide(g, w) * (value - x) if use else x)

    margin, fast_tau, scale_tau, hold_s = consts[0], consts[1], consts[2], consts[3]
    sig2, floor2 = consts[4], consts[5]
    n = soc.shape[0]
    q = quality.copy()
    new_stats = stats  # in place: each cell's are read before they are written
    soc_bad = np.zeros(n, dtype=np.bool_)
    reinit = np.zeros(n, dtype=np.bool_)
    why = np.zeros(n, dtype=np.int64)  # the CAUSE_* bits of what is wrong now
    any_episode = False
    for i in range(n):  # what is wrong now, and the model-error test
        conv = q[i] == CONVERGING
        s = soc[i]
        soc_bad[i] = not (s >= -margin and s <= 1.0 + margin)
        p_bad = False
        for r in range(len(LOWER)):
            p = params[r, i]
            if not (p > LOWER[r] and p < math.inf):
                p_bad = True
        e = err[i]
        fin = math.isfinite(e)
        e2 = e * e
        fast_s, e2_fast = ewma(stats[1, i], stats[0, i], e2, fin, fast_tau)
        e2_scale, scale_s = stats[2, i], stats[3, i]
        limit = sig2 * mx(e2_scale, floor2)
        judged = fin and not conv and learn[i]
        excess = judged and scale_s >= fast_tau and e2_fast > limit
        young = scale_s < scale_tau
        teach = (
            judged and q[i] != POORLY_EXCITED and not episode[i]
            and (young or (not excess and e2 <= limit))
        )  # fmt: skip
        scale_s, e2_scale = ewma(scale_s, e2_scale, e2, teach, scale_tau)
        excess_s = stats[4, i]
        excess_s = excess_s + dt if excess else (0.0 if judged else excess_s)
        new_stats[0, i], new_stats[1, i], new_stats[2, i] = e2_fast, fast_s, e2_scale
        new_stats[3, i], new_stats[4, i] = scale_s, excess_s
        e_bad = excess_s >= hold_s
        why[i] = soc_bad[i] * CAUSE_SOC | e_bad * CAUSE_ERROR | p_bad * CAUSE_PARAMS
        reinit[i] = why[i] != 0 and not episode[i]
        any_episode = any_episode or reinit[i] or episode[i]

    new_episode, new_cause, bits_out = episode, cause, bound_bits  # in place, as stats
    published = np.empty_like(params)
    soc_out = np.empty(n)
    n_reinit = 0
    n_held = 0
    masked = False
    mask = np.empty(len(BRANCH_OF_HELD), dtype=np.bool_)  # per HELD row, of one cell
    branch = np.empty(4, dtype=np.bool_)  # per branch: one of its parameters on a bound
    for i in range(n):  # episodes, then what is held and published
        conv = q[i] == CONVERGING
        if any_episode:
            over = episode[i] and why[i] == 0 and not conv
            new_episode[i] = (episode[i] or reinit[i]) and not over
            new_cause[i] = why[i] if reinit[i] else (cause[i] if new_episode[i] else 0)
            if reinit[i]:
                n_reinit += 1
                new_stats[:, i] = 0.0
            if new_episode[i]:
                q[i] = DIVERGED
        ep = new_episode[i]
        held = on_bound[i] or ep
        for r in range(len(BRANCH_OF_HELD)):
            mask[r] = held
        if has_near:
            bits = 0
            branch[:] = False
            for j in range(len(WATCHED_ROWS)):
                w = params[WATCHED_ROWS[j], i]
                if w <= near[0, j, i] or w >= near[1, j, i]:
                    bits += 1 << j
                    branch[BRANCH_OF_HELD[WATCHED_ROWS[j]]] = True
            bits_out[i] = bits
            if bits > 0:
                for r in range(len(BRANCH_OF_HELD)):
                    mask[r] = mask[r] or branch[BRANCH_OF_HELD[r]]
                if not ep and not conv:
                    q[i] = OUT_OF_BOUNDS
        t1 = good[TAU1, i] if mask[TAU1] else params[TAU1, i]
        t2 = good[TAU2, i] if mask[TAU2] else params[TAU2, i]
        if not (t1 < t2):  # NaN included
            for r in range(len(BRANCH_OF_HELD)):
                mask[r] = mask[r] or BRANCH_OF_HELD[r] == 1 or BRANCH_OF_HELD[r] == 2
        any_held = False
        for r in range(len(BRANCH_OF_HELD)):
            any_held = any_held or mask[r]
            published[r, i] = good[r, i] if mask[r] else params[r, i]
        if any_held:
            masked = True
            if not ep:
                n_held += 1
        s = good_soc[i] if soc_bad[i] else soc[i]
        soc_out[i] = mn(mx(s, 0.0), 1.0)
    return published, soc_out, q, reinit, n_reinit, n_held, masked


def _warm(kernel: Any) -> object:
    for n in (1, 2):
        ones, f = np.ones(n), np.zeros(n, dtype=bool)
        i = np.zeros(n, dtype=np.int64)
        for has_near in (False, True):
            kernel(1.0, ones * 0.5, np.ones((8, n)), ones * 1e-3, i + 1, f, ~f, np.zeros((5, n)),
                   np.ones((8, n)), ones, f, i, i, np.ones((2, 5, n)), has_near,
                   np.array([0.02, 60.0, 3600.0, 3600.0, 25.0, 1e-6]))  # fmt: skip
    return None


KERNEL = jit.Kernel("publish guard", guard_step_numpy, _guard_source, _warm)
