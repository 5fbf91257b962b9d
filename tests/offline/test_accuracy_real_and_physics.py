"""The issue's accuracy targets on measured cells and on the PyBaMM physics data.

A representative subset, to keep CI short; ``python bench/accuracy_real.py --physics`` runs every
dataset with the same thresholds. The measured data are read from ``../shared/data/real`` (or
``$BMSID_REAL_DATA``), never copied; a missing folder fails under CI and skips elsewhere.
"""

from __future__ import annotations

from pathlib import Path

import pytest

from bmsid.config.cell import load_cell_config
from bmsid.estimate.observer_tuning import ObserverTuning
from bmsid.estimate.tuning import EstimatorTuning, Variant
from bmsid.offline.identify import IdentifySpec, identify_file
from bmsid.offline.scoring import EvalWindow, SocReference, score

REPO = Path(__file__).resolve().parents[2]
CELLS = REPO / "configs" / "cells"
PHYSICS = REPO / "data" / "physics"


def _rmse(
    path: Path,
    cfg: Path,
    variant: Variant,
    score_soc0: float | None,
    soc0: float | None = None,
    tuning: EstimatorTuning | None = None,
) -> float:
    """Defaults only (the shipped config has no start values or bounds); scored on SOC 95..15 %
    of a coulomb count from the known start, or after the first 10 % of the ticks."""
    cell = load_cell_config(cfg)
    window = (
        EvalWindow(skip_fraction=0.1)
        if score_soc0 is None
        else EvalWindow(soc_lo=0.15, soc_hi=0.95, soc_reference=SocReference.from_cell(
            cell, score_soc0))
    )  # fmt: skip
    res = identify_file(path, IdentifySpec(cell=cell, variant=variant, soc0=soc0, tuning=tuning))
    return score(res.trace, window).window.rmse_V


@pytest.mark.slow
def test_a123_lfp_hysteresis_fusion_beats_the_plain_model(real_data_dir: Path) -> None:
    """RMSE <= 10 mV between 95 % and 15 % SOC (defaults, SOC observer on), and >= 30 % below
    non-hy-affrls in the paper's comparison, where SOC is the plain count of Eq. 2 for every
    variant (issue 15). With the observer, the plain model's SOC absorbs the hysteresis too."""
    path = real_data_dir / "a123_lfp_25C" / "a123_25C_DYN50.csv.gz"
    cfg = CELLS / "a123_lfp_25C.toml"
    assert _rmse(path, cfg, "hy-affrls-lpso", 1.0) <= 10e-3
    paper = EstimatorTuning(observer=ObserverTuning(enabled=False))
    fused = _rmse(path, cfg, "hy-affrls-lpso", 1.0, tuning=paper)
    plain = _rmse(path, cfg, "non-hy-affrls", 1.0, tuning=paper)
    assert fused <= 10e-3
    assert fused <= 0.7 * plain


@pytest.mark.slow
@pytest.mark.parametrize(("profile", "temp"), [("DST", 25), ("BJDST", 45)])
def test_calce_nmc_within_6_mV(real_data_dir: Path, profile: str, temp: int) -> None:
    """OCV from the shipped rest-point tables (configs/cells/README.md), 80 % SOC start."""
    name = f"calce_inr18650-20r_{temp}C_{profile}_80soc.csv.gz"
    path = real_data_dir / "calce_inr18650-20r" / name
    cfg = CELLS / f"calce_inr18650_20r_{temp}C.toml"
    assert _rmse(path, cfg, "hy-affrls-lpso", 0.8, soc0=0.8) <= 6e-3


@pytest.mark.slow
def test_a_swarm_result_with_a_tiny_resistance_does_not_step_the_model(real_data_dir: Path) -> None:
    """CALCE US06 45 C with the observer updating every 60 s: one swarm's window fit had R2 in
    (0, its lower bound); applied clipped with the fit's branch state (the start voltage over
    the tiny R2), the model voltage stepped by 284 mV at once and the run scored 59.7 mV. The
    fusion now keeps that branch's voltage (estimate/fusion.py, _apply_swarm)."""
    path = real_data_dir / "calce_inr18650-20r" / "calce_inr18650-20r_45C_US06_80soc.csv.gz"
    cfg = CELLS / "calce_inr18650_20r_45C.toml"
    tuning = EstimatorTuning(observer=ObserverTuning(update_period_s=60.0))
    assert _rmse(path, cfg, "hy-affrls-lpso", 0.8, soc0=0.8, tuning=tuning) <= 6e-3


@pytest.mark.slow
@pytest.mark.parametrize("name", ["dfn_nmc_dst_15C", "dfn_nmc_bbdst_35C"])
def test_physics_fusion_within_10_mV_and_best(name: str) -> None:
    """OCV fitted by fit-ocv from the C/20 test (configs/cells/dfn_nmc_lgm50_25C.toml)."""
    path = PHYSICS / f"{name}.csv.gz"
    cfg = CELLS / "dfn_nmc_lgm50_25C.toml"
    r = {v: _rmse(path, cfg, v, None) for v in ("non-hy-affrls", "hy-affrls", "hy-affrls-lpso")}
    assert r["hy-affrls-lpso"] <= 10e-3
    assert r["hy-affrls-lpso"] < min(r["hy-affrls"], r["non-hy-affrls"])


@pytest.mark.slow
def test_a_start_still_relaxing_costs_little_without_soc0(real_data_dir: Path) -> None:
    """CALCE US06 25 C from 50 %: the record opens 7 s after a discharge, its voltage climbing
    3.6 mV and 33 mV below the relaxed OCV. Read from the first voltage, no soc0, it scored
    5.09 mV worse than with the start given; with the first rest's climb widening the start
    SOC's uncertainty (estimate/start_relaxation.py), 1.21 mV (bench/starts_real.py)."""
    path = real_data_dir / "calce_inr18650-20r" / "calce_inr18650-20r_25C_US06_50soc.csv.gz"
    cfg = CELLS / "calce_inr18650_20r_25C.toml"
    given = _rmse(path, cfg, "hy-affrls-lpso", 0.5, soc0=0.5)
    free = _rmse(path, cfg, "hy-affrls-lpso", 0.5)
    assert free - given <= 2e-3, (free, given)
