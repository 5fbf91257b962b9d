"""Missing values in the outputs: a cell whose voltage the input gate refuses from its first
sample (``no_data``), refused readings, and what params.csv, params.parquet, metrics.json and the
report lines make of them (empty cells, nulls, a ``no_data`` status, never ``nan``)."""

from __future__ import annotations

import csv
import json
import re
import tempfile
from pathlib import Path

import numpy as np
import pyarrow.parquet as pq
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from test_identify_cli import synthetic_columns, write_csv

from bmsid.cli.main import main
from bmsid.estimate.fields import CELL_FIELDS, FIELD_NAMES
from bmsid.estimate.types import EstimateBlock, Quality
from bmsid.offline.record_cell import cell_from_record
from bmsid.offline.writers import ParamsCsvWriter

NAN_TOKEN = re.compile(r"(?i)\bnan\b|\binf\b")


@pytest.fixture(scope="module")
def dead_cell_csv(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """Three cells, 600 s: cell 2 reads 0 V throughout, cell 3 reads 0 V for the first 30 s."""
    cols = synthetic_columns(600, n_cells=3, seed=5)
    cols["v_cell_02"] = np.zeros(600)
    cols["v_cell_03"] = np.where(np.arange(600) < 30, 0.0, cols["v_cell_03"])
    return write_csv(tmp_path_factory.mktemp("dead") / "pack.csv", cols)


@pytest.mark.parametrize("fmt", ["csv", "parquet"])
def test_a_cell_refused_from_its_first_sample_is_no_data_and_the_rest_identified(
    dead_cell_csv: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str], fmt: str
) -> None:
    out = tmp_path / fmt
    assert main(["identify", str(dead_cell_csv), "--out", str(out), "--format", fmt]) == 0
    printed = capsys.readouterr()
    assert not NAN_TOKEN.search(printed.out), printed.out
    if fmt == "csv":
        text = (out / "params.csv").read_text()
        assert not NAN_TOKEN.search(text)
        rows = list(csv.DictReader(text.splitlines()))
    else:
        rows = [{k: ("" if v is None else str(v)) for k, v in r.items()}
                for r in pq.read_table(out / "params.parquet").to_pylist()]  # fmt: skip
    by_cell: dict[str, list[dict[str, str]]] = {}
    for r in rows:
        by_cell.setdefault(r["cell"], []).append(r)
    keys = [s.out_key for s in CELL_FIELDS]
    # the dead cell: no_data in every row, every field empty (null)
    assert {r["quality"] for r in by_cell["v_cell_02"]} == {str(int(Quality.NO_DATA))}
    assert all(r[k] == "" for r in by_cell["v_cell_02"] for k in keys)
    # the late cell: no_data until its first valid reading, then identified
    late = by_cell["v_cell_03"]
    assert late[0]["quality"] == str(int(Quality.NO_DATA))
    assert late[-1]["quality"] != str(int(Quality.NO_DATA)) and late[-1]["R0_ohm"] != ""
    assert all(r["R0_ohm"] != "" and r["on_bound"] != "" for r in by_cell["v_cell_01"])
    doc = json.loads((out / "metrics.json").read_text())
    dead = doc["cells"]["v_cell_02"]
    assert dead["status"] == "no_data" and dead["n_samples"] == 0
    assert dead["rmse_V"] is None and dead["overall"]["rmse_V"] is None
    assert "status" not in doc["cells"]["v_cell_01"] and doc["cells"]["v_cell_01"]["rmse_V"] > 0
    assert doc["rmse_V"] > 0 and "status" not in doc


def test_a_record_without_any_valid_voltage_reports_no_rmse(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    cols = synthetic_columns(300, seed=6)
    cols["voltage_V"] = np.zeros(300)
    src = write_csv(tmp_path / "zero.csv", cols)
    assert main(["identify", str(src), "--out", str(tmp_path / "o")]) == 0
    printed = capsys.readouterr().out
    assert not NAN_TOKEN.search(printed) and "RMSE 0.00" not in printed and "no RMSE" in printed
    doc = json.loads((tmp_path / "o" / "metrics.json").read_text())
    assert doc["status"] == "no_data" and doc["rmse_V"] is None and doc["n_samples"] == 0


@settings(max_examples=40, deadline=None)
@given(st.data())
def test_csv_writes_an_empty_cell_exactly_where_a_value_is_missing(data: st.DataObject) -> None:
    n_ticks, n_cells = data.draw(st.integers(1, 6)), data.draw(st.integers(1, 3))
    shape = (n_ticks, n_cells)
    value = st.one_of(st.floats(-1e6, 1e6), st.just(np.nan), st.just(np.inf))
    cells = {
        k: np.array(data.draw(st.lists(value, min_size=n_ticks * n_cells,
                                       max_size=n_ticks * n_cells))).reshape(shape)
        for k in FIELD_NAMES
    }  # fmt: skip
    cells["on_bound"] = np.where(np.isfinite(cells["on_bound"]), 2.0, cells["on_bound"])
    block = EstimateBlock(t_s=np.arange(n_ticks, dtype=float), current_A=np.zeros(n_ticks),
                          cells=cells, quality=np.zeros(shape, dtype=np.int64))  # fmt: skip
    names = [f"c{j}" for j in range(n_cells)]
    # a temporary directory per example: hypothesis and function-scoped fixtures do not mix
    with tempfile.TemporaryDirectory() as d:
        path = Path(d) / "params.csv"
        with ParamsCsvWriter(path, names) as w:
            w.append(block)
        rows = list(csv.DictReader(path.read_text().splitlines()))
    assert len(rows) == n_ticks * n_cells
    for k, r in enumerate(rows):
        tick, cell = divmod(k, n_cells)
        for s in CELL_FIELDS:
            x = cells[s.name][tick, cell]
            assert (r[s.out_key] == "") == (not np.isfinite(x)), (s.out_key, x, r[s.out_key])
            if np.isfinite(x):
                assert float(r[s.out_key]) == pytest.approx(float(s.fmt % x))


@pytest.mark.parametrize("dead_V", [0.0, 1.0])
def test_a_dead_tap_tells_no_capacity(dead_V: float) -> None:
    """A cell reading 0 V (or 1 V) from the start is no discharge to the cut-off: the record's
    cell (no config) is what the live cells alone make of it."""
    # twelve live cells: one dead tap pulls the pack's resting mean into the part-charged range
    cols = synthetic_columns(1200, n_cells=12, seed=7)
    t, i = cols["t_s"], cols["current_A"]
    live = np.column_stack([v for k, v in cols.items() if k.startswith("v_cell_")])
    dead = np.column_stack([live, np.full(t.size, dead_V)])
    alone = cell_from_record(t, i, live, 30.0)
    found = cell_from_record(t, i, dead, 30.0)
    assert (found is None) == (alone is None)
    if found is not None and alone is not None:
        assert found.cell.capacity_Ah == alone.cell.capacity_Ah
    assert cell_from_record(t, i, np.full((t.size, 1), dead_V), 30.0) is None
