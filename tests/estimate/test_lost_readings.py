"""A cell whose readings stop is published ``no_data`` after ``gap_s``, not as a live estimate."""

from __future__ import annotations

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st

from bmsid.config.engine import build_bank
from bmsid.estimate.lost_readings import ReadingWatch
from bmsid.estimate.types import Quality
from bmsid.samples import SampleBlock
from bmsid.synthetic import paper_dst_case

LOST_FROM_S, LOST_TO_S = 1500.0, 2100.0  # cell 1's readings refused for 10 min


def _run(blocks: int) -> tuple[np.ndarray, np.ndarray, dict[str, np.ndarray], dict[str, int]]:
    run = paper_dst_case(3000, r0_spread=np.array([1.0, 1.1]))
    v = run.voltages_V.copy()
    v[(run.t_s >= LOST_FROM_S) & (run.t_s < LOST_TO_S), 1] = np.nan
    bank = build_bank(run.cell, 2, "hy-affrls-lpso", soc0=0.98)
    q, t, cells = [], [], []
    for part in np.array_split(np.arange(run.t_s.size), blocks):
        est = bank.update_block(
            SampleBlock.from_arrays(run.t_s[part], run.current_A[part], v[part])
        )
        q.append(est.quality)
        t.append(est.t_s)
        cells.append(dict(est.cells))
    merged = {k: np.concatenate([c[k] for c in cells]) for k in cells[0]}
    return np.concatenate(t), np.concatenate(q), merged, bank.counters


def test_a_cell_without_readings_is_no_data_after_gap_s_and_resumes() -> None:
    t, q, cells, counters = _run(1)
    gap_s = 30.0  # EstimatorTuning.gap_s
    lost = (t >= LOST_FROM_S + gap_s + 1.0) & (t < LOST_TO_S)
    early = (t >= LOST_FROM_S) & (t < LOST_FROM_S + gap_s - 1.0)
    back = t >= LOST_TO_S + 1.0
    assert np.all(q[lost, 1] == Quality.NO_DATA)
    assert np.all(np.isnan(cells["R0_ohm"][lost, 1])) and np.all(np.isnan(cells["soc"][lost, 1]))
    # before gap_s, after the readings return, and the other cell throughout: live values
    assert not np.any(q[early | back, 1] == Quality.NO_DATA)
    assert np.all(np.isfinite(cells["R0_ohm"][back, 1]))
    assert not np.any(q[:, 0] == Quality.NO_DATA)
    assert counters["readings_lost"] == 1


def test_blocks_and_whole_record_agree() -> None:
    t1, q1, c1, n1 = _run(1)
    t5, q5, c5, n5 = _run(5)
    np.testing.assert_array_equal(t1, t5)
    np.testing.assert_array_equal(q1, q5)
    np.testing.assert_array_equal(c1["soc"], c5["soc"])
    assert n1["readings_lost"] == n5["readings_lost"]


def test_sample_by_sample_update_agrees() -> None:
    run = paper_dst_case(2200)
    v = run.voltages_V.copy()
    v[(run.t_s >= LOST_FROM_S) & (run.t_s < LOST_TO_S)] = np.nan
    bank = build_bank(run.cell, 1, "hy-affrls", soc0=0.98)
    q = [e.quality[0] for k in range(run.t_s.size)
         if (e := bank.update(run.t_s[k], run.current_A[k], v[k])) is not None]  # fmt: skip
    blocked = build_bank(run.cell, 1, "hy-affrls", soc0=0.98).update_block(
        SampleBlock.from_arrays(run.t_s, run.current_A, v)
    )
    np.testing.assert_array_equal(np.array(q), blocked.quality[:, 0])
    assert np.any(blocked.quality[:, 0] == Quality.NO_DATA)


def test_checkpoint_mid_loss_keeps_the_clock() -> None:
    w = ReadingWatch(1, 30.0)
    nan_row = {"v_meas_V": np.array([[np.nan]])}
    w.apply(np.array([0.0]), {"v_meas_V": np.array([[3.7]])}, np.array([[1]]))
    w.apply(np.array([20.0]), nan_row, np.array([[1]]))
    restored = ReadingWatch(1, 30.0)
    restored.load_state_dict(w.state_dict())
    _, q = restored.apply(np.array([31.0]), nan_row, np.array([[1]]))
    assert q[0, 0] == Quality.NO_DATA


@settings(max_examples=60, deadline=None)
@given(
    st.lists(st.tuples(st.floats(0.1, 20.0), st.booleans()), min_size=1, max_size=60),
    st.integers(1, 5),
)
def test_watch_is_the_time_since_the_last_valid_reading(
    steps: list[tuple[float, bool]], n_parts: int
) -> None:
    """Lost exactly where the time since the cell's last valid reading exceeds the hold (never
    before its first), the same however the ticks are split into blocks."""
    t = np.cumsum([s for s, _ in steps])
    ok = np.array([o for _, o in steps])
    v = np.where(ok, 3.7, np.nan)[:, None]
    w = ReadingWatch(1, 30.0)
    q = np.concatenate([
        w.apply(t[p], {"v_meas_V": v[p]}, np.ones((p.size, 1), dtype=np.int64))[1][:, 0]
        for p in np.array_split(np.arange(t.size), n_parts) if p.size
    ])  # fmt: skip
    last = np.nan
    for k in range(t.size):
        last = t[k] if ok[k] else last
        assert (q[k] == Quality.NO_DATA) == bool(t[k] - last > 30.0), k
