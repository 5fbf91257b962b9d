"""An OCV read off the record when no config is given and the record is not NMC-like
(offline/pseudo_ocv.py, cli/identify.py).

The record: an LFP cell (the shipped A123 config's fit-ocv curve, a repository file, not the
measured data) on DST at 3C peak (0.37C mean) from a rest at full to the cut-off, 1 s, 1 mV of
noise.
"""

from __future__ import annotations

import functools
import json
from pathlib import Path

import numpy as np
import numpy.typing as npt
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from bmsid.cli.main import main
from bmsid.config.cell import load_cell_config, paper_cell, save_cell_config
from bmsid.config.engine import ocv_model
from bmsid.model.ocv import eval_docv_dz, eval_ocv
from bmsid.model.simulator import simulate
from bmsid.offline import plausibility as pl
from bmsid.offline.csvio import TesterData, write_tester_csv
from bmsid.offline.pseudo_ocv import MIN_SPAN, pseudo_ocv
from bmsid.profiles import dst_current

FloatArray = npt.NDArray[np.float64]
LFP = load_cell_config(Path(__file__).resolve().parents[2] / "configs/cells/a123_lfp_25C.toml")
Q_AH, R0, R1, R2 = 2.0, 0.010, 0.006, 0.008


@functools.cache
def lfp_record() -> tuple[FloatArray, FloatArray, FloatArray]:
    n = 12000
    t = np.arange(n, dtype=np.float64)
    i = np.where(t < 120, 0.0, dst_current(t - 120, 3.0 * Q_AH))
    sim = simulate(
        t, i, ocv_model(LFP), capacity_Ah=Q_AH, gamma=30.0, soc0=1.0,
        R0_ohm=R0, R1_ohm=R1, tau1_s=20.0, R2_ohm=R2, tau2_s=400.0,
    )  # fmt: skip
    v = sim.v_V[0] + np.random.default_rng(3).normal(0.0, 1e-3, n)
    assert np.any(v <= 2.6), "the record must reach the cut-off"
    end = int(np.argmax(v <= 2.6)) + 1
    return t[:end], i[:end], v[:end]


def test_the_record_is_lfp_like_and_its_capacity_is_read() -> None:
    t, i, v = lfp_record()
    est = pl.derive_capacity(t, i, v)
    assert est is not None and est.chemistry == "LFP"
    assert est.capacity_Ah == pytest.approx(Q_AH, rel=0.05)


def test_the_pseudo_ocv_is_the_curve_less_the_mean_polarisation() -> None:
    """Within the fitted range the curve rises, and it lies within the mean current x (R1 + R2)
    plus a few mV of the true discharge branch (OCV - M: one direction, h at -1) over 20-80 %
    (the plateau the run lives on)."""
    t, i, v = lfp_record()
    ps = pseudo_ocv(t, i, v, Q_AH, 1.0, gap_s=30.0)
    assert ps is not None
    c = ps.curve
    assert c.soc_min >= 0.05 and c.soc_max <= 0.95 and c.soc_max - c.soc_min >= MIN_SPAN
    z = np.linspace(0.2, 0.8, 61)
    assert np.all(eval_docv_dz(c.mean, np.linspace(c.soc_min, c.soc_max, 101)) > 0)
    true = ocv_model(LFP).ocv(z) - ocv_model(LFP).hysteresis_M(z)
    pseudo = eval_ocv(c.mean, z)
    allowance = float(np.mean(np.abs(i))) * (R1 + R2) + 0.005
    assert np.max(np.abs(pseudo - true)) <= allowance, np.max(np.abs(pseudo - true))
    assert ps.r0_ohm == pytest.approx(R0, rel=0.2)


def test_a_discharge_over_too_little_soc_gives_none() -> None:
    t, i, v = lfp_record()
    k = int(np.argmax(np.cumsum(i) / 3600 / Q_AH >= 0.3))  # 30 % of the capacity
    assert pseudo_ocv(t[:k], i[:k], v[:k], Q_AH, 1.0, gap_s=30.0) is None


def _rmse(tmp_path: Path, name: str, *extra: str) -> tuple[float, str]:
    t, i, v = lfp_record()
    src = tmp_path / "lfp.csv"
    write_tester_csv(TesterData(t, i, v[:, None], ["voltage_V"]), src)
    out = tmp_path / name
    assert main(["identify", str(src), "--out", str(out), "-q", *extra]) == 0
    m = json.loads((out / "metrics.json").read_text())
    return float(m["rmse_V"]), str(m["cell_config"])


def test_without_a_config_an_lfp_record_runs_on_its_own_pseudo_ocv(tmp_path: Path) -> None:
    """The paper's NMC curve at the capacity read off cannot follow an LFP plateau; the curve
    read off the record can (both measured: see the asserts' messages)."""
    own, note = _rmse(tmp_path, "own")
    assert "pseudo-OCV" in note
    nmc_cfg = tmp_path / "nmc.toml"
    save_cell_config(paper_cell().model_copy(update={"capacity_Ah": Q_AH}), nmc_cfg)
    nmc, _ = _rmse(tmp_path, "nmc", "--cell-config", str(nmc_cfg))
    assert own <= 0.02, f"pseudo-OCV run {1e3 * own:.1f} mV"
    assert own <= 0.5 * nmc, f"pseudo-OCV {1e3 * own:.1f} mV vs NMC curve {1e3 * nmc:.1f} mV"


def test_a_fleet_without_a_config_reads_each_inputs_cell_as_a_single_run(tmp_path: Path) -> None:
    """An LFP record and a part-charged NMC discharge in one fleet run, no config: each input's
    metrics.json names the cell read off it, as ``bmsid identify`` of that file alone does."""
    from test_plausibility import part_charged_discharge

    t, i, v = lfp_record()
    write_tester_csv(TesterData(t, i, v[:, None], ["voltage_V"]), tmp_path / "lfp.csv")
    t, i, v = part_charged_discharge(0.8)
    write_tester_csv(TesterData(t, i, v[:, None], ["voltage_V"]), tmp_path / "nmc.csv")
    files = [str(tmp_path / "lfp.csv"), str(tmp_path / "nmc.csv")]
    fast = ["--algorithm", "non-hy-affrls", "-q"]
    fleet_out = str(tmp_path / "fleet")
    assert main(["identify", *files, "--out", fleet_out, "--workers", "1", *fast]) == 0
    fleet_notes = {
        p.parent.name: json.loads(p.read_text())["cell_config"]
        for p in (tmp_path / "fleet").glob("*/metrics.json")
    }
    assert len(fleet_notes) == 2
    for f in files:
        out = tmp_path / ("one_" + Path(f).stem)
        assert main(["identify", f, "--out", str(out), *fast]) == 0
        single = json.loads((out / "metrics.json").read_text())["cell_config"]
        assert single in fleet_notes.values(), (single, fleet_notes)
    texts = " | ".join(fleet_notes.values())
    assert "pseudo-OCV" in texts and "on the assumed OCV) to the cut-off" in texts


@settings(max_examples=60, deadline=None)
@given(
    n=st.integers(10, 400),
    seed=st.integers(0, 2**32 - 1),
    nan_share=st.sampled_from([0.0, 0.01, 0.2]),
    start_soc=st.floats(0.0, 1.2),
    discharge=st.booleans(),
)
def test_any_record_gives_none_or_a_rising_curve(
    n: int, seed: int, nan_share: float, start_soc: float, discharge: bool
) -> None:
    """Random currents and voltages (or a noisy discharge through the paper's curve), NaN
    among them: never an exception, and a curve only when it rises over its SOC range, which
    lies within [0.05, 0.95]."""
    rng = np.random.default_rng(seed)
    t = np.cumsum(rng.uniform(0.5, 20.0 if discharge else 60.0, n))
    if discharge:  # ~1C steps of a 1 Ah cell, so the record spans most of the capacity
        i = np.where(rng.random(n) < 0.3, 0.0, rng.uniform(0.5, 2.0, n))
        z = np.clip(1.0 - np.cumsum(i * np.diff(t, prepend=t[0])) / 3600.0, 0.01, 0.99)
        v = eval_ocv(paper_cell().ocv.mean, z) - 0.05 * i + rng.normal(0.0, 0.003, n)
    else:
        i = rng.normal(1.0, 3.0, n)
        v = 3.3 - 0.001 * np.cumsum(i) + rng.normal(0.0, 0.01, n)
    i[rng.random(n) < nan_share] = np.nan
    v[rng.random(n) < nan_share] = np.nan
    ps = pseudo_ocv(t, i, v, 1.0, start_soc, gap_s=30.0)
    if ps is None:
        return
    c = ps.curve
    assert 0.05 <= c.soc_min < c.soc_max <= 0.95
    assert np.all(eval_docv_dz(c.mean, np.linspace(c.soc_min, c.soc_max, 101)) > 0)
    assert np.isfinite(ps.rmse_V) and np.isfinite(ps.r0_ohm) and ps.r0_ohm > 0
