"""Pack measurements, the unit that flows from the CAN layer and the file readers to the engine.

Two shapes of the same data: :class:`Sample`, one synchronised pack measurement (what a decoder
completes), and :class:`SampleBlock`, consecutive samples as columns (what the estimator bank
consumes, the daemon's worker receives and the offline readers yield).
"""

from __future__ import annotations

from collections.abc import Sequence
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


@dataclass(frozen=True, slots=True)
class SampleBlock:
    """Consecutive pack samples as columns: what the estimator bank consumes.

    Only what the bank reads is carried (the pack temperature included: the mean of the
    sample's sensors); the bus counter and the decoder's flags stay with the decoder. As
    columns, a backlog of blocks costs the garbage collector nothing (numpy arrays are not
    tracked; 50k queued ``Sample`` objects cost ~55 ms per full collection on the daemon's
    loop) and a block pickles to the bank worker in one piece.

    Attributes:
        t_s: sample times in seconds, shape (n,).
        current_A: pack current in amperes, positive = discharge, shape (n,).
        cell_voltages_V: cell terminal voltages in volts, NaN where missing, shape (n, n_cells).
        t_complete_mono: monotonic time in seconds at which each sample was complete (the
            start of the daemon's publish latency), shape (n,); None offline.
        temperature_C: pack temperature in degC (mean of the sample's sensors), NaN where none,
            shape (n,); None when the source has no temperature at all.
    """

    t_s: FloatArray
    current_A: FloatArray
    cell_voltages_V: FloatArray
    t_complete_mono: FloatArray | None = None
    temperature_C: FloatArray | None = None

    def __post_init__(self) -> None:
        n = self.t_s.shape[0]
        if self.cell_voltages_V.ndim != 2:
            raise ValueError("cell_voltages_V must have shape (n_samples, n_cells)")
        if self.current_A.shape != (n,) or self.cell_voltages_V.shape[0] != n:
            raise ValueError("t_s, current_A and cell_voltages_V need the same number of samples")
        if self.t_complete_mono is not None and self.t_complete_mono.shape != (n,):
            raise ValueError("t_complete_mono needs one value per sample")
        if self.temperature_C is not None and self.temperature_C.shape != (n,):
            raise ValueError("temperature_C needs one value per sample")

    def __len__(self) -> int:
        return int(self.t_s.shape[0])

    @property
    def n_cells(self) -> int:
        return int(self.cell_voltages_V.shape[1])

    @classmethod
    def from_arrays(
        cls,
        t_s: npt.ArrayLike,
        current_A: npt.ArrayLike,
        cell_voltages_V: npt.ArrayLike,
        temperature_C: npt.ArrayLike | None = None,
    ) -> SampleBlock:
        """A block from columns (voltages (n,) for one cell or (n, n_cells)), as float64."""
        v = np.asarray(cell_voltages_V, dtype=np.float64)
        return cls(
            t_s=np.asarray(t_s, dtype=np.float64).reshape(-1),
            current_A=np.asarray(current_A, dtype=np.float64).reshape(-1),
            cell_voltages_V=v[:, None] if v.ndim == 1 else v,
            temperature_C=(
                None if temperature_C is None
                else np.asarray(temperature_C, dtype=np.float64).reshape(-1)
            ),
        )  # fmt: skip

    @classmethod
    def from_samples(
        cls, samples: Sequence[Sample], t_complete_mono: Sequence[float] | None = None
    ) -> SampleBlock:
        if not samples or (t_complete_mono is not None and len(samples) != len(t_complete_mono)):
            raise ValueError("a block needs a sample, and one completion time per sample")
        return cls(
            t_s=np.fromiter((s.t_s for s in samples), np.float64, len(samples)),
            current_A=np.fromiter((s.current_A for s in samples), np.float64, len(samples)),
            cell_voltages_V=np.stack([s.cell_voltages_V for s in samples]).astype(
                np.float64, copy=False
            ),
            t_complete_mono=(
                None if t_complete_mono is None else np.asarray(t_complete_mono, dtype=np.float64)
            ),
            temperature_C=_pack_temperatures(samples),
        )

    @classmethod
    def concat(cls, blocks: Sequence[SampleBlock]) -> SampleBlock:
        if len(blocks) == 1:
            return blocks[0]
        monos = [b.t_complete_mono for b in blocks]
        temps = [b.temperature_C for b in blocks]
        return cls(
            t_s=np.concatenate([b.t_s for b in blocks]),
            current_A=np.concatenate([b.current_A for b in blocks]),
            cell_voltages_V=np.concatenate([b.cell_voltages_V for b in blocks]),
            t_complete_mono=(
                None
                if any(m is None for m in monos)
                else np.concatenate([m for m in monos if m is not None])
            ),
            temperature_C=(
                None
                if all(x is None for x in temps)
                else np.concatenate(
                    [
                        np.full(len(b), np.nan) if x is None else x
                        for b, x in zip(blocks, temps, strict=True)
                    ]
                )
            ),
        )

    def slice(self, start: int, stop: int) -> SampleBlock:
        """Samples ``start:stop`` (views, no copy)."""
        m, temp = self.t_complete_mono, self.temperature_C
        return SampleBlock(
            self.t_s[start:stop],
            self.current_A[start:stop],
            self.cell_voltages_V[start:stop],
            None if m is None else m[start:stop],
            None if temp is None else temp[start:stop],
        )


def _pack_temperatures(samples: Sequence[Sample]) -> FloatArray | None:
    """Per sample the mean of its finite temperatures, degC (NaN: none); None if no sample
    carries any."""
    if all(s.temperatures_C is None for s in samples):
        return None
    out = np.full(len(samples), np.nan)
    for k, s in enumerate(samples):
        if s.temperatures_C is not None:
            fin = s.temperatures_C[np.isfinite(s.temperatures_C)]
            if fin.size:
                out[k] = float(fin.mean())
    return out
