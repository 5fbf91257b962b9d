"""The OCV curve's end segments (model/ocv.py): continuity, C1 joins, monotonicity, the inverse
over the whole SOC range, and curves without ends exactly as before."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from bmsid.config.cell import PAPER_OCV_MEAN, OcvCurve
from bmsid.model.ocv import OcvModel, end_segment, eval_docv_dz, eval_ocv

PAPER = np.asarray(PAPER_OCV_MEAN)
#: The A123 LFP mean curve shipped before the ends existed (flat plateau, steep knees).
LFP = np.array([3.544655696, -0.372057763, 0.129794717, -0.005095261, 0.129556318, -0.027847578])


def _model(coeffs: np.ndarray, lo: float, hi: float, r_lo: float, r_hi: float) -> OcvModel:
    """Ends whose secant is the join slope / r (r in (1/3, ...): monotone C1 segments exist)."""
    v_lo, v_hi = float(eval_ocv(coeffs, lo)), float(eval_ocv(coeffs, hi))
    d_lo, d_hi = float(eval_docv_dz(coeffs, lo)), float(eval_docv_dz(coeffs, hi))
    return OcvModel.from_coeffs(
        coeffs, lo, hi, [0.0, 1.0], [0.0, 0.0],
        v_empty_V=v_lo - d_lo / r_lo * lo, v_full_V=v_hi + d_hi / r_hi * (1 - hi),
    )  # fmt: skip


curves = st.sampled_from([PAPER, LFP])
joins = st.tuples(st.floats(0.01, 0.08), st.floats(0.92, 0.98))
ratios = st.tuples(st.floats(0.05, 2.99), st.floats(0.05, 2.99))


@settings(max_examples=60, deadline=None)
@given(curves, joins, ratios)
def test_end_segments_are_continuous_c1_and_monotone(
    c: np.ndarray, j: tuple[float, float], r: tuple[float, float]
) -> None:
    m = _model(c, j[0], j[1], r[0], r[1])
    assert (m.soc_min, m.soc_max) == (0.0, 1.0)
    for z0 in j:
        eps = 1e-9
        left, right = m.ocv(np.array([z0 - eps])), m.ocv(np.array([z0 + eps]))
        assert abs(float(right[0] - left[0])) < 1e-6
        d_l, d_r = m.docv_dz(np.array([z0 - eps])), m.docv_dz(np.array([z0 + eps]))
        assert float(d_l[0]) == pytest.approx(float(d_r[0]), rel=1e-5, abs=1e-6)
    z = np.linspace(0.0, 1.0, 20001)
    v = m.ocv(z)
    lo_v = float(eval_ocv(c, j[0]))
    # Monotone on the end segments (Eq. 4 itself may wiggle on an LFP plateau).
    assert np.all(np.diff(v[z <= j[0]]) >= -1e-12)
    assert np.all(np.diff(v[z >= j[1]]) >= -1e-12)
    assert v[0] < lo_v
    # The slope is what the derivative says (finite differences on a fine grid).
    num = np.gradient(v, z)
    inner = (np.abs(z - j[0]) > 1e-3) & (np.abs(z - j[1]) > 1e-3) & (z > 1e-3) & (z < 1 - 1e-3)
    np.testing.assert_allclose(num[inner], m.docv_dz(z)[inner], rtol=2e-3, atol=2e-3)


@settings(max_examples=40, deadline=None)
@given(joins, ratios, st.floats(0.0, 1.0))
def test_inverse_round_trips_over_the_whole_range(
    j: tuple[float, float], r: tuple[float, float], z: float
) -> None:
    m = _model(PAPER, j[0], j[1], r[0], r[1])  # strictly monotone: z itself comes back
    back = float(m.soc_from_ocv(m.ocv(np.array([z])))[0])
    assert back == pytest.approx(z, abs=2e-3)
    lfp = _model(LFP, j[0], j[1], r[0], r[1])  # flat plateau: the voltage comes back
    v = lfp.ocv(np.array([z]))
    assert float(lfp.ocv(lfp.soc_from_ocv(v))[0]) == pytest.approx(float(v[0]), abs=2e-3)


def test_a_full_lfp_cell_at_rest_reads_full() -> None:
    m = OcvModel.from_coeffs(LFP, 0.02, 0.98, [0.0, 1.0], [0.0, 0.0], v_full_V=3.584)
    assert float(m.soc_from_ocv(3.584)) == pytest.approx(1.0, abs=1e-9)
    assert float(m.soc_from_ocv(3.575)) > 0.995
    old = OcvModel.from_coeffs(LFP, 0.02, 0.98, [0.0, 1.0], [0.0, 0.0])
    assert float(old.soc_from_ocv(3.584)) == 0.98  # what the clamped curve did


@given(st.floats(-0.5, 1.5, allow_nan=False))
def test_without_ends_the_curve_is_exactly_the_old_one(z: float) -> None:
    m = OcvModel.from_coeffs(PAPER, 0.02, 0.98, [0.0, 1.0], [0.015, 0.015])
    assert not m.has_ends and (m.soc_min, m.soc_max) == (0.02, 0.98)
    zc = min(max(z, 0.02), 0.98)
    c = PAPER
    old = c[0] + zc * (c[1] + c[2] * zc) + c[3] / zc + c[4] * np.log(zc) + c[5] * np.log1p(-zc)
    assert float(m.ocv(np.array([z]))[0]) == old  # bit for bit
    old_d = c[1] + 2 * c[2] * zc - c[3] / zc**2 + c[4] / zc - c[5] / (1 - zc)
    assert float(m.docv_dz(np.array([z]))[0]) == old_d
    grid = np.linspace(0.02, 0.98, 2001)
    np.testing.assert_array_equal(m._inv_z, grid)


def test_impossible_ends_are_refused() -> None:
    v_hi = float(eval_ocv(PAPER, 0.98))
    with pytest.raises(ValueError, match="monotonically"):
        end_segment(PAPER, 0.98, 1.0, v_hi - 0.01)
    d = float(eval_docv_dz(PAPER, 0.98))
    with pytest.raises(ValueError, match="move the join inwards"):
        end_segment(PAPER, 0.98, 1.0, v_hi + d / 3.5 * 0.02)
    with pytest.raises(ValueError, match="monotonically"):
        OcvCurve(mean=PAPER_OCV_MEAN, soc_min=0.02, soc_max=0.98, v_full_V=v_hi - 0.01)
    ok = OcvCurve(mean=PAPER_OCV_MEAN, soc_min=0.02, soc_max=0.98, v_full_V=v_hi + 0.05)
    assert ok.v_empty_V is None


@settings(max_examples=80, deadline=None)
@given(curves, joins, ratios, st.floats(0.02, 0.98), st.floats(0.02, 0.98))
def test_a_step_along_the_secant_lands_on_the_inverse(
    c: np.ndarray, j: tuple[float, float], r: tuple[float, float], z: float, z_true: float
) -> None:
    """The observer's anchor (weak prior): z + e / slope with e = OCV(z') - OCV(z) is z', where
    the tangent overshoots or falls short on a curved OCV; slope > 0 on a monotone curve, and
    z' the SOC whose OCV was measured."""
    m = _model(c, j[0], j[1], r[0], r[1])
    v = m.ocv(np.array([z_true]))
    slope, z_to = m.secant_slope(np.array([z]), v)
    assert np.isfinite(slope).all() and slope[0] > 0
    e = float(m.ocv(z_to)[0] - m.ocv(np.array([z]))[0])  # the innovation the inverse implies
    if abs(z_to[0] - z) > 1e-3:
        assert z + e / slope[0] == pytest.approx(z_to[0], abs=1e-9)
    else:
        assert slope[0] == pytest.approx(float(m.docv_dz(np.array([z]))[0]))
    assert z_to[0] == pytest.approx(z_true, abs=2e-3)
