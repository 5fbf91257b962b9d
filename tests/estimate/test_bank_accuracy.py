"""The issue's acceptance case on known-truth synthetic data (see bmsid.synthetic)."""

from __future__ import annotations

from functools import cache

import numpy as np
import numpy.typing as npt
import pytest

from bmsid.config.cell import paper_cell
from bmsid.config.engine import build_bank, ocv_model
from bmsid.estimate.tuning import EstimatorTuning, Variant
from bmsid.metrics import voltage_metrics
from bmsid.model.simulator import simulate
from bmsid.profiles import dst_current
from bmsid.samples import SampleBlock
from bmsid.synthetic import TRUTH, SyntheticRun, paper_dst_case

Arr = npt.NDArray[np.float64]


@cache
def _case(ramp: float) -> SyntheticRun:
    return paper_dst_case(r0_ramp=ramp)


@cache
def _run(variant: Variant, ramp: float = 0.0) -> dict[str, Arr]:
    run = _case(ramp)
    bank = build_bank(run.cell, 1, variant, soc0=0.98)
    keys = ("R0_ohm", "R1_ohm", "R2_ohm", "tau1_s", "tau2_s", "v_model_V", "v_meas_V", "lambda_")
    out: dict[str, list[float]] = {k: [] for k in keys}
    for k in range(run.t_s.shape[0]):
        est = bank.update(run.t_s[k], run.current_A[k], run.voltages_V[k])
        assert est is not None  # 1 s data at a 1 s identification period: a tick per sample
        for key in keys:
            out[key].append(float(getattr(est, key)[0]))
    return {k: np.asarray(v) for k, v in out.items()}


def _after_10pct(x: Arr) -> Arr:
    return x[x.shape[0] // 10 :]


def test_fusion_meets_the_accuracy_targets() -> None:
    r = _run("hy-affrls-lpso")
    t = _case(0.0).truth
    r0 = _after_10pct(r["R0_ohm"])
    rsum = _after_10pct(r["R0_ohm"] + r["R1_ohm"] + r["R2_ohm"])
    tau1 = _after_10pct(r["tau1_s"])
    assert np.max(np.abs(r0 / t["R0_ohm"] - 1)) <= 0.03
    assert np.max(np.abs(rsum / (t["R0_ohm"] + t["R1_ohm"] + t["R2_ohm"]) - 1)) <= 0.10
    assert np.max(np.abs(tau1 / t["tau1_s"] - 1)) <= 0.25
    m = voltage_metrics(_after_10pct(r["v_meas_V"]), _after_10pct(r["v_model_V"]))
    assert m.rmse_V <= 3e-3


def test_non_hysteresis_affrls_is_measurably_worse_on_hysteretic_data() -> None:
    fused = _run("hy-affrls-lpso")
    plain = _run("non-hy-affrls")
    m_f = voltage_metrics(_after_10pct(fused["v_meas_V"]), _after_10pct(fused["v_model_V"]))
    m_p = voltage_metrics(_after_10pct(plain["v_meas_V"]), _after_10pct(plain["v_model_V"]))
    assert m_p.rmse_V > 2.0 * m_f.rmse_V
    assert m_p.max_abs_error_V > m_f.max_abs_error_V


def test_fusion_tracks_a_30_percent_r0_ramp() -> None:
    r = _run("hy-affrls-lpso", ramp=0.3)
    truth = _case(0.3).R0_true_ohm[:, 0]
    err = np.abs(_after_10pct(r["R0_ohm"]) / _after_10pct(truth) - 1)
    assert np.max(err) <= 0.05


def test_a_start_just_after_a_full_charge_keeps_the_slow_branch() -> None:
    """Issue 11 item 7: the true hysteresis state starts at +1 (a full charge, then rest), the
    engine, told nothing (no soc0), starts it at 0; its swing to -1 in the first Ah of the drive
    must not be learnt as the slow branch (DC resistance is what power limits use)."""
    run = paper_dst_case(h0=1.0)
    bank = build_bank(run.cell, 1, "hy-affrls-lpso")
    est = bank.update_block(SampleBlock.from_arrays(run.t_s, run.current_A, run.voltages_V))
    t = run.truth
    r0 = _after_10pct(est["R0_ohm"][:, 0])
    rsum = _after_10pct(est["R0_ohm"][:, 0] + est["R1_ohm"][:, 0] + est["R2_ohm"][:, 0])
    assert np.median(np.abs(r0 / t["R0_ohm"] - 1)) <= 0.03
    assert np.median(np.abs(rsum / (t["R0_ohm"] + t["R1_ohm"] + t["R2_ohm"]) - 1)) <= 0.10
    m = voltage_metrics(_after_10pct(est["v_meas_V"][:, 0]), _after_10pct(est["v_model_V"][:, 0]))
    assert m.rmse_V <= 3e-3


def test_forgetting_factor_stays_in_its_interval() -> None:
    lam = _run("hy-affrls-lpso")["lambda_"]
    assert np.all((lam >= 0.98) & (lam <= 1.0))


@pytest.mark.parametrize(("dt_s", "duration_s"), [(0.01, 1300.0), (10.0, 9000.0)])
def test_sample_periods_from_10_ms_to_10_s_identify_the_same_cell(
    dt_s: float, duration_s: float
) -> None:
    """100 Hz data are averaged to 1 s ticks; 10 s data are identified at their own rate."""
    cell = paper_cell(M_V=0.015, gamma=30.0)
    t = np.arange(0.0, duration_s, dt_s)
    i = dst_current(t, 140.0)
    sim = simulate(t, i, ocv_model(cell), capacity_Ah=70.0, R0_ohm=1.2e-3,
                   R1_ohm=0.8e-3, tau1_s=32.0, R2_ohm=1.0e-3, tau2_s=600.0, gamma=30.0,
                   soc0=0.98)  # fmt: skip
    v = sim.v_V[0] + np.random.default_rng(0).normal(0.0, 1e-3, t.size)
    bank = build_bank(cell, 1, "hy-affrls-lpso", soc0=0.98)
    last = None
    for k in range(t.size):
        est = bank.update(t[k], i[k], v[k : k + 1])
        last = est or last
    assert last is not None and bank.counters["swarms"] >= 2
    assert abs(last.R0_ohm[0] / 1.2e-3 - 1) < 0.03
    assert abs(last.tau1_s[0] / 32.0 - 1) < 0.25


def test_an_hppc_test_identifies_both_time_constants() -> None:
    """A known-truth HPPC test (the paper cell from 95 %: per SOC step a 10 s 1C discharge pulse,
    40 s rest, a 10 s 0.75C charge pulse, 10 min rest, 0.1C h of discharge, 30 min rest): its
    30-minute windows hold 4 current steps at most (two pulses), never a drive's hundreds. The
    swarm must run on them: with 10 steps required it never did, and tau1, tau2 stayed at their
    start values (10 / 300 s against 32 / 600)."""
    cell = paper_cell(M_V=0.015, gamma=30.0)
    c_A = cell.capacity_Ah
    segments = [(600, 0.0)]
    for _ in range(6):
        segments += [(10, c_A), (40, 0.0), (10, -0.75 * c_A), (600, 0.0), (360, c_A), (1800, 0.0)]
    i = np.concatenate([np.full(d, a) for d, a in segments])
    t = np.arange(i.size, dtype=np.float64)
    sim = simulate(
        t, i, ocv_model(cell), capacity_Ah=c_A, gamma=30.0, soc0=0.95,
        **{k: TRUTH[k] for k in ("R0_ohm", "R1_ohm", "tau1_s", "R2_ohm", "tau2_s")},
    )  # fmt: skip
    rng = np.random.default_rng(1)
    block = SampleBlock.from_arrays(
        t, i + rng.normal(0.0, 0.05, t.size), sim.v_V.T + rng.normal(0.0, 1e-3, (t.size, 1))
    )
    bank = build_bank(cell, 1, "hy-affrls-lpso", EstimatorTuning())
    out = bank.update_block(block)
    assert bank.counters["swarms"] >= 5
    half = slice(out.t_s.size // 2, None)

    def med(key: str) -> float:
        return float(np.median(out[key][half, 0]))

    # 10 s pulses barely move the slow branch (R2 I 10 / tau2: about the noise), so tau2 is
    # the loosest: +13 % at the end of this record, +1 % with another noise draw
    assert med("tau1_s") == pytest.approx(TRUTH["tau1_s"], rel=0.1)
    assert med("tau2_s") == pytest.approx(TRUTH["tau2_s"], rel=0.4)
    assert med("R0_ohm") == pytest.approx(TRUTH["R0_ohm"], rel=0.05)
    r_dc = med("R0_ohm") + med("R1_ohm") + med("R2_ohm")
    assert r_dc == pytest.approx(TRUTH["R0_ohm"] + TRUTH["R1_ohm"] + TRUTH["R2_ohm"], rel=0.1)
