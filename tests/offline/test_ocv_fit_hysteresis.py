"""fit-ocv on known-truth C/20 tests (``bmsid.synthetic.ocv_test``): the hysteresis half-gap is
recovered with a CI that holds the truth once the whole DC polarisation (R0 + R1 + R2, measured
on the test's rests and steps) is out of the gap; a test without hysteresis gets none; a real
hysteresis is never written as 0 (issue 11, item 6)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from bmsid.cli.main import main
from bmsid.config.cell import load_cell_config
from bmsid.offline.csvio import TesterData, write_tester_csv
from bmsid.offline.ocv_fit import (
    OcvFitResult,
    OcvTestPart,
    build_cell_config,
    decide_hysteresis,
    extract_branches,
    fit_ocv_test,
    fit_rest_points,
)
from bmsid.synthetic.ocv_test import LFP_CELL, NMC_CELL, OcvTestCell, SyntheticOcvTest, c20_ocv_test

M_TRUE = 0.015
TOL = 0.003
CELLS = pytest.mark.parametrize("cell", [NMC_CELL, LFP_CELL], ids=["nmc", "lfp"])


def write_ocv_test_csv(test: SyntheticOcvTest, path: Path, stop: int | None = None) -> Path:
    """A synthetic OCV test (its samples before ``stop``) as a one-cell tester CSV (what a user
    hands ``fit-ocv``)."""
    k = slice(stop)
    data = TesterData(
        t_s=test.t_s[k], current_A=test.current_A[k], cell_voltages_V=test.v_V[k, None],
        cell_names=["voltage_V"],
    )  # fmt: skip
    write_tester_csv(data, path)
    return path


def _fit(test: SyntheticOcvTest, **kw: float) -> OcvFitResult:
    part = OcvTestPart(test.t_s, test.current_A, test.v_V)
    return fit_ocv_test(extract_branches([part], **kw))


def _measured(res: OcvFitResult) -> np.ndarray:
    """Knots the test measured (not the ends pinned to the rested voltages)."""
    assert res.hysteresis is not None
    return np.array([s != "pinned" for s in res.hysteresis.status])


def _mid(res: OcvFitResult) -> np.ndarray:
    """The Eq. 32 knots inside the branches (12 % and 88 %), away from the branch starts."""
    return (res.m_soc > 0.1) & (res.m_soc < 0.9)


@CELLS
def test_c20_test_recovers_a_15_mV_half_gap(cell: OcvTestCell) -> None:
    test = c20_ocv_test(cell, m_V=M_TRUE)  # gamma 100: h turns within ~3 % SOC
    res = _fit(test)  # at fit-ocv's default gamma (30), as a user runs it
    assert res.test is not None and res.hysteresis is not None
    assert res.m_fit_V is not None and res.m_fit_ci95_V is not None and res.m_ci95_V is not None
    assert res.half_gap_raw_V is not None
    pol = res.test.polarisation
    # The whole DC resistance, from the rests' relaxations, not R0 alone and not the gap.
    assert pol.relaxations and pol.r_total_se_ohm is not None
    assert abs(pol.r_total_ohm - cell.r_total_ohm) <= 3 * pol.r_total_se_ohm
    assert pol.r_total_ohm > 1.5 * cell.R0_ohm
    # The raw gap holds both branches' steady polarisation I (R0 + R1 + R2) on top of 2 M.
    i = cell.capacity_Ah / 20
    assert np.median(res.half_gap_raw_V) == pytest.approx(M_TRUE + i * cell.r_total_ohm, abs=1e-3)
    # Recovered: the pooled mid-SOC M and the mid knots within 3 mV, their CIs hold the truth.
    ev = res.hysteresis
    assert ev.present
    assert ev.pooled_V == pytest.approx(M_TRUE, abs=TOL)
    assert abs(ev.pooled_V - M_TRUE) <= ev.pooled_ci95_V
    mid, meas = _mid(res), _measured(res)
    np.testing.assert_allclose(res.m_fit_V[mid], M_TRUE, atol=TOL)
    np.testing.assert_allclose(res.m_V[mid], M_TRUE, atol=TOL)
    assert np.all(res.m_fit_ci95_V[mid] < 0.005)
    # Every measured knot's CI holds the truth (the branch-start knots carry gamma's effect).
    assert np.all(np.abs(res.m_fit_V[meas] - M_TRUE) <= res.m_fit_ci95_V[meas])
    assert np.all(np.abs(res.m_V[meas] - M_TRUE) <= res.m_ci95_V[meas])
    assert np.all(res.m_V[meas] > 0.01)  # never zeroed


@CELLS
def test_with_the_true_gamma_every_knot_is_within_3_mV(cell: OcvTestCell) -> None:
    test = c20_ocv_test(cell, m_V=M_TRUE, gamma=100.0)
    res = _fit(test, gamma=100.0)
    assert res.m_fit_V is not None and res.m_fit_ci95_V is not None
    meas = _measured(res)
    np.testing.assert_allclose(res.m_fit_V[meas], M_TRUE, atol=TOL)
    np.testing.assert_allclose(res.m_V[meas], M_TRUE, atol=TOL)
    assert np.all(np.abs(res.m_fit_V[meas] - M_TRUE) <= res.m_fit_ci95_V[meas])


@CELLS
def test_no_hysteresis_gives_a_ci_with_zero_and_no_fake_m(cell: OcvTestCell) -> None:
    res = _fit(c20_ocv_test(cell, m_V=0.0, seed=3))
    assert res.hysteresis is not None and res.m_fit_V is not None
    assert res.m_fit_ci95_V is not None and res.m_ci95_V is not None
    ev = res.hysteresis
    assert not ev.present
    assert abs(ev.pooled_V) <= ev.pooled_ci95_V  # the CI includes 0
    assert abs(ev.pooled_V) < 0.002
    meas = _measured(res)
    assert np.all(np.abs(res.m_fit_V[meas]) <= res.m_fit_ci95_V[meas])
    assert np.all(res.m_V <= 0.003)
    # The zeros are said, with the knots' upper bounds as their CI.
    assert any("no hysteresis resolved" in n for n in res.notes)
    assert np.all(res.m_ci95_V[meas] > 0)


def test_pulses_and_a_charge_efficiency_below_one() -> None:
    test = c20_ocv_test(NMC_CELL, m_V=M_TRUE, pulse_C=1.0, eta=0.995, seed=5)
    part = OcvTestPart(test.t_s, test.current_A, test.v_V)
    br = extract_branches([part])
    # z = 1 is the rest before the pulse, not the start of the C/20 branch after it.
    assert br.capacity_Ah == pytest.approx(NMC_CELL.capacity_Ah, rel=3e-3)
    assert br.coulombic_efficiency == pytest.approx(0.995, abs=1e-3)
    res = fit_ocv_test(br)
    assert res.m_fit_V is not None and res.hysteresis is not None
    np.testing.assert_allclose(res.m_fit_V[_mid(res)], M_TRUE, atol=TOL)
    assert res.hysteresis.pooled_V == pytest.approx(M_TRUE, abs=TOL)


@pytest.mark.parametrize("m_true", [M_TRUE, 0.0], ids=["m15", "m0"])
def test_without_long_rests_r0_from_the_steps_and_the_rc_part_in_the_ci(m_true: float) -> None:
    """No rest after the branches to fit (as in Plett's A123 test): R0 from the one-sample
    steps (here the 1C pulses resolve it), the unmeasured RC part assumed and in the CI."""
    test = c20_ocv_test(
        NMC_CELL, m_V=m_true, rest_empty_s=10.0, rest_end_s=10.0, pulse_C=1.0, seed=7
    )
    res = _fit(test)
    assert res.test is not None and res.hysteresis is not None and res.m_fit_V is not None
    assert res.m_fit_ci95_V is not None
    pol = res.test.polarisation
    assert not pol.relaxations and pol.r_total_se_ohm is not None
    assert pol.R0_ohm == pytest.approx(NMC_CELL.R0_ohm, rel=0.2)  # the 1C pulse's step
    assert any("does not measure the RC part" in n for n in res.notes)
    ev, mid = res.hysteresis, _mid(res)
    assert abs(ev.pooled_V - m_true) <= ev.pooled_ci95_V
    np.testing.assert_allclose(res.m_fit_V[mid], m_true, atol=TOL)
    assert np.all(np.abs(res.m_fit_V[mid] - m_true) <= res.m_fit_ci95_V[mid])
    assert ev.present == (m_true > 0)


def test_a_wide_or_negative_knot_is_kept_non_zero_when_hysteresis_is_present() -> None:
    soc = np.array([0.02, 0.12, 0.88, 0.98])
    fit = np.array([0.030, 0.016, -0.004, 0.004])
    ci = np.array([0.040, 0.002, 0.006, 0.010])
    notes: list[str] = []
    m, m_ci, ev = decide_hysteresis(soc, fit, ci, (0.015, 0.002, 0.2, 0.8), notes)
    assert ev.present
    assert ev.status == ("wide", "fit", "conservative", "conservative")
    np.testing.assert_allclose(m, [0.030, 0.016, 0.013, 0.013])
    # The stored CI covers the knot's own interval clipped at 0.
    assert np.all(m - m_ci <= np.maximum(fit - ci, 0.0) + 1e-12)
    assert np.all(m + m_ci >= fit + ci - 1e-12)
    assert any("88 %" in n and "98 %" in n and "not 0" in n for n in notes)
    # Without evidence, the same knots are 0, and said to be.
    notes = []
    m, m_ci, ev = decide_hysteresis(soc, fit, ci, (0.001, 0.002, 0.2, 0.8), notes)
    assert not ev.present
    assert ev.status == ("zero", "fit", "zero", "zero")
    np.testing.assert_allclose(m, [0.0, 0.016, 0.0, 0.0])
    assert any("no hysteresis resolved" in n and "2 %" in n for n in notes)


def test_rest_point_tables_never_zero_a_knot_silently() -> None:
    z = np.linspace(0.05, 0.95, 19)
    v_mean = 3.4 + 0.6 * z
    m_true = np.where(z > 0.8, 0.0, 0.012)  # none left at the top
    rng = np.random.default_rng(2)
    res = fit_rest_points(
        (z, v_mean - m_true + rng.normal(0, 5e-4, z.size)),
        (z, v_mean + m_true + rng.normal(0, 5e-4, z.size)),
    )
    assert res.hysteresis is not None and res.hysteresis.present
    assert res.m_ci95_V is not None
    assert np.all(res.m_V > 0)  # the top knot keeps the pooled lower bound
    assert res.hysteresis.status[-1] == "conservative"
    assert any("not 0" in n for n in res.notes)


def test_config_ci_is_the_stored_values_ci(tmp_path: Path) -> None:
    res = _fit(c20_ocv_test(NMC_CELL, m_V=M_TRUE))
    assert res.test is not None and res.m_ci95_V is not None
    cfg = build_cell_config(
        res, name="syn", capacity_Ah=res.test.capacity_Ah,
        coulombic_efficiency=res.test.coulombic_efficiency,
    )  # fmt: skip
    hy = cfg.hysteresis
    assert hy.M_ci95_V is not None
    np.testing.assert_allclose(hy.M_V, res.m_V)
    np.testing.assert_allclose(hy.M_ci95_V, res.m_ci95_V)
    meas = _measured(res)
    lo = np.asarray(hy.M_V) - np.asarray(hy.M_ci95_V)
    hi = np.asarray(hy.M_V) + np.asarray(hy.M_ci95_V)
    assert np.all((lo[meas] <= M_TRUE) & (hi[meas] >= M_TRUE))


def test_cli_reports_the_half_gap_with_its_ci(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    test = c20_ocv_test(LFP_CELL, m_V=M_TRUE)
    src = write_ocv_test_csv(test, tmp_path / "ocv.csv.gz")
    out = tmp_path / "lfp.toml"
    assert main(["fit-ocv", str(src), "--out", str(out), "--chemistry", "LFP"]) == 0
    text = capsys.readouterr().out
    assert "hysteresis evidence: pooled M" in text and "hysteresis present" in text
    cfg = load_cell_config(out)
    assert cfg.hysteresis.M_ci95_V is not None
    inner = [
        m for s, m in zip(cfg.hysteresis.soc, cfg.hysteresis.M_V, strict=True) if 0.1 < s < 0.9
    ]
    np.testing.assert_allclose(inner, M_TRUE, atol=TOL)
    report = (tmp_path / "lfp_report" / "ocv_fit.txt").read_text()
    assert "hysteresis M(z) fitted" in report
