"""Frames -> samples: assembly rules, bad frames counted, random frames never raise."""

from __future__ import annotations

import math
from pathlib import Path

import can
import numpy as np
import pytest
from can_helpers import frames, synthetic
from hypothesis import given, settings
from hypothesis import strategies as st

from bmsid.canbus.frames_to_samples import FrameToSamples
from bmsid.canbus.logs import csv_to_messages
from bmsid.canbus.mapping import BusMapping, default_mapping, load_mapping
from bmsid.errors import UserError

REPO = Path(__file__).resolve().parents[2]
OWN = default_mapping()
FOREIGN = load_mapping(REPO / "dbc" / "example_bms_mapping.toml")


def run(f2s: FrameToSamples, msgs: list[can.Message]) -> list:
    out = []
    for m in msgs:
        out += f2s.feed(m)
    return out


@pytest.mark.parametrize(("mapping", "tol_A", "tol_V"), [(OWN, 5e-4, 5e-4), (FOREIGN, 0.05, 5e-5)])
def test_one_sample_per_tick_within_resolution(
    mapping: BusMapping, tol_A: float, tol_V: float
) -> None:
    t, i, v = synthetic()
    f2s = FrameToSamples(mapping, 6)
    samples = run(f2s, frames(mapping))
    assert f2s.flush() == []
    assert len(samples) == len(t)
    assert np.allclose([s.t_s for s in samples], t + 1000.0)
    assert np.max(np.abs([s.current_A for s in samples] - i)) <= tol_A * 1.0001
    assert np.max(np.abs(np.array([s.cell_voltages_V for s in samples]) - v)) <= tol_V * 1.0001
    assert [s.counter for s in samples] == [
        k % (65536 if mapping is OWN else 256) for k in range(len(t))
    ]
    assert all(s.flags == frozenset() for s in samples)
    assert f2s.counters["samples"] == len(t) and f2s.counters["decoded"] == f2s.counters["frames"]


def test_foreign_sign_convention_is_corrected() -> None:
    msgs = frames(FOREIGN, n=3)
    _t, i, _ = synthetic(3)
    raw = FOREIGN.database().decode_message(msgs[0].arbitration_id, msgs[0].data)
    assert raw["PackCurrent"] == pytest.approx(-i[0] * 10, abs=0.5)  # dA, positive = charge


def test_lost_frame_gives_half_complete_sample_with_nan() -> None:
    msgs = frames(OWN, n=3, n_cells=8)  # per tick: current, cells 0-3, cells 4-7
    del msgs[1]  # tick 0, cells 0-3 lost
    f2s = FrameToSamples(OWN, 8)
    samples = run(f2s, msgs)
    assert len(samples) == 3
    first = samples[0]
    assert "incomplete" in first.flags
    assert (
        np.isnan(first.cell_voltages_V[:4]).all() and np.isfinite(first.cell_voltages_V[4:]).all()
    )
    assert f2s.counters["incomplete_cycles"] == 1


def test_flush_emits_the_half_cycle() -> None:
    msgs = frames(OWN, n=2, n_cells=8)[:-1]  # last frame of tick 1 missing
    f2s = FrameToSamples(OWN, 8)
    assert len(run(f2s, msgs)) == 1
    tail = f2s.flush()
    assert len(tail) == 1 and "incomplete" in tail[0].flags


def test_repeated_cell_closes_cycle_without_counter() -> None:
    mapping = OWN.model_copy(update={"counter": None})
    msgs = [m for m in frames(mapping, n=3, n_cells=8)]
    del msgs[2]  # tick 0 cells 4-7 lost: tick 1 cells 0-3 repeat cells of the open cycle
    f2s = FrameToSamples(mapping, 8)
    samples = run(f2s, msgs)
    assert len(samples) == 3 and "incomplete" in samples[0].flags


def test_stale_current_drops_the_cycle() -> None:
    msgs = [
        m for m in frames(OWN, n=10, n_cells=4) if m.arbitration_id != 0x100 or m.timestamp < 1002
    ]
    f2s = FrameToSamples(OWN, 4, staleness_s=2.0)
    samples = run(f2s, msgs)
    assert [s.t_s for s in samples] == [1000.0, 1001.0, 1002.0, 1003.0]
    assert f2s.counters["stale_current"] == 6


@settings(max_examples=40, deadline=None)
@given(
    lost=st.lists(st.booleans(), min_size=240, max_size=240),
    n_cells=st.sampled_from([1, 4, 8]),
)
def test_a_lost_current_frame_never_pairs_a_held_current_with_new_voltages(
    lost: list[bool], n_cells: int
) -> None:
    """Frames of ticks 20..79 lost at random (current and voltage alike): every sample still
    carries its own tick's current (a held one is a cycle old: across a step, a sample the
    cell never produced)."""
    _t, i, _ = synthetic(80, n_cells)
    msgs = frames(OWN, n=80, n_cells=n_cells)
    kept = [m for k, m in enumerate(msgs) if m.timestamp < 1020.0 or not lost[k % len(lost)]]
    f2s = FrameToSamples(OWN, n_cells)
    samples = run(f2s, kept) + f2s.flush()
    for smp in samples:
        tick = round(smp.t_s - 1000.0)
        assert smp.current_A == pytest.approx(i[tick], abs=5e-4), f"tick {tick}"
    assert f2s.counters["samples"] + f2s.counters["stale_current"] >= 20


def test_a_current_sent_faster_than_the_voltages_drops_no_cycle() -> None:
    """A BMS sending the current every 10 ms and the cells every 100 ms, with 3 ms of bus
    jitter: the held current is never more than a few ms old, and no cycle is lost (judged on
    the current's own 10 ms period, 40 of the 280 were)."""
    rng = np.random.default_rng(3)
    db = OWN.database()
    cur, cells = (
        db.get_message_by_name("BMSID_PackCurrent"),
        db.get_message_by_name("BMSID_CellVoltages"),
    )
    msgs: list[can.Message] = []
    for k in range(3000):  # 30 s of current frames, each 0-3 ms late
        data = cur.encode({"PackCurrent": 10.0 + k % 7, "SampleCounter": 0})
        t = 1000.0 + 0.01 * k + rng.uniform(0.0, 0.003)
        msgs.append(can.Message(arbitration_id=cur.frame_id, data=data, timestamp=t))
    volts = cells.encode({"CellGroup": 0} | {f"CellVoltage{j}": 3.7 for j in range(4)})
    for m in range(280):  # the cells on their own clock (~10 Hz), also 0-3 ms late
        t = 1000.005 + 0.1037 * m + rng.uniform(0.0, 0.003)
        msgs.append(can.Message(arbitration_id=cells.frame_id, data=volts, timestamp=t))
    msgs.sort(key=lambda msg: msg.timestamp)
    for msg in msgs:
        msg.is_extended_id = False
    f2s = FrameToSamples(OWN.model_copy(update={"counter": None}), 4)
    samples = run(f2s, msgs)
    assert f2s.counters["stale_current"] == 0 and len(samples) == 280


def test_a_current_sent_at_half_the_voltages_rate_is_held() -> None:
    msgs = frames(OWN, n=60, n_cells=4)
    slow = [m for m in msgs if m.arbitration_id != 0x100 or round(m.timestamp) % 2 == 0]
    f2s = FrameToSamples(OWN, 4)
    samples = run(f2s, slow)
    assert len(samples) == 60 and f2s.counters["stale_current"] == 0


def test_stale_open_cycle_is_closed_by_time() -> None:
    msgs = frames(OWN, n=1, n_cells=8)[:-1]
    f2s = FrameToSamples(OWN, 8, staleness_s=1.0)
    run(f2s, msgs)
    assert f2s.expire(1000.5) == []
    out = f2s.expire(1001.5)
    assert len(out) == 1 and "incomplete" in out[0].flags


def test_backwards_timestamp_keeps_time_monotonic() -> None:
    msgs = frames(OWN, n=4, n_cells=4)
    for m in msgs[4:]:
        m.timestamp -= 3600.0  # NTP step back after two ticks
    f2s = FrameToSamples(OWN, 4)
    ts = [s.t_s for s in run(f2s, msgs)]
    assert ts == sorted(ts) and len(ts) == 4
    assert f2s.counters["time_backwards"] == 1


def _bad(**kw: object) -> can.Message:
    base: dict[str, object] = {
        "arbitration_id": 0x110,
        "is_extended_id": False,
        "data": bytes(8),
        "timestamp": 1.0,
    }
    base.update(kw)
    return can.Message(**base)  # type: ignore[arg-type]


@pytest.mark.parametrize(
    ("msg", "counter"),
    [
        (_bad(data=bytes(5)), "wrong_dlc"),
        (_bad(arbitration_id=0x7AB), "unknown_id"),
        (_bad(arbitration_id=0x110, is_extended_id=True), "unknown_id"),
        (_bad(data=bytes([200, 0, 0, 0, 0, 0, 0, 0])), "mux_out_of_range"),  # beyond the DBC
        (_bad(data=bytes([5, 0, 0, 0, 0, 0, 0, 0])), "mux_out_of_range"),  # cells 20-23 of 8
        (_bad(is_error_frame=True), "error_frames"),
        (_bad(is_remote_frame=True, data=None, dlc=8), "remote_frames"),
        (_bad(data=bytes([0, 0xFF, 0xFF, 0xFF, 0xFF, 0xFF, 0xFF, 0xFF])), "not_available"),
    ],
)
def test_bad_frames_are_counted_not_used(msg: can.Message, counter: str) -> None:
    f2s = FrameToSamples(OWN, 8)
    assert f2s.feed(msg) == []
    assert f2s.counters[counter] >= 1
    assert f2s.counters["samples"] == 0


def test_a_cell_not_available_is_nan_and_flagged_not_available() -> None:
    msgs = frames(OWN, n=1, n_cells=4)
    cells = msgs[-1]
    cells.data = bytearray(cells.data)
    cells.data[1] |= 0xFF
    cells.data[2] |= 0x3F  # cell 0 raw = 0x3FFF = not available
    f2s = FrameToSamples(OWN, 4)
    out = run(f2s, msgs)
    assert len(out) == 1 and math.isnan(out[0].cell_voltages_V[0])
    assert out[0].flags == {"not_available"}
    assert (f2s.counters["not_available"], f2s.counters["out_of_range"]) == (1, 0)


@settings(max_examples=60, deadline=None)
@given(
    st.sampled_from([OWN, FOREIGN]),
    st.lists(st.booleans(), min_size=6 * 8, max_size=6 * 8),
    st.lists(st.booleans(), min_size=8, max_size=8),
)
def test_a_not_available_value_is_counted_as_such_for_every_signal_kind(
    mapping: BusMapping, cell_na: list[bool], current_na: list[bool]
) -> None:
    """A sweep: a BMS's SNA (NaN, as make-log sends it) was logged as ``out_of_range``. Every
    cell's and current's is ``not_available`` now; a temperature's stays silent (not fitted)."""
    t, i, v = synthetic(8, 6)
    i[np.array(current_na)] = np.nan
    v[np.array(cell_na).reshape(8, 6)] = np.nan
    temps = np.full(8, 25.0)
    f2s = FrameToSamples(mapping, 6)
    out = run(f2s, list(csv_to_messages(t, i, v, mapping, temperature_C=temps, t0_s=1000.0)))
    out += f2s.flush()
    assert f2s.counters["not_available"] == sum(cell_na) + sum(current_na)
    assert f2s.counters["out_of_range"] == 0
    for s in out:
        assert "out_of_range" not in s.flags
        assert ("not_available" in s.flags) == bool(np.isnan(s.cell_voltages_V).any())


def test_a_temperature_sensor_not_fitted_is_missing_not_an_error() -> None:
    """make-log sends one pack temperature in a group of three: the other two are the DBC's
    not-available value, which is no decode error (20 warnings on a CALCE round trip before)."""
    _t, i, v = synthetic(5, 4)
    temps = np.full(5, 25.0)
    msgs = list(csv_to_messages(np.arange(5.0), i, v, OWN, temperature_C=temps, t0_s=1000.0))
    assert any(m.arbitration_id == 0x120 for m in msgs)
    f2s = FrameToSamples(OWN, 4)
    out = run(f2s, msgs)
    assert len(out) == 5 and f2s.counters["out_of_range"] == 0
    assert out[0].temperatures_C is not None
    assert out[0].temperatures_C[0] == pytest.approx(25.0)
    assert np.isnan(out[0].temperatures_C[1:3]).all()


def test_too_many_cells_for_the_mapping() -> None:
    with pytest.raises(UserError, match="n_cells"):
        FrameToSamples(FOREIGN, 17)


_ids = st.one_of(
    st.sampled_from([0x100, 0x110, 0x120, 0x18FF10F3, 0x18FF20F3, 0x18FF30F3]),
    st.integers(0, 0x1FFFFFFF),
)


@settings(max_examples=300, deadline=None)
@given(
    st.lists(
        st.tuples(
            _ids,
            st.booleans(),
            st.binary(min_size=0, max_size=8),
            st.floats(0, 1e4),
            st.booleans(),
            st.booleans(),
        ),
        max_size=40,
    ),
    st.sampled_from([OWN, FOREIGN]),
)
def test_random_frames_never_raise_and_samples_are_sane(frames_: list, mapping: BusMapping) -> None:
    f2s = FrameToSamples(mapping, 8)
    out = []
    for ident, ext, data, ts, err, rtr in frames_:
        msg = can.Message(
            arbitration_id=ident if ext else ident & 0x7FF,
            is_extended_id=ext,
            data=data,
            timestamp=ts,
            is_error_frame=err,
            is_remote_frame=rtr and not err,
        )
        out += f2s.feed(msg)
    out += f2s.flush()
    c = f2s.counters
    assert c["frames"] == len(frames_) and c["samples"] == len(out)
    for s in out:
        assert s.cell_voltages_V.shape == (8,) and math.isfinite(s.current_A)
        finite = s.cell_voltages_V[np.isfinite(s.cell_voltages_V)]
        assert ((finite >= 0) & (finite <= 17)).all()


@settings(max_examples=60, deadline=None)
@given(st.sampled_from([OWN, FOREIGN]), st.lists(st.integers(0, 2), min_size=1, max_size=200))
def test_a_repeated_frame_is_used_once(mapping: BusMapping, copies: list[int]) -> None:
    """A sweep: a log holding each frame twice (same timestamp) gave twice the samples, each
    repeated cell frame closing its cycle. Exact repeats are dropped and counted now."""
    msgs = frames(mapping, n=10, n_cells=6)
    twice = [m for m, k in zip(msgs, copies + [0] * len(msgs), strict=False) for _ in range(k + 1)]
    f2s, ref = FrameToSamples(mapping, 6), FrameToSamples(mapping, 6)
    got, want = run(f2s, twice) + f2s.flush(), run(ref, msgs) + ref.flush()
    assert [s.t_s for s in got] == [s.t_s for s in want] and len(got) == 10
    np.testing.assert_array_equal(
        [s.cell_voltages_V for s in got], [s.cell_voltages_V for s in want]
    )
    assert f2s.counters["duplicate_frames"] == len(twice) - len(msgs)
    assert f2s.counters["decoded"] == ref.counters["decoded"] == len(msgs)
