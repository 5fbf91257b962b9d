"""The swarm's window fits (``estimate/varpro.py``) and what the fusion does with a result.

``fixed_rmse`` judges one fixed parameter set on a window: at ``fit_linear``'s optimum it must give
``fit_linear``'s own RMSE; the fusion uses it to refuse a swarm result that,
clipped to the bounds, fits the window worse than the parameters already in force.
"""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from bmsid.config.engine import build_bank
from bmsid.estimate.fusion import FusionStage
from bmsid.estimate.observer_tuning import ObserverTuning
from bmsid.estimate.tuning import EstimatorTuning
from bmsid.estimate.varpro import Window, fit_linear, fixed_rmse
from bmsid.model.ecm import rc_decay, rc_filter
from bmsid.samples import SampleBlock
from bmsid.synthetic import paper_dst_case

#: Short swarms so that 900 s of DST fuse the cell.
FAST = EstimatorTuning(window_s=120.0, min_window_s=40.0, swarm_period_s=60.0, n_iter=3,
                       n_iter_first=4, n_particles=4, swarm_min_steps=0,
                       observer=ObserverTuning(enabled=False))  # fmt: skip


@settings(max_examples=60, deadline=None)
@given(
    seed=st.integers(0, 2**32 - 1),
    tau1=st.floats(2.0, 60.0),
    ratio=st.floats(3.0, 100.0),
    n_w=st.integers(40, 400),
)
def test_fixed_rmse_at_the_linear_optimum_is_the_optimum(
    seed: int, tau1: float, ratio: float, n_w: int
) -> None:
    rng = np.random.default_rng(seed)
    i = np.repeat(rng.uniform(-3.0, 3.0, n_w // 10 + 1), 10)[:n_w]
    a1, a2 = rc_decay(1.0, tau1), rc_decay(1.0, tau1 * ratio)
    y = (-2e-3 * i - 1e-3 * rc_filter(i, float(a1)) - 1.5e-3 * rc_filter(i, float(a2))
         + 4e-3 * a1 ** np.arange(n_w) + 1e-4 * rng.standard_normal(n_w))  # fmt: skip
    w = Window(i, y, np.zeros(n_w), 1.0, use_hysteresis=False, use_offset=False)
    weights = rng.uniform(0.5, 1.0, n_w)
    scale = np.array([1e-3, 1e-3, 1e-3, 1.0, 0.05])
    fit = fit_linear(w, np.array([tau1]), np.array([tau1 * ratio]), scale, weights)
    theta = fit.theta[0]
    rmse = fixed_rmse(w, tau1, tau1 * ratio, theta, weights)
    assert np.isfinite(rmse)
    np.testing.assert_allclose(rmse, fit.rmse_V[0], rtol=1e-5, atol=1e-9)
    # any other parameter set fits worse
    assert fixed_rmse(w, tau1, tau1 * ratio, theta * 1.1, weights) >= rmse


def test_a_swarm_result_worse_than_the_parameters_in_force_is_not_applied() -> None:
    """A fused cell and a 'finished swarm' whose optimum is far off (two equal poles at the
    fast branch's upper bound: 300x worse on the window, beyond swarm_reject_ratio): the
    fusion keeps its poles, R and states, and counts the refusal; the same result on a cell not
    yet fused is applied (there is nothing better to keep)."""
    run = paper_dst_case(900)
    bank = build_bank(run.cell, 1, "hy-affrls-lpso", FAST, soc0=0.98)
    bank.update_block(SampleBlock.from_arrays(run.t_s, run.current_A, run.voltages_V))
    stage = bank.params
    assert isinstance(stage, FusionStage) and stage.fused[0]
    before = {k: np.array(getattr(stage, k)) for k in ("tau1", "tau2", "theta", "x1", "x2")}
    hi = stage._tau_box(0)[1]
    bad = np.log([0.99 * hi[0], hi[0]])
    stage.swarms.gbest[0], stage.swarms.gbest_f[0] = bad, 1e-3
    n_rejected = stage.counters["swarms_rejected"]
    stage._apply_swarm(0)
    assert stage.counters["swarms_rejected"] == n_rejected + 1
    for k, v in before.items():
        np.testing.assert_array_equal(getattr(stage, k), v, err_msg=k)
    stage.fused[0] = False
    stage._apply_swarm(0)
    assert stage.fused[0] and stage.tau2[0] == pytest.approx(hi[0])
