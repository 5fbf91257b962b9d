"""fit-ocv on exports of one test that differ in sampling or file split (sweep D): a rest that
does not settle, a knee's relaxation or a knee's step is not taken as the polarisation, and an
unphysical fit is refused instead of written."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from bmsid.errors import UserError
from bmsid.offline.ocv_config import efficiency_warning
from bmsid.offline.ocv_fit import (
    CurrentStep,
    OcvFitResult,
    OcvTestPart,
    Polarisation,
    Throughput,
    _choose_polarisation,
    check_physical,
    extract_branches,
    fit_eq4,
    fit_ocv_test,
    fit_relaxation,
)
from bmsid.synthetic.ocv_test import LFP_CELL, NMC_CELL, SyntheticOcvTest, c20_ocv_test

M_TRUE = 0.015


def _fit(test: SyntheticOcvTest, v_V: np.ndarray) -> OcvFitResult:
    return fit_ocv_test(extract_branches([OcvTestPart(test.t_s, test.current_A, v_V)]))


def _segment(test: SyntheticOcvTest, name: str) -> tuple[int, int]:
    return next((a, b) for n, a, b in test.segments if n == name)


def _assert_m_recovered(res: OcvFitResult) -> None:
    ev = res.hysteresis
    assert ev is not None and ev.present
    assert abs(ev.pooled_V - M_TRUE) <= ev.pooled_ci95_V


def test_a_rest_that_does_not_settle_gives_no_relaxation_fit() -> None:
    """60 s samples of a rest still drifting at its end: a 2RC fit extrapolates v_inf (W1: an
    R0 of 5451 ohm and an OCV of -8 V were written)."""
    t = np.arange(0.0, 7200.0, 60.0)
    v = 3.40 - 2e-6 * t + np.random.default_rng(1).normal(0.0, 1e-4, t.shape[0])
    assert fit_relaxation(t, v, current_A=-0.0766, v_load_V=3.405, run_s=9e4) is None


def test_an_unphysical_mean_ocv_is_refused() -> None:
    z = np.linspace(0.02, 0.98, 200)
    bad = fit_eq4(z, -8.0 - 2.0 * z)
    pol = Polarisation(5451.0, 0.0, 1.0, 0.0, 1.0, 1.0, "relaxation fit")
    with pytest.raises(UserError, match="not physical"):
        check_physical(bad, np.array([2.0, 3.6]), pol)


def test_a_knee_relaxation_is_not_the_polarisation() -> None:
    """The OCV's own relaxation after the branches end in the knees (as in the A123 test when
    its rests are in the same file as the branches: W2) would reverse the gap: left out."""
    test = c20_ocv_test(LFP_CELL, m_V=M_TRUE)
    v = test.v_V.copy()
    for name, dv in (("rest empty", 0.08), ("rest end", -0.06)):
        a, b = _segment(test, name)
        v[a:b] -= dv * np.exp(-(test.t_s[a:b] - test.t_s[a]) / 600.0)
    res = _fit(test, v)
    assert res.test is not None
    pol = res.test.polarisation
    assert len(pol.knee) == 2 and not pol.relaxations
    assert pol.r_total_ohm < 3 * LFP_CELL.r_total_ohm
    _assert_m_recovered(res)


def test_a_knee_step_is_not_r0() -> None:
    """A one-sample step where the voltage recovers 150 mV at the knee (the A123 test resampled
    to 10 s: 1452 mOhm taken as R0, W3) is left out of R0."""
    test = c20_ocv_test(LFP_CELL, m_V=M_TRUE, rest_empty_s=60.0, rest_end_s=60.0)
    v = test.v_V.copy()
    a, b = _segment(test, "rest empty")
    v[a:b] += 0.15
    res = _fit(test, v)
    assert res.test is not None
    assert res.test.polarisation.R0_ohm < 3 * LFP_CELL.R0_ohm
    assert any("not used for R0" in n for n in res.notes)
    _assert_m_recovered(res)


def test_a_test_without_rests_does_not_claim_hysteresis() -> None:
    """The branches alone (rests cut out) of a cell without hysteresis: the gap is polarisation,
    which the test cannot measure (W5: "M 9.9 +- 0.9 mV, hysteresis present")."""
    test = c20_ocv_test(NMC_CELL, m_V=0.0)
    keep = np.concatenate(
        [np.arange(a, b) for n, a, b in test.segments if n in ("discharge", "charge")]
    )
    part = OcvTestPart(test.t_s[keep], test.current_A[keep], test.v_V[keep])
    res = fit_ocv_test(extract_branches([part]))
    ev = res.hysteresis
    assert ev is not None and ev.unresolved is not None and not ev.present
    assert ev.pooled_V - ev.pooled_ci95_V > 0  # the gap alone would have said "present"
    assert np.all(res.m_V == 0.0)
    assert any("hysteresis not resolved" in n for n in res.notes)


def test_an_implausible_coulombic_efficiency_is_warned() -> None:
    """The A123 test resampled to 60 s counts 6 % more charge in than out (its pulses held over
    whole samples): 0.942 was stored silently, and identify gave 9.5 mV instead of 4.9."""
    off = Throughput(2.0774, 2.2100, "normalised", 2.0774 / 2.2100, "measured")
    [line] = efficiency_warning(off)
    assert "0.9400" in line and "--coulombic-efficiency" in line
    assert efficiency_warning(replace(off, charge_Ah=2.0859, eta=2.0774 / 2.0859)) == []


def test_r0_is_the_step_with_the_lowest_upper_bound() -> None:
    """The A123 test resampled to 60 s: a 216.7 +- 28.3 mOhm step (a minute of relaxation in
    it) "resolves" R0 and zeroed M; an 18.3 +- 9.4 mOhm one bounds R0 tighter (W1/W3)."""
    steps = [CurrentStep(0.2167, 0.0283, 10, True), CurrentStep(0.0183, 0.0094, 20, True)]
    pol = _choose_polarisation([], steps, 0.29, [])
    assert pol.R0_ohm == pytest.approx(0.0183)


def test_current_noise_at_rest_is_not_a_branch() -> None:
    """A C/20 discharge alone, its rests' current noise (1 mA) crossing the rest threshold for a
    few samples: that was taken for the charge branch and crashed the split (an internal
    error); it is no branch, and the test is refused for what it lacks."""
    test = c20_ocv_test(NMC_CELL, m_V=M_TRUE)
    k = _segment(test, "rest empty")[1]
    i = test.current_A[:k]
    assert np.count_nonzero(i < -0.001) > 0  # the noise does cross it
    with pytest.raises(UserError, match="the OCV test has no charge branch"):
        extract_branches([OcvTestPart(test.t_s[:k], i, test.v_V[:k])])
