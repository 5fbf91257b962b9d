"""Streamed identification (issue 12): the same params.csv and metrics.json as the whole-file
path, inputs read in pieces, decimated and Parquet output, plots from a min-max decimation."""

from __future__ import annotations

import csv
import gzip
import itertools
import json
from pathlib import Path
from typing import Any

import numpy as np
import pyarrow.parquet as pq
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from test_identify_cli import synthetic_columns, write_csv

from bmsid.cli.main import main
from bmsid.config.cell import paper_cell
from bmsid.config.engine import ocv_model
from bmsid.estimate.fields import CELL_FIELDS, FIELD_NAMES
from bmsid.estimate.guard import WATCHED
from bmsid.estimate.types import EstimateBlock, Quality
from bmsid.offline import outputs
from bmsid.offline.accumulate import IDENTIFIED, MinMaxDecimator, StreamedMedian
from bmsid.offline.csvio import iter_tester_csv, read_tester_csv
from bmsid.offline.identify import IdentifySpec, RecordScan, identify_source, params_interval
from bmsid.offline.inputs import open_input
from bmsid.offline.outputs import (
    OutputSpec,
    auto_every_s,
    start_fit_warning,
    start_std_warning,
)
from bmsid.offline.scoring import (
    EvalWindow,
    IdentifyResult,
    RunScorer,
    SocReference,
    current_dependence_warnings,
    held_warnings,
    lone_cell_warnings,
    past_empty_warnings,
)
from bmsid.offline.writers import TickDecimator


@pytest.fixture(scope="module")
def pack_csv(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """Two cells, 900 s, with rows logged twice (merged) and a NaN-free clock."""
    cols = synthetic_columns(900, n_cells=2, seed=3)
    keep = np.ones(900, dtype=int)
    keep[[100, 333, 640]] = 2  # repeated time stamps across the reader's pieces
    cols = {k: np.repeat(v, keep) for k, v in cols.items()}
    return write_csv(tmp_path_factory.mktemp("stream") / "pack.csv", cols)


def _close(a: Any, b: Any, path: str = "") -> None:
    """Equal JSON documents, numbers to float rounding."""
    if isinstance(a, dict):
        assert set(a) == set(b), path
        for k in a:
            _close(a[k], b[k], f"{path}.{k}")
    elif isinstance(a, list):
        assert len(a) == len(b), path
        for k, (x, y) in enumerate(zip(a, b, strict=True)):
            _close(x, y, f"{path}[{k}]")
    elif isinstance(a, float) and isinstance(b, float):
        assert a == pytest.approx(b, rel=1e-9, abs=1e-15, nan_ok=True), path
    else:
        assert a == b, path


@pytest.mark.parametrize("window", [
    EvalWindow(),
    EvalWindow(skip_fraction=0.1, soc_lo=0.6, soc_hi=0.9,
               soc_reference=SocReference(0.95, 70.0)),
])  # fmt: skip
def test_streamed_run_writes_what_the_whole_file_run_writes(
    pack_csv: Path, tmp_path: Path, window: EvalWindow
) -> None:
    whole_spec = IdentifySpec(cell=paper_cell(), variant="hy-affrls-lpso", window=window)
    whole = identify_source(open_input(pack_csv), whole_spec, tmp_path / "whole")
    assert whole.trace is not None and whole.trace.n_ticks == 900
    # pieces of 101 rows (a merged repeat straddles one), blocks of 37 samples, no trace kept
    streamed_spec = IdentifySpec(cell=paper_cell(), variant="hy-affrls-lpso", window=window,
                                 block_size=37, keep_trace=False)  # fmt: skip
    streamed = identify_source(
        open_input(pack_csv, chunk_rows=101), streamed_spec, tmp_path / "streamed"
    )
    assert streamed.trace is None and streamed.n_ticks == 900
    a = (tmp_path / "whole" / "params.csv").read_text()
    b = (tmp_path / "streamed" / "params.csv").read_text()
    assert a == b and a.count("\n") == 1 + 2 * 900
    ma = json.loads((tmp_path / "whole" / "metrics.json").read_text())
    mb = json.loads((tmp_path / "streamed" / "metrics.json").read_text())
    for doc in (ma, mb):
        doc.pop("runtime_s")
        for cell in doc["cells"].values():
            cell.pop("runtime_s")
    assert ma["input_checks"]["merged_repeats"] == 3
    assert ma["startup"]["n_ticks"] == 90 and ma["bounds"]["share_of_ticks_on_a_bound"]
    _close(ma, mb)
    for name in ("parameters.png", "voltage_v_cell_01.png", "voltage_v_cell_02.png"):
        assert (tmp_path / "streamed" / name).stat().st_size > 0


def test_reader_pieces_join_to_the_whole_file(pack_csv: Path) -> None:
    whole = read_tester_csv(pack_csv)
    for rows in (1, 2, 101, 334, 10_000):
        pieces = list(iter_tester_csv(pack_csv, chunk_rows=rows))
        np.testing.assert_array_equal(np.concatenate([p.t_s for p in pieces]), whole.t_s)
        np.testing.assert_array_equal(
            np.concatenate([p.cell_voltages_V for p in pieces]), whole.cell_voltages_V
        )
        assert sum(p.merged_repeats for p in pieces) == whole.merged_repeats == 3
        assert max(p.n_samples for p in pieces) <= rows


def _block(t: np.ndarray, n_cells: int = 2) -> EstimateBlock:
    x = np.repeat(t[:, None], n_cells, axis=1) + np.arange(n_cells)[None, :]
    cells = {k: x.copy() for k in FIELD_NAMES}
    cells["on_bound"] = np.zeros_like(x)
    return EstimateBlock(t_s=t, current_A=t.copy(), cells=cells,
                         quality=np.zeros(x.shape, dtype=np.int64))  # fmt: skip


class _Collect:
    def __init__(self) -> None:
        self.blocks: list[EstimateBlock] = []
        self.closed = False

    def append(self, block: EstimateBlock) -> None:
        self.blocks.append(block)

    def close(self) -> None:
        self.closed = True


@pytest.mark.parametrize("cuts", [(), (1,), (9, 10, 11), (5, 37, 38, 80)])
def test_decimation_keeps_the_last_tick_of_each_interval(cuts: tuple[int, ...]) -> None:
    t = 100.0 + np.arange(95) * 1.0  # 95 ticks of 1 s from t = 100 s
    t[50:] += 0.5  # an uneven clock
    full = _block(t)
    for mode in ("last", "mean"):
        sink = _Collect()
        dec = TickDecimator(sink, 10.0, mode)
        edges = (0, *cuts, full.n_ticks)
        for a, b in itertools.pairwise(edges):
            dec.append(full.select(slice(a, b)))
        dec.close()
        out = EstimateBlock.concat(sink.blocks, 2)
        k = np.floor((t - t[0]) / 10.0)
        last = np.flatnonzero(np.append(np.diff(k) != 0, True))
        assert sink.closed
        np.testing.assert_array_equal(out.t_s, t[last])  # the interval's last tick's time
        if mode == "last":
            np.testing.assert_array_equal(out["R0_ohm"], full["R0_ohm"][last])
        else:
            means = [full["R0_ohm"][k == j].mean(axis=0) for j in np.unique(k)]
            np.testing.assert_allclose(out["R0_ohm"], np.array(means), rtol=1e-12)


@settings(max_examples=200, deadline=None)
@given(
    st.lists(st.floats(1e-5, 5.0), min_size=1, max_size=300),
    st.lists(st.integers(0, 299), max_size=3),
)
def test_the_streamed_median_is_the_median_to_its_bin_width(
    values: list[float], cuts: list[int]
) -> None:
    x = np.array(values)
    masked = np.column_stack([x, np.where(np.arange(x.size) % 3 == 0, np.nan, x)])
    median = StreamedMedian(2, rel_width=2e-3)
    edges = sorted({0, *(c for c in cuts if c < x.size), x.size})
    for a, b in itertools.pairwise(edges):  # in blocks, a NaN and a masked-out value skipped
        median.add(masked[a:b], np.ones((b - a, 2), bool) & (np.arange(a, b) != 1)[:, None])
    for c in range(2):
        keep = np.isfinite(masked[:, c]) & (np.arange(x.size) != 1)
        if not keep.any():
            assert np.isnan(median.median()[c])
            continue
        exact = np.sort(masked[keep, c])[(keep.sum() + 1) // 2 - 1]  # the lower median
        assert median.median()[c] == pytest.approx(exact, rel=1.01e-3)


@settings(max_examples=50, deadline=None)
@given(st.integers(0, 2**32 - 1), st.lists(st.integers(1, 199), max_size=3))
def test_the_streamed_held_share_counts_the_window(seed: int, cuts: list[int]) -> None:
    """Where the published values were held, counted block by block (identify's warning,
    metrics.json, compare's table): the window's ticks whose quality is not an identified one,
    and the ``on_bound`` bit most often set there."""
    rng = np.random.default_rng(seed)
    full = _block(np.arange(200.0), n_cells=3)
    full.quality[:] = rng.integers(0, 5, full.quality.shape)
    full.cells["on_bound"][:] = rng.integers(0, 32, full.quality.shape)
    window = EvalWindow(skip_fraction=0.1)
    streamed = RunScorer(full.n_ticks, 3, window)
    for a, b in itertools.pairwise(sorted({0, *cuts, full.n_ticks})):
        streamed.add(full.select(slice(a, b)))
    m = window.mask(full)
    for c in range(3):
        q, bits = full.quality[m[:, c], c], full["on_bound"][m[:, c], c].astype(np.int64)
        shares = [float(np.mean((bits >> j) & 1)) for j in range(len(WATCHED))]
        held, name, share = streamed.acc.held(c)
        assert held == pytest.approx(np.mean(np.isin(q, IDENTIFIED, invert=True)))
        assert (name, share) == (WATCHED[int(np.argmax(shares))], pytest.approx(max(shares)))


def test_a_cell_held_on_most_ticks_is_warned_about() -> None:
    full = _block(np.arange(100.0), n_cells=2)
    full.quality[40:, 0] = int(Quality.OUT_OF_BOUNDS)  # cell a: held on 60 % of the ticks
    full.cells["on_bound"][40:, 0] = 1 << WATCHED.index("tau2_s")
    full.quality[:40, 1] = int(Quality.OUT_OF_BOUNDS)  # cell b: 40 %, under the flag
    result = IdentifyResult("hy-affrls-lpso", full, "given", {}, 0.0, 100, ["a", "b"])
    lines = held_warnings(result, EvalWindow())
    assert lines == [
        "WARNING: a: parameters held (last good values) on 60 % of the scored ticks; tau2_s on "
        "a bound on 60 %: the model does not follow this cell within its bounds there (an OCV "
        "curve that misfits it, or dynamics outside them); params.csv's quality column says where"
    ]


@pytest.mark.parametrize("n_cells", [2, 4])
def test_a_cell_far_worse_than_its_pack_is_warned_about(n_cells: int) -> None:
    """Cells b.. miss the voltage by 1 mV, cell a by 15 mV (every tenth tick 150 mV): a pack of
    4 names a; a pair cannot tell which cell is off and says nothing."""
    full = _block(np.arange(100.0), n_cells=n_cells)
    full.cells["v_meas_V"][:] = 3.0
    full.cells["v_model_V"][:] = 3.001
    full.cells["v_model_V"][::10, 0] = 3.15
    names = [chr(ord("a") + c) for c in range(n_cells)]
    result = IdentifyResult("hy-affrls-lpso", full, "given", {}, 0.0, 100, names)
    lines = lone_cell_warnings(result, EvalWindow())
    if n_cells == 2:
        assert lines == []
        return
    assert len(lines) == 1 and lines[0].startswith(
        "WARNING: a: model error 47.44 mV RMS, 47.4x the pack's median (1.00 mV)"
    ), lines


@pytest.mark.parametrize("peak_error_V", [0.002, 0.05])
def test_a_model_error_that_grows_with_the_current_is_warned_about(peak_error_V: float) -> None:
    """1 Ah cells: 300 ticks at 0.3 A and 300 at 2 A (discharge), 300 at -2 A (charge); the
    model misses the 2 A ticks by ``peak_error_V`` (above the measured voltage when
    discharging, below it when charging: a resistance that falls as the current grows) and
    the others by 1 mV. Warned about from 15 mV between two bands, each band's mean said."""
    full = _block(np.arange(900.0), n_cells=1)
    full.current_A[:] = np.repeat([0.3, 2.0, -2.0], 300)
    full.cells["capacity_Ah"][:] = 1.0
    full.cells["v_meas_V"][:] = 3.0
    err = np.where(np.abs(full.current_A) > 1.0, peak_error_V, 0.001) * np.sign(full.current_A)
    full.cells["v_model_V"][:, 0] = 3.0 - err
    full.quality[:] = int(Quality.CONVERGED)
    result = IdentifyResult("hy-affrls-lpso", full, "given", {}, 0.0, 900, ["a"])
    lines = current_dependence_warnings(result, EvalWindow(skip_fraction=0.0))
    if peak_error_V < 0.015:
        assert lines == []
        return
    assert len(lines) == 1 and lines[0].startswith(
        "WARNING: a: the model error depends on the current (+1 mV at 0.05-0.6C, +50 mV at > 1.3C;"
    ), lines


_STARTS = [(0.0137, "window_fit", True), (0.002, "window_fit", False), (0.0137, "given", False)]


@pytest.mark.parametrize(("rmse_V", "method", "warned"), _STARTS)
def test_a_start_fit_that_misses_its_window_is_warned_about(
    rmse_V: float, method: str, warned: bool
) -> None:
    """The start SOC fitted over the first minutes with a 13.7 mV misfit: the line names the
    cell, the misfit and what it is worth in SOC on the paper cell's curve at its start."""
    full = _block(np.arange(10.0), n_cells=2)
    full.cells["soc"][:] = 0.5
    result = IdentifyResult("hy-affrls-lpso", full, method, {}, 0.0, 10, ["a", "b"],
                            start_fit_rmse_V=np.array([np.nan, rmse_V]))  # fmt: skip
    ocv = ocv_model(paper_cell())
    line = start_fit_warning(result, ocv)
    if not warned:
        assert line is None
        return
    pts = round(100 * rmse_V / float(ocv.docv_dz(np.array([0.5]))[0]))
    assert (
        line is not None
        and line.startswith(
            "WARNING: b: the start SOC fitted over the first 20 min misses them by 13.7 mV RMS"
        )
        and f"about {pts} point" in line
    ), line


_FLAT = [(0.207, "ocv_at_rest", True), (0.011, "ocv_at_rest", False), (0.207, "given", False)]


@pytest.mark.parametrize(("std", "method", "warned"), _FLAT)
def test_a_start_read_off_a_flat_ocv_is_warned_about(std: float, method: str, warned: bool) -> None:
    """The first voltage read on an LFP plateau: a start std of 21 points is said."""
    full = _block(np.arange(10.0), n_cells=2)
    full.cells["soc"][:] = 0.754
    full.cells["soc_std"][:] = 0.01
    full.cells["soc_std"][0, 1] = std
    result = IdentifyResult("hy-affrls-lpso", full, method, {}, 0.0, 10, ["a", "b"])
    line = start_std_warning(result)
    assert (line is not None) == warned
    if warned:
        assert line is not None and line.startswith(
            "WARNING: b: the start SOC read off the first voltage (75.4 %) is uncertain by +-21"
        )


@pytest.mark.parametrize("cuts", [(), (1,), (55, 56, 70)])
def test_a_discharge_past_the_estimated_empty_is_counted_and_warned_about(
    cuts: tuple[int, ...],
) -> None:
    """Cell a's SOC reaches 0 at t = 50 s and the cell goes on giving 2 A for 30 ticks (one step
    of them a 101 s gap) and is charged at SOC 0 after; cell b never reaches 0. Counted the same
    however the run is cut into blocks; the warning names the charge past empty and the RMSE
    there."""
    t = np.arange(100.0)
    t[61:] += 100.0  # a gap: no charge counted over it
    full = _block(t)
    full.current_A[:] = np.where(np.arange(100) < 80, 2.0, -1.0)
    full.cells["soc"][:] = 0.5
    full.cells["soc"][50:, 0] = 0.0
    full.cells["capacity_Ah"][:] = 0.01  # 2 A for 29 s = 0.016 Ah: past 0.5 % of it
    full.cells["v_meas_V"][:] = 3.0
    full.cells["v_model_V"][:] = 3.0
    full.cells["v_model_V"][50:80, 0] = 3.1  # 100 mV off while past empty
    window = EvalWindow()
    scorer = RunScorer(full.n_ticks, 2, window)
    for a, b in itertools.pairwise(sorted({0, *cuts, full.n_ticks})):
        scorer.add(full.select(slice(a, b)))
    past = scorer.acc.past_empty(0)
    assert past is not None and scorer.acc.past_empty(1) is None
    assert past["ticks"] == 30 and past["from_t_s"] == 50.0
    assert past["charge_Ah"] == pytest.approx(2.0 * 29 / 3600)  # the step over the gap: none
    assert past["rmse_V"] == pytest.approx(0.1)
    result = IdentifyResult("hy-affrls-lpso", full, "given", {}, 0.0, 100, ["a", "b"])
    assert past_empty_warnings(result, window) == [
        "WARNING: a: SOC at 0 % on 30 ticks of discharge from t = 50 s, over which the cell "
        "gave 0.0161 Ah more: it holds more than the 0.01 Ah in use (or started fuller than "
        "estimated), and the model cannot follow it past its empty (RMSE 100.0 mV on those "
        "ticks); --capacity-ah or the cell config's capacity_Ah at this temperature"
    ]
    full.cells["capacity_Ah"][:] = 10.0  # 0.016 Ah is 0.16 % of 10 Ah: no warning
    assert past_empty_warnings(IdentifyResult("hy-affrls-lpso", full, "given", {}, 0.0, 100,
                                              ["a", "b"]), window) == []  # fmt: skip


def test_min_max_decimation_keeps_spikes_and_short_records_whole() -> None:
    n = 10_000
    t = np.arange(n, dtype=float)
    y = np.sin(t / 500.0)
    y[4321] = 50.0  # a one-tick spike
    y[777] = np.nan
    dec = MinMaxDecimator.for_ticks(n, 1, 1, n_bins=100)
    for a in range(0, n, 333):
        dec.add(t[a : a + 333], y[a : a + 333, None, None])
    ts, ys = dec.series(0, 0)
    assert ys.size <= 200 and 50.0 in ys and ts[np.argmax(ys)] == 4321.0
    assert np.all(np.diff(ts) > 0) and np.isfinite(ys).all()
    small = MinMaxDecimator.for_ticks(50, 1, 1, n_bins=100)
    small.add(t[:50], y[:50, None, None])
    ts, ys = small.series(0, 0)
    np.testing.assert_array_equal(ts, t[:50])
    np.testing.assert_array_equal(ys, y[:50])


def test_parquet_holds_the_csv_columns_and_values_every_interval(
    pack_csv: Path, tmp_path: Path
) -> None:
    a, b = tmp_path / "csv", tmp_path / "pq"
    assert main(["identify", str(pack_csv), "--out", str(a), "--algorithm", "hy-affrls"]) == 0
    assert main(["identify", str(pack_csv), "--out", str(b), "--algorithm", "hy-affrls",
                 "--format", "parquet", "--every", "10"]) == 0  # fmt: skip
    with (a / "params.csv").open() as fh:
        rows = list(csv.DictReader(fh))
    table = pq.read_table(b / "params.parquet")
    assert table.column_names == list(rows[0])
    assert not (b / "params.csv").exists()
    got = table.to_pylist()
    t_all = np.unique([float(r["t_s"]) for r in rows])
    k = np.floor((t_all - t_all[0]) / 10.0)
    last = t_all[np.append(np.diff(k) != 0, True)]
    assert len(got) == 2 * last.size
    np.testing.assert_allclose(sorted({r["t_s"] for r in got}), last, rtol=0, atol=1e-6)
    fmt = {s.out_key: s.fmt for s in CELL_FIELDS} | {"t_s": "%.6f", "quality": "%d"}
    by_key = {(r["t_s"], r["cell"]): r for r in rows}
    for row in got:
        ref = by_key[(f"{row['t_s']:.6f}", row["cell"])]
        for name, value in row.items():
            if name == "cell":
                assert value == ref[name]
            else:  # the CSV's text is the Parquet value in the field's CSV format
                assert fmt[name] % value == ref[name], name
    doc = json.loads((b / "metrics.json").read_text())
    assert doc["output"]["every_s"] == 10.0 and not doc["output"]["default_decimation"]
    assert doc["output"]["params_file"] == "params.parquet"


def test_an_interval_shorter_than_the_tick_is_every_tick(
    pack_csv: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """``--every 0.5`` on 1 s ticks was accepted and metrics.json said "one per 0.5 s" while
    params.csv had one row per tick: it is every tick, and says so."""
    out = tmp_path / "o"
    assert main(["identify", str(pack_csv), "--out", str(out), "--algorithm", "hy-affrls",
                 "--every", "0.5"]) == 0  # fmt: skip
    said = capsys.readouterr().out
    assert "--every 0.5 s is no longer than the identification tick (1 s)" in said
    doc = json.loads((out / "metrics.json").read_text())
    assert doc["output"]["every_s"] is None and doc["output"]["rows"] == "every tick and cell"
    assert params_interval(OutputSpec(every_s=0.5), None, 1.0) == (None, False)
    assert params_interval(OutputSpec(every_s=2.0), None, 1.0) == (2.0, False)


def test_a_long_record_gets_an_announced_decimation(
    pack_csv: Path,
    tmp_path: Path,
    monkeypatch: pytest.MonkeyPatch,
    capsys: pytest.CaptureFixture[str],
) -> None:
    assert auto_every_s(86_400, 86_399.0) is None
    assert auto_every_s(259_200, 259_199.0) == 5.0  # 3 days of 1 s ticks
    assert auto_every_s(2_592_000, 2_591_999.0) == 30.0  # 30 days
    scan = RecordScan(n_samples=10**6, n_ticks=10**6, t_first_s=0.0, t_last_s=999_999.0)
    assert params_interval(OutputSpec(), scan) == (20.0, True)
    assert params_interval(OutputSpec(every_s=0.0), scan) == (None, False)
    assert params_interval(OutputSpec(every_s=3.0), scan) == (3.0, False)
    monkeypatch.setattr(outputs, "AUTO_EVERY_MAX_ROWS", 300)  # the 900-tick record is "long"
    out = tmp_path / "auto"
    assert main(["identify", str(pack_csv), "--out", str(out), "--algorithm", "hy-affrls"]) == 0
    said = capsys.readouterr().out
    assert "900 ticks: params.csv gets one row per 5 s and cell (last value" in said
    doc = json.loads((out / "metrics.json").read_text())
    assert doc["output"]["default_decimation"] and doc["output"]["every_s"] == 5.0
    assert doc["n_ticks"] == 900  # the metrics still score every tick
    lines = (out / "params.csv").read_text().splitlines()
    assert len(lines) == 1 + 2 * 180


def test_bad_rows_anywhere_stop_the_run_before_it_starts(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    cols = synthetic_columns(300)
    p = write_csv(tmp_path / "nan.csv", cols)
    lines = p.read_text().splitlines()
    # text that is no number (a blank or NaN reading is a missing one, not a bad row)
    lines[250] = lines[250].replace(lines[250].split(",")[2], "x", 1)
    p.write_text("\n".join(lines) + "\n")
    assert main(["identify", str(p), "--out", str(tmp_path / "o")]) == 2
    err = capsys.readouterr().err
    assert "line(s) 251" in err and "Traceback" not in err
    assert not (tmp_path / "o" / "params.csv").exists()
    gz = write_csv(tmp_path / "cut.csv.gz", cols)
    gz.write_bytes(gz.read_bytes()[:-200])  # a truncated download
    assert main(["identify", str(gz), "--out", str(tmp_path / "g")]) == 2
    err = capsys.readouterr().err
    assert "cut.csv.gz: cannot read" in err and "Traceback" not in err
    with gzip.open(gz, "rt") as fh, pytest.raises(EOFError):
        fh.read()
