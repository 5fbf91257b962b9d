"""The bundled demo log (``bmsid/data/demo_pack.log``): a simulated 8-cell pack of the paper's
70 Ah NMC cell under the DST current profile, as bmsid's own CAN frames (candump ``-l``).

Regenerate (deterministic: same bytes every time)::

    python -m bmsid.daemon.demo_data service/bmsid/data/demo_pack.log

The cells share the current and differ in their parameters: one has a 60 % higher R0 (the
"weak cell" the pack summary should point at). The voltage carries 0.5 mV of Gaussian noise and
the 1 mV quantisation of the CAN signal. The pack starts at rest (the SOC is initialised from
the OCV), then runs DST cycles with a peak of 1.5C.
"""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np

from bmsid.canbus.logs import csv_to_messages, write_log
from bmsid.canbus.mapping import default_mapping
from bmsid.config.cell import paper_cell
from bmsid.config.engine import ocv_model
from bmsid.model.simulator import simulate
from bmsid.profiles import dst_current

DEMO_LOG = Path(__file__).resolve().parent.parent / "data" / "demo_pack.log"
N_CELLS = 8
DURATION_S = 3600.0
REST_S = 60.0
RATE_HZ = 1.0
PEAK_C = 1.5
SOC0 = 0.9
WEAK_CELL = 5
#: Unix time of t = 0 in the log, s.
T0_S = 1_700_000_000.0
#: True parameters per cell: R0, R1, tau1, R2, tau2 (ohm, s).
R0_OHM = np.array([1.8, 1.9, 2.0, 2.1, 1.95, 3.2, 2.05, 1.85]) * 1e-3
R1_OHM = np.full(N_CELLS, 0.8e-3)
TAU1_S = np.full(N_CELLS, 12.0)
R2_OHM = np.full(N_CELLS, 1.0e-3)
TAU2_S = np.full(N_CELLS, 400.0)
NOISE_V = 0.5e-3


def demo_arrays(seed: int = 7) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(t_s, current_A, cell_voltages_V (n, N_CELLS)) of the demo pack."""
    cell = paper_cell()
    t = np.arange(0.0, DURATION_S, 1.0 / RATE_HZ)
    i = np.where(t < REST_S, 0.0, dst_current(t - REST_S, PEAK_C * cell.capacity_Ah))
    sim = simulate(
        t,
        i,
        ocv_model(cell),
        capacity_Ah=cell.capacity_Ah,
        R0_ohm=R0_OHM,
        R1_ohm=R1_OHM,
        tau1_s=TAU1_S,
        R2_ohm=R2_OHM,
        tau2_s=TAU2_S,
        gamma=cell.hysteresis.gamma,
        soc0=SOC0,
        n_sets=N_CELLS,
    )
    rng = np.random.default_rng(seed)
    v = sim.v_V.T + rng.normal(0.0, NOISE_V, size=sim.v_V.T.shape)
    return t, i, np.asarray(v)


def write_demo_log(path: Path = DEMO_LOG) -> Path:
    t, i, v = demo_arrays()
    write_log(path, csv_to_messages(t, i, v, default_mapping(), t0_s=T0_S))
    return path


if __name__ == "__main__":
    print(write_demo_log(Path(sys.argv[1]) if len(sys.argv) > 1 else DEMO_LOG))
