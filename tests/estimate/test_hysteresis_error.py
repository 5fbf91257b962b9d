"""The hysteresis state's error in the observer (estimate/hysteresis_error.py) and a rest's
reading as a measurement of the offset (rest_anchor.draw_update): the covariance algebra, and a
checkpoint from before the error."""

from __future__ import annotations

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st

from bmsid.config.engine import build_bank
from bmsid.estimate.hysteresis_error import fold, predict, target_variance
from bmsid.estimate.rest_anchor import draw_update
from bmsid.samples import SampleBlock
from bmsid.synthetic import paper_dst_case


def _covariance(rng: np.random.Generator, n: int) -> np.ndarray:
    a = rng.normal(size=(n, n))
    return a @ a.T * 1e-2 + np.eye(n) * 1e-4


@settings(max_examples=100, deadline=None)
@given(
    h=st.lists(st.floats(-1.5, 1.5), min_size=1, max_size=8),
    floor=st.floats(0.0, 1.0 / 3.0),
)  # fmt: skip
def test_the_target_variance_is_what_a_bounded_state_allows(h: list[float], floor: float) -> None:
    """(1 - h^2) / 3 per cell, h within [-1, 1]: at most 1/3 (h = 0), 0 where h saturates;
    never below the floor (the play law's)."""
    v = target_variance(np.asarray(h), 0.0)
    hc = np.clip(h, -1.0, 1.0)
    assert np.isclose(v, np.mean((1.0 - hc**2) / 3.0), rtol=1e-12, atol=0.0)
    assert 0.0 <= v <= 1.0 / 3.0
    assert target_variance(np.array([1.0, -1.0]), 0.0) == 0.0
    assert target_variance(np.asarray(h), floor) == max(v, floor)
    assert target_variance(np.array([1.0, -1.0]), floor) == floor


@settings(max_examples=100, deadline=None)
@given(
    n=st.integers(2, 8),
    seed=st.integers(0, 2**32 - 1),
    log_a=st.floats(-30.0, 0.0),
    v_target=st.floats(0.0, 1.0 / 3.0),
)
def test_the_prediction_forgets_what_the_current_moved(
    n: int, seed: int, log_a: float, v_target: float
) -> None:
    """Only the last row and column move: scaled by A, the variance pulled to the target by
    1 - A^2; the covariance stays symmetric positive semi-definite; the decays are zeroed. No
    current (A = 1): nothing changes; a saturating one (A -> 0): the error is the target's,
    uncorrelated with the rest."""
    rng = np.random.default_rng(seed)
    P = _covariance(rng, n)
    before = P.copy()
    decay = np.full(n - 1, log_a)
    predict(P, decay, v_target)
    a = np.exp(log_a)
    np.testing.assert_array_equal(decay, 0.0)
    np.testing.assert_array_equal(P[:-1, :-1], before[:-1, :-1])
    np.testing.assert_allclose(P[-1, :-1], a * before[-1, :-1], rtol=1e-12)
    np.testing.assert_array_equal(P, P.T)
    want = a * a * before[-1, -1] + (1.0 - a * a) * v_target
    assert np.isclose(P[-1, -1], want, rtol=1e-12, atol=0.0)
    assert np.linalg.eigvalsh(P).min() > -1e-12
    Q = before.copy()
    predict(Q, np.zeros(n - 1), v_target)
    np.testing.assert_array_equal(Q, before)


def test_fold_keeps_h_within_its_branches() -> None:
    h = np.array([-0.9, 0.0, 0.95])
    np.testing.assert_allclose(fold(h, 0.1), [-0.8, 0.1, 1.0])
    np.testing.assert_allclose(fold(h, -0.2), [-1.0, -0.2, 0.75])
    np.testing.assert_array_equal(h, [-0.9, 0.0, 0.95])  # a new array


@settings(max_examples=100, deadline=None)
@given(
    n=st.integers(3, 8),
    seed=st.integers(0, 2**32 - 1),
    reading=st.floats(-2.0, 2.0),
    limit=st.floats(0.01, 1.0),
)
def test_a_rests_reading_pulls_the_offset_by_its_weight(
    n: int, seed: int, reading: float, limit: float
) -> None:
    """The offset (index 1 here) moves towards the reading by P_bb / (P_bb + limit^2 / 3), its
    variance shrinks by that factor, the other states move by their correlation with it, and
    the covariance stays symmetric positive semi-definite."""
    rng = np.random.default_rng(seed)
    P = _covariance(rng, n)
    b = float(rng.uniform(-1.0, 1.0))
    dx, P_new = draw_update(P, 1, b, reading, limit)
    w = P[1, 1] / (P[1, 1] + limit**2 / 3.0)
    assert np.isclose(dx[1], w * (reading - b), rtol=1e-9, atol=1e-15)
    assert np.isclose(P_new[1, 1], (1.0 - w) * P[1, 1], rtol=1e-9, atol=1e-18)
    np.testing.assert_allclose(dx, P[:, 1] / P[1, 1] * dx[1], rtol=1e-9, atol=1e-15)
    np.testing.assert_array_equal(P_new, P_new.T)
    assert np.linalg.eigvalsh(P_new).min() > -1e-12
    assert np.all(np.diag(P_new) <= np.diag(P) + 1e-15)


def test_a_checkpoint_from_before_the_hysteresis_error_restores_with_its_prior() -> None:
    """A bank's checkpoint written before the observer carried the hysteresis error has a
    covariance one row and column smaller: restored, its SOC, offset and map block are the
    checkpoint's, the error's row is uncorrelated and its variance what h allows; the bank
    runs on with finite estimates."""
    run = paper_dst_case(600)
    block = SampleBlock.from_arrays(run.t_s, run.current_A, run.voltages_V)
    bank = build_bank(run.cell, 1, "hy-affrls", soc0=0.98)
    bank.update_block(block.slice(0, 400))
    st = bank.state_dict()
    P = np.asarray(st["state"]["observer"]["P"])
    st["state"]["observer"]["P"] = P[:-1, :-1]  # the older format
    del st["state"]["observer"]["lh"]
    restored = build_bank(run.cell, 1, "hy-affrls", soc0=0.98)
    restored.load_state_dict(st)
    Q = restored.state.P  # type: ignore[attr-defined]
    assert Q.shape == P.shape
    np.testing.assert_array_equal(Q[:-1, :-1], P[:-1, :-1])
    np.testing.assert_array_equal(Q[-1, :-1], 0.0)
    assert Q[-1, -1] == target_variance(np.zeros(1), 0.0)  # Plett's law: no floor
    out = restored.update_block(block.slice(400, 600))
    assert np.all(np.isfinite(out["soc"])) and np.all(np.isfinite(out["v_model_V"]))


def test_after_a_long_discharge_the_play_s_hysteresis_error_stays_open() -> None:
    """A one-hour 0.5 C discharge takes h to -1 under either law. Plett's error variance goes
    to (1 - h^2) / 3, 0 there; the play's to its floor (``play_error_variance``, 1/3): the
    branch was reached at a rate that is a guess."""
    run = paper_dst_case(60)
    t = np.arange(0.0, 3600.0)
    i = np.full_like(t, 35.0)
    v = np.full((t.size, 1), 3.6)
    var = {}
    for law in ("plett", "play"):
        cell = run.cell.model_copy(
            update={"hysteresis": run.cell.hysteresis.model_copy(update={"law": law})}
        )
        bank = build_bank(cell, 1, "hy-affrls", soc0=0.9)
        bank.update_block(SampleBlock.from_arrays(t, i, v))
        assert float(bank.state.h[0]) < -0.999  # type: ignore[attr-defined]
        var[law] = float(bank.state.P[-1, -1])  # type: ignore[attr-defined]
    assert var["plett"] < 1e-6
    assert var["play"] > 0.3
