"""Result files written block by block as identification runs (``params.csv``).

The columns are ``t_s,cell``, the ``out_key`` of every field of
:data:`~bmsid.estimate.fields.CELL_FIELDS` in table order, then ``quality``; one row per tick and
cell (for each tick, every cell). A writer appends each :class:`EstimateBlock` as it comes, so a
run's memory does not grow with the length of its output.
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path
from types import TracebackType
from typing import TextIO

import numpy as np
import numpy.typing as npt

from bmsid.estimate import fields
from bmsid.estimate.fields import QUALITY_KEY
from bmsid.estimate.types import EstimateBlock

StrArray = npt.NDArray[np.str_]


class ParamsCsvWriter:
    """``params.csv``: created (or truncated) with its header at construction, rows appended.

    The columns are fixed when the writer is made (``CELL_FIELDS`` read then), so every row
    matches the header. Times are written with ``%.6f`` (s), fields with their ``fmt`` (SI units
    of the table), quality as its integer code.
    """

    def __init__(self, path: Path, cell_names: Sequence[str]) -> None:
        self.path = path
        self._fields = tuple(fields.CELL_FIELDS)
        self._cells: StrArray = np.asarray(list(cell_names), dtype=np.str_)
        header = ["t_s", "cell", *(s.out_key for s in self._fields), QUALITY_KEY]
        self._fh: TextIO | None = path.open("w", encoding="utf-8")
        self._fh.write(",".join(header) + "\n")

    def append(self, block: EstimateBlock) -> None:
        """Write the rows of ``block``'s ticks (tick by tick, every cell of a tick in order)."""
        if self._fh is None:
            raise ValueError(f"{self.path}: writer is closed")
        if block.n_ticks == 0:
            return
        if block.n_cells != self._cells.shape[0]:
            raise ValueError(
                f"{self.path}: block has {block.n_cells} cells, the file {self._cells.shape[0]}"
            )
        missing = [s.name for s in self._fields if s.name not in block.cells]
        if missing:
            raise ValueError(f"{self.path}: estimate block lacks field(s) {', '.join(missing)}")
        # (n_ticks, n_cells) string columns joined elementwise: numpy does the per-row work
        t = np.char.mod("%.6f", block.t_s)[:, None]
        rows = np.char.add(np.char.add(t, ","), self._cells[None, :])
        for s in self._fields:
            col = np.char.mod(s.fmt, np.asarray(block.cells[s.name], dtype=np.float64))
            rows = np.char.add(np.char.add(rows, ","), col)
        rows = np.char.add(np.char.add(rows, ","), block.quality.astype(np.int64).astype(np.str_))
        self._fh.write("\n".join(rows.ravel().tolist()) + "\n")

    def close(self) -> None:
        if self._fh is not None:
            self._fh.close()
            self._fh = None

    def __enter__(self) -> ParamsCsvWriter:
        return self

    def __exit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        tb: TracebackType | None,
    ) -> None:
        self.close()


def write_params_csv(block: EstimateBlock, cell_names: Sequence[str], path: Path) -> None:
    """``params.csv`` of a whole run at once (``ParamsCsvWriter`` with one block)."""
    with ParamsCsvWriter(path, cell_names) as w:
        w.append(block)
