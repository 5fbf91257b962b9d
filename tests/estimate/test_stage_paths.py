"""The per-tick shortcuts of the stages give the same bits as the computations they replace."""

from __future__ import annotations

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st

from bmsid.estimate.stage import (
    Forgetting,
    _adapt_arrays,
    _adapt_one,
    _innovation_gain,
    innovation_constants,
)
from bmsid.estimate.ticks import Tick
from bmsid.estimate.tuning import EstimatorTuning

TUNING = EstimatorTuning()
CONSTS = innovation_constants(TUNING)
ANY = st.floats(allow_nan=True, allow_infinity=True, width=64)
#: errors (V) and RMS values around the ones a tick sees, and any float
VOLTS = st.one_of(st.floats(-0.2, 0.2), st.floats(0.0, 0.02), ANY)


def _bits(a: np.ndarray) -> bytes:
    return np.asarray(a, dtype=np.float64).tobytes()


@settings(max_examples=2000, deadline=None)
@given(
    e=VOLTS,
    sig=VOLTS,
    ok=st.booleans(),
    quiet=st.one_of(  # a pack's current: a bool (a float, or a numpy float), or per cell
        st.booleans(), st.booleans().map(np.bool_), st.booleans().map(lambda q: np.array([q]))
    ),
    dt=st.one_of(st.sampled_from([1.0, 0.1, 10.0]), st.floats(1e-9, 1e5)),
    lo=st.floats(0.5, 1.0),
    hi=st.floats(0.5, 1.0),
)
def test_one_cell_innovation_path_equals_the_array_path(
    e: float,
    sig: float,
    ok: bool,
    quiet: bool | np.bool_ | np.ndarray,
    dt: float,
    lo: float,
    hi: float,
) -> None:
    forget = Forgetting(min(lo, hi), max(lo, hi), 1.0)
    g = _innovation_gain(dt, TUNING.innovation_scale_s)
    args = (np.array([e]), np.array([sig]), np.array([ok]), quiet, g, forget.lam_lo, forget.lam_hi,
            CONSTS)  # fmt: skip
    with np.errstate(all="ignore"):
        want = _adapt_arrays(*args)
    got = _adapt_one(*args)
    for w, h in zip(want, got, strict=True):
        assert h.shape == (1,) and h.dtype == np.float64
        assert _bits(h) == _bits(w), (w, h)


def test_one_cell_innovation_path_over_the_errors_of_a_drive() -> None:
    """Errors of up to the clip (6 sigma) in fine steps: every forgetting exponent eps
    (0.00 ... 4.00, where numpy's power and libm's part in the last bit) and the clip's edges."""
    e = np.linspace(-0.07, 0.07, 14001)
    sig = np.full(e.shape, 0.01)
    forget = Forgetting(TUNING.lambda_min, TUNING.lambda_max, 1.0)
    g = _innovation_gain(1.0, TUNING.innovation_scale_s)
    ok = np.ones(e.shape, dtype=bool)
    want = _adapt_arrays(e, sig, ok, False, g, forget.lam_lo, forget.lam_hi, CONSTS)
    for k in range(e.shape[0]):
        got = _adapt_one(e[k : k + 1], sig[k : k + 1], ok[k : k + 1], False, g, forget.lam_lo,
                         forget.lam_hi, CONSTS)  # fmt: skip
        assert b"".join(_bits(h) for h in got) == b"".join(_bits(w[k : k + 1]) for w in want)


@given(dt=st.floats(-10.0, 1e4), period=st.floats(0.01, 100.0))
def test_forgetting_limits_equal_their_formula(dt: float, period: float) -> None:
    tick = Tick(0.0, 0.0, 0.0, dt, period, np.zeros(1), np.ones(1, dtype=bool), (), 0.0,
                np.nan, False, False)  # fmt: skip
    got = Forgetting.for_tick(tick, TUNING)
    dt_f = min(dt, period) if dt > 0 else TUNING.id_period_s
    want = (TUNING.lambda_min**dt_f, TUNING.lambda_max**dt_f, 1.0 / dt_f)
    assert _bits(np.array([got.lam_lo, got.lam_hi, got.per_second_exp])) == _bits(np.array(want))
