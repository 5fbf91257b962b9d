"""Honest metrics (``bmsid.offline.scoring``): the whole record, its start-up and the rest, the
SOC bands, the evaluation window, and the reference SOC counted from a known start."""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from test_identify_cli import synthetic_columns, write_csv

from bmsid.config.cell import paper_cell
from bmsid.estimate.fields import FIELD_NAMES
from bmsid.estimate.observer_tuning import ObserverTuning
from bmsid.estimate.tuning import EstimatorTuning
from bmsid.estimate.types import EstimateBlock
from bmsid.metrics import VoltageMetrics
from bmsid.offline.identify import IdentifySpec, identify_file, run_arrays
from bmsid.offline.outputs import error_band_line, summary_line
from bmsid.offline.scoring import (
    SOC_BANDS,
    EvalWindow,
    IdentifyResult,
    SocReference,
    band_index,
    metrics_document,
    reference_soc,
    score,
    startup_ticks,
)

V_CELL = 3.6  # V, the measured voltage of the synthetic traces


def trace(
    err_V: np.ndarray,
    soc: np.ndarray,
    t_s: np.ndarray | None = None,
    current_A: np.ndarray | None = None,
) -> EstimateBlock:
    """A trace whose model voltage misses a constant measured voltage by ``err_V`` (n, cells)."""
    n, nc = err_V.shape
    cells = {k: np.zeros((n, nc)) for k in FIELD_NAMES}
    cells["v_meas_V"] = np.full((n, nc), V_CELL)
    cells["v_model_V"] = V_CELL - err_V
    cells["soc"] = soc
    return EstimateBlock(
        t_s=np.arange(float(n)) if t_s is None else t_s,
        current_A=np.zeros(n) if current_A is None else current_A,
        cells=cells,
        quality=np.zeros((n, nc), dtype=np.int64),
    )


def result(tr: EstimateBlock) -> IdentifyResult:
    names = [f"cell_{c + 1:02d}" for c in range(tr.n_cells)]
    return IdentifyResult("hy-affrls", tr, "given", {}, 1.0, tr.n_ticks, names)


def sse(m: VoltageMetrics) -> float:
    return m.n_samples * m.rmse_V**2


errors = st.floats(-0.5, 0.5, allow_nan=False)
socs = st.one_of(st.floats(-0.3, 1.3), st.sampled_from([0.0, 0.1, 0.3, 0.7, 0.9, 1.0]))


@settings(max_examples=60, deadline=None)
@given(data=st.data(), n=st.integers(1, 60), nc=st.integers(1, 3))
def test_soc_bands_partition_the_ticks(data: st.DataObject, n: int, nc: int) -> None:
    z = np.array(data.draw(st.lists(socs, min_size=n * nc, max_size=n * nc))).reshape(n, nc)
    e = np.array(data.draw(st.lists(errors, min_size=n * nc, max_size=n * nc))).reshape(n, nc)
    k = band_index(z)
    for idx, zz in zip(k.ravel(), z.ravel(), strict=True):  # each tick in the band holding it
        b = SOC_BANDS[idx]
        assert (b.lo is None or zz >= b.lo) and (b.hi is None or zz < b.hi or zz == 1.0)
    s = score(trace(e, z), EvalWindow())
    for part in (s.pooled, *s.cells):
        assert sum(b.metrics.n_samples for b in part.soc_bands) == part.overall.n_samples
        assert sum(sse(b.metrics) for b in part.soc_bands) == pytest.approx(sse(part.overall))
        worst = max(b.metrics.max_abs_error_V for b in part.soc_bands)
        assert worst == part.overall.max_abs_error_V
        assert all(b.metrics.n_samples > 0 for b in part.soc_bands)  # empty bands left out


def test_band_edges() -> None:
    z = np.array([-0.01, 0.0, 0.0999, 0.1, 0.3, 0.7, 0.95, 1.0, 1.01, np.nan])
    labels = [SOC_BANDS[k].label if k >= 0 else None for k in band_index(z)]
    assert labels == [
        "<0 %", "0-10 %", "0-10 %", "10-20 %", "30-40 %", "70-80 %", "90-100 %", "90-100 %",
        ">100 %", None,
    ]  # fmt: skip


@settings(max_examples=60, deadline=None)
@given(data=st.data(), n=st.integers(1, 80), nc=st.integers(1, 3))
def test_whole_record_is_the_startup_and_the_rest_pooled(
    data: st.DataObject, n: int, nc: int
) -> None:
    """n and squared errors add, the max is the larger max, MAPE is the n-weighted mean."""
    e = np.array(data.draw(st.lists(errors, min_size=n * nc, max_size=n * nc))).reshape(n, nc)
    s = score(trace(e, np.full((n, nc), 0.5)), EvalWindow())
    assert s.n_startup_ticks == startup_ticks(n) == math.floor(0.1 * n)
    for part in (s.pooled, *s.cells):
        a, b, whole = part.startup, part.after_startup, part.overall
        assert a.n_samples + b.n_samples == whole.n_samples
        assert sse(a) + sse(b) == pytest.approx(sse(whole), rel=1e-9, abs=1e-15)
        assert max(a.max_abs_error_V, b.max_abs_error_V) == whole.max_abs_error_V
        mape = (a.n_samples * a.mape_pct + b.n_samples * b.mape_pct) / whole.n_samples
        assert mape == pytest.approx(whole.mape_pct, rel=1e-9, abs=1e-12)
    assert s.window == s.overall  # the default window is the whole record


def test_startup_blowup_shows_in_whole_and_startup_not_in_the_rest() -> None:
    n = 1000
    e = np.random.default_rng(0).normal(0.0, 1e-3, (n, 2))
    e[:100] += 0.2  # the estimator blew up in its first 10 % of the ticks
    doc = metrics_document(result(trace(e, np.full((n, 2), 0.5))), EvalWindow())
    for part in (doc, *doc["cells"].values()):
        assert part["startup"]["rmse_V"] > 0.19
        assert part["overall"]["rmse_V"] > 0.06  # sqrt(0.1) x 0.2 V
        assert part["after_startup"]["rmse_V"] < 1.5e-3
        assert part["after_startup"]["max_abs_error_V"] < 5e-3
        assert part["startup"]["n_ticks"] == 100 and part["after_startup"]["n_ticks"] == 900
        assert part["rmse_V"] == part["overall"]["rmse_V"]  # default window: every tick
    skipped = metrics_document(result(trace(e, np.full((n, 2), 0.5))), EvalWindow(0.1))
    assert skipped["rmse_V"] == doc["after_startup"]["rmse_V"]  # the old default's number
    assert skipped["overall"] == doc["overall"]


def test_score_soc0_is_a_hand_coulomb_count() -> None:
    """Held current until the next tick, the efficiency on charge only, no charge across a gap
    (> 30 s) or a step back in time; + = discharge."""
    t = np.array([0.0, 1.0, 2.5, 3.0, 100.0, 101.0, 50.0, 52.0])
    i = np.array([2.0, -1.0, 3.0, 0.5, 1.0, -2.0, 4.0, 1.0])
    cap_Ah, eta, z0 = 0.01, 0.9, 0.8
    want = [z0]
    for k in range(t.size - 1):
        dt = t[k + 1] - t[k]
        if dt <= 0 or dt > 30.0:
            dt = 0.0
        q = i[k] * dt * (eta if i[k] < 0 else 1.0)
        want.append(want[-1] - q / (cap_Ah * 3600.0))
    np.testing.assert_allclose(reference_soc(t, i, z0, cap_Ah, eta), want, rtol=0, atol=1e-15)
    ref = SocReference(z0, cap_Ah, eta)
    np.testing.assert_allclose(ref.soc(trace(np.zeros((8, 1)), np.zeros((8, 1)), t, i)), want)
    assert reference_soc(np.zeros(0), np.zeros(0), z0, cap_Ah).shape == (0,)
    with pytest.raises(ValueError, match="fraction"):
        SocReference(1.5, cap_Ah)


def test_score_soc0_equals_the_estimators_count_from_the_same_start() -> None:
    """1 s samples, one tick each: the reference is the estimator's own (unclamped) count when
    no observer corrects it from the voltage."""
    n = 600
    t = np.arange(float(n))
    i = 70.0 * np.sin(t / 40.0)  # charge and discharge of the paper's 70 Ah cell
    cell = paper_cell()
    count_only = EstimatorTuning(observer=ObserverTuning(enabled=False))
    # a voltage that answers the current (a constant one under load is a frozen front end: the
    # gates refuse it, and a cell without valid readings is published no_data)
    v = 3.7 - 1.5e-3 * i
    res = run_arrays(t, i, v, cell, "non-hy-affrls", count_only, soc0=0.9)
    ref = SocReference.from_cell(cell, 0.9).soc(res.trace)
    np.testing.assert_allclose(ref, res.trace["soc"][:, 0], rtol=0, atol=1e-12)


def test_windows_and_bands_follow_the_reference_soc() -> None:
    """The estimator believes 50 % throughout; the count from a full start says 100 -> 0 %."""
    n = 1000
    cap_Ah = n / 3600.0  # 1 A for 1000 s empties it
    e = np.full((n, 1), 1e-3)
    tr = trace(e, np.full((n, 1), 0.5), current_A=np.ones(n))
    ref = SocReference(1.0, cap_Ah)
    window = EvalWindow(soc_lo=0.15, soc_hi=0.95, soc_reference=ref)
    doc = metrics_document(result(tr), window)
    z = ref.soc(tr)
    assert doc["n_samples"] == int(np.sum((z >= 0.15) & (z <= 0.95)))
    assert abs(doc["n_samples"] - 800) <= 1  # counted SOC 95 ... 15 %, 1 s at 0.1 % each
    assert doc["scoring_soc"]["source"] == doc["evaluation_window"]["soc_source"] == "coulomb_count"
    assert doc["scoring_soc"]["soc0"] == 1.0 and doc["scoring_soc"]["capacity_Ah"] == cap_Ah
    assert doc["scoring_soc"]["soc_max"] == 1.0 and doc["scoring_soc"]["soc_min"] < 0.002
    assert [b["band"] for b in doc["soc_bands"]] == [b.label for b in SOC_BANDS[1:11]]
    assert "coulomb count" in doc["evaluation_window"]["description"]
    own = metrics_document(result(tr), EvalWindow(soc_lo=0.15, soc_hi=0.95))
    assert own["scoring_soc"]["source"] == "estimator"
    assert own["n_samples"] == n  # the estimator's 50 % is always inside
    assert [b["band"] for b in own["soc_bands"]] == ["50-60 %"]
    json.dumps(doc, allow_nan=False)  # strict JSON


def test_metrics_json_records_the_scoring_soc(tmp_path: Path) -> None:
    """identify_file with a count from 95 % (the simulation's start) writes which SOC decided."""
    src = write_csv(tmp_path / "syn.csv", synthetic_columns(600))
    cell = paper_cell()
    ref = SocReference.from_cell(cell, 0.95)
    window = EvalWindow(soc_lo=0.9, soc_hi=0.94, soc_reference=ref)
    spec = IdentifySpec(cell=cell, variant="non-hy-affrls", soc0=0.5, window=window)
    identify_file(src, spec, tmp_path / "out")
    doc = json.loads((tmp_path / "out" / "metrics.json").read_text(encoding="utf-8"))
    assert doc["scoring_soc"]["source"] == "coulomb_count"
    assert doc["scoring_soc"]["soc_first"] == 0.95
    assert doc["evaluation_window"]["soc_lo"] == 0.9
    soc_true = synthetic_columns(600)["soc_true"]
    assert abs(doc["n_samples"] - int(np.sum((soc_true >= 0.9) & (soc_true <= 0.94)))) <= 1
    assert 0 < doc["n_samples"] < 600  # the estimator's 50 % would have scored nothing


def test_default_window_is_the_whole_record() -> None:
    assert EvalWindow().is_whole_record and EvalWindow().describe() == "all ticks"
    assert IdentifySpec(cell=paper_cell()).window == EvalWindow()
    assert not EvalWindow(0.1).is_whole_record
    assert not EvalWindow(soc_lo=0.2).is_whole_record


def test_a_soc_band_holding_most_of_the_error_is_named() -> None:
    """200 ticks from SOC 100 % to 0 %, 1 mV of error but in the last 20 (SOC 0-10 %): 50 mV
    there holds 99.6 % of the squared error and is named, so is 5 mV (74 %, 5x the rest's);
    2 mV (31 %) and an even error are not."""
    n = 200
    for err_mV, named in ((50.0, True), (5.0, True), (2.0, False), (1.0, False)):
        e = np.full((n, 1), 1e-3)
        e[-20:] = err_mV * 1e-3
        tr = trace(e, np.linspace(1.0, 0.0, n)[:, None])
        line = error_band_line(metrics_document(result(tr), EvalWindow()))
        assert (line is not None) == named, (err_mV, line)
    e = np.full((n, 1), 1e-3)
    e[-20:] = 0.05
    line = error_band_line(metrics_document(result(trace(e, np.linspace(1.0, 0.0, n)[:, None])),
                                            EvalWindow()))  # fmt: skip
    assert line == (
        "most of the model error lies at SOC 0-10 %: 50.0 mV RMSE over its 20 ticks, 100 % of the "
        "squared error; 1.00 mV over the other 180 (metrics.json soc_bands)"
    )


def test_summary_line_gives_the_whole_record_and_the_startup() -> None:
    n = 200
    e = np.full((n, 1), 1e-3)
    e[:20] = 0.1
    tr = trace(e, np.linspace(1.0, 0.0, n)[:, None])
    line = summary_line(metrics_document(result(tr), EvalWindow()))
    assert line.startswith("hy-affrls: RMSE 31.64 mV over all 200 ticks (max 100.0 mV")
    assert "first 10 % 100.00 mV, after it 1.00 mV" in line
    assert "window" not in line
    line = summary_line(metrics_document(result(tr), EvalWindow(soc_lo=0.15, soc_hi=0.85)))
    assert "window (estimated SOC within 15-85 %) 1.00 mV over 140 ticks" in line
