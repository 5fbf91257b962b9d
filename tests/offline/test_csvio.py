"""Tester-CSV loader: round trips, column rules and one-line errors with line numbers."""

from __future__ import annotations

import gzip
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from bmsid.errors import UserError
from bmsid.offline.csvio import TesterData, read_ocv_points, read_tester_csv, write_tester_csv


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
        ("t_s,current_A,voltage_V\n0,1,3.3\n1,nan,3.3\n2,1,\n3,1,3.3\n", "line(s) 3"),
        ("t_s,current_A,voltage_V\n0,1,3.3\n1,1,3.3\n2,1,x\n", "'voltage_V' has empty"),
        ("t_s,current_A,voltage_V\n0,1,3.3\n\n2,1,3.3\n", "line(s) 3 are empty"),
        ("t_s,current_A,voltage_V\n0,1,3.3\n2,1,3.3\n2,1,3.3\n", "not increasing at line 4"),
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


def test_nan_lines_are_all_reported(tmp_path: Path) -> None:
    rows = [f"{k},1,{'nan' if k in (3, 7) else '3.3'}" for k in range(10)]
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
