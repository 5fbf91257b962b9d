"""Tester-CSV loader: round trips, column rules and one-line errors with line numbers."""

from __future__ import annotations

import gzip
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from bmsid.errors import UserError
from bmsid.offline import csvio
from bmsid.offline.csvio import (
    MAX_TIME_RESTARTS,
    RESTART_GAP_S,
    ColumnMap,
    TesterData,
    read_ocv_points,
    read_tester_csv,
    write_tester_csv,
)
from bmsid.offline.timetext import DURATION, seconds_from_text


def _write(path: Path, text: str) -> Path:
    path.write_text(text, encoding="utf-8")
    return path


@settings(max_examples=25, deadline=None)
@given(
    n=st.integers(2, 60),
    n_cells=st.integers(1, 4),
    gz=st.booleans(),
    seed=st.integers(0, 2**31),
)
def test_round_trip(
    tmp_path_factory: pytest.TempPathFactory, n: int, n_cells: int, gz: bool, seed: int
) -> None:
    rng = np.random.default_rng(seed)
    t = np.cumsum(rng.uniform(0.1, 2.0, n))
    names = [f"v_cell_{k + 1:02d}" for k in range(n_cells)] if n_cells > 1 else ["voltage_V"]
    data = TesterData(
        t_s=t,
        current_A=rng.normal(0, 20, n),
        cell_voltages_V=rng.uniform(2.5, 4.2, (n, n_cells)),
        cell_names=names,
        temperature_C=rng.uniform(0, 45, n),
        extra={"soc_true": rng.uniform(0, 1, n)},
    )
    path = tmp_path_factory.mktemp("rt") / ("x.csv.gz" if gz else "x.csv")
    write_tester_csv(data, path)
    back = read_tester_csv(path)
    assert back.cell_names == names
    np.testing.assert_allclose(back.t_s, t, rtol=1e-9)
    np.testing.assert_allclose(back.current_A, data.current_A, rtol=1e-9, atol=1e-12)
    np.testing.assert_allclose(back.cell_voltages_V, data.cell_voltages_V, rtol=1e-9)
    assert back.temperature_C is not None
    np.testing.assert_allclose(back.extra["soc_true"], data.extra["soc_true"], rtol=1e-9)
    flipped = read_tester_csv(path, charge_positive=True)
    np.testing.assert_allclose(flipped.current_A, -back.current_A)


def test_cells_ordered_by_number_and_text_columns_ignored(tmp_path: Path) -> None:
    p = _write(
        tmp_path / "a.csv",
        "T_s, Current_A,v_cell_10,v_cell_2,step,voltage_V\n"
        "0,1,3.1,3.2,cc,6.3\n1,1,3.0,3.1,cc,6.1\n",
    )
    d = read_tester_csv(p)
    assert d.cell_names == ["v_cell_2", "v_cell_10"]
    np.testing.assert_allclose(d.cell_voltages_V[:, 0], [3.2, 3.1])
    assert set(d.extra) == {"voltage_V"}
    assert d.temperature_C is None


def test_gzip_is_read(tmp_path: Path) -> None:
    p = tmp_path / "a.csv.gz"
    with gzip.open(p, "wt") as fh:
        fh.write("t_s,current_A,voltage_V\n0,0,3.3\n1,0.5,3.29\n")
    assert read_tester_csv(p).n_samples == 2


@pytest.mark.parametrize(
    ("text", "expected"),
    [
        ("", "empty file"),
        ("t_s,current_A,voltage_V\n", "no data rows"),
        ("t_s,voltage_V\n0,3.3\n", "missing column(s) current_A"),
        ("t_s,current_A\n0,1\n", "missing column(s) voltage_V"),
        ("t_s,current_A,voltage_V\n0,1,3.3\nnan,1,3.3\n,1,3.3\n3,1,3.3\n", "line(s) 3, 4"),
        ("t_s,current_A,voltage_V\n0,1,3.3\n1,1,3.3\n2,1,x\n", "'voltage_V' has empty"),
        ("t_s;current_A;voltage_V\n0,0;1,5;3,3\n", "'0,0' looks like a decimal comma"),
        ("t_s,current_A,voltage_V\n0,1,3.3\n\n2,1,3.3\n", "line(s) 3 are empty"),
        ("t_s,current_A,voltage_V\n0,1,3.3\n2,1,3.3\n1.5,1,3.3\n", "not increasing at line 4"),
        ("t_s,current_A,voltage_V\n0,1,3300\n1,1,3301\n", "millivolts"),
        ("t_s,current_A,voltage_V\n0,5000,3.3\n1,1,3.3\n", "milliamperes"),
    ],
)
def test_bad_files_raise_one_line(tmp_path: Path, text: str, expected: str) -> None:
    p = _write(tmp_path / "bad.csv", text)
    with pytest.raises(UserError) as err:
        read_tester_csv(p)
    msg = str(err.value)
    assert expected in msg
    assert "\n" not in msg


def test_missing_readings_are_nan_and_counted(tmp_path: Path) -> None:
    """A blank or NaN current, voltage or temperature is a missing reading (the engine holds
    the current, leaves the cell out of its tick), counted; the run goes on."""
    rows = [f"{k},{'' if k == 2 else 1},{'nan' if k in (3, 7) else '3.3'},25" for k in range(10)]
    p = _write(tmp_path / "m.csv", "t_s,current_A,voltage_V,temperature_C\n" + "\n".join(rows))
    with pytest.raises(UserError, match="has empty, NaN or non-numeric"):
        read_tester_csv(p)  # strict by default (an OCV fit needs every reading)
    d = read_tester_csv(p, missing_ok=True)
    assert d.n_samples == 10 and d.missing_values == 3
    assert np.isnan(d.current_A[2]) and np.isnan(d.cell_voltages_V[[3, 7], 0]).all()


def test_nan_time_lines_are_all_reported(tmp_path: Path) -> None:
    rows = [f"{'nan' if k in (3, 7) else k},1,3.3" for k in range(10)]
    p = _write(tmp_path / "n.csv", "t_s,current_A,voltage_V\n" + "\n".join(rows) + "\n")
    with pytest.raises(UserError, match=r"line\(s\) 5, 9$"):
        read_tester_csv(p)


def test_missing_file() -> None:
    with pytest.raises(UserError, match="no such file"):
        read_tester_csv("/nonexistent/x.csv")


def test_ocv_points_pairs_and_percent(tmp_path: Path) -> None:
    p = _write(
        tmp_path / "p.csv",
        "SOC_discharge,OCV_discharge_V,SOC_charge,OCV_charge_V\n"
        "10,3.4,,\n50,3.6,40,3.62\n90,4.0,80,3.95\n",
    )
    d, c = read_ocv_points(p)
    assert (d.branch, c.branch) == ("discharge", "charge")
    np.testing.assert_allclose(d.soc, [0.1, 0.5, 0.9])
    np.testing.assert_allclose(c.ocv_V, [3.62, 3.95])


# ----------------------------------------------------------------------------- what testers write
def _rows(path: Path, header: str, rows: list[tuple[float, ...]]) -> Path:
    body = "\n".join(",".join(f"{x:g}" for x in r) for r in rows)
    return _write(path, header + "\n" + body + "\n")


def test_repeated_timestamps_are_merged_keeping_the_last(tmp_path: Path) -> None:
    # A tester logs the end of the old step and the start of the new one at the same time.
    rows = [(0, 0, 3.60, 25, 0.1), (1, 0, 3.60, 25, 0.2), (1, 5, 3.55, 25, 0.3),
            (2, 5, 3.54, 25, 0.4), (3, 5, 3.53, 25, 0.5), (3, 0, 3.57, 25, 0.6),
            (3, -2, 3.58, 25, 0.7), (4, -2, 3.58, 25, 0.8)]  # fmt: skip
    p = _rows(tmp_path / "r.csv", "t_s,current_A,voltage_V,temperature_C,step", rows)
    d = read_tester_csv(p)
    assert d.merged_repeats == 3
    np.testing.assert_array_equal(d.t_s, [0, 1, 2, 3, 4])
    np.testing.assert_array_equal(d.current_A, [0, 5, 5, -2, -2])  # the new step's current
    np.testing.assert_array_equal(d.cell_voltages_V[:, 0], [3.60, 3.55, 3.54, 3.58, 3.58])
    np.testing.assert_array_equal(d.extra["step"], [0.1, 0.3, 0.4, 0.7, 0.8])
    assert d.temperature_C is not None and d.temperature_C.shape == (5,)
    clean = _write(tmp_path / "c.csv", "t_s,current_A,voltage_V\n0,0,3\n1,0,3\n")
    assert read_tester_csv(clean).merged_repeats == 0


@settings(max_examples=40, deadline=None)
@given(
    steps=st.lists(st.sampled_from([0.0, 0.0, 0.5, 1.0, 7.25, 45.0]), min_size=1, max_size=60),
    seed=st.integers(0, 2**31),
)
def test_merging_keeps_every_distinct_time_in_order(
    tmp_path_factory: pytest.TempPathFactory, steps: list[float], seed: int
) -> None:
    t = np.concatenate([[100.0], 100.0 + np.cumsum(steps)])
    rng = np.random.default_rng(seed)
    i = np.round(rng.normal(0, 5, t.size), 3)
    v = np.round(rng.uniform(3.0, 4.0, t.size), 4)
    p = tmp_path_factory.mktemp("m") / "m.csv"
    _rows(p, "t_s,current_A,voltage_V", list(zip(t, i, v, strict=True)))
    d = read_tester_csv(p)
    distinct = np.unique(t)
    np.testing.assert_array_equal(d.t_s, distinct)  # none lost, strictly increasing
    assert d.merged_repeats == t.size - distinct.size
    last = [int(np.flatnonzero(t == x)[-1]) for x in distinct]
    np.testing.assert_array_equal(d.current_A, i[last])
    np.testing.assert_array_equal(d.cell_voltages_V[:, 0], v[last])


def test_gaps_and_rate_changes_load_unchanged(tmp_path: Path) -> None:
    t = np.concatenate([np.arange(0, 10.0), 10 + 0.1 * np.arange(50), 3600 + np.arange(5.0)])
    p = _rows(tmp_path / "g.csv", "t_s,current_A,voltage_V",
              [(x, 1.0, 3.5) for x in t])  # fmt: skip
    d = read_tester_csv(p)
    np.testing.assert_allclose(d.t_s, t)
    assert d.merged_repeats == 0 and d.time_restarts == ()


def test_clock_restart_is_stitched_on_after_a_gap(tmp_path: Path) -> None:
    # Two records appended: the second's clock starts at 0 again (line 2 + 200 = 202).
    t = np.concatenate([np.arange(200.0), np.arange(100.0)])
    p = _rows(tmp_path / "s.csv", "t_s,current_A,voltage_V", [(x, 1.0, 3.5) for x in t])
    d = read_tester_csv(p)
    assert d.time_restarts == (202,)
    assert np.all(np.diff(d.t_s) > 0)
    assert d.t_s[200] - d.t_s[199] == pytest.approx(RESTART_GAP_S)
    np.testing.assert_allclose(d.t_s[201:] - d.t_s[200], np.arange(1.0, 100.0))


def test_per_step_time_column_is_refused(tmp_path: Path) -> None:
    t = np.concatenate([np.arange(100.0)] * (MAX_TIME_RESTARTS + 2))
    p = _rows(tmp_path / "s.csv", "t_s,current_A,voltage_V", [(x, 1.0, 3.5) for x in t])
    with pytest.raises(UserError, match=r"restarts 4 times \(line\(s\) 102, 202, 302, 402\): "
                       r"a per-step time column\?"):  # fmt: skip
        read_tester_csv(p)


def test_step_back_that_is_no_restart_names_its_line(tmp_path: Path) -> None:
    t = [0.0, 100.0, 200.0, 150.0, 300.0]  # back to 150 s, not to the start
    p = _rows(tmp_path / "b.csv", "t_s,current_A,voltage_V", [(x, 1.0, 3.5) for x in t])
    with pytest.raises(UserError, match=r"not increasing at line 5 \(150 s after 200 s\)"):
        read_tester_csv(p)


@pytest.mark.parametrize(
    "header",
    [
        "t_s,current_A,voltage_V,voltage_V",
        "t_s,current_A,v_cell_01,V_CELL_01",
        "t_s,t_s,current_A,voltage_V",
    ],
)
def test_a_column_named_twice_is_refused_not_guessed(tmp_path: Path, header: str) -> None:
    """Two voltage_V columns were read silently, the first used (a sweep)."""
    p = _write(tmp_path / "twice.csv", header + "\n0,1,3.7,3.8\n1,1,3.7,3.8\n")
    with pytest.raises(UserError, match=r"appear more than once in the header: which is meant"):
        read_tester_csv(p)


def test_a_row_of_units_under_the_header_is_skipped(tmp_path: Path) -> None:
    """Testers write units under the names ("s,A,V"): it stopped the run ("line 2" non-numeric,
    no hint). It is skipped; later lines keep their file line numbers in messages."""
    p = _write(tmp_path / "units.csv", "t_s,current_A,voltage_V\ns,A,V\n0,1,3.7\n1,1,3.69\n")
    d = read_tester_csv(p)
    np.testing.assert_array_equal(d.t_s, [0.0, 1.0])
    bad = _write(tmp_path / "bad.csv", "t_s,current_A,voltage_V\n[s],[A],[V]\n0,1,3.7\n1,x,3.69\n")
    with pytest.raises(UserError, match=r"line\(s\) 4"):
        read_tester_csv(bad)
    text = _write(
        tmp_path / "time.csv", "t_s,current_A,voltage_V\n00:00:00,1,3.7\n00:00:01,1,3.6\n"
    )
    assert read_tester_csv(text).t_s.tolist() == [0.0, 1.0]  # a time as text is a row


@pytest.mark.parametrize("gz", [False, True])
def test_a_windows_1252_export_reads_as_its_utf8_twin(tmp_path: Path, gz: bool) -> None:
    """Arbin's Windows software writes "Temperature(°C)" in Windows-1252: the file failed
    with "'utf-8' codec can't decode byte 0xb0" and no way around it. The numbers are ASCII:
    the file reads as its UTF-8 twin, the header's degree sign included."""
    text = (
        "Test_Time(s),Current(A),Voltage(V),Temperature(°C)\n"
        "0,0,3.61,25.0\n1,-0.5,3.66,25.1\n2,1.5,3.55,25.2\n"
    )
    suffix = ".csv.gz" if gz else ".csv"
    raw = {enc: text.encode(enc) for enc in ("cp1252", "utf-8")}
    for enc, data in raw.items():
        (tmp_path / f"{enc}{suffix}").write_bytes(gzip.compress(data) if gz else data)
    cols = {
        "t_s": ColumnMap("Test_Time(s)"), "current_A": ColumnMap("Current(A)"),
        "voltage_V": ColumnMap("Voltage(V)"), "temperature_C": ColumnMap("Temperature(°C)"),
    }  # fmt: skip
    a, b = (read_tester_csv(tmp_path / f"{enc}{suffix}", columns=cols) for enc in raw)
    for x, y in (
        (a.t_s, b.t_s),
        (a.current_A, b.current_A),
        (a.cell_voltages_V, b.cell_voltages_V),
    ):
        np.testing.assert_array_equal(x, y)
    assert a.temperature_C is not None and a.temperature_C.tolist() == [25.0, 25.1, 25.2]


def test_foreign_export_loads_with_a_column_map(tmp_path: Path) -> None:
    # Arbin-like names, time in ms, current in mA, a semicolon export with quoted names.
    p = _write(
        tmp_path / "arbin.csv",
        '"Data_Point";"Test_Time(ms)";"Current(mA)";"Voltage(V)";"t_s"\n'
        "1;0;0;3.61;7\n2;1000;-500;3.66;7\n3;2000;1500;3.55;7\n",
    )
    cols = {
        "t_s": ColumnMap("Test_Time(ms)", 0.001),
        "current_A": ColumnMap("current(ma)", 0.001),  # names match case-insensitively
        "voltage_V": ColumnMap("Voltage(V)"),
    }
    d = read_tester_csv(p, columns=cols, charge_positive=True)
    np.testing.assert_allclose(d.t_s, [0, 1, 2])
    np.testing.assert_allclose(d.current_A, [0, 0.5, -1.5])
    np.testing.assert_allclose(d.cell_voltages_V[:, 0], [3.61, 3.66, 3.55])
    assert set(d.extra) == {"Data_Point", "t_s_unmapped"}  # the file's own t_s gave way
    with pytest.raises(UserError, match=r"no column 'Time' \(mapped to t_s\); found: Data_Point"):
        read_tester_csv(p, columns={"t_s": ColumnMap("Time")})
    with pytest.raises(UserError, match="other names: --columns"):
        read_tester_csv(p)


def _hms(t: float, days: bool) -> str:
    whole, frac = divmod(t, 1.0)
    d, rest = divmod(int(whole), 86400)
    h, rest = divmod(rest, 3600)
    m, s = divmod(rest, 60)
    hours = h if days else h + 24 * d
    head = f"{d}." if days else ""
    return f"{head}{hours:02d}:{m:02d}:{s + frac:06.3f}"


@settings(max_examples=40, deadline=None)
@given(
    steps=st.lists(st.integers(1, 50_000_000), min_size=2, max_size=40),
    days=st.booleans(),
)
def test_cycler_time_text_reads_as_the_seconds_it_writes(steps: list[int], days: bool) -> None:
    """Digatron/Neware ``hh:mm:ss.fff`` (hours past 24 go on) and Maccor ``d.hh:mm:ss``: the
    seconds they write, to the millisecond."""
    t = np.cumsum(np.asarray(steps, dtype=float) / 1000.0)
    read = seconds_from_text([_hms(x, days) for x in t])
    assert read is not None and read[1] == DURATION
    np.testing.assert_allclose(read[0], np.round(t, 3), rtol=0, atol=1e-6)


def test_time_as_text_loads_like_seconds_and_other_text_is_refused(tmp_path: Path) -> None:
    rows = [(0.0, 0.0, 3.61), (1.5, 2.0, 3.55), (3602.25, -1.0, 3.64)]
    hms = _write(
        tmp_path / "hms.csv",
        "t_s,current_A,voltage_V\n" + "".join(f"{_hms(t, False)},{i},{v}\n" for t, i, v in rows),
    )
    iso = _write(
        tmp_path / "iso.csv",
        "t_s,current_A,voltage_V\n2024-03-01 23:59:59,0,3.61\n2024-03-02T00:00:00.5,2,3.55\n"
        "2024-03-02 01:00:01.25,-1,3.64\n",
    )
    for p in (hms, iso):
        d = read_tester_csv(p)
        np.testing.assert_allclose(d.t_s - d.t_s[0], [0.0, 1.5, 3602.25], atol=1e-6)
        np.testing.assert_allclose(d.current_A, [0.0, 2.0, -1.0])
    for bad in ("1:00:00 PM", "2024-13-01 10:00:00"):  # a 12-hour clock, no such month
        p = _write(tmp_path / "bad.csv", f"t_s,current_A,voltage_V\n{bad},0,3.6\n")
        with pytest.raises(UserError, match=r"column 't_s' has empty, NaN or non-numeric"):
            read_tester_csv(p)


#: cells a tester export may hold: numbers in several spellings, quoted or padded, and the
#: exceptions (blank, NaN, text) that must leave the fast whole-piece parse to the per-cell one
_CELL = st.one_of(
    st.floats(-50.0, 50.0, allow_nan=False).map(repr),
    st.floats(2.5, 4.2, allow_nan=False).map(lambda x: f"{x:.6e}"),
    st.floats(2.5, 4.2, allow_nan=False).map(lambda x: f' "{x:.4f}" '),
    st.sampled_from(["", "nan", "NaN", "abc", "1,5", "inf"]),
)


@settings(max_examples=60, deadline=None)
@given(rows=st.lists(st.tuples(_CELL, _CELL, _CELL), min_size=1, max_size=40),
       chunk=st.integers(1, 9), missing_ok=st.booleans(), blank_at=st.integers(-1, 45))  # fmt: skip
def test_the_fast_piece_parse_reads_what_the_per_cell_parse_reads(
    tmp_path_factory: pytest.TempPathFactory, rows: list[tuple[str, str, str]], chunk: int,
    missing_ok: bool, blank_at: int,
) -> None:  # fmt: skip
    """Pieces after the first are parsed whole in C when every field is a finite number
    (``_finite_numbers``): the same arrays, counts and errors as the per-cell parse."""
    lines = [f"{k},{i},{v},{c}" for k, (i, v, c) in enumerate(rows)]
    if 0 <= blank_at < len(lines):
        lines.insert(blank_at, "")
    path = tmp_path_factory.mktemp("fast") / "rec.csv"
    path.write_text("t_s,current_A,voltage_V,note\n" + "\n".join(lines) + "\n")

    def read(fast: bool) -> list[TesterData] | str:
        with pytest.MonkeyPatch.context() as mp:
            if not fast:
                mp.setattr(csvio, "_finite_numbers", lambda *a: None)
            try:
                return list(csvio.iter_tester_csv(path, chunk_rows=chunk, missing_ok=missing_ok))
            except UserError as exc:
                return str(exc)

    slow, quick = read(False), read(True)
    if isinstance(slow, str) or isinstance(quick, str):
        assert slow == quick
        return
    assert len(slow) == len(quick)
    for a, b in zip(slow, quick, strict=True):
        for key, x in a.__dict__.items():
            y = b.__dict__[key]
            if isinstance(x, np.ndarray):
                np.testing.assert_array_equal(x, y)
            elif isinstance(x, dict):
                assert x.keys() == y.keys()
                for name in x:
                    np.testing.assert_array_equal(x[name], y[name])
            else:
                assert x == y, key


def test_a_blank_or_nan_line_in_a_later_piece_is_still_named(tmp_path: Path) -> None:
    """The whole-piece parse skips blank lines and reads NaN: a later piece with either goes
    to the per-cell parse, which refuses (or, with ``missing_ok``, counts) it by line."""
    lines = [f"{k},{0.5 * k},3.7" for k in range(12)]
    path = tmp_path / "blank.csv"
    path.write_text("t_s,current_A,voltage_V\n" + "\n".join([*lines[:7], "", *lines[7:]]) + "\n")
    with pytest.raises(UserError, match=r"line\(s\) 9 are empty"):
        list(csvio.iter_tester_csv(path, chunk_rows=3))
    lines[8] = "8,nan,3.7"
    path.write_text("t_s,current_A,voltage_V\n" + "\n".join(lines) + "\n")
    with pytest.raises(UserError, match=r"line\(s\) 10"):
        list(csvio.iter_tester_csv(path, chunk_rows=3))
    pieces = list(csvio.iter_tester_csv(path, chunk_rows=3, missing_ok=True))
    assert sum(p.missing_values for p in pieces) == 1
