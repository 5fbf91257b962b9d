"""A cell whose R0 and R1 follow a daily temperature swing at 50 kJ/mol where the engine's prior
is 30 (``estimate/arrhenius.py``): one day of the multi-day known truth through ``identify``, no
start values, no bounds. Under the evening's constant-current charge R0 is not excited and
follows the law from what the drive left, so it is as good as the window fits' R0 (taken to the
temperature now) and the activation energy learnt from them."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from bmsid.config.cell import save_cell_config
from bmsid.offline.identify import IdentifySpec, identify_file, run_arrays
from bmsid.offline.inputs import load_config
from bmsid.offline.outputs import temperature_law_text
from bmsid.offline.scoring import EvalWindow, metrics_document
from bmsid.synthetic import paper_dst_case
from bmsid.synthetic.multiday import (
    MultidayOptions,
    Phase,
    generate,
    reference_cell,
    write_record,
)


def test_r0_under_the_evening_charge_follows_a_temperature_law_learnt_from_the_drives(
    tmp_path: Path,
) -> None:
    """16 h from 07:00 (+-8 degC, warmest at 15:00): the two drives 7 K apart teach B; the
    charge at 20:00 cools 25 -> 22 degC. R0's median error under the charge 3.4 %, in the
    drives 0.7 % (7.8 and 1.5 % with the window fits' R0 at the window's temperature and B
    learnt from R0 tick by tick, where the carry with the prior's B had already moved it)."""
    opt = MultidayOptions(
        n_days=1, duration_s=16 * 3600, temp_swing_C=8.0, activation_energy_J_mol=50_000.0
    )
    rec = generate(opt)
    write_record(rec, tmp_path / "record.csv.gz", tmp_path / "truth.npz")
    cell = reference_cell().model_copy(update={"initial": None, "bounds": None})
    save_cell_config(cell, tmp_path / "cell.toml")
    spec = IdentifySpec(cell=load_config(tmp_path / "cell.toml"), variant="hy-affrls-lpso")
    res = identify_file(tmp_path / "record.csv.gz", spec)
    trace = res.kept_trace()
    tr = rec.truth
    k = np.clip(np.searchsorted(tr.t_s, trace.t_s, side="right") - 1, 0, tr.t_s.shape[0] - 1)
    err = np.abs(np.asarray(trace["R0_ohm"][:, 0]) / tr.R0_ohm[k] - 1.0)
    charge = tr.phase[k] == Phase.CHARGE
    drive = (tr.phase[k] == Phase.DRIVE) & (trace.t_s > 3600.0)
    assert charge.sum() > 3000 and drive.sum() > 3000
    assert np.median(err[charge]) < 0.05
    assert np.median(err[drive]) < 0.01
    # the law's activation energy, reported (metrics.json, the console): 50.4 kJ/mol, one pair
    assert res.activation_energy_J_mol is not None and res.counters["arrhenius_pairs"] >= 1
    assert abs(res.activation_energy_J_mol[0] / 50_000.0 - 1.0) < 0.1
    assert temperature_law_text(res) is not None
    doc = metrics_document(res, EvalWindow())
    assert doc["activation_energy_J_mol"] == [float(res.activation_energy_J_mol[0])]


def test_without_a_moving_temperature_no_law_is_reported() -> None:
    """The paper's DST case has no temperature column: no activation energy in the results."""
    run = paper_dst_case(1500)
    res = run_arrays(run.t_s, run.current_A, run.voltages_V, run.cell, "hy-affrls-lpso", soc0=0.98)
    assert res.activation_energy_J_mol is None and temperature_law_text(res) is None
    assert metrics_document(res, EvalWindow())["activation_energy_J_mol"] is None
