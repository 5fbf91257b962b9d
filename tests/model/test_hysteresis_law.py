"""The cell config's hysteresis law (``hysteresis.law``): by chemistry where it is not set, and
carried to the model the engine and the simulator run."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from bmsid.config.cell import load_cell_config, paper_cell
from bmsid.config.engine import cell_model, ocv_model
from bmsid.model.simulator import simulate

A123 = Path(__file__).resolve().parents[2] / "configs" / "cells" / "a123_lfp_25C.toml"


@pytest.mark.parametrize(
    ("chemistry", "law", "want"),
    [("LFP", None, "play"), (" lfp ", None, "play"), ("LiFePO4", None, "play"),
     ("NMC", None, "plett"), ("unknown", None, "plett"), ("LFP", "plett", "plett"),
     ("NMC", "play", "play")],
)  # fmt: skip
def test_the_law_follows_the_chemistry_unless_it_is_set(
    chemistry: str, law: str | None, want: str
) -> None:
    cell = paper_cell()
    cell = cell.model_copy(
        update={"chemistry": chemistry,
                "hysteresis": cell.hysteresis.model_copy(update={"law": law})}
    )  # fmt: skip
    assert cell.hysteresis_law == want
    assert cell_model(cell, 2).hysteresis_play is (want == "play")


def test_the_shipped_lfp_config_runs_the_play_and_its_simulation_stays_at_the_branch() -> None:
    """The A123 config (chemistry LFP): a discharge with short regeneration pulses keeps the
    play's h within 2 kappa x 15 A s (0.12) of -1, where Plett's sits between the branches."""
    cell = load_cell_config(A123)
    assert cell.hysteresis_law == "play"
    t = np.arange(0.0, 3600.0)
    i = np.where(t % 75 < 60, 1.0, -1.0)
    kw = {
        "capacity_Ah": cell.capacity_Ah,
        "R0_ohm": 0.01,
        "R1_ohm": 0.0,
        "tau1_s": 10.0,
        "R2_ohm": 0.0,
        "tau2_s": 100.0,
        "gamma": cell.hysteresis.gamma,
        "soc0": 0.9,
        "h0": 1.0,
    }
    play = simulate(t, i, ocv_model(cell), play=True, **kw)  # type: ignore[arg-type]
    plett = simulate(t, i, ocv_model(cell), **kw)  # type: ignore[arg-type]
    late = t > 1800
    assert play.h[0, late].min() == -1.0 and play.h[0, late].max() < -0.87
    assert -0.75 < plett.h[0, late].mean() < -0.45


def test_an_unlabelled_cell_gets_the_play_where_its_ocv_is_an_lfp_plateau() -> None:
    """``fit-ocv`` without ``--chemistry`` writes ``unknown``: the A123 curve (0.09 V over SOC
    20-80 % around 3.30 V) still gets the play; the NMC curves (0.39-0.57 V) and an unlabelled
    paper cell keep Plett's law; a label other than LFP is taken at its word."""
    a123 = load_cell_config(A123)
    assert a123.model_copy(update={"chemistry": "unknown"}).hysteresis_law == "play"
    assert a123.model_copy(update={"chemistry": ""}).hysteresis_law == "play"
    assert a123.model_copy(update={"chemistry": "LTO"}).hysteresis_law == "plett"
    for name in ("calce_inr18650_20r_25C", "dfn_nmc_lgm50_25C"):
        cell = load_cell_config(A123.parent / f"{name}.toml")
        assert cell.model_copy(update={"chemistry": "unknown"}).hysteresis_law == "plett"
    assert paper_cell().model_copy(update={"chemistry": "unknown"}).hysteresis_law == "plett"
