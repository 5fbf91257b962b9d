"""One synchronised pack measurement: the unit that flows from the CAN layer to the estimators."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import numpy.typing as npt

FloatArray = npt.NDArray[np.float64]


@dataclass(frozen=True, slots=True)
class Sample:
    """A pack sample at one tick.

    Attributes:
        t_s: sample time in seconds (monotonic within one source).
        current_A: pack current in amperes, positive = discharge.
        cell_voltages_V: terminal voltage of each cell in volts, shape (n_cells,); NaN where a
            cell's value is missing or invalid for this tick.
        temperatures_C: optional temperatures in degrees Celsius (cell or pack sensors).
        counter: optional sample counter carried on the bus.
    """

    t_s: float
    current_A: float
    cell_voltages_V: FloatArray
    temperatures_C: FloatArray | None = None
    counter: int | None = None
    flags: frozenset[str] = field(default_factory=frozenset)

    @property
    def n_cells(self) -> int:
        return int(self.cell_voltages_V.shape[0])
