"""OCV fitting: Eq. 4 recovery and bounds, branch extraction, polarisation-corrected M(z), CLI
errors (the hysteresis against known-truth tests: ``test_ocv_fit_hysteresis.py``)."""

from __future__ import annotations

import gzip
import re
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from bmsid.cli.main import main
from bmsid.config.cell import PAPER_OCV_MEAN, CellConfig, OcvCurve, load_cell_config
from bmsid.config.engine import ocv_model
from bmsid.model.ocv import OcvModel, eval_ocv
from bmsid.model.simulator import simulate
from bmsid.offline.csvio import TesterData, read_tester_csv, write_tester_csv
from bmsid.offline.ocv_config import partial_range_warning
from bmsid.offline.ocv_fit import (
    OcvTestPart,
    build_cell_config,
    c_rate_text,
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
    t = np.arange(current.size, dtype=np.float64) * dt
    return TesterData(
        t_s=t, current_A=current, cell_voltages_V=v[:, None], cell_names=["voltage_V"]
    )


def test_synthetic_test_recovers_capacity_resistance_and_m() -> None:
    data = _synthetic_ocv_test(r_ohm=0.040, m_V=0.010)
    part = OcvTestPart(data.t_s, data.current_A, data.cell_voltages_V[:, 0])
    br = extract_branches([part], gamma=1e4)  # its branches switch at once: a very fast h
    assert br.capacity_Ah == pytest.approx(2.0, rel=2e-3)
    # Pure IR drop: the rests relax by nothing, the jump is R0.
    assert br.polarisation.r_total_ohm == pytest.approx(0.040, rel=0.02)
    res = fit_ocv_test(br)
    assert res.half_gap_V is not None and res.half_gap_raw_V is not None
    # The raw half-gap overstates M by I R = 80 mA x 40 mOhm = 3.2 mV; the corrected one does not.
    assert np.median(res.half_gap_raw_V) == pytest.approx(0.0132, abs=3e-4)
    inner = (res.m_soc > 0.0) & (res.m_soc < 1.0)
    np.testing.assert_allclose(res.m_V[inner], 0.010, atol=5e-4)
    grid = np.linspace(res.soc_min, res.soc_max, 200)
    assert np.max(np.abs(eval_ocv(res.mean.coeffs, grid) - eval_ocv(PAPER, grid))) < 2e-3


def _c20_test(
    ocv: OcvModel,
    *,
    cap: float = 5.0,
    m_V: float = 0.015,
    r: tuple[float, float, float, float, float] = (0.04, 0.02, 30.0, 0.03, 600.0),
    charge_gain: float = 1.0,
    charge_to: float = 1.0,
    seed: int = 1,
) -> OcvTestPart:
    """C/20 test from the full model (2RC + one-state hysteresis, gamma 30), 10 s samples, 1 mV
    noise: 1 h rest full (after a charge: h = +1), discharge to empty, 2 h rest, charge to
    ``charge_to``, 1 h rest. The tester reads charge current times ``charge_gain``."""
    dt, i = 10.0, cap / 20.0
    n = round(cap * 3600 / i / dt)
    cur = np.concatenate(
        [np.zeros(360), np.full(n, i), np.zeros(720), np.full(round(charge_to * n), -i),
         np.zeros(360)]
    )  # fmt: skip
    t = np.arange(cur.size, dtype=np.float64) * dt
    r0, r1, t1, r2, t2 = r
    sim = simulate(
        t, cur, ocv, capacity_Ah=cap, R0_ohm=r0, R1_ohm=r1, tau1_s=t1, R2_ohm=r2, tau2_s=t2,
        gamma=30.0, soc0=1.0, h0=1.0,
    )  # fmt: skip
    rng = np.random.default_rng(seed)
    v = sim.v_V[0] + rng.normal(0.0, 1e-3, cur.size)
    meas = np.where(cur < 0, cur * charge_gain, cur) + rng.normal(0.0, 1e-3, cur.size)
    return OcvTestPart(t, meas, v)


NMC = OcvModel.from_coeffs(PAPER, 0.02, 0.98, [0.0, 1.0], [0.015, 0.015],
                           v_empty_V=3.0, v_full_V=4.2)  # fmt: skip
LFP = OcvModel.from_coeffs(
    [3.544655696, -0.372057763, 0.129794717, -0.005095261, 0.129556318, -0.027847578],
    0.02, 0.98, [0.0, 1.0], [0.015, 0.015], v_empty_V=2.6, v_full_V=3.55,
)  # fmt: skip


@pytest.mark.parametrize(
    ("ocv", "cap", "r"),
    [(NMC, 5.0, (0.04, 0.02, 30.0, 0.03, 600.0)), (LFP, 2.0, (0.01, 0.005, 20.0, 0.01, 800.0))],
    ids=["nmc", "lfp"],
)
def test_c20_test_recovers_a_15_mV_half_gap_with_polarisation(
    ocv: OcvModel, cap: float, r: tuple[float, float, float, float, float]
) -> None:
    res = fit_ocv_test(extract_branches([_c20_test(ocv, cap=cap, r=r)]))
    assert res.m_fit_V is not None and res.m_ci95_V is not None
    assert res.half_gap_raw_V is not None
    inner = (res.m_soc > 0.0) & (res.m_soc < 1.0)
    # The polarisation is a real part of the raw gap (issue 11: one IR drop zeroed M).
    assert np.median(res.half_gap_raw_V) > 0.017
    np.testing.assert_allclose(res.m_fit_V[inner], 0.015, atol=0.003)
    # Mid knots are tight; the branch-start knots (2 %, 98 %) carry gamma's effect (not fitted).
    mid = (res.m_soc > 0.1) & (res.m_soc < 0.9)
    assert np.all(res.m_ci95_V[mid] < 0.005)
    assert np.all(np.abs(res.m_fit_V[inner] - 0.015) <= res.m_ci95_V[inner] + 1e-3)
    # The rested voltages at both ends are found and the extended curve reaches them.
    assert res.v_empty_V is not None and res.v_full_V is not None
    # The rested voltages lie M off the mean (h = +1 full, -1 empty); the curve reaches them.
    v_full = float(ocv.ocv(np.array([1.0]))[0]) + 0.015
    v_empty = float(ocv.ocv(np.array([0.0]))[0]) - 0.015
    assert res.v_full_V == pytest.approx(v_full, abs=0.002)
    assert res.v_empty_V == pytest.approx(v_empty, abs=0.02)  # still relaxing after 2 h
    model = res.ocv_model()
    assert float(model.ocv(np.array([1.0]))[0]) == pytest.approx(res.v_full_V, abs=1e-9)
    assert float(model.ocv(np.array([0.0]))[0]) == pytest.approx(res.v_empty_V, abs=1e-9)
    assert float(model.soc_from_ocv(res.v_full_V)) == pytest.approx(1.0, abs=1e-6)


def test_throughput_mismatch_is_normalised_not_a_fake_hysteresis() -> None:
    # The tester counts charge 13 % low; the cell still returns to the same rested voltage.
    br = extract_branches([_c20_test(NMC, charge_gain=0.87)])
    tp = br.throughput
    assert tp.method == "normalised"
    assert tp.mismatch_pct == pytest.approx(-13.0, abs=0.3)
    assert br.coulombic_efficiency == pytest.approx(1 / 0.87, rel=5e-3)
    res = fit_ocv_test(br)
    assert res.m_fit_V is not None
    inner = (res.m_soc > 0.0) & (res.m_soc < 1.0)
    np.testing.assert_allclose(res.m_fit_V[inner], 0.015, atol=0.003)
    assert res.soc_max >= 0.97
    # The config takes the measured counting factor (> 1) as it is.
    cfg = build_cell_config(res, name="x", capacity_Ah=br.capacity_Ah,
                            coulombic_efficiency=br.coulombic_efficiency)  # fmt: skip
    assert cfg.coulombic_efficiency > 1.1
    with pytest.raises(ValueError, match="less than or equal to 2"):
        CellConfig(capacity_Ah=5.0, coulombic_efficiency=99.5, ocv=OcvCurve(mean=PAPER_OCV_MEAN))


def test_a_charge_that_ends_short_is_counted() -> None:
    br = extract_branches([_c20_test(NMC, charge_to=0.93)])
    assert br.throughput.method == "counted"
    assert br.coulombic_efficiency == 1.0
    assert float(np.max(br.charge.z)) == pytest.approx(0.93, abs=0.005)


def test_a123_c30_test_fits_with_r2_above_099(real_data_dir: Path) -> None:
    parts = []
    for k in (1, 2, 3, 4):
        d = read_tester_csv(real_data_dir / "a123_lfp_25C" / f"a123_25C_OCV_S{k}.csv.gz")
        parts.append(OcvTestPart(d.t_s, d.current_A, d.cell_voltages_V[:, 0]))
    br = extract_branches(parts)
    assert br.capacity_Ah == pytest.approx(2.07, abs=0.02)
    assert 0.99 <= br.coulombic_efficiency <= 1.0
    assert br.throughput.method == "normalised"
    res = fit_ocv_test(br)
    assert res.discharge is not None and res.charge is not None
    for fit in (res.discharge, res.charge, res.mean):
        assert fit.r2 >= 0.99
    # M is positive where measured, below the raw half-gap, with a CI; 0 at the rested ends.
    assert res.half_gap_raw_V is not None and res.gap_soc is not None and res.m_ci95_V is not None
    inner = (res.m_soc > 0.0) & (res.m_soc < 1.0)
    _, raw_m = fit_piecewise_linear(res.gap_soc, res.half_gap_raw_V, res.m_soc[inner].tolist())
    assert np.all(res.m_V[inner] > res.m_ci95_V[inner] / 2)
    # Mid knots: below the raw half-gap (the polarisation is out); the end knots may exceed it,
    # where h is still turning at a branch start and the gap is divided by less than 2.
    assert np.all(res.m_V[inner][1:-1] < raw_m[1:-1])
    assert res.v_full_V == pytest.approx(3.584, abs=0.002)
    assert res.v_empty_V is not None and res.v_empty_V < 2.5
    model = res.ocv_model()
    assert float(model.soc_from_ocv(3.575)) > 0.99  # a full cell at rest reads full
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
    # No hand-set start values or bounds: identify and the daemon measure them on the record.
    assert cfg.initial is None and cfg.bounds is None
    model = ocv_model(cfg)  # with the end segments, where the config has them
    for lo, hi in ((0.0, cfg.ocv.soc_min), (cfg.ocv.soc_max, 1.0)):
        v = model.ocv(np.linspace(lo, hi, 200))
        assert np.all(np.diff(v) >= -1e-12)
    if cfg.ocv.v_full_V is not None:
        assert float(model.ocv(np.array([1.0]))[0]) == pytest.approx(cfg.ocv.v_full_V, abs=1e-9)


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
    assert cfg.bounds is None and cfg.initial is None  # nothing the user did not give
    assert cfg.hysteresis.M_ci95_V is not None
    for name in ("ocv_fit.txt", "ocv_fit.json", "ocv_fit.png"):
        assert (tmp_path / "cell_report" / name).stat().st_size > 0


@pytest.mark.parametrize(
    ("mutate", "expected"),
    [
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
    # (a discharge alone is no bad file since ocv_one_branch.py: test_ocv_one_branch.py)
    if mutate == "nan_rows":
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


def test_fit_ocv_reports_merged_repeated_timestamps(tmp_path: Path) -> None:
    """A tester logging a record twice at a step change: the OCV test still fits, and the
    report says how many rows were merged."""
    from bmsid.offline.ocv_config import OcvFitSpec, fit_ocv_files

    src = REPO / "data" / "physics" / "dfn_nmc_ocv_c20_25C.csv.gz"
    lines = gzip.decompress(src.read_bytes()).decode().splitlines()
    doubled = [*lines[:1000], lines[999], *lines[1000:]]  # one record logged twice
    path = tmp_path / "ocv_repeat.csv"
    path.write_text("\n".join(doubled) + "\n", encoding="utf-8")
    fit = fit_ocv_files([path], OcvFitSpec("repeat"))
    assert any("merged 1 rows with repeated timestamps" in line for line in fit.info)


def test_c_rates_print_as_a_tester_writes_them() -> None:
    assert [c_rate_text(r) for r in (0.05, 1 / 27, 0.25, 1.0, 2.0, 15.3)] == [
        "C/20", "C/27", "C/4", "1C", "2C", "15.3C",
    ]  # fmt: skip


@pytest.mark.parametrize(
    ("capacity", "expected"),
    [
        ("1.0", "warning: capacity_mismatch: --capacity-ah 1 Ah is 0.5x the 2 Ah the test"),
        ("0.04", "= 2C for 0.04 Ah (given by --capacity-ah; the test measures 2 Ah)"),
        ("2000", "of the capacity, 2000 Ah (given by --capacity-ah; the test measures 2 Ah: Ah, "),
    ],
    ids=["half", "fast", "mAh"],
)
def test_cli_says_a_given_capacity_is_off_the_measured_one(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], capacity: str, expected: str
) -> None:
    src = tmp_path / "ocv.csv"
    write_tester_csv(_synthetic_ocv_test(r_ohm=0.03, m_V=0.01), src)
    code = main(["fit-ocv", str(src), "--capacity-ah", capacity, "--out", str(tmp_path / "c.toml")])
    out, err = capsys.readouterr()
    assert code == (0 if capacity == "1.0" else 2)
    assert expected in out + err


@pytest.mark.parametrize("charge_to", [0.6, 0.9])
def test_a_charge_stopped_early_is_warned_and_no_soc_beyond_100(charge_to: float) -> None:
    """An LFP charge cut short below its top knee (W7: accepted silently with "SOC 172.86 %")."""
    br = extract_branches([_c20_test(LFP, charge_to=charge_to)])
    res = fit_ocv_test(br)
    [line] = partial_range_warning(res, 0.02)
    assert f"OCV above {100 * res.mean.soc_hi:.1f} % is not measured" in line
    assert res.mean.soc_hi == pytest.approx(charge_to, abs=0.01)
    pcts = [float(x) for x in re.findall(r"([-\d.]+) %", br.throughput.reason)]
    assert pcts and all(0.0 <= x <= 100.0 for x in pcts)
    assert partial_range_warning(fit_ocv_test(extract_branches([_c20_test(LFP)])), 0.02) == []


@pytest.mark.parametrize("fault", ["order", "sign"])
def test_files_out_of_order_or_sign_flipped_get_a_hint(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], fault: str
) -> None:
    """M2: the files in the wrong order or charge counted positive gave "overlap only on SOC
    2--1 %" without a hint."""
    data = _synthetic_ocv_test(r_ohm=0.03, m_V=0.01)
    k = int(np.flatnonzero(data.current_A < 0)[0]) - 30  # the discharge file, then the charge
    parts = [
        TesterData(data.t_s[a:b], data.current_A[a:b], data.cell_voltages_V[a:b], ["voltage_V"])
        for a, b in ((0, k), (k, data.t_s.shape[0]))
    ]
    paths = [tmp_path / "dis.csv", tmp_path / "chg.csv"]
    for part, path in zip(parts, paths, strict=True):
        write_tester_csv(part, path)
    files = [str(p) for p in (paths[::-1] if fault == "order" else paths)]
    sign = ["--charge-positive"] if fault == "sign" else []
    code, err = _run_cli([*files, *sign, "--out", str(tmp_path / "c.toml")], capsys)
    assert code == 2
    assert "--charge-positive" in err
    assert not re.search(r"\d--\d", err)  # no "2--1 %"


def test_cli_reads_another_export_with_columns(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """M1: fit-ocv's errors suggested --columns, which it did not take; an ms/mA export loads."""
    data = _synthetic_ocv_test(r_ohm=0.03, m_V=0.01)
    src = tmp_path / "msma.csv"
    rows = zip(1e3 * data.t_s, 1e3 * data.current_A, data.cell_voltages_V[:, 0], strict=True)
    src.write_text("Time_ms,I_mA,U\n" + "".join(f"{t:.1f},{i:.4f},{v:.6f}\n" for t, i, v in rows))
    out = tmp_path / "c.toml"
    cols = "t_s=Time_ms*0.001,current_A=I_mA*0.001,voltage_V=U"
    code, err = _run_cli([str(src), "--columns", cols, "--out", str(out)], capsys)
    assert code == 0, err
    assert load_cell_config(out).capacity_Ah == pytest.approx(2.0, rel=2e-3)


def test_cli_says_a_directory_is_a_directory(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    code, err = _run_cli([str(tmp_path), "--out", str(tmp_path / "c.toml")], capsys)
    assert code == 2
    assert f"{tmp_path}: is a directory; give the CSV files in it" in err


def test_cli_says_a_rest_point_table_needs_points(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """M1: a rest-point table without --points got the --columns hint."""
    src = tmp_path / "pts.csv"
    src.write_text("SOC_percent,OCV_discharge_V\n10,3.45\n50,3.70\n90,4.05\n")
    code, err = _run_cli([str(src), "--out", str(tmp_path / "c.toml")], capsys)
    assert code == 2
    assert "a rest-point table (SOC and OCV columns), not a test: pass --points" in err
