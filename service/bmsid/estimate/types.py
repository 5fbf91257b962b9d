"""What an estimator bank reports: one tick (:class:`Estimates`) or many (:class:`EstimateBlock`).

Both hold the per-cell fields of :data:`~bmsid.estimate.fields.CELL_FIELDS` by name, so adding a
field to that table needs no change here.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from enum import IntEnum

import numpy as np
import numpy.typing as npt

from bmsid.estimate.fields import FIELD_NAMES
from bmsid.estimate.tuning import VARIANTS_T

FloatArray = npt.NDArray[np.float64]
IntArray = npt.NDArray[np.int64]


class Quality(IntEnum):
    """Quality flag of an estimate (also the CAN/MQTT code)."""

    CONVERGING = 0  #: not enough excitation seen yet; parameters are still the start values
    CONVERGED = 1  #: estimates settled and the model tracks the cell
    POORLY_EXCITED = 2  #: current carries too little information (rest, constant current)
    OUT_OF_BOUNDS = 3  #: a parameter hit its configured bound; the last good values are published
    #: the model error stayed far beyond its running scale, or SOC left [0, 1] (or a value was not
    #: finite): the last good values are published, the cell re-initialised (``estimate/guard.py``)
    DIVERGED = 4
    #: no valid reading of the cell since its (re)start, or none for ``gap_s``: its SOC is
    #: unknown (or unchecked), every field is null (NaN) and the cell counts in no pack
    #: aggregate (``CoulombState.no_data``, ``lost_readings.ReadingWatch``)
    NO_DATA = 5


@dataclass(frozen=True, slots=True)
class Estimates:
    """Identified parameters and model outputs of ``n`` cells at time ``t_s`` (s).

    ``cells[name]`` has shape (n_cells,) for every name of ``CELL_FIELDS`` (units there) and is
    also an attribute: ``est.R0_ohm``. Branch 1 is the fast RC branch (``tau1_s < tau2_s``).
    ``v_model_V`` is the a-priori model voltage (states propagated from the current only, with
    the parameters identified up to the previous tick; Eq. 9); ``v_meas_V`` the measured one.
    ``current_A`` is the tick's mean pack current (A, + = discharge).
    """

    t_s: float
    current_A: float
    cells: Mapping[str, FloatArray]
    quality: IntArray

    def __getattr__(self, name: str) -> FloatArray:
        try:
            return self.cells[name]
        except KeyError:
            raise AttributeError(name) from None

    def __getitem__(self, name: str) -> FloatArray:
        return self.cells[name]

    @property
    def n_cells(self) -> int:
        return int(self.quality.shape[0])


@dataclass(frozen=True, slots=True)
class EstimateBlock:
    """The estimates of consecutive ticks as columns (the bank's output for a sample block).

    ``t_s`` and ``current_A`` (tick mean, A, + = discharge) have shape (n_ticks,); every
    ``cells[name]`` and ``quality`` have shape (n_ticks, n_cells), units as in ``CELL_FIELDS``.
    """

    t_s: FloatArray
    current_A: FloatArray
    cells: Mapping[str, FloatArray]
    quality: IntArray

    @property
    def n_ticks(self) -> int:
        return int(self.t_s.shape[0])

    @property
    def n_cells(self) -> int:
        return int(self.quality.shape[1])

    def __len__(self) -> int:
        return self.n_ticks

    def __getitem__(self, name: str) -> FloatArray:
        return self.cells[name]

    def row(self, k: int) -> Estimates:
        """Tick ``k`` (negative counts from the end) as :class:`Estimates` (views)."""
        return Estimates(
            t_s=float(self.t_s[k]),
            current_A=float(self.current_A[k]),
            cells={name: col[k] for name, col in self.cells.items()},
            quality=self.quality[k],
        )

    def rows(self) -> list[Estimates]:
        return [self.row(k) for k in range(self.n_ticks)]

    def select(self, index: slice | npt.ArrayLike) -> EstimateBlock:
        """The ticks at ``index`` (a slice, a boolean mask or indices)."""
        idx = index if isinstance(index, slice) else np.asarray(index)
        return EstimateBlock(
            t_s=self.t_s[idx],
            current_A=self.current_A[idx],
            cells={name: col[idx] for name, col in self.cells.items()},
            quality=self.quality[idx],
        )

    @classmethod
    def empty(cls, n_cells: int, names: Sequence[str] = FIELD_NAMES) -> EstimateBlock:
        return cls(
            t_s=np.zeros(0),
            current_A=np.zeros(0),
            cells={k: np.zeros((0, n_cells)) for k in names},
            quality=np.zeros((0, n_cells), dtype=np.int64),
        )

    @classmethod
    def from_rows(cls, rows: Sequence[Estimates], n_cells: int) -> EstimateBlock:
        if not rows:
            return cls.empty(n_cells)
        names = list(rows[0].cells)
        return cls(
            t_s=np.array([e.t_s for e in rows], dtype=np.float64),
            current_A=np.array([e.current_A for e in rows], dtype=np.float64),
            cells={k: np.stack([e.cells[k] for e in rows]).astype(np.float64) for k in names},
            quality=np.stack([e.quality for e in rows]).astype(np.int64),
        )

    @classmethod
    def concat(cls, blocks: Sequence[EstimateBlock], n_cells: int) -> EstimateBlock:
        blocks = [b for b in blocks if b.n_ticks]
        if not blocks:
            return cls.empty(n_cells)
        if len(blocks) == 1:
            return blocks[0]
        return cls(
            t_s=np.concatenate([b.t_s for b in blocks]),
            current_A=np.concatenate([b.current_A for b in blocks]),
            cells={k: np.concatenate([b.cells[k] for b in blocks]) for k in blocks[0].cells},
            quality=np.concatenate([b.quality for b in blocks]),
        )


#: The paper's three variants (``bmsid.estimate.bank.VARIANT_STAGES`` composes each).
VARIANTS = VARIANTS_T
