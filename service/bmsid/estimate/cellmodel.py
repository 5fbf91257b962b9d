"""What the engine knows about the cells it identifies: numbers per cell, no file format.

Built from a cell config by ``bmsid.config.engine.cell_model``; the core never sees a pydantic
model. Every per-cell quantity is an array of shape (n_cells,) so cells of one bank may differ
(a measured capacity per cell, ageing-dependent bounds).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

import numpy as np
import numpy.typing as npt

from bmsid.model.ocv import OcvModel

FloatArray = npt.NDArray[np.float64]

#: Order of the bounded parameters in ``CellModel.lo`` / ``hi`` (ohm, ohm, ohm, s, s, -, V).
BOUNDED = ("R0_ohm", "R1_ohm", "R2_ohm", "tau1_s", "tau2_s", "M_scale", "ocv_offset_V")
#: Order of the start values in ``CellModel.initial`` (ohm, ohm, s, ohm, s).
INITIAL = ("R0_ohm", "R1_ohm", "tau1_s", "R2_ohm", "tau2_s")

SocPolicy = Literal["ocv_at_rest", "fixed"]


@dataclass(frozen=True)
class SocStart:
    """How SOC starts when none is given: ``ocv_at_rest`` inverts the OCV at each cell's first
    valid voltage (IR-corrected when |I| > ``rest_current_C`` x capacity; a cell without one
    waits for it: ``CoulombState.no_data``); ``fixed`` starts every cell at ``soc0`` (a
    fraction; ``fixed`` without ``soc0`` behaves as ``ocv_at_rest``)."""

    policy: SocPolicy = "ocv_at_rest"
    soc0: float | None = None
    rest_current_C: float = 0.01


@dataclass(frozen=True)
class CellModel:
    """Per-cell constants of the model (Eq. 2, 4-9) and of the search.

    Attributes:
        name: cell type, for checkpoints and reports.
        ocv: mean OCV curve and hysteresis table M(z), shared by the cells (one cell type).
        capacity_Ah: capacity per cell, Ah, shape (n,).
        efficiency: coulombic efficiency on charge, shape (n,).
        gamma: Plett's dimensionless hysteresis rate, shape (n,) (kappa = eta gamma / Q).
        hysteresis_play: h moves as a play (backlash) operator instead of Plett's exponential
            (Eq. 5): ``ecm.hysteresis_step``; one cell type, so one law for the pack.
        initial: start values, shape (n, 5), columns ``INITIAL``.
        lo, hi: bounds, shape (n, 7), columns ``BOUNDED``.
        soc_start: how SOC starts when the caller gives none.
    """

    name: str
    ocv: OcvModel
    capacity_Ah: FloatArray
    efficiency: FloatArray
    gamma: FloatArray
    initial: FloatArray
    lo: FloatArray
    hi: FloatArray
    soc_start: SocStart = SocStart()
    hysteresis_play: bool = False

    def __post_init__(self) -> None:
        n = self.capacity_Ah.shape[0]
        shapes = {
            "efficiency": (self.efficiency.shape, (n,)),
            "gamma": (self.gamma.shape, (n,)),
            "initial": (self.initial.shape, (n, len(INITIAL))),
            "lo": (self.lo.shape, (n, len(BOUNDED))),
            "hi": (self.hi.shape, (n, len(BOUNDED))),
        }
        for name, (got, want) in shapes.items():
            if got != want:
                raise ValueError(f"CellModel.{name} has shape {got}, need {want}")
        if not (np.all(self.capacity_Ah > 0) and np.all(self.hi > self.lo)):
            raise ValueError("CellModel needs capacities > 0 and bounds lo < hi")

    @property
    def n_cells(self) -> int:
        return int(self.capacity_Ah.shape[0])

    @property
    def capacity_As(self) -> FloatArray:
        """Capacity in ampere-seconds (the unit of Eq. 2), shape (n,)."""
        return np.asarray(self.capacity_Ah * 3600.0, dtype=np.float64)

    def bound(self, name: str) -> tuple[FloatArray, FloatArray]:
        """(lo, hi) of one parameter of ``BOUNDED``, each shape (n,)."""
        j = BOUNDED.index(name)
        return self.lo[:, j], self.hi[:, j]

    def start(self, name: str) -> FloatArray:
        """Start value of one parameter of ``INITIAL``, shape (n,)."""
        return np.asarray(self.initial[:, INITIAL.index(name)], dtype=np.float64)

    @classmethod
    def uniform(
        cls,
        n_cells: int,
        *,
        name: str,
        ocv: OcvModel,
        capacity_Ah: float,
        efficiency: float,
        gamma: float,
        initial: dict[str, float],
        bounds: dict[str, tuple[float, float]],
        soc_start: SocStart = SocStart(),
        hysteresis_play: bool = False,
    ) -> CellModel:
        """``n_cells`` identical cells from scalars (``initial`` keyed by ``INITIAL``,
        ``bounds`` by ``BOUNDED``)."""

        def col(x: float) -> FloatArray:
            return np.full(n_cells, float(x))

        return cls(
            name=name,
            ocv=ocv,
            capacity_Ah=col(capacity_Ah),
            efficiency=col(efficiency),
            gamma=col(gamma),
            initial=np.tile([float(initial[k]) for k in INITIAL], (n_cells, 1)),
            lo=np.tile([float(bounds[k][0]) for k in BOUNDED], (n_cells, 1)),
            hi=np.tile([float(bounds[k][1]) for k in BOUNDED], (n_cells, 1)),
            soc_start=soc_start,
            hysteresis_play=hysteresis_play,
        )

    def take(self, cells: npt.ArrayLike) -> CellModel:
        """The model of a subset of the cells (indices)."""
        idx = np.asarray(cells, dtype=np.intp)
        return CellModel(
            name=self.name,
            ocv=self.ocv,
            capacity_Ah=self.capacity_Ah[idx],
            efficiency=self.efficiency[idx],
            gamma=self.gamma[idx],
            initial=self.initial[idx],
            lo=self.lo[idx],
            hi=self.hi[idx],
            soc_start=self.soc_start,
            hysteresis_play=self.hysteresis_play,
        )
