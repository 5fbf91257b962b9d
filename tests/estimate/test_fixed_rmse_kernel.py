"""The compiled fixed-parameter window RMSE agrees with its numpy reference to rounding."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import example, given, settings
from hypothesis import strategies as st

from bmsid.estimate.fixed_rmse_kernel import KERNEL, fixed_rmse_numpy


@settings(max_examples=80, deadline=None)
@given(
    seed=st.integers(0, 2**32 - 1),
    n=st.integers(3, 2500),
    taus=st.tuples(st.floats(0.5, 5000.0), st.floats(0.5, 5000.0)),
    use_h=st.booleans(),
    use_off=st.booleans(),
    weighted=st.booleans(),
)
@example(seed=157075143, n=3, taus=(1.0, 1.0), use_h=False, use_off=False, weighted=True)
@example(seed=3423, n=3, taus=(1.0, 1.0), use_h=False, use_off=True, weighted=True)
def test_compiled_and_reference_agree(
    seed: int, n: int, taus: tuple[float, float], use_h: bool, use_off: bool, weighted: bool
) -> None:
    """Random windows (a current of +-300 A, a voltage of the model's size plus noise, some
    ticks weighted 0 as the knees and gaps are), taus anywhere in the box, equal ones too."""
    compiled = KERNEL.compiled()
    assert compiled is not None
    rng = np.random.default_rng(seed)
    i = rng.uniform(-300.0, 300.0, n)
    y = -2e-3 * i + rng.normal(0.0, 5e-3, n)
    hm = rng.uniform(-0.02, 0.02, n)
    w = np.where(rng.random(n) < 0.1, 0.0, rng.uniform(0.5, 1.0, n)) if weighted else np.ones(n)
    theta = np.array([1.2e-3, 0.8e-3, 1.0e-3, 1.1, 2e-3]) * rng.uniform(0.5, 1.5, 5)
    a1, a2 = (float(np.exp(-1.0 / t)) for t in taus)
    args = (i, y, hm, w, a1, a2, theta, use_h, use_off)
    ref, new = fixed_rmse_numpy(*args), compiled(*args)
    assert np.isfinite(new)
    # Close taus or a few ticks make the two window-start columns nearly one (equal taus: only
    # the ridge tells them apart), and both solves round at that conditioning: 3e-5 of the RMSE
    # at worst in 3,000 random windows with equal taus, 2.5e-4 with 3 ticks. The RMSE decides a
    # ratio test (``swarm_reject_ratio``): 0.1 % is ample. A window the model fits exactly (3
    # ticks: the examples) has an RMSE of rounding only (3.6e-14 and 5.4e-6 V): there
    # the bound is 1 % of the noise the windows carry (5 mV), far below what the test decides.
    np.testing.assert_allclose(new, ref, rtol=1e-3, atol=1e-2 * 5e-3)


@pytest.mark.parametrize(("tau1_s", "tau2_s"), [(30.0, 600.0), (5.0, 60.0), (100.0, 3000.0)])
def test_a_swarms_window_agrees_to_rounding(tau1_s: float, tau2_s: float) -> None:
    """An 1,800-tick window of distinct taus, as a swarm's: the same to 1e-12 of the RMSE."""
    compiled = KERNEL.compiled()
    assert compiled is not None
    rng = np.random.default_rng(7)
    i = rng.uniform(-140.0, 140.0, 1800)
    y = -2e-3 * i + rng.normal(0.0, 1e-3, 1800)
    w = 0.999 ** np.arange(1800.0)[::-1]
    theta = np.array([1.2e-3, 0.8e-3, 1.0e-3, 1.0, 1e-3])
    args = (i, y, y * 0.0, w, float(np.exp(-1 / tau1_s)), float(np.exp(-1 / tau2_s)), theta,
            True, True)  # fmt: skip
    np.testing.assert_allclose(compiled(*args), fixed_rmse_numpy(*args), rtol=1e-12, atol=0.0)
