"""The streamed run's tick count from sample times alone equals the tick assembler's."""

from __future__ import annotations

import math

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st

from bmsid.estimate.ticks import TickAssembler
from bmsid.estimate.tuning import EstimatorTuning
from bmsid.offline.tick_count import count_tick_times

TUNING = EstimatorTuning()  # id_period_s 1 s, gap_s 30 s

#: time steps, s: sub-period samples, the period, jitter, repeats, small steps back, gaps,
#: jumps back beyond gap_s, and lost times
STEPS = st.one_of(
    st.sampled_from([0.1, 0.25, 0.5, 1.0, 1.0, 1.0, 2.0, 10.0, 0.0, -0.5, 31.0, 600.0, -100.0,
                     math.nan, math.inf]),
    st.floats(0.01, 3.0),
    st.floats(-35.0, 40.0),
)  # fmt: skip


def _assembler(t: np.ndarray) -> tuple[int, float, float]:
    ticks = TickAssembler(2, TUNING)
    n, first, last = 0, math.nan, math.nan
    for x in t.tolist():
        tick = ticks.push(x, 1.0, np.array([3.7, 3.7]))
        if tick is not None:
            first = tick.t_s if n == 0 else first
            last = tick.t_s
            n += 1
    return n, first, last


@settings(max_examples=300, deadline=None)
@given(st.lists(STEPS, min_size=1, max_size=300), st.floats(-1e6, 1e6), st.data())
def test_the_count_from_times_equals_the_assemblers(steps: list[float], t0: float,
                                                    data: st.DataObject) -> None:  # fmt: skip
    dt = np.array(steps)
    t = t0 + np.cumsum(np.where(np.isfinite(dt), dt, 0.0))
    t[~np.isfinite(dt)] = dt[~np.isfinite(dt)]  # the lost times themselves
    cuts = sorted(data.draw(st.lists(st.integers(0, len(t)), max_size=5)))
    blocks = np.split(t, cuts)  # however the reader cuts the file
    clock = count_tick_times(blocks, TUNING)
    n, first, last = _assembler(t)
    assert (clock.n_ticks, clock.n_samples) == (n, len(t))
    np.testing.assert_array_equal([clock.t_first_s, clock.t_last_s], [first, last])
