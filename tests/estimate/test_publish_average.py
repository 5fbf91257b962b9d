"""Published parameters averaged over the fast time constant (``estimate/publish_average.py``):
the property of the step, the bank's use of it, and the transient it removes."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from bmsid.config.engine import build_bank
from bmsid.estimate.publish_average import AVERAGED, PublishAverage, average_step
from bmsid.estimate.tuning import EstimatorTuning
from bmsid.estimate.types import Quality
from bmsid.samples import SampleBlock
from bmsid.synthetic import paper_dst_case

finite = st.floats(1e-6, 1e4)


@settings(max_examples=200, deadline=None)
@given(
    avg=st.lists(finite, min_size=4, max_size=4),
    raw=st.lists(finite, min_size=4, max_size=4),
    dt=st.floats(0.0, 1e4),
    tau=st.floats(1e-3, 1e5),
    fresh=st.booleans(),
)
def test_a_step_stays_between_the_average_and_the_new_value(
    avg: list[float], raw: list[float], dt: float, tau: float, fresh: bool
) -> None:
    a, r = np.array(avg)[:, None], np.array(raw)[:, None]
    out = average_step(a, r, dt, np.array([tau]), np.array([fresh]))
    assert np.all(np.isfinite(out))
    if fresh:
        assert np.array_equal(out, r)
    else:
        lo, hi = np.minimum(a, r), np.maximum(a, r)
        ulp = 4 * np.finfo(np.float64).eps * hi  # the rounding of a + g (r - a)
        assert np.all((out >= lo - ulp) & (out <= hi + ulp))
        if dt == 0.0:
            assert np.array_equal(out, a)


def test_an_average_without_a_finite_past_or_time_constant_starts_at_the_new_value() -> None:
    raw = np.arange(1.0, 9.0).reshape(4, 2)
    avg = np.full((4, 2), np.nan)
    tau = np.array([30.0, 30.0])
    assert np.array_equal(average_step(avg, raw, 1.0, tau, np.zeros(2, bool)), raw)
    avg = np.ones((4, 2))
    out = average_step(avg, raw, 1.0, np.array([np.nan, 30.0]), np.zeros(2, bool))
    assert np.array_equal(out[:, 0], raw[:, 0]) and np.all(out[:, 1] < raw[:, 1])


def test_converging_cells_publish_raw_and_c_stays_tau_over_r() -> None:
    avg = PublishAverage(2, 1.0)
    other = {"R0_ohm": np.ones(2), "C1_F": np.ones(2), "soc": np.ones(2)}
    cells = {k: np.array([1.0, 2.0]) for k in AVERAGED} | other
    q = np.array([int(Quality.CONVERGED), int(Quality.CONVERGED)])
    avg.apply(cells, q, 1.0)  # first tick: raw
    new = {k: np.array([3.0, 4.0]) for k in AVERAGED} | other
    q_next = np.array([int(Quality.CONVERGING), int(Quality.CONVERGED)])
    out = avg.apply(new, q_next, 1.0)
    assert out["R1_ohm"][0] == 3.0  # converging: raw
    assert 2.0 < out["R1_ohm"][1] < 4.0  # averaged
    assert np.array_equal(out["C1_F"], out["tau1_s"] / out["R1_ohm"])
    assert out["soc"] is new["soc"] and out["R0_ohm"] is new["R0_ohm"]  # passed through
    avg.reset(np.array([False, True]))
    out = avg.apply(new, q, 1.0)
    assert out["R1_ohm"][1] == 4.0  # re-initialised: raw again


def test_zero_publishes_the_raw_estimates() -> None:
    run = paper_dst_case(3000)
    blk = SampleBlock.from_arrays(run.t_s, run.current_A, run.voltages_V)
    outs = [
        build_bank(run.cell, 1, "hy-affrls-lpso", EstimatorTuning(publish_average_tau1=k),
                   soc0=0.98).update_block(blk)
        for k in (0.0, 1.0)
    ]  # fmt: skip
    raw, avg = outs
    assert np.array_equal(raw["v_model_V"], avg["v_model_V"])  # the engine is the same
    assert np.array_equal(raw["soc"], avg["soc"])
    assert np.array_equal(raw["R0_ohm"], avg["R0_ohm"])
    assert not np.array_equal(raw["R1_ohm"], avg["R1_ohm"])


@pytest.mark.parametrize(("tau1_multiple", "most"), [(1.0, 0.03), (0.0, None)])
def test_the_restart_transient_is_not_published(tau1_multiple: float, most: float | None) -> None:
    """The known-truth DST: right after a swarm's RLS restart one noisy sample moved the raw
    R0+R1+R2 by 7.5 % for a tick (README); averaged over tau1 the largest error after the first
    10 % stays within 3 % (measured 1.8 %); raw it does not (the test can fail)."""
    run = paper_dst_case()
    bank = build_bank(run.cell, 1, "hy-affrls-lpso",
                      EstimatorTuning(publish_average_tau1=tau1_multiple), soc0=0.98)  # fmt: skip
    est = bank.update_block(SampleBlock.from_arrays(run.t_s, run.current_A, run.voltages_V))
    s = est.n_ticks // 10
    t = run.truth
    rsum = (est["R0_ohm"] + est["R1_ohm"] + est["R2_ohm"])[s:, 0]
    err = np.max(np.abs(rsum / (run.R0_true_ohm[s:, 0] + t["R1_ohm"] + t["R2_ohm"]) - 1))
    if most is None:
        assert err > 0.05
    else:
        assert err <= most


def test_the_average_survives_a_checkpoint() -> None:
    """A bank restored from its state_dict mid-run publishes what the uninterrupted one does."""
    run = paper_dst_case(2400)
    t, i, v = run.t_s, run.current_A, run.voltages_V
    whole = build_bank(run.cell, 1, "hy-affrls-lpso", soc0=0.98)
    ref = whole.update_block(SampleBlock.from_arrays(t, i, v))
    first = build_bank(run.cell, 1, "hy-affrls-lpso", soc0=0.98)
    first.update_block(SampleBlock.from_arrays(t[:1500], i[:1500], v[:1500]))
    second = build_bank(run.cell, 1, "hy-affrls-lpso", soc0=0.98)
    second.load_state_dict(first.state_dict())
    rest = second.update_block(SampleBlock.from_arrays(t[1500:], i[1500:], v[1500:]))
    for k in ("R1_ohm", "R2_ohm", "tau1_s", "C2_F"):
        assert np.array_equal(rest[k], ref[k][-rest.n_ticks :]), k


@settings(max_examples=100, deadline=None)
@given(
    steps=st.lists(
        st.tuples(
            st.lists(st.floats(1e-4, 1e4), min_size=4, max_size=4),
            st.floats(0.0, 100.0),
            st.sampled_from([int(Quality.CONVERGED), int(Quality.CONVERGING)]),
        ),
        min_size=1,
        max_size=8,
    )
)
def test_one_cell_averages_as_a_bank_does(
    steps: list[tuple[list[float], float, int]],
) -> None:
    """The one-cell path (Python floats) gives the bits of the array path, step by step."""
    one, two = PublishAverage(1, 1.0), PublishAverage(2, 1.0)
    for values, dt, q in steps:
        c1 = {k: np.array([x]) for k, x in zip(AVERAGED, values, strict=True)}
        c2 = {k: np.array([x, x]) for k, x in zip(AVERAGED, values, strict=True)}
        o1 = one.apply(c1, np.array([q]), dt)
        o2 = two.apply(c2, np.array([q, q]), dt)
        for k in (*AVERAGED, "C1_F", "C2_F"):
            assert o1[k][0] == o2[k][0] == o2[k][1], k
