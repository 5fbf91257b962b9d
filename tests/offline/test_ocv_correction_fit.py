"""fit-ocv's correction table beyond Eq. 4 (``bmsid.offline.ocv_correction``) on known-truth
C/20 tests whose mean OCV is NOT of Eq. 4's form (Eq. 4 plus a 20 mV staging-like bump,
``bmsid.synthetic.ocv_test``): with the table the mean OCV comes back within 2 mV where Eq. 4
alone misses it by much more, a 15 mV half-gap still comes back within 3 mV and unchanged by
the table, a residual within the test's noise gets no table, and the CLI writes, reports and
opts out of it."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from test_ocv_fit_hysteresis import write_ocv_test_csv

from bmsid.cli.main import main
from bmsid.config.cell import load_cell_config
from bmsid.config.engine import ocv_model
from bmsid.offline.ocv_correction import KNOT_SPACING, correction_knots, fit_correction
from bmsid.offline.ocv_fit import OcvFitResult, OcvTestPart, extract_branches, fit_ocv_test
from bmsid.synthetic.ocv_test import NMC_CELL, SyntheticOcvTest, c20_ocv_test

BUMP_V = 0.020
M_TRUE = 0.015
#: Where the mean is scored: the fitted range less the branch starts (h still turning there).
Z = np.linspace(0.08, 0.88, 801)


def _fit(test: SyntheticOcvTest, correction: bool = True) -> OcvFitResult:
    part = OcvTestPart(test.t_s, test.current_A, test.v_V)
    return fit_ocv_test(extract_branches([part]), correction=correction)


def _error_mV(res: OcvFitResult, test: SyntheticOcvTest) -> np.ndarray:
    truth = test.cell.ocv(test.m_V, test.bump_V).ocv(Z)
    return np.asarray(1e3 * (res.ocv_model().ocv(Z) - truth))


@pytest.mark.parametrize("m_true", [0.0, M_TRUE])
def test_the_table_recovers_a_mean_ocv_eq4_cannot_follow(m_true: float) -> None:
    test = c20_ocv_test(NMC_CELL, m_V=m_true, bump_V=BUMP_V, seed=11)
    with_table, eq4_only = _fit(test), _fit(test, correction=False)
    err, err_eq4 = _error_mV(with_table, test), _error_mV(eq4_only, test)
    assert with_table.correction is not None and with_table.correction.written
    assert np.max(np.abs(err)) < 2.0, np.max(np.abs(err))
    assert np.max(np.abs(err_eq4)) > 8.0  # Eq. 4's six terms miss the bump
    assert np.sqrt(np.mean(err**2)) < 0.3 * np.sqrt(np.mean(err_eq4**2))
    c = with_table.correction
    assert c.rmse_V < 0.3 * c.eq4_rmse_V and c.table_rms_V > c.noise_V
    # The hysteresis comes from the branch gap, before the table: the same with and without.
    np.testing.assert_array_equal(with_table.m_V, eq4_only.m_V)
    np.testing.assert_array_equal(with_table.m_fit_V, eq4_only.m_fit_V)  # type: ignore[arg-type]
    inner = (with_table.m_soc > 0.1) & (with_table.m_soc < 0.9)
    np.testing.assert_allclose(with_table.m_V[inner], m_true, atol=0.003)


def test_a_residual_within_the_noise_gives_no_table() -> None:
    """Branch residuals that are the test's 1 mV noise alone: the binned table is well within
    it, so none is written; a 5 mV bump on top is written."""
    rng = np.random.default_rng(12)
    z = np.linspace(0.05, 0.9, 6000)
    coeffs = np.asarray(NMC_CELL.coeffs)
    noise = [(z, rng.normal(0.0, 1e-3, z.shape[0])) for _ in range(2)]
    res = fit_correction(coeffs, noise, 0.05, 0.9, 1e-3)
    assert not res.written and res.table is None
    assert "within the test's voltage noise (1.00 mV" in res.reason
    bump = 0.005 * np.exp(-0.5 * ((z - 0.5) / 0.03) ** 2)
    res = fit_correction(coeffs, [(zz, r + bump) for zz, r in noise], 0.05, 0.9, 1e-3)
    assert res.written and res.table is not None and "exceeds" in res.reason


def test_knots_are_dense_where_the_data_is() -> None:
    dense = np.linspace(0.02, 0.98, 5000)
    k = correction_knots([dense, dense], 0.02, 0.98)
    assert k[0] == 0.02 and k[-1] == 0.98
    assert np.allclose(np.diff(k)[:-1], KNOT_SPACING)
    sparse = np.concatenate([np.linspace(0.02, 0.5, 4000), np.linspace(0.5, 0.98, 60)])
    k2 = correction_knots([sparse, dense], 0.02, 0.98)
    assert np.max(np.diff(k2[k2 > 0.55])) > 4 * KNOT_SPACING  # 20 samples per interval


def test_cli_writes_reports_and_opts_out_of_the_table(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    test = c20_ocv_test(NMC_CELL, m_V=M_TRUE, bump_V=BUMP_V, seed=13)
    src = write_ocv_test_csv(test, tmp_path / "ocv.csv.gz")
    out = tmp_path / "nmc.toml"
    assert main(["fit-ocv", str(src), "--out", str(out)]) == 0
    text = capsys.readouterr().out
    assert "OCV correction table: Eq. 4 RMSE" in text and "with the correction table" in text
    cfg = load_cell_config(out)
    assert cfg.ocv.correction_soc is not None and cfg.ocv.correction_V is not None
    assert len(cfg.ocv.correction_soc) >= 20
    truth = test.cell.ocv(M_TRUE, BUMP_V).ocv(Z)
    assert np.max(np.abs(ocv_model(cfg).ocv(Z) - truth)) < 0.002
    doc = json.loads((tmp_path / "nmc_report" / "ocv_fit.json").read_text())
    assert doc["ocv_correction"]["written"] and doc["ocv_correction"]["n_knots"] >= 20
    plain = tmp_path / "plain.toml"
    assert main(["fit-ocv", str(src), "--out", str(plain), "--no-ocv-correction"]) == 0
    assert "not fitted (--no-ocv-correction)" in capsys.readouterr().out
    assert load_cell_config(plain).ocv.correction_soc is None
    assert "correction" not in plain.read_text()
