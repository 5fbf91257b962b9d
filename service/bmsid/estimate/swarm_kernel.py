"""One call a tick for every running swarm of a bank: the due window fits and the moves.

A running swarm evaluates ``fits_per_update`` particles a tick (``swarms.py``); once all of its
particles are evaluated it moves (``lpso.swarm_tell``, Eq. 28-30). Called per cell from Python,
a 96-cell bank spent more on the calls, slices and small arrays around each fit than on half of
the fits themselves (issue 12); here a tick's fits and moves of every running swarm are one call:

* ``step_numpy``: the reference, per running cell the fitness reference
  (``varpro_kernel.fitness_numpy``) and ``lpso.tell``;
* a compiled kernel (numba): per running cell the compiled fitness (``varpro_kernel.FITNESS``,
  the same compiled code as when called alone, so the same bits), then the move in scalar
  loops in ``lpso.tell``'s operations and order (no fastmath: the same bits as numpy's).

Both take the swarms' arrays (``swarms.RunningSwarms``) and write them in place; they return
which cells moved (their poles are refreshed by numpy's exp, ``RunningSwarms.refresh_poles``).
Random numbers and inertia come drawn in advance, so neither needs a generator.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from typing import Any

import numpy as np
import numpy.typing as npt

from bmsid.estimate import jit, lpso, varpro_kernel, varpro_sums

FloatArray = npt.NDArray[np.float64]
BoolArray = npt.NDArray[np.bool_]
IntArray = npt.NDArray[np.int64]

#: Layout of the move's constants ``consts``: c1, c2 (Eq. 28), velocity clamp (fraction of the
#: box width), ratio tau_hi / tau_lo below which the fitness is penalised.
C1, C2, VMAX_FRAC, TAU_RATIO_MIN, N_CONSTS = 0, 1, 2, 3, 4


def consts(p: lpso.SwarmParams, tau_ratio_min: float) -> FloatArray:
    """The constants vector of the kernel (layout above)."""
    return np.array([p.c1, p.c2, p.vmax_frac, tau_ratio_min])


def step_numpy(
    active: BoolArray, x: FloatArray, v: FloatArray, pbest: FloatArray, pbest_f: FloatArray,
    gbest: FloatArray, gbest_f: FloatArray, iteration: IntArray, lo: FloatArray,
    hi: FloatArray, fitness: FloatArray, done_fits: IntArray, rand: FloatArray,
    inertia: FloatArray, a1: FloatArray, a2: FloatArray, t_lo: FloatArray, t_hi: FloatArray,
    win: FloatArray, win_len: IntArray, s_full: FloatArray, idx: IntArray, use_h: bool,
    use_off: bool, prior: FloatArray, j_off: int, lin_lo: FloatArray, lin_hi: FloatArray,
    abs_scale: FloatArray, budget: int, k: FloatArray,
) -> BoolArray:  # fmt: skip
    """The reference: per running cell ``c`` the fitness of particles ``done_fits[c]`` on (at
    most ``budget``) on its window ``win[c, :, :win_len[c]]``; a swarm whose particles are all
    evaluated moves (``lpso.tell`` with its iteration's random numbers and inertia) and its
    iteration counts on. Returns the cells that moved."""
    n, n_p = pbest_f.shape
    moved = np.zeros(n, dtype=bool)
    params = lpso.SwarmParams(c1=float(k[C1]), c2=float(k[C2]), vmax_frac=float(k[VMAX_FRAC]))
    for c in np.flatnonzero(active).tolist():
        n_w, j0 = int(win_len[c]), int(done_fits[c])
        j1 = min(j0 + budget, n_p)
        wc = win[c, :, :n_w]
        fitness[c, j0:j1] = varpro_kernel.fitness_numpy(
            wc[0], wc[1], wc[2], wc[3], a1[c, j0:j1], a2[c, j0:j1], s_full[c], idx, use_h,
            use_off, float(prior[c]), j_off, lin_lo[c], lin_hi[c], abs_scale[c], t_lo[c, j0:j1],
            t_hi[c, j0:j1], float(k[TAU_RATIO_MIN]),
        )  # fmt: skip
        done_fits[c] = j1
        if j1 < n_p:
            continue
        it = int(iteration[c])
        x[c], v[c], pbest[c], pbest_f[c], gbest[c], gbest_f[c] = lpso.tell(
            x[c], v[c], pbest[c], pbest_f[c], gbest[c], float(gbest_f[c]), fitness[c],
            rand[c, it, 0], rand[c, it, 1], float(inertia[c, it]), lo[c], hi[c], params,
        )  # fmt: skip
        iteration[c] = it + 1
        done_fits[c] = 0
        moved[c] = True
    return moved


#: The compiled fitness, called by the compiled step (set by its warm-up, before it compiles).
_FITNESS: Callable[..., FloatArray] | None = None


def _step_source(
    active: BoolArray, x: FloatArray, v: FloatArray, pbest: FloatArray, pbest_f: FloatArray,
    gbest: FloatArray, gbest_f: FloatArray, iteration: IntArray, lo: FloatArray,
    hi: FloatArray, fitness: FloatArray, done_fits: IntArray, rand: FloatArray,
    inertia: FloatArray, a1: FloatArray, a2: FloatArray, t_lo: FloatArray, t_hi: FloatArray,
    win: FloatArray, win_len: IntArray, s_full: FloatArray, idx: IntArray, use_h: bool,
    use_off: bool, prior: FloatArray, j_off: int, lin_lo: FloatArray, lin_hi: FloatArray,
    abs_scale: FloatArray, budget: int, k: FloatArray,
) -> BoolArray:  # fmt: skip
    """The same (compiled by numba): the compiled fitness, then the move per particle and
    coordinate in ``lpso.tell``'s operations and order."""
    n, n_p, n_d = x.shape
    moved = np.zeros(n, dtype=np.bool_)
    for c in range(n):
        if not active[c]:
            continue
        n_w, j0 = win_len[c], done_fits[c]
        j1 = min(j0 + budget, n_p)
        f = _FITNESS(  # type: ignore[misc]
            win[c, 0, :n_w], win[c, 1, :n_w], win[c, 2, :n_w], win[c, 3, :n_w], a1[c, j0:j1],
            a2[c, j0:j1], s_full[c], idx, use_h, use_off, prior[c], j_off, lin_lo[c],
            lin_hi[c], abs_scale[c], t_lo[c, j0:j1], t_hi[c, j0:j1], k[TAU_RATIO_MIN],
        )  # fmt: skip
        for j in range(j0, j1):
            fitness[c, j] = f[j - j0]
        done_fits[c] = j1
        if j1 < n_p:
            continue
        # lpso.tell: personal bests (a non-finite fitness counts as inf), then the global one
        for j in range(n_p):
            fj = fitness[c, j]
            fj = fj if math.isfinite(fj) else math.inf
            if fj < pbest_f[c, j]:
                pbest_f[c, j] = fj
                for d in range(n_d):
                    pbest[c, j, d] = x[c, j, d]
        jb = 0  # np.argmin: the first smallest (no NaN here)
        for j in range(1, n_p):
            if pbest_f[c, j] < pbest_f[c, jb]:
                jb = j
        if pbest_f[c, jb] < gbest_f[c]:
            gbest_f[c] = pbest_f[c, jb]
            for d in range(n_d):
                gbest[c, d] = pbest[c, jb, d]
        it = iteration[c]
        w = inertia[c, it]
        for d in range(n_d):
            vmax = k[VMAX_FRAC] * (hi[c, d] - lo[c, d])
            for j in range(n_p):
                xo = x[c, j, d]
                vn = (w * v[c, j, d] + k[C1] * rand[c, it, 0, j, d] * (pbest[c, j, d] - xo)
                      + k[C2] * rand[c, it, 1, j, d] * (gbest[c, d] - xo))  # fmt: skip
                vn = min(max(vn, -vmax), vmax)
                xn = xo + vn
                if xn < lo[c, d] or xn > hi[c, d]:  # the wall stops it
                    xn = min(max(xn, lo[c, d]), hi[c, d])
                    vn = 0.0
                x[c, j, d] = xn
                v[c, j, d] = vn
        iteration[c] = it + 1
        done_fits[c] = 0
        moved[c] = True
    return moved


def warm_args(n: int = 2, n_p: int = 4, n_w: int = 6, n_iter: int = 2) -> tuple[Any, ...]:
    """Small arguments of every type the kernel takes (its warm-up; tests build on them)."""
    rng = np.random.default_rng(0)
    lo, hi = np.zeros((n, 2)), np.full((n, 2), 8.0)
    x = rng.uniform(0.0, 8.0, (n, n_p, 2))
    taus = np.exp(x)
    t_lo, t_hi = np.minimum(taus[:, :, 0], taus[:, :, 1]), np.maximum(taus[:, :, 0], taus[:, :, 1])
    win = rng.normal(size=(n, 4, n_w))
    win[:, 3] = 1.0
    return (
        np.ones(n, dtype=np.bool_), x, np.zeros_like(x), x.copy(), np.full((n, n_p), np.inf),
        x[:, 0].copy(), np.full(n, np.inf), np.zeros(n, dtype=np.int64), lo, hi,
        np.zeros((n, n_p)), np.zeros(n, dtype=np.int64), rng.random((n, n_iter, 2, n_p, 2)),
        np.full((n, n_iter), 0.5), np.exp(-1.0 / t_lo), np.exp(-1.0 / t_hi), t_lo, t_hi, win,
        np.full(n, n_w, dtype=np.int64), np.ones((n, 5)), np.array([0, 1, 2, 5, 6]), False,
        False, np.zeros(n), -1, np.zeros((n, 5)), np.full((n, 5), 2.0), np.ones((n, 5)), n_p,
        consts(lpso.SwarmParams(), 2.0),
    )  # fmt: skip


def _warm(kernel: Callable[..., BoolArray]) -> object:
    global _FITNESS  # noqa: PLW0603 (the compiled callee, bound before this kernel compiles)
    _FITNESS = varpro_kernel.FITNESS.compiled()
    if _FITNESS is None:
        raise RuntimeError("the swarm fitness did not compile")
    return kernel(*warm_args())


#: A tick's fits and moves of every running swarm (``FusionStage._step_swarms``); it embeds the
#: compiled fitness (``varpro_kernel.py``) and its normal equations (``varpro_sums.py``).
STEP = jit.Kernel(
    "swarm step", step_numpy, _step_source, _warm,
    depends=(str(varpro_kernel.__file__), str(varpro_sums.__file__)),
)  # fmt: skip
