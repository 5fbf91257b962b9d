"""The swarm's fitness in one compiled call (``varpro_kernel.FITNESS``, issue 12) against the
kernels it replaces called one by one, and against its numpy reference."""

from __future__ import annotations

from typing import Any

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st

from bmsid.estimate import varpro_kernel


@settings(max_examples=60, deadline=None)
@given(
    seed=st.integers(0, 2**32 - 1),
    n_w=st.integers(8, 300),
    p=st.integers(1, 6),
    use_h=st.booleans(),
    use_off=st.booleans(),
    prior=st.sampled_from([0.0, 1e-6, 1.0]),
)
def test_the_compiled_fitness_is_its_kernels_and_the_penalty(
    seed: int, n_w: int, p: int, use_h: bool, use_off: bool, prior: float
) -> None:
    """Bit for bit the compiled normal equations and solves followed by the reference's
    penalty (what the fusion computed before the fitness was one call); the reference bit for
    bit the kernels' references one by one."""
    fitness = varpro_kernel.FITNESS.compiled()
    normal, solve = varpro_kernel.KERNEL.compiled(), varpro_kernel.SOLVE.compiled()
    assert fitness is not None and normal is not None and solve is not None
    rng = np.random.default_rng(seed)
    i = np.repeat(rng.uniform(-100.0, 100.0, n_w // 7 + 1), 7)[:n_w]
    y = rng.normal(0.0, 0.02, n_w) - 0.001 * i
    hm = rng.uniform(-0.02, 0.02, n_w)
    w = rng.uniform(0.1, 1.0, n_w)
    tau = np.exp(rng.uniform(0.0, 8.5, (p, 2)))
    t_lo, t_hi = np.minimum(tau[:, 0], tau[:, 1]), np.maximum(tau[:, 0], tau[:, 1])
    a1, a2 = np.exp(-1.0 / t_lo), np.exp(-1.0 / t_hi)
    active = np.array([True, True, True, use_h, use_off, True, True])
    idx = np.flatnonzero(active)
    scale = np.concatenate([rng.uniform(1e-4, 1e-2, 3), [1.0, 0.05]])
    s = np.concatenate([scale, [1.0, 1.0]])[active]
    j_off = 3 + int(use_h) if use_off else -1
    # bounds that some candidates violate (and NaN-free otherwise)
    lin_lo = np.array([1e-4, 1e-4, 1e-4, 0.5, -0.02]) * rng.uniform(0.5, 2.0, 5)
    lin_hi = lin_lo * rng.uniform(1.5, 50.0, 5) + np.array([0, 0, 0, 0, 0.04])
    args = (i, y, hm, w, a1, a2, s, idx, use_h, use_off, prior, j_off, lin_lo, lin_hi,
            np.abs(scale), t_lo, t_hi, 1.5)  # fmt: skip
    got = fitness(*args)

    def one_by_one(normal_eq: Any, solve_eq: Any) -> Any:
        G, b, last = normal_eq(i, y, hm, w, a1, a2, s, use_h, use_off)
        theta, rmse, _, _ = solve_eq(G, b, last, y, w, a1, a2, s, idx, prior, j_off, False)
        viol = (np.maximum(lin_lo - theta, 0.0) + np.maximum(theta - lin_hi, 0.0)) / np.abs(scale)
        viol_r = np.maximum(1.5 / (t_hi / t_lo) - 1.0, 0.0)
        return rmse * (1.0 + 10.0 * (viol.sum(axis=1) + viol_r))

    np.testing.assert_array_equal(got, one_by_one(normal, solve))
    # the reference: the kernels' references one by one (they agree with the compiled ones to
    # rounding times the window's condition: tests/estimate/test_varpro_kernel.py)
    ref = varpro_kernel.fitness_numpy(*args)
    assert got.shape == ref.shape == (p,)
    np.testing.assert_array_equal(
        ref, one_by_one(varpro_kernel.normal_equations_numpy, varpro_kernel.solve_numpy)
    )
