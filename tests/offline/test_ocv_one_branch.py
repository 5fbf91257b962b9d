"""fit-ocv on a low-rate test with one branch only (``ocv_one_branch.py``): a C/20 discharge
alone was refused ("give both branches"); now its voltage, corrected for the polarisation the
rest after it measures, is fitted as rest points (known truth: ``c20_ocv_test`` cut after its
discharge)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from test_ocv_fit_hysteresis import write_ocv_test_csv

from bmsid.cli.main import main
from bmsid.config.cell import save_cell_config
from bmsid.config.engine import ocv_model
from bmsid.offline.ocv_config import OcvFitSpec, fit_ocv_files
from bmsid.offline.ocv_fit import OcvTestPart
from bmsid.offline.ocv_one_branch import one_branch_points
from bmsid.synthetic.ocv_test import LFP_CELL, NMC_CELL, OcvTestCell, SyntheticOcvTest, c20_ocv_test

M_TRUE = 0.015
CELLS = pytest.mark.parametrize("cell", [NMC_CELL, LFP_CELL], ids=["nmc", "lfp"])


def _discharge_only(test: SyntheticOcvTest, path: Path) -> Path:
    return write_ocv_test_csv(test, path, _discharge_end(test))


def _discharge_end(test: SyntheticOcvTest) -> int:
    return next(b for name, _, b in test.segments if name == "rest empty")


@CELLS
def test_a_discharge_alone_gives_the_discharge_ocv(cell: OcvTestCell, tmp_path: Path) -> None:
    """The corrected points lie within 4 mV of the true discharge OCV (mean - M) in each 10 %
    band of SOC 10-90 %, the curve (Eq. 4 and the correction table the whole branch gives)
    within 3.5 mV RMS over 15-85 %, the capacity within 0.5 %; with no hysteresis table M is 0
    and the curve is that branch."""
    test = c20_ocv_test(cell, m_V=M_TRUE)
    src = _discharge_only(test, tmp_path / "dis.csv")
    fit = fit_ocv_files([src], OcvFitSpec("dis"))
    assert fit.info[0].startswith("one branch: a discharge at")
    assert fit.config.capacity_Ah == pytest.approx(cell.capacity_Ah, rel=0.005)
    assert max(fit.config.hysteresis.M_V) == 0.0
    k = _discharge_end(test)
    pts = one_branch_points([OcvTestPart(test.t_s[:k], test.current_A[:k], test.v_V[:k])])
    assert pts is not None and pts.discharge is not None and pts.charge is None
    z, v = pts.discharge
    err_pts = v - (cell.ocv().ocv(z) - M_TRUE)
    # per 10 % band (the 1 mV noise averaged): what is left is the correction's error, the C/20
    # onset step's noise (1 se: 2.8 mV of the 5.5 mV the NMC cell's branch holds)
    for lo in np.arange(0.1, 0.9, 0.1):
        band = (z >= lo) & (z < lo + 0.1)
        assert abs(float(np.mean(err_pts[band]))) < 0.004
    zz = np.linspace(0.15, 0.85, 71)
    err = ocv_model(fit.config).ocv(zz) - (cell.ocv().ocv(zz) - M_TRUE)
    assert np.sqrt(np.mean(err**2)) < 0.0035  # with the correction table beyond Eq. 4
    assert fit.result.correction is not None and fit.result.correction.written


def test_with_a_hysteresis_table_the_mean_is_the_cells(tmp_path: Path) -> None:
    """``--hysteresis-from`` a config holding the cell's M: the curve is the true mean."""
    test = c20_ocv_test(NMC_CELL, m_V=M_TRUE)
    both = fit_ocv_files([write_ocv_test_csv(test, tmp_path / "full.csv")], OcvFitSpec("both"))
    save_cell_config(both.config, tmp_path / "both.toml")
    src = _discharge_only(test, tmp_path / "dis.csv")
    fit = fit_ocv_files([src], OcvFitSpec("dis", hysteresis_from=str(tmp_path / "both.toml")))
    zz = np.linspace(0.15, 0.85, 71)
    err = ocv_model(fit.config).ocv(zz) - NMC_CELL.ocv().ocv(zz)
    assert np.sqrt(np.mean(err**2)) < 0.0045  # 3.5 mV: the branch's, and M's from the table


def test_cli_fits_a_discharge_alone(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    src = _discharge_only(c20_ocv_test(LFP_CELL, m_V=M_TRUE), tmp_path / "dis.csv")
    assert main(["fit-ocv", str(src), "--out", str(tmp_path / "c.toml")]) == 0
    out = capsys.readouterr().out
    assert "one branch: a discharge at" in out and "no hysteresis table: M = 0" in out


def test_a_drive_is_no_ocv_test(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """A DST drive handed to fit-ocv: said to be no OCV test (it read "no charge branch ...
    give both branches", which a discharge alone no longer needs)."""
    from bmsid.offline.csvio import TesterData, write_tester_csv
    from bmsid.synthetic import paper_dst_case

    run = paper_dst_case(3000)
    src = tmp_path / "dst.csv"
    write_tester_csv(
        TesterData(t_s=run.t_s, current_A=run.current_A, cell_voltages_V=run.voltages_V,
                   cell_names=["voltage_V"]),
        src,
    )  # fmt: skip
    assert main(["fit-ocv", str(src), "--out", str(tmp_path / "c.toml")]) == 2
    err = capsys.readouterr().err
    assert "no OCV test: its longest discharge run is" in err and "bmsid identify" in err


def test_a_charge_alone_gives_the_charge_ocv() -> None:
    """The charge half of the same test (from the rest at empty): SOC counted up from empty,
    the corrected points on the charge branch (mean + M) within 4 mV per 10 % band."""
    test = c20_ocv_test(NMC_CELL, m_V=M_TRUE)
    k = next(a for name, a, _ in test.segments if name == "rest empty")
    pts = one_branch_points([OcvTestPart(test.t_s[k:], test.current_A[k:], test.v_V[k:])])
    assert pts is not None and pts.charge is not None and pts.discharge is None
    assert pts.capacity_Ah == pytest.approx(NMC_CELL.capacity_Ah, rel=0.005)
    z, v = pts.charge
    err = v - (NMC_CELL.ocv().ocv(z) + M_TRUE)
    for lo in np.arange(0.1, 0.9, 0.1):
        band = (z >= lo) & (z < lo + 0.1)
        assert abs(float(np.mean(err[band]))) < 0.004
