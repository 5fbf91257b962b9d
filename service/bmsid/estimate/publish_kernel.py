"""The end of a tick in one compiled call (issue 12): quality codes, publish guard, average.

``bank._run_tick`` ends with the quality codes (excited, clamped, converged), the publish guard
(``guard_kernel.py``), the published average (``publish_average.py``) and the flag of
converging cells on a bound, with only a little Python between them. Compiled, ``TAIL`` runs
them as one kernel: the guard's and the average's compiled kernels called in that order (the
same compiled code: the same bits as when called one by one), the codes and the flag in loops.
The numpy mode keeps the bank's own calls of the stages; ``tail_numpy``, the same sequence over
the stages' references, is what the compiled kernel is tested against
(``tests/estimate/test_publish_kernel.py``). :func:`publish` is the bank's call.

numba caches a kernel by its own file only; this one embeds the guard's and the average's
compiled code, so its cache entry is named after their files too (``jit.Kernel``'s ``depends``).
"""

from __future__ import annotations

from collections.abc import Callable
from typing import TYPE_CHECKING, Any

import numpy as np
import numpy.typing as npt

from bmsid.estimate import guard_kernel, jit, publish_average
from bmsid.estimate.guard_kernel import CONVERGING, HELD, OUT_OF_BOUNDS, POORLY_EXCITED
from bmsid.estimate.publish_average import AVERAGED, PUBLISHED, average_numpy
from bmsid.estimate.stage import nnz
from bmsid.estimate.types import Quality

if TYPE_CHECKING:
    from bmsid.estimate.guard import PublishGuard
    from bmsid.estimate.publish_average import PublishAverage

FloatArray = npt.NDArray[np.float64]
BoolArray = npt.NDArray[np.bool_]
IntArray = npt.NDArray[np.int64]

if HELD != ("R0_ohm", "R1_ohm", "C1_F", "R2_ohm", "C2_F", "tau1_s", "tau2_s", "ocv_offset_V"):
    raise RuntimeError("publish_kernel: the kernels' parameter arguments no longer match HELD")
#: A literal, read by the compiled kernel (checked against its source below).
CONVERGED = 1
if CONVERGED != Quality.CONVERGED:
    raise RuntimeError("publish_kernel: CONVERGED no longer matches Quality.CONVERGED")
#: The rows of the guarded parameters (``HELD``) that the average reads (``AVERAGED``).
AVG_ROWS = tuple(HELD.index(k) for k in AVERAGED)
#: Rows of the kernels' float result: the guard's published HELD rows, its SOC, its bound bits
#: (as floats: the ``on_bound`` field), the average's PUBLISHED rows.
SOC_ROW, BITS_ROW, AVG_ROW = len(HELD), len(HELD) + 1, len(HELD) + 2
N_FLOATS = AVG_ROW + len(PUBLISHED)


def _codes(excited: BoolArray, clamped: BoolArray, converged: BoolArray) -> IntArray:
    """The bank's quality codes before the guard (the later rule wins)."""
    q = np.full(excited.shape[0], CONVERGED, dtype=np.int64)
    q[~excited] = POORLY_EXCITED
    q[clamped] = OUT_OF_BOUNDS
    q[~converged] = CONVERGING
    return q


def tail_numpy(
    dt_guard: float, soc: FloatArray, r0: FloatArray, r1: FloatArray, c1: FloatArray,
    r2: FloatArray, c2: FloatArray, tau1: FloatArray, tau2: FloatArray, offset: FloatArray,
    err: FloatArray, excited: BoolArray, clamped: BoolArray, converged: BoolArray,
    learn: BoolArray, stats: FloatArray, good: FloatArray, good_soc: FloatArray,
    episode: BoolArray, cause: IntArray, bound_bits: IntArray, near: FloatArray, has_near: bool,
    consts: FloatArray, avg: FloatArray, restart: BoolArray, dt_s: float, tau1_multiple: float,
) -> tuple[Any, ...]:  # fmt: skip
    """The reference: the codes, ``guard_kernel.guard_step_numpy`` on the :data:`HELD`
    parameters ``r0`` .. ``offset`` (its state arguments updated in place),
    ``publish_average.average_numpy`` on the guarded R1, R2, tau1, tau2 (``avg`` in place;
    skipped when ``tau1_multiple`` <= 0: its rows are then NaN), the flag. Returns (the floats
    (N_FLOATS, n): the guard's published HELD rows, its SOC and bound bits, the average's
    PUBLISHED rows; the quality codes; the cells to re-initialise; the guard's counts and
    whether it held any)."""
    params = np.array([r0, r1, c1, r2, c2, tau1, tau2, offset], dtype=np.float64)
    q = _codes(excited, clamped, converged)
    published, soc_out, q, reinit, n_reinit, n_held, masked = guard_kernel.guard_step_numpy(
        dt_guard, soc, params, err, q, clamped, learn, stats, good, good_soc, episode, cause,
        bound_bits, near, has_near, consts,
    )  # fmt: skip
    floats = np.full((N_FLOATS, soc.shape[0]), np.nan)
    floats[: len(HELD)] = published
    floats[SOC_ROW] = soc_out
    floats[BITS_ROW] = bound_bits
    if tau1_multiple > 0.0:
        raw = np.array(published[list(AVG_ROWS)], dtype=np.float64)
        floats[AVG_ROW:] = average_numpy(avg, raw, q, restart, dt_s, tau1_multiple)
    q[(q == CONVERGING) & (bound_bits > 0)] = OUT_OF_BOUNDS
    return floats, q, reinit, n_reinit, n_held, masked


#: The compiled guard and average, called by the compiled tail (bound by its warm-up, before it
#: compiles: the same compiled code as when they are called alone).
_GUARD: Callable[..., tuple[Any, ...]] | None = None
_AVERAGE: Callable[..., FloatArray] | None = None


def _tail_source(
    dt_guard: float, soc: FloatArray, r0: FloatArray, r1: FloatArray, c1: FloatArray,
    r2: FloatArray, c2: FloatArray, tau1: FloatArray, tau2: FloatArray, offset: FloatArray,
    err: FloatArray, excited: BoolArray, clamped: BoolArray, converged: BoolArray,
    learn: BoolArray, stats: FloatArray, good: FloatArray, good_soc: FloatArray,
    episode: BoolArray, cause: IntArray, bound_bits: IntArray, near: FloatArray, has_near: bool,
    consts: FloatArray, avg: FloatArray, restart: BoolArray, dt_s: float, tau1_multiple: float,
) -> tuple[Any, ...]:  # fmt: skip
    """The same in one call (compiled by numba): the parameters come as separate rows and the
    floats leave as one array (each array built or returned costs the Python side more than
    the loops here)."""
    n = soc.shape[0]
    params = np.empty((len(HELD), n))
    params[0], params[1], params[2], params[3] = r0, r1, c1, r2
    params[4], params[5], params[6], params[7] = c2, tau1, tau2, offset
    q = np.empty(n, dtype=np.int64)
    for i in range(n):
        code = CONVERGED
        if not excited[i]:
            code = POORLY_EXCITED
        if clamped[i]:
            code = OUT_OF_BOUNDS
        if not converged[i]:
            code = CONVERGING
        q[i] = code
    published, soc_out, q, reinit, n_reinit, n_held, masked = _GUARD(  # type: ignore[misc]
        dt_guard, soc, params, err, q, clamped, learn, stats, good, good_soc, episode, cause,
        bound_bits, near, has_near, consts,
    )  # fmt: skip
    floats = np.full((N_FLOATS, n), np.nan)
    floats[: len(HELD)] = published
    floats[SOC_ROW] = soc_out
    for i in range(n):
        floats[BITS_ROW, i] = bound_bits[i]
    if tau1_multiple > 0.0:
        raw = np.empty((len(AVG_ROWS), n))
        for r in range(len(AVG_ROWS)):
            raw[r] = published[AVG_ROWS[r]]
        floats[AVG_ROW:] = _AVERAGE(avg, raw, q, restart, dt_s, tau1_multiple)  # type: ignore[misc]
    for i in range(n):
        if q[i] == CONVERGING and bound_bits[i] > 0:
            q[i] = OUT_OF_BOUNDS
    return floats, q, reinit, n_reinit, n_held, masked


def _warm(kernel: Callable[..., tuple[Any, ...]]) -> object:
    global _GUARD, _AVERAGE  # the compiled callees, bound before this kernel compiles
    _GUARD, _AVERAGE = guard_kernel.KERNEL.compiled(), publish_average.KERNEL.compiled()
    if _GUARD is None or _AVERAGE is None:
        raise RuntimeError("the guard or average kernel did not compile")
    for n in (1, 2):
        ones, f = np.ones(n), np.zeros(n, dtype=bool)
        i = np.zeros(n, dtype=np.int64)
        for has_near in (False, True):
            kernel(1.0, ones * 0.5, *([ones] * len(HELD)), ones * 1e-3, ~f, f, ~f, ~f,
                   np.zeros((5, n)), np.ones((8, n)), ones, f.copy(), i.copy(), i.copy(),
                   np.ones((2, 5, n)), has_near,
                   np.array([0.02, 60.0, 3600.0, 3600.0, 25.0, 1e-6]),
                   np.ones((len(AVERAGED), n)), f.copy(), 1.0, 1.0)  # fmt: skip
    return None


TAIL = jit.Kernel(
    "tick tail", tail_numpy, _tail_source, _warm,
    depends=(guard_kernel.__file__, publish_average.__file__),
)  # fmt: skip


def publish(
    guard: PublishGuard, average: PublishAverage, t_s: float, dt_s: float,
    cells: dict[str, FloatArray], excited: BoolArray, clamped: BoolArray, converged: BoolArray,
    learn: BoolArray,
) -> tuple[dict[str, FloatArray], IntArray, BoolArray]:  # fmt: skip
    """The bank's tick from its quality codes on, by the compiled ``TAIL``: what
    ``PublishGuard.apply`` and ``PublishAverage.apply`` do around their kernels, with ``cells``
    (the bank's own dict of the tick) updated in place. Returns (cells, quality, cells to
    re-initialise)."""
    floats, q, reinit, n_reinit, n_held, masked = TAIL.impl(
        guard._data_dt(t_s), cells["soc"], cells["R0_ohm"], cells["R1_ohm"], cells["C1_F"],
        cells["R2_ohm"], cells["C2_F"], cells["tau1_s"], cells["tau2_s"], cells["ocv_offset_V"],
        cells["v_error_V"], excited, clamped,
        converged, learn, guard._stats, guard.good, guard.good_soc, guard.episode, guard.cause,
        guard.bound_bits, guard._near, guard._has_near, guard._consts, average.avg,
        average.restart, dt_s, average.tau1_multiple,
    )  # fmt: skip
    if n_reinit:
        guard.counters["diverged"] += n_reinit
    if n_held:
        guard.counters["held_on_bound"] += n_held
    cells["on_bound"] = floats[BITS_ROW]
    if masked:  # else the stages' own arrays are published
        for j, k in enumerate(HELD):
            cells[k] = floats[j]
    guard.good = floats[: len(HELD)]  # (C-contiguous rows: the kernel's type next tick too)
    cells["soc"] = guard.good_soc = floats[SOC_ROW]
    if average.tau1_multiple > 0.0:
        if nnz(average.restart):
            average.restart = np.zeros(average.n, dtype=bool)
        for j, k in enumerate(PUBLISHED):
            cells[k] = floats[AVG_ROW + j]
    return cells, q, reinit
