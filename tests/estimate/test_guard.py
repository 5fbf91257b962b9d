"""The publish guard (``estimate/guard.py``): nothing garbage is published, a bound never shows.

Properties over random tick sequences (garbage included): published parameters are always
finite and inside the bounds, held together (C = tau / R) and never a bound-hit value; a
diverging cell is re-initialised once per episode; n cells in one guard equal n one-cell guards.
Then each rule on its own, with the default tuning at 1 Hz.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from bmsid.config.cell import paper_cell
from bmsid.config.engine import cell_model
from bmsid.daemon.demo_data import DEMO_LOG
from bmsid.estimate import jit
from bmsid.estimate.guard import (
    CAUSE_ERROR,
    CAUSE_PARAMS,
    CAUSE_SOC,
    HELD,
    WATCHED,
    PublishGuard,
)
from bmsid.estimate.publish_average import PublishAverage
from bmsid.estimate.tuning import EstimatorTuning
from bmsid.estimate.types import Quality
from bmsid.offline.identify import IdentifySpec, identify_file

FloatArray = np.ndarray

#: Bounds of the test's parameters (R ohm, tau s, OCV offset V); C = tau / R follows.
BOUNDS = {
    "R0_ohm": (1e-4, 0.1),
    "R1_ohm": (1e-4, 0.1),
    "R2_ohm": (1e-4, 0.1),
    "tau1_s": (1.0, 100.0),
    "tau2_s": (100.0, 5000.0),
    "ocv_offset_V": (-0.05, 0.05),
}
START = {"R0_ohm": 1e-3, "R1_ohm": 5e-4, "R2_ohm": 5e-4, "tau1_s": 10.0, "tau2_s": 300.0,
         "ocv_offset_V": 0.0}  # fmt: skip
START_C = {"C1_F": START["tau1_s"] / START["R1_ohm"], "C2_F": START["tau2_s"] / START["R2_ohm"]}
#: Short time constants, so that random sequences of tens of ticks reach every rule.
FAST = EstimatorTuning(
    id_period_s=1.0,
    gap_s=10.0,
    divergence_fast_s=2.0,
    divergence_scale_s=20.0,
    divergence_hold_s=5.0,
)


def guard(n: int, tuning: EstimatorTuning = FAST) -> PublishGuard:
    return PublishGuard(n, tuning, {**START, **START_C})


def cells_of(n: int, **over: float | FloatArray) -> dict[str, FloatArray]:
    """Every field a bank publishes; the parameters at their start values unless given."""
    base: dict[str, float | FloatArray] = {
        **START, "soc": 0.5, "v_error_V": 0.0, "h": 0.0, "lambda_": 0.999, "v_meas_V": 3.3,
        "v_model_V": 3.3,
    }  # fmt: skip
    base |= over
    out = {
        k: np.broadcast_to(np.asarray(v, dtype=np.float64), (n,)).copy() for k, v in base.items()
    }
    with np.errstate(divide="ignore", invalid="ignore"):  # garbage R gives garbage C
        out["C1_F"] = out["tau1_s"] / out["R1_ohm"]
        out["C2_F"] = out["tau2_s"] / out["R2_ohm"]
    return out


def q_of(n: int, code: int = Quality.CONVERGED) -> np.ndarray:
    return np.full(n, int(code), dtype=np.int64)


NO = np.zeros(1, dtype=bool)
YES = np.ones(1, dtype=bool)


# ----------------------------------------------------------------------- random tick sequences
@dataclass(frozen=True)
class TickIn:
    t_s: float
    cells: dict[str, FloatArray]
    quality: np.ndarray
    on_bound: np.ndarray
    learn: np.ndarray


@st.composite
def sequences(draw: st.DrawFn) -> tuple[int, list[TickIn]]:
    """Ticks of 1-4 cells: parameters inside the bounds (or, rarely, NaN / negative), random
    bound hits and qualities, SOC in [-0.1, 1.1] or NaN, model errors from noise to 0.2 V or
    NaN, time steps regular, short, gaps and jumps back."""
    n = draw(st.integers(1, 4))
    n_ticks = draw(st.integers(1, 40))
    rng = np.random.default_rng(draw(st.integers(0, 2**32 - 1)))
    p_bound = draw(st.sampled_from([0.0, 0.1, 0.5]))
    p_bad = draw(st.sampled_from([0.0, 0.02, 0.2]))
    p_big_error = draw(st.sampled_from([0.0, 0.5, 0.95]))
    t = 1.7e9
    ticks = []
    for _ in range(n_ticks):
        t += float(rng.choice([1.0, 1.0, 1.0, 0.5, 50.0, -30.0]))
        vals = {k: rng.uniform(lo, hi, n) for k, (lo, hi) in BOUNDS.items()}
        bad = rng.random(n) < p_bad
        vals["R1_ohm"] = np.where(bad, rng.choice([np.nan, -1e-3, np.inf], n), vals["R1_ohm"])
        soc = np.where(rng.random(n) < 0.05, np.nan, rng.uniform(-0.1, 1.1, n))
        err = np.where(rng.random(n) < p_big_error, 0.2, 1e-3) * rng.standard_normal(n)
        err = np.where(rng.random(n) < 0.05, np.nan, err)
        ticks.append(
            TickIn(
                t,
                cells_of(n, **vals, soc=soc, v_error_V=err),
                rng.choice([0, 1, 1, 1, 2, 3], n).astype(np.int64),
                rng.random(n) < p_bound,
                rng.random(n) < 0.9,
            )
        )
    return n, ticks


@settings(max_examples=300, deadline=None)
@given(sequences())
def test_published_parameters_are_finite_in_bounds_and_held_together(
    seq: tuple[int, list[TickIn]],
) -> None:
    n, ticks = seq
    g = guard(n)
    for tk in ticks:
        out, q, _ = g.apply(tk.t_s, tk.cells, tk.quality, tk.on_bound, tk.learn)
        for k, (lo, hi) in BOUNDS.items():
            assert np.all(np.isfinite(out[k])), k
            assert np.all((out[k] >= lo) & (out[k] <= hi)), k
        # one tick's parameters, all of them: C = tau / R still holds
        np.testing.assert_allclose(out["C1_F"], out["tau1_s"] / out["R1_ohm"], rtol=1e-12)
        np.testing.assert_allclose(out["C2_F"], out["tau2_s"] / out["R2_ohm"], rtol=1e-12)
        assert set(np.unique(q)) <= {int(c) for c in Quality}


@settings(max_examples=300, deadline=None)
@given(sequences())
def test_a_bound_hit_never_reaches_the_output(seq: tuple[int, list[TickIn]]) -> None:
    """A reference of the rule: a cell on a bound or diverged publishes its last published
    good values (the start values before any), every other cell its own."""
    n, ticks = seq
    g = guard(n)
    good = {k: np.full(n, v) for k, v in {**START, **START_C}.items()}
    for tk in ticks:
        out, q, _ = g.apply(tk.t_s, tk.cells, tk.quality, tk.on_bound, tk.learn)
        held = tk.on_bound | (q == Quality.DIVERGED)
        for k in HELD:
            np.testing.assert_array_equal(out[k], np.where(held, good[k], tk.cells[k]), k)
            good[k] = np.where(held, good[k], tk.cells[k])
        # quality: DIVERGED where held by an episode, the bank's code everywhere else
        keep = q != Quality.DIVERGED
        np.testing.assert_array_equal(q[keep], tk.quality[keep])
        # SOC passes unless it is itself bad; the evidence always passes
        margin = FAST.divergence_soc_margin
        soc_ok = (tk.cells["soc"] >= -margin) & (tk.cells["soc"] <= 1 + margin)
        np.testing.assert_array_equal(out["soc"][soc_ok], np.clip(tk.cells["soc"], 0, 1)[soc_ok])
        assert np.all((out["soc"] >= 0.0) & (out["soc"] <= 1.0) | np.isnan(out["soc"]))
        for k in ("v_error_V", "v_meas_V", "v_model_V", "lambda_", "h"):
            assert out[k] is tk.cells[k]


@settings(max_examples=300, deadline=None)
@given(sequences())
def test_a_diverging_cell_is_reinitialised_once_per_episode(
    seq: tuple[int, list[TickIn]],
) -> None:
    n, ticks = seq
    g = guard(n)
    was_diverged = np.zeros(n, dtype=bool)
    total = 0
    for tk in ticks:
        _, q, reinit = g.apply(tk.t_s, tk.cells, tk.quality, tk.on_bound, tk.learn)
        diverged = q == Quality.DIVERGED
        np.testing.assert_array_equal(reinit, diverged & ~was_diverged)  # at an episode's start
        assert np.all(g.cause[diverged] != 0) and np.all(g.cause[~diverged] == 0)
        was_diverged = diverged
        total += int(reinit.sum())
    assert g.counters["diverged"] == total


@settings(max_examples=200, deadline=None)
@given(sequences())
def test_the_guard_is_per_cell(seq: tuple[int, list[TickIn]]) -> None:
    """n cells in one guard give what n one-cell guards give (no cell sees another)."""
    n, ticks = seq
    together = guard(n)
    alone = [guard(1) for _ in range(n)]
    for tk in ticks:
        out, q, reinit = together.apply(tk.t_s, tk.cells, tk.quality, tk.on_bound, tk.learn)
        for i, gi in enumerate(alone):
            cells = {k: v[i : i + 1] for k, v in tk.cells.items()}
            sl = slice(i, i + 1)
            out_i, q_i, re_i = gi.apply(
                tk.t_s, cells, tk.quality[sl], tk.on_bound[sl], tk.learn[sl]
            )
            for k in out:
                np.testing.assert_array_equal(out[k][sl], out_i[k], k)
            assert q[i] == q_i[0] and reinit[i] == re_i[0]
    for key in together.counters:
        assert together.counters[key] == sum(gi.counters[key] for gi in alone)


@settings(max_examples=200, deadline=None)
@given(sequences())
def test_the_one_cell_path_keeps_the_array_paths_statistics(seq: tuple[int, list[TickIn]]) -> None:
    """A one-cell guard (its model-error test in Python floats) holds the statistics the same
    cell holds in a guard of several (arrays), to the bit."""
    n, ticks = seq
    together = guard(n + 1)  # the last cell repeats the first: at least two cells, arrays
    alone = [guard(1) for _ in range(n)]
    for tk in ticks:
        cells = {k: np.append(v, v[:1]) for k, v in tk.cells.items()}
        together.apply(
            tk.t_s, cells, np.append(tk.quality, tk.quality[:1]),
            np.append(tk.on_bound, tk.on_bound[:1]), np.append(tk.learn, tk.learn[:1]),
        )  # fmt: skip
        for i, gi in enumerate(alone):
            sl = slice(i, i + 1)
            gi.apply(
                tk.t_s, {k: v[sl] for k, v in tk.cells.items()}, tk.quality[sl],
                tk.on_bound[sl], tk.learn[sl],
            )  # fmt: skip
            for k in ("e2_fast", "fast_s", "e2_scale", "scale_s", "excess_s", "episode"):
                assert getattr(together, k)[i].tobytes() == getattr(gi, k)[0].tobytes(), k


# ----------------------------------------------------------------------- the rules, one by one
def test_good_ticks_pass_through_unchanged() -> None:
    g = guard(3)
    cells = cells_of(3, R0_ohm=np.array([1e-3, 2e-3, 3e-3]), soc=np.array([0.0, 0.5, 1.0]))
    snapshot = {k: v.copy() for k, v in cells.items()}
    q_in = np.array([0, 1, 2])
    out, q, reinit = g.apply(0.0, cells, q_in, np.zeros(3, dtype=bool))
    for k, v in cells.items():
        np.testing.assert_array_equal(out[k], v)
        np.testing.assert_array_equal(v, snapshot[k])  # inputs untouched
    np.testing.assert_array_equal(q, q_in)
    assert q is not q_in and not reinit.any()
    assert g.counters == {"diverged": 0, "held_on_bound": 0}


def test_bound_hit_holds_the_last_good_values_and_keeps_out_of_bounds() -> None:
    g = guard(2)
    first = cells_of(2, R0_ohm=np.array([1e-3, 2e-3]), tau2_s=np.array([400.0, 500.0]))
    g.apply(0.0, first, q_of(2), np.zeros(2, dtype=bool))
    on_bound = cells_of(2, R0_ohm=0.1, tau2_s=5000.0)  # both parameters at their upper bound
    q_in = np.array([Quality.OUT_OF_BOUNDS, Quality.CONVERGED])
    out, q, reinit = g.apply(1.0, on_bound, q_in, np.array([True, False]))
    assert out["R0_ohm"].tolist() == [1e-3, 0.1] and out["tau2_s"].tolist() == [400.0, 5000.0]
    assert out["C2_F"][0] == first["C2_F"][0]
    assert q.tolist() == [Quality.OUT_OF_BOUNDS, Quality.CONVERGED] and not reinit.any()
    assert g.counters["held_on_bound"] == 1
    # off the bound again: its own values at once
    out, _, _ = g.apply(2.0, cells_of(2, R0_ohm=0.05), q_of(2), np.zeros(2, dtype=bool))
    assert out["R0_ohm"].tolist() == [0.05, 0.05]


def test_bound_before_any_good_tick_publishes_the_models_start_values() -> None:
    model = cell_model(paper_cell(), 2)
    g = PublishGuard.for_model(model, FAST)
    out, _, _ = g.apply(0.0, cells_of(2, R0_ohm=0.1), q_of(2, 0), np.ones(2, dtype=bool))
    for k in ("R0_ohm", "R1_ohm", "R2_ohm", "tau1_s", "tau2_s"):
        lo, hi = model.bound(k)
        np.testing.assert_array_equal(out[k], np.clip(model.start(k), lo, hi), k)
    np.testing.assert_allclose(out["C1_F"], out["tau1_s"] / out["R1_ohm"])
    np.testing.assert_allclose(out["C2_F"], out["tau2_s"] / out["R2_ohm"])
    assert out["ocv_offset_V"].tolist() == [0.0, 0.0]


def test_soc_outside_0_1_is_diverged_once_per_episode_until_converged_again() -> None:
    g = guard(2)
    g.apply(0.0, cells_of(2, soc=0.97, R0_ohm=2e-3), q_of(2), np.zeros(2, dtype=bool))
    bad = cells_of(2, soc=np.array([1.05, 0.98]), R0_ohm=3e-3)
    out, q, reinit = g.apply(1.0, bad, q_of(2), np.zeros(2, dtype=bool))
    assert reinit.tolist() == [True, False] and q.tolist() == [Quality.DIVERGED, 1]
    assert out["soc"].tolist() == [0.97, 0.98]  # the last good SOC, never 1.05
    assert out["R0_ohm"].tolist() == [2e-3, 3e-3]  # the cell's last good parameters
    assert g.cause.tolist() == [CAUSE_SOC, 0] and g.counters["diverged"] == 1
    # still bad next tick: no second re-initialisation
    out, q, reinit = g.apply(2.0, bad, q_of(2), np.zeros(2, dtype=bool))
    assert not reinit.any() and q[0] == Quality.DIVERGED and out["soc"][0] == 0.97
    # re-initialised by the bank: SOC fine, quality CONVERGING -> still diverged, values held
    fresh = cells_of(2, soc=0.9, R0_ohm=1e-3)
    out, q, reinit = g.apply(3.0, fresh, q_of(2, Quality.CONVERGING), np.zeros(2, dtype=bool))
    assert q[0] == Quality.DIVERGED and out["R0_ohm"][0] == 2e-3 and out["soc"][0] == 0.9
    # converged again: the episode is over, its own values published
    out, q, reinit = g.apply(4.0, fresh, q_of(2), np.zeros(2, dtype=bool))
    assert q.tolist() == [1, 1] and out["R0_ohm"][0] == 1e-3 and g.cause[0] == 0
    # a new episode is re-initialised again
    _, _, reinit = g.apply(5.0, cells_of(2, soc=-0.2), q_of(2), np.zeros(2, dtype=bool))
    assert reinit.tolist() == [True, True] and g.counters["diverged"] == 3


def test_soc_within_the_margin_passes() -> None:
    g = guard(2)
    margin = FAST.divergence_soc_margin
    soc = np.array([-margin, 1 + margin])
    out, q, reinit = g.apply(0.0, cells_of(2, soc=soc), q_of(2), np.zeros(2, dtype=bool))
    assert q.tolist() == [1, 1] and not reinit.any()
    assert out["soc"].tolist() == [0.0, 1.0]  # no divergence, but published in [0, 1]


@pytest.mark.parametrize("bad", [np.nan, np.inf, -1e-3, 0.0])
def test_a_parameter_that_is_not_finite_or_not_positive_is_held_and_diverges(bad: float) -> None:
    g = guard(1)
    g.apply(0.0, cells_of(1, R1_ohm=7e-4), q_of(1), NO)
    out, q, reinit = g.apply(1.0, cells_of(1, R1_ohm=bad), q_of(1), NO)
    assert out["R1_ohm"][0] == 7e-4 and out["C1_F"][0] == START["tau1_s"] / 7e-4
    assert q[0] == Quality.DIVERGED and reinit[0] and g.cause[0] == CAUSE_PARAMS


def test_ocv_offset_may_be_negative() -> None:
    g = guard(1)
    out, q, _ = g.apply(0.0, cells_of(1, ocv_offset_V=-0.02), q_of(1), NO)
    assert out["ocv_offset_V"][0] == -0.02 and q[0] == Quality.CONVERGED


def run_error(
    g: PublishGuard,
    errors_V: FloatArray,
    *,
    t0: float = 0.0,
    quality: int = Quality.CONVERGED,
    learn: bool = True,
    until_reinit: bool = False,
) -> tuple[list[int], list[int]]:
    """Feed 1 Hz ticks with these model errors (up to the first re-initialisation if asked);
    the tick indices that re-initialised and the published qualities."""
    reinits, qs = [], []
    for k, e in enumerate(errors_V):
        _, q, reinit = g.apply(
            t0 + k, cells_of(1, v_error_V=e), q_of(1, quality), NO, np.array([learn])
        )
        qs.append(int(q[0]))
        if reinit[0]:
            reinits.append(k)
            if until_reinit:
                break
    return reinits, qs


NOISE = np.random.default_rng(7).standard_normal(30_000) * 2e-3  # a model that tracks: 2 mV RMS


@pytest.mark.parametrize("rms_V", [2e-3, 6e-3])
def test_model_error_far_beyond_its_scale_for_the_hold_time_diverges(rms_V: float) -> None:
    """A model that tracks to 2 mV (6 mV: A123 DYN50's level) is 50 mV off from one tick on."""
    tun = EstimatorTuning()
    g = PublishGuard(1, tun)
    noise = NOISE * rms_V / 2e-3
    reinits, _ = run_error(g, noise[:7200])  # two hours of a good model: the scale learns it
    assert reinits == [] and np.sqrt(g.e2_scale[0]) == pytest.approx(rms_V, rel=0.1)
    reinits, qs = run_error(g, 0.05 + noise[7200:12000], t0=7200.0, until_reinit=True)
    hold = tun.divergence_hold_s
    # in excess once the fast RMS passes 5 sigma (a few tens of s), diverged a hold later
    assert len(reinits) == 1 and hold < reinits[0] < hold + 120
    k = reinits[0]
    assert set(qs[:k]) == {Quality.CONVERGED} and qs[k] == Quality.DIVERGED
    assert g.cause[0] == CAUSE_ERROR
    assert g.excess_s[0] == 0 and g.scale_s[0] == 0  # learnt again after re-initialisation
    # the bank re-initialised the cell: CONVERGING, and the guard keeps it DIVERGED meanwhile
    t = 7200.0 + k + 1
    reinits, qs = run_error(g, 0.05 + noise[12000:13000], t0=t, quality=Quality.CONVERGING)
    assert reinits == [] and set(qs) == {Quality.DIVERGED}
    reinits, qs = run_error(g, noise[13000:13010], t0=t + 1000.0)  # converged again
    assert reinits == [] and set(qs) == {Quality.CONVERGED} and g.cause[0] == 0


def test_an_excess_shorter_than_the_hold_is_not_a_divergence() -> None:
    g = PublishGuard(1, EstimatorTuning())
    run_error(g, NOISE[:7200])
    errors = np.concatenate([0.05 + NOISE[7200:9600], NOISE[9600:11000]])  # 40 min off
    reinits, qs = run_error(g, errors, t0=7200.0)
    assert reinits == [] and set(qs) == {Quality.CONVERGED} and g.excess_s[0] == 0


def test_the_scale_does_not_learn_an_excess() -> None:
    g = PublishGuard(1, EstimatorTuning())
    run_error(g, NOISE[:7200])
    scale = g.e2_scale[0]
    run_error(g, 0.05 + NOISE[7200:8400], t0=7200.0)
    assert g.e2_scale[0] < 1.1 * scale


def test_a_rest_does_not_shrink_the_scale() -> None:
    """Hours of a resting pack (sub-mV errors, POORLY_EXCITED) then driving again at 3x the
    earlier level: not a divergence (the scale learns from excited ticks only)."""
    g = PublishGuard(1, EstimatorTuning())
    run_error(g, NOISE[:7200])
    scale = g.e2_scale[0]
    reinits, _ = run_error(g, NOISE[:10800] / 10, t0=7200.0, quality=Quality.POORLY_EXCITED)
    assert reinits == [] and g.e2_scale[0] == scale
    reinits, qs = run_error(g, 3 * NOISE[10800:18000], t0=18000.0)
    assert reinits == [] and set(qs) == {Quality.CONVERGED}


def test_the_level_is_found_while_the_scale_is_young() -> None:
    """A quiet start (1 mV) then a cell whose model tracks to 15 mV only (a cold 18650): the
    first ``divergence_scale_s`` of data teach the scale whatever the level is."""
    g = PublishGuard(1, EstimatorTuning())
    errors = np.concatenate([NOISE[:600] / 2, 7.5 * NOISE[600:10000]])
    reinits, qs = run_error(g, errors)
    assert reinits == [] and set(qs) == {Quality.CONVERGED}
    assert np.sqrt(g.e2_scale[0]) == pytest.approx(15e-3, rel=0.15)


def test_a_drifting_level_is_followed() -> None:
    """After the scale matured, the error level quadruples over six hours (temperature, a
    harder duty): followed, never a divergence."""
    g = PublishGuard(1, EstimatorTuning())
    run_error(g, NOISE[:7200])
    ramp = np.tile(NOISE, 2)[:21600] * np.linspace(1.0, 4.0, 21600)
    reinits, qs = run_error(g, ramp, t0=7200.0)
    assert reinits == [] and set(qs) == {Quality.CONVERGED}
    assert np.sqrt(g.e2_scale[0]) > 5e-3


def test_ticks_that_may_not_learn_neither_count_nor_clear_an_excess() -> None:
    """In the OCV curve's knees the model error is SOC's: not judged, the excess time paused."""
    tun = EstimatorTuning()
    g = PublishGuard(1, tun)
    run_error(g, NOISE[:7200])
    run_error(g, 0.05 + NOISE[7200:8200], t0=7200.0)  # 1000 s in excess
    paused = g.excess_s[0]
    assert 900 < paused < 1001
    reinits, _ = run_error(g, 0.2 + NOISE[8200:12000], t0=8200.0, learn=False)  # an hour in a knee
    assert reinits == [] and g.excess_s[0] == paused
    reinits, _ = run_error(g, 0.05 + NOISE[12000:15000], t0=12000.0)  # in excess again
    assert reinits == [int(np.ceil(tun.divergence_hold_s - paused)) - 1]


def test_converging_cells_are_not_judged_and_do_not_teach_the_scale() -> None:
    g = PublishGuard(1, EstimatorTuning())
    reinits, qs = run_error(g, 0.3 + NOISE[:5000], quality=Quality.CONVERGING)
    assert reinits == [] and set(qs) == {Quality.CONVERGING} and g.scale_s[0] == 0


def test_missing_errors_change_nothing() -> None:
    g = PublishGuard(1, EstimatorTuning())
    run_error(g, NOISE[:3600])
    before = g.state_dict()
    run_error(g, np.full(600, np.nan), t0=3600.0)
    after = g.state_dict()
    for k in ("e2_fast", "fast_s", "e2_scale", "scale_s", "excess_s"):
        np.testing.assert_array_equal(after[k], before[k], k)


def test_a_gap_counts_as_one_tick_of_data() -> None:
    tun = EstimatorTuning()
    g = PublishGuard(1, tun)
    run_error(g, NOISE[:7200])
    run_error(g, 0.05 + NOISE[7200:8200], t0=7200.0)
    t = g.excess_s[0]
    g.apply(8200.0 + 3600.0, cells_of(1, v_error_V=0.05), q_of(1), NO)  # an hour later
    assert g.excess_s[0] == t + tun.id_period_s


# ----------------------------------------------------------------------- protocol
def test_state_dict_restores_the_guard_exactly() -> None:
    rng = np.random.default_rng(3)
    a = guard(3)
    for k in range(30):
        err = rng.standard_normal(3) * (1e-3 if k < 15 else 0.2)
        a.apply(float(k), cells_of(3, v_error_V=err, R0_ohm=rng.uniform(1e-3, 2e-3, 3)),
                q_of(3), rng.random(3) < 0.3)  # fmt: skip
    b = guard(3)
    b.load_state_dict(a.state_dict())
    b.counters = dict(a.counters)
    for k in range(30, 60):
        cells = cells_of(3, v_error_V=rng.standard_normal(3) * 0.2, soc=rng.uniform(-0.1, 1.1, 3))
        on_bound = rng.random(3) < 0.3
        ra, rb = (g.apply(float(k), cells, q_of(3), on_bound) for g in (a, b))
        for x, y in zip(ra[0].values(), rb[0].values(), strict=True):
            np.testing.assert_array_equal(x, y)
        np.testing.assert_array_equal(ra[1], rb[1])
        np.testing.assert_array_equal(ra[2], rb[2])
    assert a.counters == b.counters


def test_state_dict_of_a_fresh_guard_and_a_wrong_one() -> None:
    st = guard(2).state_dict()
    assert np.isnan(st["t_prev"])
    g = guard(2)
    g.load_state_dict(st)
    assert g.t_prev is None
    with pytest.raises(ValueError, match=r"checkpoint field guard/\w+ has shape \(2,\)"):
        guard(3).load_state_dict(st)
    with pytest.raises(KeyError):
        guard(2).load_state_dict({k: v for k, v in st.items() if k != "episode"})


def test_reset_forgets_statistics_but_keeps_episodes_and_last_good_values() -> None:
    g = guard(2)
    g.apply(0.0, cells_of(2, R0_ohm=2e-3), q_of(2), np.zeros(2, dtype=bool))
    g.apply(1.0, cells_of(2, soc=np.array([2.0, 0.5]), v_error_V=0.01), q_of(2),
            np.zeros(2, dtype=bool))  # fmt: skip
    assert g.fast_s[1] > 0
    g.reset(np.array([False, True]))
    assert g.fast_s[1] == 0 and g.episode.tolist() == [True, False]
    np.testing.assert_array_equal(g.good[HELD.index("R0_ohm")], [2e-3, 1e-3])


def test_tuning_checks_the_time_constants() -> None:
    with pytest.raises(ValueError, match="divergence_fast_s"):
        EstimatorTuning(divergence_fast_s=600.0, divergence_scale_s=600.0)


# ------------------------------------------------------------ a parameter that sits on a bound
WATCH_BOUNDS = {k: BOUNDS[k] for k in ("R0_ohm", "R1_ohm", "R2_ohm", "tau1_s", "tau2_s")}


def bounded_guard(n: int) -> PublishGuard:
    return PublishGuard(n, FAST, {**START, **START_C}, WATCH_BOUNDS)


def test_a_parameter_sitting_on_a_bound_holds_its_branch_only() -> None:
    """tau2 stays on its upper bound for many ticks with no clamp flagged: R2, C2, tau2 publish
    their last good values, R0 and the fast branch keep following the estimator, the quality
    is OUT_OF_BOUNDS, and ``on_bound`` names tau2 (bit 16)."""
    g = bounded_guard(1)
    g.apply(0.0, cells_of(1, tau2_s=800.0, R2_ohm=6e-4), q_of(1), NO)
    hi = BOUNDS["tau2_s"][1]
    for k in range(1, 50):
        r0 = 1e-3 * (1 + 0.01 * k)  # R0 follows temperature meanwhile
        out, q, reinit = g.apply(
            float(k), cells_of(1, tau2_s=hi, R2_ohm=9e-4, R0_ohm=r0, R1_ohm=4e-4), q_of(1), NO
        )
        assert out["tau2_s"][0] == 800.0 and out["R2_ohm"][0] == 6e-4
        assert out["C2_F"][0] == pytest.approx(800.0 / 6e-4, rel=1e-12)
        assert out["R0_ohm"][0] == r0 and out["R1_ohm"][0] == 4e-4
        assert q[0] == Quality.OUT_OF_BOUNDS and out["on_bound"][0] == 16 and not reinit[0]
    # back inside (by more than ON_BOUND_REL): published again, quality back
    out, q, _ = g.apply(60.0, cells_of(1, tau2_s=0.9 * hi), q_of(1), NO)
    assert out["tau2_s"][0] == 0.9 * hi and q[0] == Quality.CONVERGED and out["on_bound"][0] == 0


@pytest.mark.parametrize(
    ("name", "value", "bit"),
    [("R0_ohm", 1e-4, 1), ("R1_ohm", 0.1, 2), ("R2_ohm", 1e-4, 4), ("tau1_s", 1.0, 8),
     ("tau2_s", 100.0, 16)],
)  # fmt: skip
def test_each_watched_parameter_on_either_bound_is_flagged_and_never_published(
    name: str, value: float, bit: int
) -> None:
    g = bounded_guard(2)
    over = {name: np.array([value, START[name]])}
    out, q, _ = g.apply(0.0, cells_of(2, **over), q_of(2), np.zeros(2, dtype=bool))
    assert out["on_bound"].tolist() == [bit, 0]
    assert out[name].tolist() == [START[name], START[name]]
    assert q.tolist() == [Quality.OUT_OF_BOUNDS, Quality.CONVERGED]


def test_a_converging_cell_on_a_bound_keeps_its_quality_but_not_the_bound() -> None:
    """A converging cell on a bound publishes its start values (what it held last), quality
    CONVERGING: the bound value never becomes a "last good" one."""
    g = bounded_guard(1)
    out, q, _ = g.apply(0.0, cells_of(1, tau2_s=100.0), q_of(1, Quality.CONVERGING), NO)
    assert q[0] == Quality.CONVERGING and out["on_bound"][0] == 16
    assert out["tau2_s"][0] == START["tau2_s"]
    out, q, _ = g.apply(1.0, cells_of(1, tau2_s=100.0), q_of(1), NO)
    assert q[0] == Quality.OUT_OF_BOUNDS and out["tau2_s"][0] == START["tau2_s"]


# ----------------------------------------------------------------------- branch order
#: tau bounds that overlap, as the shipped configs' (tau1 0.5-200 s, tau2 20-8000 s)
OVERLAP = {**BOUNDS, "tau1_s": (0.5, 200.0), "tau2_s": (20.0, 8000.0)}


@settings(max_examples=300, deadline=None)
@given(n=st.integers(1, 3), seed=st.integers(0, 2**32 - 1), n_ticks=st.integers(1, 40),
       p_clamp=st.sampled_from([0.0, 0.2]))  # fmt: skip
def test_branch_one_is_the_fast_one_in_every_published_tick(
    n: int, seed: int, n_ticks: int, p_clamp: float
) -> None:
    """Raw pairs with tau2 often on its lower bound (held) while tau1 moves on, now and then
    crossed themselves, give ordered published pairs, after the guard and after the average."""
    rng = np.random.default_rng(seed)
    g = PublishGuard(n, FAST, {**START, **START_C}, {k: OVERLAP[k] for k in WATCHED})
    avg = PublishAverage(n, 1.0)
    for k in range(n_ticks):
        tau2 = np.where(rng.random(n) < 0.5, 20.0, rng.uniform(20.0, 400.0, n))
        tau1 = tau2 * rng.uniform(0.05, 1.2, n)  # now and then crossed (the RLS map's clip)
        cells = cells_of(n, tau1_s=tau1, tau2_s=tau2, R1_ohm=rng.uniform(1e-3, 0.05, n),
                         R2_ohm=rng.uniform(1e-3, 0.05, n))  # fmt: skip
        q = rng.choice([0, 1, 1, 2], n).astype(np.int64)
        out, q_out, _ = g.apply(float(k), cells, q, rng.random(n) < p_clamp)
        assert np.all(out["tau1_s"] < out["tau2_s"]), (out["tau1_s"], out["tau2_s"])
        np.testing.assert_allclose(out["C1_F"], out["tau1_s"] / out["R1_ohm"], rtol=1e-12)
        pub = avg.apply(out, q_out, 1.0)
        assert np.all(pub["tau1_s"] < pub["tau2_s"]), (pub["tau1_s"], pub["tau2_s"])


def test_a_branch_held_on_its_bound_does_not_let_the_other_cross_it() -> None:
    """The CALCE DST case: tau2 good at 21.4 s, then on its 20 s bound (held at 21.4 s) while
    tau1 moves on; once tau1 would pass 21.4 s both RC branches are held, R0 still passes."""
    g = PublishGuard(1, FAST, {**START, **START_C}, {k: OVERLAP[k] for k in WATCHED})
    g.apply(0.0, cells_of(1, tau1_s=15.0, tau2_s=21.4), q_of(1), NO)
    out, q, _ = g.apply(1.0, cells_of(1, tau1_s=18.0, tau2_s=20.0), q_of(1), NO)
    assert (out["tau1_s"][0], out["tau2_s"][0]) == (18.0, 21.4)  # tau2's branch held only
    assert q[0] == Quality.OUT_OF_BOUNDS and out["on_bound"][0] == 16
    out, q, _ = g.apply(2.0, cells_of(1, tau1_s=22.0, tau2_s=20.0, R0_ohm=2e-3), q_of(1), NO)
    assert (out["tau1_s"][0], out["tau2_s"][0], out["R0_ohm"][0]) == (18.0, 21.4, 2e-3)
    assert out["C1_F"][0] == 18.0 / START["R1_ohm"] and q[0] == Quality.OUT_OF_BOUNDS


@pytest.mark.parametrize("kernels", ["numpy", "compiled"])
def test_no_cell_is_out_of_bounds_without_a_parameter_on_a_bound(kernels: str) -> None:
    """Found by a sweep of the daemon: every swarm flagged its cell ``out_of_bounds`` for one
    tick (the fit's unestimated M-scale column, 0, "clamped" to the held 1), and its published
    values were held: 44 flickers in the demo hour, pack health bit 4 flapping every 10 min
    per cell. An out_of_bounds tick must name the parameter on its bound (``on_bound``)."""
    before = jit.MODE
    try:
        jit.select(kernels)
        res = identify_file(DEMO_LOG, IdentifySpec(paper_cell()))
    finally:
        jit.restore(before)
    assert res.counters["swarms"] >= 40
    oob = res.trace.quality == Quality.OUT_OF_BOUNDS
    assert np.all(res.trace["on_bound"][oob] != 0), int(oob.sum())
