"""The publish guard's and the publish average's compiled tick kernels against their numpy
references (``estimate/guard_kernel.py``, ``estimate/publish_average.py``; issue 12: compiled,
kept equal to the reference to float tolerance).

The decisions (quality codes, holds, re-initialisations, episodes, causes, bound bits, counters)
and every held or passed value are the same to the bit; the model-error statistics and the
averages, which go through ``expm1`` (libm's compiled, numpy's own in the reference), agree to
rounding.
"""

from __future__ import annotations

from collections.abc import Iterator
from contextlib import contextmanager
from typing import Any

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from bmsid.config.engine import build_bank
from bmsid.estimate import guard_kernel, jit, publish_average
from bmsid.estimate.guard import HELD, WATCHED, PublishGuard
from bmsid.estimate.publish_average import AVERAGED, PUBLISHED, PublishAverage
from bmsid.estimate.tuning import EstimatorTuning
from bmsid.estimate.types import Quality
from bmsid.samples import SampleBlock
from bmsid.synthetic import paper_dst_case

#: Bounds of the random parameters (R ohm, tau s, OCV offset V); the taus' overlap (as the
#: shipped configs') lets the pairs cross.
BOUNDS = {
    "R0_ohm": (1e-4, 0.1),
    "R1_ohm": (1e-4, 0.1),
    "R2_ohm": (1e-4, 0.1),
    "tau1_s": (0.5, 200.0),
    "tau2_s": (20.0, 8000.0),
    "ocv_offset_V": (-0.05, 0.05),
}
START = {"R0_ohm": 1e-3, "R1_ohm": 5e-4, "R2_ohm": 5e-4, "tau1_s": 10.0, "tau2_s": 300.0,
         "ocv_offset_V": 0.0, "C1_F": 10.0 / 5e-4, "C2_F": 300.0 / 5e-4}  # fmt: skip
#: Short time constants, so that sequences of tens of ticks reach every rule.
FAST = EstimatorTuning(
    id_period_s=1.0, gap_s=10.0, divergence_fast_s=2.0, divergence_scale_s=20.0,
    divergence_hold_s=5.0,
)  # fmt: skip


@contextmanager
def using(kernel: jit.Kernel[Any], impl: Any) -> Iterator[None]:
    """Run ``kernel`` by ``impl`` inside the block (the process-wide choice left alone)."""
    saved = kernel.impl
    kernel.impl = impl
    try:
        yield
    finally:
        kernel.impl = saved


def test_the_compiled_kernels_are_available() -> None:
    """numba is a dependency: a machine where they do not compile must fail here."""
    assert guard_kernel.KERNEL.compiled() is not None
    assert publish_average.KERNEL.compiled() is not None


def random_ticks(rng: np.random.Generator, n: int, n_ticks: int) -> Iterator[dict[str, Any]]:
    """Ticks of n cells with every kind of input the guard has rules for: parameters inside
    the bounds, on them, just inside the "on a bound" share, or garbage (NaN, inf, 0, < 0);
    crossed time constants; SOC inside, at and past the margin, or NaN; model errors from
    noise to 0.2 V, exactly 0, or NaN; all quality codes; random clamps and learn masks;
    regular steps, short ones, gaps, repeats and jumps back."""
    p_bound, p_bad, p_big = rng.choice([0.0, 0.1, 0.5]), rng.choice([0.0, 0.05]), rng.random()
    t = 1.7e9
    for _ in range(n_ticks):
        t += float(rng.choice([1.0, 1.0, 1.0, 0.5, 0.0, 50.0, -30.0]))
        vals = {k: rng.uniform(lo, hi, n) for k, (lo, hi) in BOUNDS.items()}
        for k in WATCHED:
            lo, hi = BOUNDS[k]
            edge = rng.choice([lo, hi, lo * 1.01, hi * 0.99, lo * 1.0100001], n)
            vals[k] = np.where(rng.random(n) < p_bound, edge, vals[k])
        vals["tau1_s"] = np.where(rng.random(n) < 0.2, vals["tau2_s"] * 1.1, vals["tau1_s"])
        for k in ("R1_ohm", "tau2_s", "ocv_offset_V"):
            bad = rng.choice([np.nan, np.inf, -np.inf, 0.0, -1e-3], n)
            vals[k] = np.where(rng.random(n) < p_bad, bad, vals[k])
        cells = {k: np.ascontiguousarray(v) for k, v in vals.items()}
        with np.errstate(divide="ignore", invalid="ignore"):
            cells["C1_F"] = cells["tau1_s"] / cells["R1_ohm"]
            cells["C2_F"] = cells["tau2_s"] / cells["R2_ohm"]
        margin = FAST.divergence_soc_margin
        cells["soc"] = np.where(
            rng.random(n) < 0.1, rng.choice([np.nan, -margin, 1 + margin, -0.2, 1.2], n),
            rng.uniform(-0.01, 1.01, n),
        )  # fmt: skip
        err = np.where(rng.random(n) < p_big, 0.2, 1e-3) * rng.standard_normal(n)
        cells["v_error_V"] = np.where(rng.random(n) < 0.05, rng.choice([np.nan, 0.0], n), err)
        cells |= {k: rng.random(n) for k in ("h", "lambda_", "v_meas_V", "v_model_V")}
        learn = rng.random(n) < 0.9
        yield {
            "t_s": t,
            "cells": cells,
            "quality": rng.choice([int(q) for q in Quality if q != Quality.NO_DATA], n),
            "on_bound": rng.random(n) < p_bound / 2,
            "learn": None if rng.random() < 0.1 else learn,
        }


@settings(max_examples=150, deadline=None)
@given(
    n=st.integers(1, 12),
    n_ticks=st.integers(1, 40),
    seed=st.integers(0, 2**32 - 1),
    with_bounds=st.booleans(),
)
def test_compiled_and_reference_guards_decide_alike(
    n: int, n_ticks: int, seed: int, with_bounds: bool
) -> None:
    compiled = guard_kernel.KERNEL.compiled()
    assert compiled is not None
    bounds = {k: BOUNDS[k] for k in WATCHED} if with_bounds else None
    ref, new = PublishGuard(n, FAST, START, bounds), PublishGuard(n, FAST, START, bounds)
    for tk in random_ticks(np.random.default_rng(seed), n, n_ticks):
        before = {k: v.copy() for k, v in tk["cells"].items()}
        q_in = tk["quality"].copy()
        with using(guard_kernel.KERNEL, guard_kernel.guard_step_numpy):
            out_r, q_r, re_r = ref.apply(**tk)
        with using(guard_kernel.KERNEL, compiled):
            out_n, q_n, re_n = new.apply(**tk)
        assert out_n.keys() == out_r.keys()
        for k in out_r:  # held, passed or clipped: the same bits
            np.testing.assert_array_equal(out_n[k], out_r[k], err_msg=k)
        np.testing.assert_array_equal(q_n, q_r)
        np.testing.assert_array_equal(re_n, re_r)
        assert q_n.dtype == np.int64 and re_n.dtype == np.bool_
        for k in ("episode", "cause", "bound_bits", "good", "good_soc"):
            np.testing.assert_array_equal(getattr(new, k), getattr(ref, k), err_msg=k)
        for k in ("e2_fast", "fast_s", "e2_scale", "scale_s", "excess_s"):
            np.testing.assert_allclose(getattr(new, k), getattr(ref, k), rtol=1e-12, err_msg=k)
        assert new.counters == ref.counters
        for k, v in before.items():  # the inputs are never written
            np.testing.assert_array_equal(tk["cells"][k], v, err_msg=k)
        np.testing.assert_array_equal(tk["quality"], q_in)


@settings(max_examples=150, deadline=None)
@given(
    n=st.integers(1, 12),
    n_ticks=st.integers(1, 20),
    seed=st.integers(0, 2**32 - 1),
    multiple=st.sampled_from([0.5, 1.0, 3.0]),
)
def test_compiled_and_reference_averages_agree(
    n: int, n_ticks: int, seed: int, multiple: float
) -> None:
    """Random values (now and then NaN, inf, 0 or < 0: a time constant that is no time
    constant), qualities, re-initialisations and steps (0, negative, long)."""
    compiled = publish_average.KERNEL.compiled()
    assert compiled is not None
    rng = np.random.default_rng(seed)
    ref, new = PublishAverage(n, multiple), PublishAverage(n, multiple)
    for _ in range(n_ticks):
        cells = {k: rng.uniform(1e-4, 1e3, n) for k in AVERAGED}
        for k in AVERAGED:  # R never 0: the guard's outputs are > 0 (the reference's one-cell
            # path in Python floats would raise ZeroDivisionError for C = tau / R)
            bad = rng.choice([np.nan, np.inf, -1.0, 0.0 if k.startswith("tau") else np.nan], n)
            cells[k] = np.where(rng.random(n) < 0.05, bad, cells[k])
        cells["R0_ohm"] = rng.random(n)
        q = rng.choice([int(Quality.CONVERGING), int(Quality.CONVERGED), int(Quality.DIVERGED)], n)
        dt = float(rng.choice([1.0, 1.0, 0.0, -2.0, 0.5, 300.0]))
        if rng.random() < 0.2:
            mask = rng.random(n) < 0.5
            ref.reset(mask)
            new.reset(mask)
        # the rule: a fresh cell, or one with no finite past, values or time constant, starts
        # at its raw values (in both, to the bit)
        tau = multiple * cells["tau1_s"]
        raw_rows = np.array([cells[k] for k in AVERAGED])
        with np.errstate(invalid="ignore"):
            ok = ~ref.restart & (q != int(Quality.CONVERGING)) & np.isfinite(tau) & (tau > 0)
        ok &= np.isfinite(ref.avg).all(axis=0) & np.isfinite(raw_rows).all(axis=0)
        with (
            np.errstate(all="ignore"),
            using(publish_average.KERNEL, publish_average.average_numpy),
        ):
            out_r = ref.apply(cells, q, dt)
        with using(publish_average.KERNEL, compiled):
            out_n = new.apply(cells, q, dt)
        assert out_n["R0_ohm"] is out_r["R0_ohm"] is cells["R0_ohm"]  # passed through
        with np.errstate(invalid="ignore"):
            for k in PUBLISHED:
                np.testing.assert_allclose(out_n[k], out_r[k], rtol=1e-13, atol=0, err_msg=k)
        for k in AVERAGED:
            np.testing.assert_array_equal(out_n[k][~ok], cells[k][~ok], err_msg=k)
            np.testing.assert_array_equal(out_r[k][~ok], cells[k][~ok], err_msg=k)
        np.testing.assert_allclose(new.avg, ref.avg, rtol=1e-13, atol=0)
        np.testing.assert_array_equal(new.restart, ref.restart)


@pytest.mark.parametrize("variant", ["hy-affrls", "hy-affrls-lpso"])
def test_a_bank_publishes_the_same_with_either_kernel(restore_kernel: None, variant: str) -> None:
    """Three cells of the reference DST: the same qualities and counters, every published
    estimate equal to float tolerance."""
    run = paper_dst_case(1500, r0_spread=np.array([1.0, 1.3, 0.8]))
    block = SampleBlock.from_arrays(run.t_s, run.current_A, run.voltages_V)
    out, counters = {}, {}
    for name in ("numpy", "compiled"):
        jit.select(name)
        assert guard_kernel.KERNEL.kind == publish_average.KERNEL.kind == name
        bank = build_bank(run.cell, 3, variant, soc0=0.98)  # type: ignore[arg-type]
        out[name] = bank.update_block(block)
        counters[name] = bank.counters
    ref, new = out["numpy"], out["compiled"]
    np.testing.assert_array_equal(new.quality, ref.quality)
    assert counters["compiled"] == counters["numpy"]
    for k in (*HELD, "soc", "v_model_V", "on_bound"):
        np.testing.assert_allclose(new[k], ref[k], rtol=1e-8, atol=0.0, err_msg=k)
