"""Small builders shared by the CAN tests."""

from __future__ import annotations

import can
import numpy as np
import numpy.typing as npt

from bmsid.canbus.logs import csv_to_messages
from bmsid.canbus.mapping import BusMapping

FloatArray = npt.NDArray[np.float64]


def synthetic(
    n: int = 50, n_cells: int = 6, seed: int = 0
) -> tuple[FloatArray, FloatArray, FloatArray]:
    rng = np.random.default_rng(seed)
    t = np.arange(n, dtype=np.float64)
    current = rng.uniform(-40.0, 40.0, n)
    volts = rng.uniform(3.0, 4.2, (n, n_cells))
    return t, current, volts


def frames(
    mapping: BusMapping, n: int = 50, n_cells: int = 6, t0: float = 1000.0
) -> list[can.Message]:
    t, i, v = synthetic(n, n_cells)
    return list(csv_to_messages(t, i, v, mapping, t0_s=t0))
