"""A tick's fits and moves of every running swarm in one call (``swarm_kernel.STEP``, issue 12):
the compiled kernel against the compiled fitness and ``lpso.tell`` called cell by cell (bit for
bit), against its numpy reference, and a whole swarm against ``lpso.swarm_tell`` driven by the
swarm's own generator (what the fusion ran before)."""

from __future__ import annotations

from typing import Any

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from bmsid.estimate import lpso, swarm_kernel, varpro_kernel
from bmsid.estimate.swarms import RunningSwarms
from bmsid.estimate.varpro import Window

# argument positions of the kernel (swarm_kernel.step_numpy)
ACTIVE, X, V, PBEST, PBEST_F, GBEST, GBEST_F, ITER, LO, HI = range(10)
FITNESS, DONE, RAND, INERTIA, A1, A2, T_LO, T_HI, WIN, WIN_LEN = range(10, 20)
S_FULL, IDX, USE_H, USE_OFF, PRIOR, J_OFF, LIN_LO, LIN_HI, ABS_SCALE, BUDGET, K = range(20, 31)
STATE = (X, V, PBEST, PBEST_F, GBEST, GBEST_F, ITER, FITNESS, DONE)


def _args(seed: int, n: int, n_p: int, n_w: int, use_h: bool, use_off: bool) -> list[Any]:
    """A bank of swarms in mid-run: random windows, positions, bests, and fits done."""
    rng = np.random.default_rng(seed)
    a = list(swarm_kernel.warm_args(n, n_p, n_w, 3))
    a[ACTIVE] = rng.random(n) < 0.7
    x = rng.uniform(0.0, 8.0, (n, n_p, 2))
    a[X], a[V] = x, rng.normal(0.0, 0.5, (n, n_p, 2))
    a[PBEST] = np.clip(x + rng.normal(0.0, 0.3, x.shape), 0.0, 8.0)
    a[PBEST_F] = np.where(rng.random((n, n_p)) < 0.2, np.inf, rng.uniform(0.001, 0.1, (n, n_p)))
    a[GBEST], a[GBEST_F] = a[PBEST][:, 0].copy(), np.full(n, 0.05)
    a[ITER] = rng.integers(0, 3, n)
    a[FITNESS] = rng.uniform(0.001, 0.1, (n, n_p))
    a[DONE] = rng.integers(0, n_p, n)
    taus = np.exp(x)
    a[T_LO], a[T_HI] = (
        np.minimum(taus[..., 0], taus[..., 1]),
        np.maximum(taus[..., 0], taus[..., 1]),
    )
    a[A1], a[A2] = np.exp(-1.0 / a[T_LO]), np.exp(-1.0 / a[T_HI])
    win = np.zeros((n, 4, n_w))
    win[:, 0] = np.repeat(rng.uniform(-100.0, 100.0, (n, n_w // 7 + 1)), 7, axis=1)[:, :n_w]
    win[:, 1] = rng.normal(0.0, 0.02, (n, n_w)) - 0.001 * win[:, 0]
    win[:, 2] = rng.uniform(-0.02, 0.02, (n, n_w))
    win[:, 3] = rng.uniform(0.1, 1.0, (n, n_w))
    a[WIN], a[WIN_LEN] = win, rng.integers(8, n_w + 1, n)
    active = np.array([True, True, True, use_h, use_off, True, True])
    a[IDX] = np.flatnonzero(active)
    scale = np.concatenate([rng.uniform(1e-4, 1e-2, (n, 3)), np.tile([1.0, 0.05], (n, 1))], 1)
    a[S_FULL] = np.ascontiguousarray(np.concatenate([scale, np.ones((n, 2))], 1)[:, active])
    a[USE_H], a[USE_OFF] = use_h, use_off
    a[PRIOR], a[J_OFF] = rng.uniform(0.0, 1.0, n), 3 + int(use_h) if use_off else -1
    a[LIN_LO] = np.array([1e-4, 1e-4, 1e-4, 0.5, -0.02]) * rng.uniform(0.5, 2.0, (n, 5))
    a[LIN_HI] = a[LIN_LO] * rng.uniform(1.5, 50.0, (n, 5)) + np.array([0, 0, 0, 0, 0.04])
    a[ABS_SCALE] = np.abs(scale)
    a[BUDGET] = int(rng.integers(1, n_p + 1))
    return a


def _copy(a: list[Any]) -> list[Any]:
    return [x.copy() if isinstance(x, np.ndarray) else x for x in a]


def _cell_by_cell(a: list[Any], fitness: Any) -> Any:
    """The kernel's contract spelled out: per active cell the fitness, then ``lpso.tell``."""
    n, n_p = a[PBEST_F].shape
    k = a[K]
    p = lpso.SwarmParams(c1=k[swarm_kernel.C1], c2=k[swarm_kernel.C2],
                         vmax_frac=k[swarm_kernel.VMAX_FRAC])  # fmt: skip
    moved = np.zeros(n, dtype=bool)
    for c in np.flatnonzero(a[ACTIVE]):
        n_w, j0 = a[WIN_LEN][c], a[DONE][c]
        j1 = min(j0 + a[BUDGET], n_p)
        w = a[WIN][c, :, :n_w].copy()
        s = slice(j0, j1)
        a[FITNESS][c, s] = fitness(
            w[0], w[1], w[2], w[3], a[A1][c, s].copy(), a[A2][c, s].copy(), a[S_FULL][c], a[IDX],
            a[USE_H], a[USE_OFF], float(a[PRIOR][c]), a[J_OFF], a[LIN_LO][c], a[LIN_HI][c],
            a[ABS_SCALE][c], a[T_LO][c, s].copy(), a[T_HI][c, s].copy(),
            float(k[swarm_kernel.TAU_RATIO_MIN]),
        )  # fmt: skip
        a[DONE][c] = j1
        if j1 < n_p:
            continue
        it = a[ITER][c]
        out = lpso.tell(
            a[X][c], a[V][c], a[PBEST][c], a[PBEST_F][c], a[GBEST][c], float(a[GBEST_F][c]),
            a[FITNESS][c], a[RAND][c, it, 0], a[RAND][c, it, 1], float(a[INERTIA][c, it]),
            a[LO][c], a[HI][c], p,
        )  # fmt: skip
        a[X][c], a[V][c], a[PBEST][c], a[PBEST_F][c], a[GBEST][c], a[GBEST_F][c] = out
        a[ITER][c], a[DONE][c], moved[c] = it + 1, 0, True
    return moved


CASES = dict(
    seed=st.integers(0, 2**32 - 1), n=st.integers(1, 5), n_p=st.integers(1, 7),
    n_w=st.integers(8, 200), use_h=st.booleans(), use_off=st.booleans(),
)  # fmt: skip


@settings(max_examples=60, deadline=None)
@given(**CASES)
def test_the_compiled_step_is_the_fitness_and_the_move_cell_by_cell(
    seed: int, n: int, n_p: int, n_w: int, use_h: bool, use_off: bool
) -> None:
    """Bit for bit the compiled fitness and ``lpso.tell`` per cell (what the fusion ran)."""
    kernel, fitness = swarm_kernel.STEP.compiled(), varpro_kernel.FITNESS.compiled()
    assert kernel is not None and fitness is not None
    a = _args(seed, n, n_p, n_w, use_h, use_off)
    got, want = _copy(a), _copy(a)
    moved = kernel(*got)
    np.testing.assert_array_equal(moved, _cell_by_cell(want, fitness))
    for j in STATE:
        np.testing.assert_array_equal(got[j], want[j], err_msg=str(j))


@settings(max_examples=60, deadline=None)
@given(**CASES)
def test_the_reference_is_the_fitness_reference_and_the_move_cell_by_cell(
    seed: int, n: int, n_p: int, n_w: int, use_h: bool, use_off: bool
) -> None:
    """The reference bit for bit its parts (the fitness reference agrees with the compiled
    fitness to rounding times the window's condition: test_fitness_kernel.py and
    test_varpro_kernel.py); with the compiled fitness in it, bit for bit the compiled kernel
    (its moves are numpy's operations)."""
    kernel, fitness = swarm_kernel.STEP.compiled(), varpro_kernel.FITNESS.compiled()
    assert kernel is not None and fitness is not None
    a = _args(seed, n, n_p, n_w, use_h, use_off)
    ref, want, comp, mixed = _copy(a), _copy(a), _copy(a), _copy(a)
    moved = swarm_kernel.step_numpy(*ref)
    np.testing.assert_array_equal(moved, _cell_by_cell(want, varpro_kernel.fitness_numpy))
    for j in STATE:
        np.testing.assert_array_equal(ref[j], want[j], err_msg=str(j))
    with pytest.MonkeyPatch.context() as mp:
        mp.setattr(varpro_kernel, "fitness_numpy", fitness)
        np.testing.assert_array_equal(swarm_kernel.step_numpy(*mixed), kernel(*comp))
    for j in STATE:
        np.testing.assert_array_equal(mixed[j], comp[j], err_msg=str(j))


def test_a_whole_swarm_runs_as_with_its_generator() -> None:
    """A swarm started in ``RunningSwarms`` (its random numbers drawn in advance) and stepped by
    the kernel, 3 fits a tick: the same positions, bests and fitness, bit for bit, as the same
    swarm moved by ``lpso.swarm_tell`` with its generator (the fusion's loop before)."""
    kernel, fitness = swarm_kernel.STEP.compiled(), varpro_kernel.FITNESS.compiled()
    assert kernel is not None and fitness is not None
    rng = np.random.default_rng(5)
    n_w, n_p, n_iter, budget = 300, 8, 6, 3
    cur = np.repeat(rng.uniform(-50.0, 50.0, n_w // 10), 10)
    y = -0.002 * cur + rng.normal(0.0, 0.002, n_w)
    win = Window(cur, y, np.zeros(n_w), 1.0, False, False)
    wts = np.ones(n_w)
    lo, hi = np.log([1.0, 10.0]), np.log([100.0, 5000.0])
    p = lpso.SwarmParams()
    idx = np.array([0, 1, 2, 5, 6])
    lin_lo, lin_hi, sc = np.full(5, -1.0), np.full(5, 1.0), np.full(5, 1e-3)
    s_full = np.concatenate([sc, [1.0, 1.0]])[idx]

    def start() -> tuple[lpso.Swarm, np.random.Generator]:
        g = np.random.default_rng([0, 7, 1])
        return lpso.swarm_init(lo, hi, n_p, n_iter, g, seeds=np.log([[20.0, 800.0]])), g

    rs = RunningSwarms(3, n_p, n_iter + 2, n_w + 5)
    sw, g = start()
    rs.start(1, sw, g, p, win, wts)
    k = swarm_kernel.consts(p, 2.0)
    ticks = 0
    while rs.active[1]:
        moved = kernel(
            rs.active, rs.x, rs.v, rs.pbest, rs.pbest_f, rs.gbest, rs.gbest_f, rs.iteration,
            rs.lo, rs.hi, rs.fitness, rs.done_fits, rs.rand, rs.inertia, rs.a1, rs.a2, rs.t_lo,
            rs.t_hi, rs.win, rs.win_len, np.tile(s_full, (3, 1)), idx, False, False,
            np.zeros(3), -1, np.tile(lin_lo, (3, 1)), np.tile(lin_hi, (3, 1)),
            np.tile(sc, (3, 1)), budget, k,
        )  # fmt: skip
        ticks += 1
        if moved[1]:
            rs.refresh_poles(np.array([1]))
            rs.active[1] = rs.iteration[1] < n_iter
    # the same swarm, particle slices fitted tick by tick and moved with its generator
    sw, g = start()
    f = np.zeros(n_p)
    done = 0
    while not sw.done:
        j1 = min(done + budget, n_p)
        taus = np.exp(sw.x[done:j1])
        t_lo, t_hi = np.minimum(taus[:, 0], taus[:, 1]), np.maximum(taus[:, 0], taus[:, 1])
        f[done:j1] = fitness(
            cur, win.y_V, win.hm_V, wts, np.exp(-1.0 / t_lo), np.exp(-1.0 / t_hi), s_full, idx,
            False, False, 0.0, -1, lin_lo, lin_hi, sc, t_lo, t_hi, 2.0,
        )  # fmt: skip
        done = j1
        ticks -= 1
        if done == n_p:
            sw, done = lpso.swarm_tell(sw, f, g, p), 0
    assert ticks == 0
    np.testing.assert_array_equal(rs.x[1], sw.x)
    np.testing.assert_array_equal(rs.pbest_f[1], sw.pbest_f)
    np.testing.assert_array_equal(rs.gbest[1], sw.gbest)
    assert rs.gbest_f[1] == sw.gbest_f and np.isfinite(sw.gbest_f)
