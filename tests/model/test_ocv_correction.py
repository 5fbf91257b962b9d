"""The OCV correction table (model/ocv.py, config OcvCurve): Eq. 4 + dU(z) is C1 with the slope
its derivative says, continuous at the knots and at the end-segment joins, held beyond its
knots, refused where it leaves the curve falling, validated with messages that name the field,
and a config without it is the curve exactly as before."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from pydantic import ValidationError

from bmsid.config.cell import PAPER_OCV_MEAN, OcvCurve, paper_cell
from bmsid.config.engine import ocv_model
from bmsid.model.ocv import MAX_DIP_V, OcvModel, eval_ocv, hermite_table, pchip_slopes

PAPER = np.asarray(PAPER_OCV_MEAN)
LO, HI = 0.03, 0.97


@st.composite
def tables(draw: st.DrawFn) -> tuple[np.ndarray, np.ndarray]:
    """3-25 knots on a 0.5 % grid covering [LO, HI] (fit-ocv's are >= 2 % apart), values
    within +-3 mV (the paper's curve rises by >= 0.5 V per unit SOC on [LO, HI], so the
    corrected curve mostly still increases)."""
    n = draw(st.integers(1, 23))
    inner = draw(st.lists(st.integers(7, 193), min_size=n, max_size=n))
    ends = [draw(st.integers(0, 6)), draw(st.integers(194, 200))]
    x = np.unique(inner + ends) * 0.005
    y = np.asarray(draw(st.lists(st.floats(-0.003, 0.003), min_size=x.shape[0],
                                 max_size=x.shape[0])))  # fmt: skip
    return x, y


def _with(x: np.ndarray, y: np.ndarray, ends: bool) -> OcvModel:
    kw: dict[str, float] = {}
    if ends:
        plain = OcvModel.from_coeffs(PAPER, LO, HI, [0.0, 1.0], [0.0, 0.0], corr_soc=x, corr_V=y)
        v_lo, v_hi = (float(plain.ocv(np.array([z]))[0]) for z in (LO, HI))
        d_lo, d_hi = (float(plain.docv_dz(np.array([z]))[0]) for z in (LO, HI))
        kw = {"v_empty_V": v_lo - 0.8 * d_lo * LO, "v_full_V": v_hi + 0.8 * d_hi * (1 - HI)}
    return OcvModel.from_coeffs(
        PAPER, LO, HI, [0.0, 1.0], [0.0, 0.0], corr_soc=x, corr_V=y, **kw
    )  # fmt: skip


@settings(max_examples=60, deadline=None)
@given(tables(), st.booleans())
def test_the_corrected_curve_is_c1_and_its_slope_is_its_derivative(
    t: tuple[np.ndarray, np.ndarray], ends: bool
) -> None:
    x, y = t
    try:
        m = _with(x, y, ends)
    except ValueError:  # a table that leaves the curve falling (tested below)
        return
    z = np.linspace(0.0, 1.0, 200001)
    v, d = m.ocv(z), m.docv_dz(z)
    # The value is Eq. 4 + the table on the curve's range; the table at a knot is its value.
    inside = (x >= LO) & (x <= HI)
    np.testing.assert_allclose(m.ocv(x[inside]), eval_ocv(PAPER, x[inside]) + y[inside],
                               rtol=0, atol=1e-12)  # fmt: skip
    # Continuous value and slope at every knot and at the joins (ends) or the clamps.
    for z0 in (*x, LO, HI):
        if not 0.0 < z0 < 1.0:
            continue
        eps = 1e-9
        left, right = m.ocv(np.array([z0 - eps, z0 + eps]))
        assert abs(float(right - left)) < 1e-6
        if ends or LO < z0 < HI:
            dl, dr = m.docv_dz(np.array([z0 - eps, z0 + eps]))
            assert float(dl) == pytest.approx(float(dr), rel=1e-5, abs=1e-5)
    # The slope is what the finite differences of the value say (away from the clamps).
    num = np.gradient(v, z)
    keep = (z > (1e-3 if ends else LO + 1e-3)) & (z < (1 - 1e-3 if ends else HI - 1e-3))
    np.testing.assert_allclose(num[keep], d[keep], rtol=2e-3, atol=2e-3)
    # It does not fall where it is used (the construction refuses anything else).
    used = v[(z >= LO) & (z <= HI)]
    assert np.all(np.maximum.accumulate(used) - used <= MAX_DIP_V)
    if ends:
        assert np.all(np.diff(v) >= -1e-12)


def test_the_slopes_are_scipys_pchip_and_the_table_holds_beyond_its_knots() -> None:
    from scipy.interpolate import PchipInterpolator

    rng = np.random.default_rng(7)
    for _ in range(200):
        x = np.sort(rng.choice(np.linspace(0.0, 1.0, 201), int(rng.integers(2, 12)), False))
        y = rng.normal(0.0, 0.01, x.shape[0]) * (rng.random(x.shape[0]) < 0.8)
        ref = PchipInterpolator(x, y)
        d = pchip_slopes(x, y)
        np.testing.assert_allclose(d, ref.derivative()(x), rtol=1e-12, atol=1e-12)
        z = np.linspace(x[0], x[-1], 57)
        np.testing.assert_allclose(hermite_table(x, y, d, z, False), ref(z), atol=1e-12)
        np.testing.assert_allclose(hermite_table(x, y, d, z, True), ref.derivative()(z),
                                   rtol=1e-9, atol=1e-9)  # fmt: skip
        out = np.array([x[0] - 0.1, x[-1] + 0.1, np.nan])
        np.testing.assert_array_equal(hermite_table(x, y, d, out, False), [y[0], y[-1], np.nan])
        np.testing.assert_array_equal(hermite_table(x, y, d, out, True), [0.0, 0.0, np.nan])


def test_a_table_must_cover_the_curves_range() -> None:
    x, y = np.array([0.2, 0.4, 0.6]), np.array([0.004, -0.002, 0.003])
    with pytest.raises(ValueError, match=r"knots \(SOC 20-60 %\) must cover .* SOC 3-97 %"):
        OcvModel.from_coeffs(PAPER, LO, HI, [0.0, 1.0], [0.0, 0.0], corr_soc=x, corr_V=y)


def test_the_inverse_and_the_secant_follow_the_table() -> None:
    x = np.linspace(LO, HI, 48)
    y = 0.01 * np.exp(-(((x - 0.5) / 0.05) ** 2))  # a 10 mV bump at 50 %
    m = OcvModel.from_coeffs(PAPER, LO, HI, [0.0, 1.0], [0.0, 0.0], corr_soc=x, corr_V=y)
    for z in (0.2, 0.48, 0.5, 0.55, 0.8):
        v = m.ocv(np.array([z]))
        assert float(m.soc_from_ocv(v)[0]) == pytest.approx(z, abs=5e-4)
        slope, z_to = m.secant_slope(np.array([0.3]), v)
        assert float(z_to[0]) == pytest.approx(z, abs=5e-4) and float(slope[0]) > 0


def test_a_table_that_makes_the_curve_fall_is_refused() -> None:
    x, y = np.array([0.0, 0.4, 0.5, 1.0]), np.array([0.0, 0.1, 0.0, 0.0])  # 100 mV down
    with pytest.raises(ValueError, match=r"falling at SOC 4\d\.\d+ %"):
        OcvModel.from_coeffs(PAPER, LO, HI, [0.0, 1.0], [0.0, 0.0], corr_soc=x, corr_V=y)
    with pytest.raises(ValueError, match="both its knots and its values"):
        OcvModel.from_coeffs(PAPER, LO, HI, [0.0, 1.0], [0.0, 0.0], corr_soc=x)


def test_the_end_segments_join_the_corrected_curve() -> None:
    """The join takes the corrected value and slope: with a table of +20 mV at the join, the
    segment starts 20 mV above Eq. 4 there; one the corrected slope makes impossible is refused
    with the segment's own message."""
    x, y = np.array([0.02, 0.1, 0.5, 0.98]), np.array([0.02, 0.0, 0.0, 0.0])
    m = OcvModel.from_coeffs(PAPER, 0.02, 0.98, [0.0, 1.0], [0.0, 0.0], v_empty_V=3.0,
                             corr_soc=x, corr_V=y)  # fmt: skip
    assert float(m.ocv(np.array([0.02 - 1e-12]))[0]) == pytest.approx(
        float(eval_ocv(PAPER, 0.02)) + 0.02, abs=1e-9
    )
    v_lo = float(eval_ocv(PAPER, 0.02))
    with pytest.raises(ValueError, match=r"the corrected curve's 3\.1310 V at SOC 0\.02 monoton"):
        OcvModel.from_coeffs(PAPER, 0.02, 0.98, [0.0, 1.0], [0.0, 0.0], v_empty_V=v_lo + 0.025,
                             corr_soc=x, corr_V=y)  # fmt: skip


def test_a_config_without_a_table_is_the_curve_as_before() -> None:
    cell = paper_cell()
    assert cell.ocv.correction_soc is None and "correction" not in str(cell.model_dump(
        exclude_none=True))  # fmt: skip
    m = ocv_model(cell)
    assert not m.has_table
    z = np.linspace(0.0, 1.0, 101)
    ref = OcvModel.from_coeffs(PAPER, 0.02, 0.98, [0.0, 1.0], [0.015, 0.015])
    np.testing.assert_array_equal(m.ocv(z), ref.ocv(z))
    np.testing.assert_array_equal(m.docv_dz(z), ref.docv_dz(z))
    np.testing.assert_array_equal(m._inv_v, ref._inv_v)


def test_a_config_table_reaches_the_model() -> None:
    x, y = [0.0, 0.5, 1.0], [0.002, -0.003, 0.001]
    curve = OcvCurve(
        mean=PAPER_OCV_MEAN, soc_min=0.02, soc_max=0.98, correction_soc=x, correction_V=y
    )
    cell = paper_cell().model_copy(update={"ocv": curve})
    m = ocv_model(cell)
    assert m.has_table
    assert float(m.ocv(np.array([0.5]))[0]) == pytest.approx(eval_ocv(PAPER, 0.5) - 0.003)


@pytest.mark.parametrize(
    ("soc", "dv", "message"),
    [
        ([0.1, 0.5, 0.9], None, "correction_soc and ocv.correction_V must be given together"),
        ([0.1, 0.5], [0.0, 0.0], "same length, at least 3"),
        ([0.1, 0.5, 0.9], [0.0, 0.0], "same length, at least 3"),
        ([0.1, 0.5, 0.5], [0.0, 0.0, 0.0], "correction_soc must increase strictly"),
        ([0.1, 0.5, 1.2], [0.0, 0.0, 0.0], "correction_soc must increase strictly"),
        ([10, 50, 90], [0.0, 0.0, 0.0], r"within \[0, 1\] \(fractions\)"),
        ([0.1, 0.5, 0.9], [0.0, 5.0, 0.0], r"correction_V must lie within \+-0.2 V"),
        ([0.1, 0.5, 0.9], [0.0, float("nan"), 0.0], r"correction_V must lie within"),
        ([0.0, 0.4, 0.5, 1.0], [0.0, 0.1, 0.0, 0.0], "correction_V: the OCV correction table le"),
        ([0.1, 0.5, 1.0], [0.0, 0.0, 0.0], "correction_V: the OCV correction table's knots"),
    ],
)
def test_config_tables_are_validated_with_the_field_named(
    soc: list[float], dv: list[float] | None, message: str
) -> None:
    with pytest.raises(ValidationError, match=message):
        OcvCurve(mean=PAPER_OCV_MEAN, soc_min=0.02, soc_max=0.98, correction_soc=soc,
                 correction_V=dv)  # fmt: skip


def test_a_flat_plateau_that_eq4_bends_by_microvolts_is_not_a_fall() -> None:
    # An LFP-like plateau: the corrected knot values equal over SOC 30-70 %. The table's cubic
    # is flat there, and what is left is Eq. 4 bending away from its own cubic between knots: a
    # slightly negative slope, microvolts of dip. A slope test refused it (fit-ocv then dropped
    # the plateau's knots one by one); it is flat to any measurement.
    x = np.linspace(LO, HI, 39)
    total = 3.3 + 0.1 * np.minimum(x - 0.3, 0.0) + 0.1 * np.maximum(x - 0.7, 0.0)
    y = total - eval_ocv(PAPER, x)
    m = OcvModel.from_coeffs(PAPER, LO, HI, [0.0, 1.0], [0.0, 0.0], corr_soc=x, corr_V=y)
    z = np.linspace(0.3, 0.7, 40001)
    v, d = m.ocv(z), m.docv_dz(z)
    assert float(np.min(d)) < -1e-9  # Eq. 4's bend: the slope does dip below 0 ..
    assert float(np.max(np.maximum.accumulate(v) - v)) <= MAX_DIP_V  # .. by microvolts
    assert float(np.ptp(v)) < 1e-4
