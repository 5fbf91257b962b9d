"""The end of a tick in one compiled call (``estimate/publish_kernel.py``, issue 12): against the
stages' kernels called one by one in a bank (the same bits) and against its numpy reference on
random ticks (the guard's and the average's tolerances, ``test_guard_kernel.py``)."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from test_guard_kernel import FAST, START  # the guard's own cases drive its compiled tail

from bmsid.config.engine import build_bank
from bmsid.estimate import jit, publish_kernel
from bmsid.estimate.guard import WATCHED, PublishGuard
from bmsid.estimate.publish_average import AVERAGED, PublishAverage
from bmsid.samples import SampleBlock
from bmsid.synthetic import paper_dst_case

BOUNDS = {"R0_ohm": (1e-4, 0.1), "R1_ohm": (1e-4, 0.1), "R2_ohm": (1e-4, 0.1),
          "tau1_s": (0.5, 200.0), "tau2_s": (20.0, 8000.0)}  # fmt: skip


def test_the_compiled_tail_is_available() -> None:
    assert publish_kernel.TAIL.compiled() is not None


@settings(max_examples=100, deadline=None)
@given(
    n=st.integers(1, 8),
    n_ticks=st.integers(1, 30),
    seed=st.integers(0, 2**32 - 1),
    with_bounds=st.booleans(),
    multiple=st.sampled_from([0.0, 1.0, 3.0]),
)
def test_compiled_and_reference_tails_agree(
    n: int, n_ticks: int, seed: int, with_bounds: bool, multiple: float
) -> None:
    """Random parameters (inside, on and near bounds, garbage), SOC, errors, excitation,
    clamps, convergence and steps: the same codes, holds and re-initialisations."""
    compiled = publish_kernel.TAIL.compiled()
    assert compiled is not None
    rng = np.random.default_rng(seed)
    bounds = {k: BOUNDS[k] for k in WATCHED} if with_bounds else None
    guards = [PublishGuard(n, FAST, START, bounds) for _ in range(2)]
    avgs = [PublishAverage(n, multiple) for _ in range(2)]
    t = 1.7e9
    for _ in range(n_ticks):
        t += float(rng.choice([1.0, 1.0, 0.5, 0.0, 50.0, -30.0]))
        dt = float(rng.choice([1.0, 1.0, 0.0, 300.0]))
        vals = {k: rng.uniform(lo, hi, n) for k, (lo, hi) in BOUNDS.items()}
        for k, (lo, hi) in BOUNDS.items():
            vals[k] = np.where(rng.random(n) < 0.2, rng.choice([lo, hi, lo * 1.005], n), vals[k])
        vals["R1_ohm"] = np.where(rng.random(n) < 0.05, np.nan, vals["R1_ohm"])
        vals["C1_F"], vals["C2_F"] = (
            vals["tau1_s"] / vals["R1_ohm"],
            vals["tau2_s"] / vals["R2_ohm"],
        )
        vals["ocv_offset_V"] = rng.uniform(-0.01, 0.01, n)
        params = np.array([vals[k] for k in publish_kernel.HELD])
        soc = np.where(rng.random(n) < 0.1, rng.choice([np.nan, -0.2, 1.2], n), rng.random(n))
        err = np.where(rng.random(n) < 0.1, 0.2, 1e-3) * rng.standard_normal(n)
        flags = [rng.random(n) < p for p in (0.8, 0.1, 0.7, 0.9)]  # excited .. learn
        out = []
        for impl, guard, avg in zip((compiled, publish_kernel.tail_numpy), guards, avgs,
                                    strict=True):  # fmt: skip
            res = impl(
                guard._data_dt(t), soc, *params, err, *flags, guard._stats, guard.good,
                guard.good_soc, guard.episode, guard.cause, guard.bound_bits, guard._near,
                guard._has_near, guard._consts, avg.avg, avg.restart, dt, multiple,
            )  # fmt: skip
            guard.good, guard.good_soc = res[0][:8], res[0][8]
            out.append(res)
        new, ref = out
        # the guard's results (published, SOC, bits, codes, re-initialisations, counts): the
        # same bits
        np.testing.assert_array_equal(new[0][:10], ref[0][:10])
        for j in range(1, 6):
            np.testing.assert_array_equal(new[j], ref[j], err_msg=str(j))
        np.testing.assert_allclose(new[0][10:], ref[0][10:], rtol=1e-13, atol=0, equal_nan=True)
        if multiple > 0.0:
            np.testing.assert_allclose(avgs[0].avg, avgs[1].avg, rtol=1e-13, equal_nan=True)
        for k in ("episode", "cause", "bound_bits"):
            np.testing.assert_array_equal(getattr(guards[0], k), getattr(guards[1], k))
        np.testing.assert_allclose(guards[0]._stats, guards[1]._stats, rtol=1e-12)


@pytest.mark.parametrize("variant", ["hy-affrls", "hy-affrls-lpso"])
def test_a_bank_publishes_the_same_bits_with_the_tail_in_one_call(
    restore_kernel: None, variant: str
) -> None:
    """Compiled, a bank with the tail in one call and one with the guard's and the average's
    kernels called one by one: the same bits (NaN voltages and a gap included)."""
    jit.select("compiled")
    run = paper_dst_case(1200, r0_spread=np.array([1.0, 1.3, 0.8]))
    v = run.voltages_V.copy()
    v[np.random.default_rng(3).random(v.shape) < 0.02] = np.nan
    t = run.t_s.copy()
    t[600:] += 900.0
    block = SampleBlock.from_arrays(t, run.current_A, v)
    out = []
    for kind in ("compiled", "numpy"):
        publish_kernel.TAIL.kind = kind  # "numpy": the bank calls the stages one by one
        try:
            bank = build_bank(run.cell, 3, variant, soc0=0.98)
            out.append((bank.update_block(block), bank.counters))
        finally:
            publish_kernel.TAIL.kind = "compiled"
    (new, c_new), (ref, c_ref) = out
    assert c_new == c_ref
    np.testing.assert_array_equal(new.quality, ref.quality)
    assert new.cells.keys() == ref.cells.keys()
    for k in new.cells:
        np.testing.assert_array_equal(new.cells[k], ref.cells[k], err_msg=k)
    assert set(AVERAGED) <= set(new.cells)
