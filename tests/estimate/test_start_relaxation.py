"""A start read from a voltage still relaxing (estimate/start_relaxation.py, observer.py).

The unit: the slope of the first rest, beyond two standard errors of its own residuals, times
sqrt(tau1 tau2). The bank: a record that starts seconds after a drive widens the start SOC's
uncertainty once; a rested start does not.
"""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from bmsid.config.engine import build_bank
from bmsid.estimate.start_relaxation import (
    MIN_SAMPLES,
    NOISE_FLOOR_V,
    StartRelaxation,
    relaxation_tau_s,
    slope_from_sums,
    widened_variance,
)
from bmsid.estimate.tuning import EstimatorTuning
from bmsid.samples import SampleBlock
from bmsid.synthetic.multiday import MultidayOptions, generate

ONE = np.ones(1, dtype=bool)


def _watch(t_s: np.ndarray, v_V: np.ndarray, tau_s: float = 50.0) -> np.ndarray | None:
    """Feed a rest of voltages ``v_V`` at ``t_s``, then one loaded tick; the result."""
    w = StartRelaxation(1, np.array([tau_s]), max_rest_s=600.0)
    w.begin(float(t_s[0]), ONE)
    for t, v in zip(t_s, v_V, strict=True):
        assert w.feed(float(t), np.array([v]), ONE, resting=True) is None
    return w.feed(float(t_s[-1]) + 1.0, np.array([v_V[-1]]), ONE, resting=False)


def test_a_clean_ramp_gives_its_slope_times_tau() -> None:
    t = np.arange(8.0)
    out = _watch(t, 3.65 + 0.5e-3 * t)
    assert out is not None
    se = NOISE_FLOOR_V / np.sqrt(((t - t.mean()) ** 2).sum())  # no residuals: the floor's
    assert out[0] == pytest.approx((0.5e-3 - 2 * se) * 50.0, rel=1e-6)  # ~21 mV to relax


def test_a_flat_rest_and_a_too_short_one_widen_nothing() -> None:
    assert _watch(np.arange(10.0), np.full(10, 3.7)) == pytest.approx([0.0])
    t = np.arange(float(MIN_SAMPLES - 1))
    assert _watch(t, 3.65 + 1e-3 * t) == pytest.approx([0.0])


def test_a_rest_as_long_as_the_anchor_wait_ends_without_a_result() -> None:
    w = StartRelaxation(1, np.array([50.0]), max_rest_s=600.0)
    w.begin(0.0, ONE)
    for t in range(0, 700, 10):
        assert w.feed(float(t), np.array([3.6 + 1e-5 * t]), ONE, resting=True) is None
    assert not w.active
    assert w.feed(710.0, np.array([3.6]), ONE, resting=False) is None


@settings(max_examples=200, deadline=None)
@given(
    n=st.integers(MIN_SAMPLES, 40),
    sigma=st.floats(1e-5, 5e-3),
    seed=st.integers(0, 2**32 - 1),
)
def test_noise_alone_rarely_counts_and_never_gives_nan(n: int, sigma: float, seed: int) -> None:
    """A flat rest with white noise: finite, >= 0, and no more than the 2-sigma tail of the
    slope's own error times tau (the test cannot pass on a result that ignores the error)."""
    rng = np.random.default_rng(seed)
    t = np.arange(float(n))
    out = _watch(t, 3.7 + sigma * rng.standard_normal(n))
    assert out is not None
    assert np.isfinite(out[0]) and out[0] >= 0.0
    se_slope = max(sigma, NOISE_FLOOR_V) / np.sqrt(((t - t.mean()) ** 2).sum())
    assert out[0] <= 50.0 * 6.0 * se_slope  # 2 se subtracted; beyond 8 se is ~never


@given(
    var=st.floats(0.0, 0.2),
    extra=st.floats(0.0, 0.2),
    slope=st.floats(-5.0, 5.0),
    cap=st.floats(0.0, 1.0),
)
def test_widening_never_shrinks_and_respects_the_cap(
    var: float, extra: float, slope: float, cap: float
) -> None:
    out = float(widened_variance(np.array([var]), np.array([extra]), np.array([slope]), cap)[0])
    assert np.isfinite(out)
    assert out >= var
    assert out <= max(var, cap**2) + 1e-15


@settings(max_examples=100, deadline=None)
@given(
    n=st.integers(3, 60),
    slope=st.floats(-1e-2, 1e-2),
    sigma=st.floats(0.0, 1e-2),
    seed=st.integers(0, 2**32 - 1),
)
def test_the_slope_from_sums_is_the_least_squares_slope(
    n: int, slope: float, sigma: float, seed: int
) -> None:
    rng = np.random.default_rng(seed)
    t = np.cumsum(rng.uniform(0.1, 2.0, n))
    v = slope * t + sigma * rng.standard_normal(n)
    dt, dv = t - t[0], v - v[0]
    one = np.ones(1)
    s, se = slope_from_sums(one * n, one * dt.sum(), one * dv.sum(), one * (dt**2).sum(),
                            one * (dt * dv).sum(), one * (dv**2).sum(), 0.0)  # fmt: skip
    ref, cov = np.polyfit(t, v, 1, cov="unscaled")
    assert s[0] == pytest.approx(ref[0], rel=1e-6, abs=1e-12)
    if n > 2:
        resid = v - np.polyval(ref, t)
        se_ref = np.sqrt((resid**2).sum() / (n - 2) * cov[0, 0])
        assert se[0] == pytest.approx(se_ref, rel=1e-4, abs=1e-9)


def test_tau_is_the_geometric_mean_of_the_branches() -> None:
    assert relaxation_tau_s(np.array([10.0]), np.array([360.0]))[0] == pytest.approx(60.0)


# ----------------------------------------------------------------------------- in the bank
H = 3600
TUN = EstimatorTuning(id_period_s=1.0)


def _run(a: int, b: int) -> tuple[int, float]:
    """The multi-day generator's first day, from sample ``a`` to ``b``, no soc0: the count
    of widened starts and the SOC std one tick after the first rest ended."""
    rec = generate(MultidayOptions(n_days=1, duration_s=4 * H))
    blk = SampleBlock.from_arrays(rec.t_s, rec.current_A, rec.voltage_V[:, None]).slice(a, b)
    bank = build_bank(rec.cell, 1, tuning=TUN)
    out = bank.update_block(blk)
    moving = np.flatnonzero(np.abs(rec.current_A[a:b]) > 0.7)[0]
    k = int(np.searchsorted(out.t_s, rec.t_s[a + moving])) + 1
    return bank.counters["start_relaxations"], float(out["soc_std"][k, 0])


def test_a_start_seconds_after_a_drive_is_less_certain_than_a_rested_one(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """After 07:45 in the first drive: the DST's 60 s rest step after 15 min of driving (the
    slow branch relaxing, the voltage climbs ~10 mV) widens the start once; 07:00, the
    morning's rested start, does not."""
    rec = generate(MultidayOptions(n_days=1, duration_s=4 * H))
    a = int(np.searchsorted(rec.t_s, rec.t_s[0] + 0.75 * H))
    while np.any(np.abs(rec.current_A[a : a + 30]) > 0.7) or abs(rec.current_A[a - 1]) < 0.7:
        a += 1  # the first sample of the next rest step of 30 s or more
    n_drive, sd_drive = _run(a, a + 1800)
    n_rest, _ = _run(0, 2 * H)
    assert n_drive == 1
    assert n_rest == 0
    monkeypatch.setattr(StartRelaxation, "_remaining_V", lambda self: np.zeros(self.n.shape))
    n_off, sd_off = _run(a, a + 1800)
    assert n_off == 0
    assert sd_drive > 1.05 * sd_off, (sd_drive, sd_off)  # M + 10 mV were allowed for already
