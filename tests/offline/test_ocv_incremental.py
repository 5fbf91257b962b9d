"""fit-ocv on incremental OCV tests (pulses with long rests between, ``ocv_incremental.py``):
known-truth tests from ``bmsid.synthetic.ocv_test.incremental_ocv_test``. Before, fit-ocv
refused them ("too fast for an OCV test"); now the rests' voltages are the points."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from test_ocv_fit_hysteresis import write_ocv_test_csv

from bmsid.cli.main import main
from bmsid.config.cell import load_cell_config
from bmsid.config.engine import ocv_model
from bmsid.offline.ocv_config import OcvFitSpec, fit_ocv_files
from bmsid.offline.ocv_fit import OcvTestPart
from bmsid.offline.ocv_incremental import incremental_points
from bmsid.synthetic.ocv_test import (
    LFP_CELL,
    NMC_CELL,
    OcvTestCell,
    SyntheticOcvTest,
    c20_ocv_test,
    incremental_ocv_test,
)

M_TRUE = 0.015
CELLS = pytest.mark.parametrize("cell", [NMC_CELL, LFP_CELL], ids=["nmc", "lfp"])


def _part(test: SyntheticOcvTest) -> OcvTestPart:
    return OcvTestPart(test.t_s, test.current_A, test.v_V)


@CELLS
def test_an_incremental_test_gives_the_ocv_the_half_gap_and_the_capacity(
    cell: OcvTestCell, tmp_path: Path
) -> None:
    """Ten C/2 pulses down, ten up, an hour's rest after each: the mean OCV within 2 mV of the
    truth over SOC 15-85 %, the pooled half-gap within 3 mV of 15 mV, the capacity within
    0.5 %."""
    test = incremental_ocv_test(cell, m_V=M_TRUE)
    fit = fit_ocv_files([write_ocv_test_csv(test, tmp_path / "inc.csv")], OcvFitSpec("inc"))
    assert any(line.startswith("an incremental OCV test") for line in fit.info)
    res = fit.result
    assert res.hysteresis is not None and res.hysteresis.present
    assert res.hysteresis.pooled_V == pytest.approx(M_TRUE, abs=0.003)
    assert fit.config.capacity_Ah == pytest.approx(cell.capacity_Ah, rel=0.005)
    z = np.linspace(0.15, 0.85, 71)
    err = ocv_model(fit.config).ocv(z) - cell.ocv().ocv(z)
    assert np.max(np.abs(err)) < 0.002


def test_no_hysteresis_is_not_made_up() -> None:
    """The same test without hysteresis: the pooled half-gap's CI holds 0 (the rests' leftover
    relaxation, which widens the gap, stays within it)."""
    pts = incremental_points([_part(incremental_ocv_test(NMC_CELL, m_V=0.0, seed=3))])
    assert pts is not None and pts.discharge is not None and pts.charge is not None
    from bmsid.offline.ocv_fit import fit_rest_points

    res = fit_rest_points(pts.discharge, pts.charge)
    assert res.hysteresis is not None
    assert not res.hysteresis.present
    assert abs(res.hysteresis.pooled_V) < 0.002


def test_points_sit_on_their_branches() -> None:
    """Each rest's point is on its pulse's branch at the rest's SOC; the rest before the first
    (discharge) pulse is the full end of the charge branch."""
    test = incremental_ocv_test(NMC_CELL, m_V=M_TRUE, step_soc=0.2)
    pts = incremental_points([_part(test)])
    assert pts is not None and pts.discharge is not None and pts.charge is not None
    np.testing.assert_allclose(pts.discharge[0], [0.8, 0.6, 0.4, 0.2, 0.0], atol=0.002)
    np.testing.assert_allclose(pts.charge[0], [1.0, 0.2, 0.4, 0.6, 0.8, 1.0], atol=0.002)
    ocv = NMC_CELL.ocv(M_TRUE)
    mid = (pts.discharge[0] > 0.1) & (pts.discharge[0] < 0.9)
    z = pts.discharge[0][mid]
    # discharge rests lie M below the mean (h = -1), within the leftover relaxation
    np.testing.assert_allclose(pts.discharge[1][mid], ocv.ocv(z) - M_TRUE, atol=0.002)


def test_a_discharge_only_test_has_one_branch(tmp_path: Path) -> None:
    test = incremental_ocv_test(NMC_CELL, m_V=M_TRUE, charge_back=False)
    pts = incremental_points([_part(test)])
    assert pts is not None and pts.charge is not None and pts.discharge is not None
    assert pts.charge[0].tolist() == pytest.approx([1.0], abs=1e-3)  # the rest at full only
    assert "does not return to its start" in pts.info[1]
    assert pts.eta == 1.0


def test_a_low_rate_test_is_not_incremental() -> None:
    """A C/20 test (with its short pulses at the ends) keeps the low-rate path."""
    assert incremental_points([_part(c20_ocv_test(NMC_CELL, pulse_C=1.0))]) is None
    assert incremental_points([_part(c20_ocv_test(LFP_CELL))]) is None


def test_a_coulombic_efficiency_below_one_is_measured() -> None:
    test = incremental_ocv_test(NMC_CELL, m_V=M_TRUE, eta=0.99)
    pts = incremental_points([_part(test)])
    assert pts is not None
    i = np.round(test.current_A, 2)  # the pulses' charge as scheduled (whole samples)
    assert pts.eta == pytest.approx(i[i > 0].sum() / -i[i < 0].sum(), abs=0.001)
    assert pts.eta < 0.99
    assert pts.charge is not None and pts.charge[0][-1] == pytest.approx(1.0, abs=0.002)


def test_cli_writes_a_config_from_an_incremental_test(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    src = write_ocv_test_csv(incremental_ocv_test(LFP_CELL, m_V=M_TRUE), tmp_path / "gitt.csv")
    out = tmp_path / "lfp.toml"
    assert main(["fit-ocv", str(src), "--chemistry", "LFP", "--out", str(out)]) == 0
    text = capsys.readouterr().out
    assert "an incremental OCV test (10 discharge pulses" in text
    cfg = load_cell_config(out)
    assert cfg.capacity_Ah == pytest.approx(LFP_CELL.capacity_Ah, rel=0.005)
    assert cfg.hysteresis is not None and max(cfg.hysteresis.M_V) > 0.01


def test_an_hppc_test_puts_its_rests_on_the_discharge_branch() -> None:
    """An HPPC test from full (per step a 10 s 1C discharge pulse, 40 s rest, a 10 s 0.75C
    charge pulse, 10 min rest, 10 % SOC at 1C, 30 min rest): its 10 s pulses move h too little
    to set a branch, so every rest after the first 10 % step is a discharge point, at the
    truth's discharge OCV within the leftover relaxation."""
    from bmsid.model.simulator import simulate

    cell, c_A = NMC_CELL, NMC_CELL.capacity_Ah
    segments = [(1800, 0.0)]
    for _ in range(9):
        segments += [(10, c_A), (40, 0.0), (10, -0.75 * c_A), (600, 0.0), (360, c_A), (1800, 0.0)]
    i = np.concatenate([np.full(d, a) for d, a in segments])
    t = np.arange(i.size, dtype=np.float64)
    sim = simulate(
        t, i, cell.ocv(M_TRUE), capacity_Ah=c_A, R0_ohm=cell.R0_ohm, R1_ohm=cell.R1_ohm,
        tau1_s=cell.tau1_s, R2_ohm=cell.R2_ohm, tau2_s=cell.tau2_s, gamma=30.0, soc0=1.0,
        h0=1.0,
    )  # fmt: skip
    # it ends at 7 %, not empty: the capacity is given (the charge to its deepest point is not)
    pts = incremental_points([OcvTestPart(t, i, sim.v_V[0])], capacity_Ah=c_A)
    assert pts is not None and pts.discharge is not None and pts.charge is not None
    # the rests before the first 10 % step: h still +1 from the charge that filled the cell
    np.testing.assert_allclose(pts.charge[0], [1.0, 1.0 - 10 / 3600 * 0.25], atol=1e-6)
    assert pts.discharge[0].size == 17
    z, v = pts.discharge
    np.testing.assert_allclose(v, cell.ocv(M_TRUE).ocv(z) - M_TRUE, atol=0.004)


def test_a_test_in_two_files_with_a_clock_restart(tmp_path: Path) -> None:
    """The same test exported as two files, the second's clock from 0 again, split inside the
    rest at empty: each file's rests are its own, and the fit is the single file's."""
    test = incremental_ocv_test(NMC_CELL, m_V=M_TRUE)
    a, b = next((a, b) for name, a, b in test.segments if name == "rest 10")
    k = (a + b) // 2
    first = OcvTestPart(test.t_s[:k], test.current_A[:k], test.v_V[:k])
    second = OcvTestPart(test.t_s[k:] - test.t_s[k], test.current_A[k:], test.v_V[k:])
    one = incremental_points([_part(test)])
    two = incremental_points([first, second])
    assert one is not None and two is not None
    assert two.capacity_Ah == pytest.approx(one.capacity_Ah, rel=1e-3)
    assert two.discharge is not None and one.discharge is not None
    assert two.discharge[0].size == one.discharge[0].size + 1  # the rest at empty, in halves
    from bmsid.offline.ocv_fit import fit_rest_points

    res = fit_rest_points(two.discharge, two.charge)
    assert res.hysteresis is not None
    assert res.hysteresis.pooled_V == pytest.approx(M_TRUE, abs=0.003)
