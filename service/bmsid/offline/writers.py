"""Result files written block by block as identification runs (``params.csv`` or
``params.parquet``).

The columns are ``t_s,cell``, the ``out_key`` of every field of
:data:`~bmsid.estimate.fields.CELL_FIELDS` in table order, then ``quality``; one row per tick (or
per ``--every`` interval, :class:`TickDecimator`) and cell (for each tick, every cell). A writer
appends each :class:`EstimateBlock` as it comes, so a run's memory does not grow with the length
of its output. Parquet (pyarrow) holds the same columns in the same SI units: ``t_s`` and the
fields as float64 (``on_bound`` and ``quality`` as int64, ``cell`` as text), written in row groups
of at most :data:`ROW_GROUP_ROWS` rows as the run goes. A missing value (NaN in the block: a
refused reading, a ``no_data`` cell) is an empty cell in the CSV and null in Parquet.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from pathlib import Path
from types import TracebackType
from typing import Any, Literal, Protocol, TextIO

import numpy as np
import numpy.typing as npt

from bmsid.estimate import fields
from bmsid.estimate.fields import QUALITY_KEY
from bmsid.estimate.types import EstimateBlock

StrArray = npt.NDArray[np.str_]
FloatArray = npt.NDArray[np.float64]

#: File formats of the parameter table.
ParamsFormat = Literal["csv", "parquet"]
#: Per ``--every`` interval: the last tick's values, or the mean of the interval's ticks.
EveryMode = Literal["last", "mean"]
#: Rows per Parquet row group (at most; the last group of a run is smaller).
ROW_GROUP_ROWS = 131_072


class ParamsSink(Protocol):
    """Where the rows of estimate blocks go (a file writer, a decimator in front of one)."""

    def append(self, block: EstimateBlock) -> None: ...

    def close(self) -> None: ...


class ParamsCsvWriter:
    """``params.csv``: created (or truncated) with its header at construction, rows appended.

    The columns are fixed when the writer is made (``CELL_FIELDS`` read then), so every row
    matches the header. Times are written with ``%.6f`` (s), fields with their ``fmt`` (SI units
    of the table), a missing (NaN) value as an empty cell, quality as its integer code.
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
            rows = np.char.add(np.char.add(rows, ","), _csv_column(s.fmt, block.cells[s.name]))
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


def _csv_column(fmt: str, values: FloatArray) -> StrArray:
    """``values`` formatted with ``fmt``, a missing (non-finite) value as an empty cell: the
    README's "null if missing"; ``%d`` of NaN would raise, ``%g`` writes a literal ``nan``."""
    x = np.asarray(values, dtype=np.float64)
    ok = np.isfinite(x)
    if ok.all():
        return np.char.mod(fmt, x)
    out = np.char.mod(fmt, np.where(ok, x, 0.0))
    return np.where(ok, out, "")


class ParamsParquetWriter:
    """``params.parquet``: the columns of ``params.csv`` (float64 values, int64 ``on_bound`` and
    ``quality``, text ``cell``), appended in row groups of up to ``ROW_GROUP_ROWS`` rows."""

    def __init__(self, path: Path, cell_names: Sequence[str]) -> None:
        # imported here: pyarrow adds ~50 MB of resident memory to a run that writes CSV
        import pyarrow as pa  # noqa: PLC0415
        import pyarrow.parquet as pq  # noqa: PLC0415

        self._pa = pa
        self.path = path
        self._fields = tuple(fields.CELL_FIELDS)
        self._cells = list(cell_names)
        cols = [pa.field("t_s", pa.float64()), pa.field("cell", pa.string())]
        cols += [pa.field(s.out_key, pa.int64() if s.fmt == "%d" else pa.float64())
                 for s in self._fields]  # fmt: skip
        cols.append(pa.field(QUALITY_KEY, pa.int64()))
        self._schema = pa.schema(cols)
        self._writer: Any = pq.ParquetWriter(path, self._schema)
        self._pending: list[Any] = []
        self._rows = 0

    def append(self, block: EstimateBlock) -> None:
        """Queue ``block``'s rows (tick by tick, every cell); a full row group is written."""
        if self._writer is None:
            raise ValueError(f"{self.path}: writer is closed")
        if block.n_ticks == 0:
            return
        nc = len(self._cells)
        if block.n_cells != nc:
            raise ValueError(f"{self.path}: block has {block.n_cells} cells, the file {nc}")
        pa = self._pa
        arrays = [
            pa.array(np.repeat(block.t_s, nc)),
            pa.array(self._cells * block.n_ticks, type=pa.string()),
        ]
        for s in self._fields:
            col = np.asarray(block.cells[s.name], dtype=np.float64).ravel()
            missing = ~np.isfinite(col)  # null, as the CSV's empty cell (never NaN or a cast NaN)
            if s.fmt == "%d":
                col = np.where(missing, 0.0, col).astype(np.int64)
            arrays.append(pa.array(col, mask=missing if missing.any() else None))
        arrays.append(pa.array(block.quality.astype(np.int64).ravel()))
        self._pending.append(pa.Table.from_arrays(arrays, schema=self._schema))
        self._rows += block.n_ticks * nc
        if self._rows >= ROW_GROUP_ROWS:
            self._flush()

    def _flush(self) -> None:
        if self._writer is not None and self._pending:
            self._writer.write_table(self._pa.concat_tables(self._pending), ROW_GROUP_ROWS)
        self._pending = []
        self._rows = 0

    def close(self) -> None:
        if self._writer is not None:
            self._flush()
            self._writer.close()
            self._writer = None


class TickDecimator:
    """One row per ``every_s`` interval in front of a writer: intervals of ``every_s`` seconds
    from the first tick's time, each written as its last tick (``mode="last"``: states and
    parameters as they stood at the interval's end) or as the NaN-ignoring mean of its ticks
    (``"mean"``; ``on_bound`` and ``quality``, codes, are the last tick's; ``t_s`` is the last
    tick's time in both modes). An interval is written once a later tick shows it is complete,
    the last one at :meth:`close`."""

    def __init__(self, sink: ParamsSink, every_s: float, mode: EveryMode = "last") -> None:
        if not (math.isfinite(every_s) and every_s > 0):
            raise ValueError(f"decimation interval must be positive, got {every_s:g}")
        self.sink = sink
        self.every_s = every_s
        self.mode = mode
        self._t0: float | None = None
        self._held: EstimateBlock | None = None  # ticks of the interval not known complete

    def append(self, block: EstimateBlock) -> None:
        if block.n_ticks == 0:
            return
        if self._t0 is None:
            self._t0 = float(block.t_s[0])
        if self._held is not None:
            block = EstimateBlock.concat([self._held, block], block.n_cells)
        k = np.floor((block.t_s - self._t0) / self.every_s).astype(np.int64)
        last = np.flatnonzero(k != k[-1])
        done = 0 if last.size == 0 else int(last[-1]) + 1  # ticks of complete intervals
        self._held = block.select(slice(done, block.n_ticks))
        if done:
            self.sink.append(self._reduce(block.select(slice(0, done)), k[:done]))

    def _reduce(self, block: EstimateBlock, k: npt.NDArray[np.int64]) -> EstimateBlock:
        """One tick per interval of ``block`` (complete intervals, interval numbers ``k``)."""
        ends = np.append(np.flatnonzero(np.diff(k)), k.size - 1)
        out = block.select(ends)
        if self.mode == "last":
            return out
        starts = np.append(0, ends[:-1] + 1)
        counted = {s.name for s in fields.CELL_FIELDS if s.fmt != "%d"}
        cells = dict(out.cells)
        for name in counted & set(block.cells):
            x = np.asarray(block.cells[name], dtype=np.float64)
            ok = np.isfinite(x)
            total = np.add.reduceat(np.where(ok, x, 0.0), starts, axis=0)
            n = np.add.reduceat(ok.astype(np.int64), starts, axis=0)
            with np.errstate(invalid="ignore", divide="ignore"):
                cells[name] = np.where(n > 0, total / np.maximum(n, 1), np.nan)
        current = np.add.reduceat(block.current_A, starts) / np.diff(np.append(starts, k.size))
        return EstimateBlock(t_s=out.t_s, current_A=current, cells=cells, quality=out.quality)

    def close(self) -> None:
        if self._held is not None and self._held.n_ticks:
            k = np.zeros(self._held.n_ticks, dtype=np.int64)
            self.sink.append(self._reduce(self._held, k))
        self._held = None
        self.sink.close()


def open_params_writer(
    out: Path,
    cell_names: Sequence[str],
    fmt: ParamsFormat = "csv",
    every_s: float | None = None,
    mode: EveryMode = "last",
) -> ParamsSink:
    """The parameter table of a run in ``out``: ``params.csv`` or ``params.parquet``, one row
    per tick and cell, or per ``every_s`` interval (None: every tick)."""
    sink: ParamsSink
    if fmt == "parquet":
        sink = ParamsParquetWriter(out / "params.parquet", cell_names)
    else:
        sink = ParamsCsvWriter(out / "params.csv", cell_names)
    return sink if every_s is None else TickDecimator(sink, every_s, mode)


def write_params_csv(block: EstimateBlock, cell_names: Sequence[str], path: Path) -> None:
    """``params.csv`` of a whole run at once (``ParamsCsvWriter`` with one block)."""
    with ParamsCsvWriter(path, cell_names) as w:
        w.append(block)
