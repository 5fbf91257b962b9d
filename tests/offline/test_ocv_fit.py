"""OCV fitting: Eq. 4 recovery and bounds, branch extraction, IR-corrected M(z), CLI errors."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from bmsid.cli.main import main
from bmsid.config.cell import PAPER_OCV_MEAN, load_cell_config
from bmsid.model.ocv import eval_ocv
from bmsid.offline.csvio import TesterData, read_tester_csv, write_tester_csv
from bmsid.offline.ocv_fit import (
    OcvTestPart,
    extract_branches,
    fit_eq4,
    fit_ocv_test,
    fit_piecewise_linear,
    fit_rest_points,
    monotonicity_violation_V,
)

REPO = Path(__file__).resolve().parents[2]
PAPER = np.asarray(PAPER_OCV_MEAN)


@settings(max_examples=40, deadline=None)
@given(
    scale=st.lists(st.floats(0.5, 1.5), min_size=6, max_size=6),
    lo=st.floats(0.01, 0.1),
    hi=st.floats(0.9, 0.99),
)
def test_recovers_known_coefficients(scale: list[float], lo: float, hi: float) -> None:
    truth = PAPER * np.asarray(scale)
    z = np.linspace(lo, hi, 300)
    fit = fit_eq4(z, eval_ocv(truth, z))
    np.testing.assert_allclose(fit.coeffs, truth, rtol=1e-6, atol=1e-8)
    assert fit.r2 > 0.999999
    assert fit.rmse_V < 1e-9


def test_confidence_bounds_cover_truth_about_95_percent() -> None:
    rng = np.random.default_rng(7)
    z = np.linspace(0.03, 0.97, 120)
    v_true = eval_ocv(PAPER, z)
    hits = np.zeros(6)
    n_rep = 300
    for _ in range(n_rep):
        fit = fit_eq4(z, v_true + rng.normal(0, 0.005, z.shape))
        hits += (fit.ci_low <= PAPER) & (fit.ci_high >= PAPER)
    coverage = hits / n_rep
    assert 0.92 <= coverage.mean() <= 0.98, coverage
    assert coverage.min() >= 0.88, coverage


def test_piecewise_linear_fit_reproduces_a_pwl_function() -> None:
    knots = [0.02, 0.12, 0.88, 0.98]
    vals = np.array([0.03, 0.02, 0.015, 0.025])
    z = np.linspace(0.02, 0.98, 400)
    k, m = fit_piecewise_linear(z, np.interp(z, knots, vals), knots)
    np.testing.assert_allclose(k, knots)
    np.testing.assert_allclose(m, vals, atol=1e-12)


def _synthetic_ocv_test(
    r_ohm: float, m_V: float, cap_Ah: float = 2.0, rate: float = 1 / 25
) -> TesterData:
    """Rest full, C/25 discharge to empty, rest, C/25 charge to full; 10 s samples.

    Terminal voltage = mean OCV -/+ M (discharge/charge branch) - I R, no other dynamics.
    """
    dt = 10.0
    i_A = rate * cap_Ah
    n_cc = round(cap_Ah * 3600 / i_A / dt)
    rest = np.zeros(60)
    current = np.concatenate([rest, np.full(n_cc, i_A), rest, np.full(n_cc, -i_A), rest])
    q_Ah = np.concatenate([[0.0], np.cumsum(current[:-1] * dt / 3600)])
    z = np.clip(1.0 - q_Ah / cap_Ah, 0.005, 0.995)
    branch = np.where(np.arange(current.size) < 60 + n_cc + 60, -1.0, 1.0)
    v = eval_ocv(PAPER, z) + m_V * branch - current * r_ohm
    t = np.arange(current.size) * dt
    return TesterData(
        t_s=t, current_A=current, cell_voltages_V=v[:, None], cell_names=["voltage_V"]
    )


def test_synthetic_test_recovers_capacity_resistance_and_m() -> None:
    data = _synthetic_ocv_test(r_ohm=0.040, m_V=0.010)
    br = extract_branches([OcvTestPart(data.t_s, data.current_A, data.cell_voltages_V[:, 0])])
    assert br.capacity_Ah == pytest.approx(2.0, rel=2e-3)
    assert br.resistance_ohm == pytest.approx(0.040, rel=1e-6)
    res = fit_ocv_test(br)
    assert res.half_gap_V is not None and res.half_gap_raw_V is not None
    # The raw half-gap overstates M by I R = 80 mA x 40 mOhm = 3.2 mV; the corrected one does not.
    assert np.median(res.half_gap_raw_V) == pytest.approx(0.0132, abs=3e-4)
    np.testing.assert_allclose(res.m_V, 0.010, atol=5e-4)
    grid = np.linspace(res.soc_min, res.soc_max, 200)
    assert np.max(np.abs(eval_ocv(res.mean.coeffs, grid) - eval_ocv(PAPER, grid))) < 2e-3


def test_a123_c30_test_fits_with_r2_above_099(real_data_dir: Path) -> None:
    parts = []
    for k in (1, 2, 3, 4):
        d = read_tester_csv(real_data_dir / "a123_lfp_25C" / f"a123_25C_OCV_S{k}.csv.gz")
        parts.append(OcvTestPart(d.t_s, d.current_A, d.cell_voltages_V[:, 0]))
    br = extract_branches(parts)
    assert br.capacity_Ah == pytest.approx(2.07, abs=0.02)
    assert 0.99 <= br.coulombic_efficiency <= 1.0
    res = fit_ocv_test(br)
    assert res.discharge is not None and res.charge is not None
    for fit in (res.discharge, res.charge, res.mean):
        assert fit.r2 >= 0.99
    # M is positive and below half the raw gap (the IR drop is taken out).
    assert res.half_gap_raw_V is not None
    _, raw_m = fit_piecewise_linear(res.gap_soc, res.half_gap_raw_V, res.m_soc)
    assert np.all(res.m_V > 0)
    assert np.all(res.m_V < raw_m)
    assert monotonicity_violation_V(res.mean.coeffs, res.soc_min, res.soc_max) < 1e-3


def test_one_branch_points_shift_by_the_given_m() -> None:
    z = np.linspace(0.05, 0.95, 12)
    m_soc, m_V = np.array([0.0, 1.0]), np.array([0.01, 0.01])
    res = fit_rest_points((z, eval_ocv(PAPER, z) - 0.01), None, m_table=(m_soc, m_V))
    np.testing.assert_allclose(eval_ocv(res.mean.coeffs, z), eval_ocv(PAPER, z), atol=1e-9)
    assert res.charge is None and res.discharge is not None


@pytest.mark.parametrize(
    "name", ["a123_lfp_25C", *(f"calce_inr18650_20r_{t}C" for t in (0, 25, 45))]
)
def test_committed_cell_configs_load_and_are_monotone(name: str) -> None:
    cfg = load_cell_config(REPO / "configs" / "cells" / f"{name}.toml")
    assert (
        monotonicity_violation_V(np.asarray(cfg.ocv.mean), cfg.ocv.soc_min, cfg.ocv.soc_max) < 1e-3
    )
    assert all(m >= 0 for m in cfg.hysteresis.M_V)
    assert cfg.initial is not None and 0.005 < cfg.initial.R0_ohm < 0.2


def _run_cli(args: list[str], capsys: pytest.CaptureFixture[str]) -> tuple[int, str]:
    code = main(["fit-ocv", *args])
    return code, capsys.readouterr().err


def test_cli_writes_a_config_that_loads(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    src = tmp_path / "ocv.csv.gz"
    write_tester_csv(_synthetic_ocv_test(r_ohm=0.03, m_V=0.01), src)
    out = tmp_path / "cell.json"
    code, err = _run_cli([str(src), "--out", str(out), "--name", "syn"], capsys)
    assert code == 0, err
    cfg = load_cell_config(out)
    assert cfg.name == "syn"
    assert cfg.capacity_Ah == pytest.approx(2.0, rel=2e-3)


@pytest.mark.parametrize(
    ("mutate", "expected"),
    [
        ("discharge_only", "no charge branch"),
        ("nan_rows", "line(s) 5, 8"),
        ("millivolts", "millivolts"),
        ("time_back", "not increasing at line 11"),
    ],
)
def test_cli_bad_files_exit_2_with_one_line(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], mutate: str, expected: str
) -> None:
    data = _synthetic_ocv_test(r_ohm=0.03, m_V=0.01)
    src = tmp_path / "bad.csv"
    write_tester_csv(data, src)
    lines = src.read_text().splitlines()
    if mutate == "discharge_only":
        n_keep = int(np.flatnonzero(data.current_A < 0)[0])
        lines = lines[: n_keep + 1]
    elif mutate == "nan_rows":
        for ln in (5, 8):
            f = lines[ln - 1].split(",")
            f[2] = "nan" if ln == 5 else ""
            lines[ln - 1] = ",".join(f)
    elif mutate == "millivolts":
        lines = [lines[0]] + [
            ",".join([*ln.split(",")[:2], str(1000 * float(ln.split(",")[2]))]) for ln in lines[1:]
        ]
    elif mutate == "time_back":
        lines[10], lines[9] = lines[9], lines[10]
    src.write_text("\n".join(lines) + "\n")
    code, err = _run_cli([str(src), "--out", str(tmp_path / "c.toml")], capsys)
    assert code == 2
    assert expected in err
    assert err.count("\n") == 1 and "Traceback" not in err
