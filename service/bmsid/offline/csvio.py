"""The one loader for battery-tester CSV files (``.csv`` or ``.csv.gz``).

Format: a header line, then one row per sample, comma separated (a header without commas but
with semicolons or tabs selects that separator; double quotes around names and values are
dropped). Columns (names are matched case-insensitively, surrounding blanks ignored; other
names are mapped with ``columns``, see :class:`ColumnMap`):

- ``t_s`` (s) and ``current_A`` (A, positive = discharge) are required;
- the cell voltage(s) in volts: ``voltage_V`` for one cell, or ``v_cell_01, v_cell_02, ...`` for
  several (ordered by their number; when both exist the ``v_cell_*`` columns are the cells and
  ``voltage_V`` goes to ``extra``);
- ``temperature_C`` is optional; any other column that is numeric in every row lands in
  ``extra`` (e.g. ``soc_true``), non-numeric ones (step names, dates) are ignored.

Time as testers write it (gaps and sample-rate changes need nothing: the engine handles them):

- rows with the same ``t_s`` (a record logged twice at a step change) are merged into the last
  of them and counted (``TesterData.merged_repeats``);
- a clock that restarts at the record's first time stamp (records appended to each other, a
  tester that reset its clock) is stitched: the times after it continue the previous ones after
  a gap of ``RESTART_GAP_S``, which the engine treats like any gap (a new segment after a rest
  of unknown length); the lines are in ``TesterData.time_restarts``. More than
  ``MAX_TIME_RESTARTS`` restarts look like a per-step time column and are refused;
- any other step back in time is an error naming its line.

Every rejected file raises ``UserError`` with one line that names the file and the lines
(1-based, the header being line 1). Unit heuristics:

- voltages: a median above 100 is not a cell voltage in volts (cells are below 5 V); the usual
  cause is a millivolt column;
- current: a magnitude above ``MAX_PLAUSIBLE_CURRENT_A`` (3 kA) is taken for milliamperes.
  Smaller mA values (a 2 A test logged as 2000) cannot be told from a large cell's real current
  here; ``bmsid fit-ocv`` catches them later with its C-rate check, where the capacity is known.
"""

from __future__ import annotations

import gzip
import io
import logging
import re
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import ClassVar

import numpy as np
import numpy.typing as npt

from bmsid.errors import UserError

FloatArray = npt.NDArray[np.float64]
BoolArray = npt.NDArray[np.bool_]

log = logging.getLogger(__name__)

MAX_PLAUSIBLE_CURRENT_A = 3000.0
MAX_PLAUSIBLE_CELL_VOLTAGE_V = 100.0
#: Gap (s) put where a restarted clock is stitched on: longer than the engine's gap threshold
#: (``EstimatorTuning.gap_s``, 30 s), so the pause of unknown length starts a new segment.
RESTART_GAP_S = 60.0
#: More restarts than this are a per-step time column (Arbin "Step_Time", Neware "Relative
#: Time"), not appended records: refused, the user maps the test time instead.
MAX_TIME_RESTARTS = 3
_MAX_LINES_LISTED = 5
_CELL_RE = re.compile(r"^v_cell_(\d+)$")
#: Names ``columns`` may map to (besides ``v_cell_NN``).
CANONICAL_COLUMNS = ("t_s", "current_A", "voltage_V", "temperature_C")


@dataclass(frozen=True)
class ColumnMap:
    """Where a canonical column (``t_s``, ``current_A``, ...) comes from in a foreign export.

    ``source`` is the export's column name (matched case-insensitively), ``scale`` multiplies its
    values into the canonical unit (0.001 for a time in ms or a current in mA).
    """

    source: str
    scale: float = 1.0


@dataclass(frozen=True)
class TesterData:
    """One tester file: time (s), current (A, + = discharge), cell voltages (V) and extras.

    ``cell_voltages_V`` has shape (n, n_cells) with columns named by ``cell_names``.
    """

    t_s: FloatArray
    current_A: FloatArray
    cell_voltages_V: FloatArray
    cell_names: list[str]
    temperature_C: FloatArray | None = None
    extra: dict[str, FloatArray] = field(default_factory=dict)
    source: str = ""
    #: Rows dropped because the next row has the same ``t_s`` (the last of equal times is kept).
    merged_repeats: int = 0
    #: File lines (1-based) where the clock restarted and was stitched on (see the module doc).
    time_restarts: tuple[int, ...] = ()
    __test__: ClassVar[bool] = False  # "Test..." name: not a pytest class

    @property
    def n_samples(self) -> int:
        return int(self.t_s.shape[0])

    @property
    def n_cells(self) -> int:
        return int(self.cell_voltages_V.shape[1])


def _lines_text(lines: Sequence[int]) -> str:
    shown = ", ".join(str(n) for n in lines[:_MAX_LINES_LISTED])
    more = len(lines) - _MAX_LINES_LISTED
    return shown + (f" (and {more} more)" if more > 0 else "")


def _read_text(path: Path) -> str:
    if not path.is_file():
        raise UserError(f"{path}: no such file")
    try:
        if path.name.lower().endswith(".gz"):
            with gzip.open(path, "rt", encoding="utf-8-sig", newline="") as fh:
                return fh.read()
        return path.read_text(encoding="utf-8-sig")
    except (OSError, EOFError, UnicodeDecodeError) as exc:
        raise UserError(f"{path}: cannot read: {exc}") from exc


def _parse_column(
    values: list[str], name: str, path: Path, first_line: int, required: bool
) -> FloatArray | None:
    """Column as float64; for a required column any bad cell is a UserError naming the lines."""
    try:
        arr = np.asarray(values, dtype=np.float64)
    except ValueError:
        arr = None
    if arr is not None and bool(np.all(np.isfinite(arr))):
        return arr
    if not required:
        return None
    bad: list[int] = []
    for k, s in enumerate(values):
        try:
            ok = np.isfinite(float(s))
        except ValueError:
            ok = False
        if not ok:
            bad.append(first_line + k)
    raise UserError(
        f"{path}: column {name!r} has empty, NaN or non-numeric values "
        f"on line(s) {_lines_text(bad)}"
    )


def _separator(header_line: str) -> str:
    """The field separator: a comma, else what the header uses (European exports: ';' or tab)."""
    if "," in header_line:
        return ","
    for sep in (";", "\t"):
        if sep in header_line:
            return sep
    return ","


def _apply_column_map(
    header: list[str], columns: Mapping[str, ColumnMap], path: Path
) -> tuple[list[str], dict[int, float]]:
    """``header`` with mapped columns renamed to their canonical names, and the scale per column.

    A column that already carries a mapped-to name gives way: it is renamed ``NAME_unmapped``
    (and lands in ``extra`` if numeric), so the user's mapping always wins.
    """
    keys = [h.lower() for h in header]
    out = list(header)
    scales: dict[int, float] = {}
    taken: dict[int, str] = {}
    for target, cm in columns.items():
        j = keys.index(cm.source.strip().lower()) if cm.source.strip().lower() in keys else -1
        if j < 0:
            raise UserError(
                f"{path}: no column {cm.source!r} (mapped to {target}); found: {', '.join(header)}"
            )
        if j in taken:
            raise UserError(f"{path}: column {cm.source!r} is mapped to {taken[j]} and {target}")
        taken[j] = target
        scales[j] = cm.scale
    for j, target in taken.items():
        for k, key in enumerate(keys):
            if k not in taken and key == target.lower():
                out[k] = f"{header[k]}_unmapped"
        out[j] = target
    return out, scales


def _clean_time(t: FloatArray, path: Path) -> tuple[FloatArray, BoolArray, tuple[int, ...]]:
    """Stitched time, the rows to keep (the last of equal times) and the restart lines.

    Lines are 1-based file lines (the header is line 1, row k is line k + 2). Raises
    ``UserError`` for a step back that is not a restart of the clock (see the module doc).
    """
    steps = np.diff(t)
    back = np.flatnonzero(steps < 0)
    restarts: list[int] = []
    if back.size:
        forward = steps[steps > 0]
        dt_med = float(np.median(forward)) if forward.size else 1.0
        # A restart goes back to where the record started (t[0], usually 0) from far beyond
        # it; anything else (rows out of order, a clock stepping back a little) is refused.
        near_start = t[back + 1] <= t[0] + max(dt_med, 1.0)
        far = t[back] - t[back + 1] > RESTART_GAP_S
        bad = back[~(near_start & far)]
        if bad.size:
            k = int(bad[0])
            raise UserError(
                f"{path}: time t_s is not increasing at line {k + 3} ({t[k + 1]:g} s after "
                f"{t[k]:g} s): rows out of order? (equal times are merged and a clock that "
                f"restarts at the record's start, {t[0]:g} s, is stitched on)"
            )
        restarts = [int(k) + 3 for k in back]
        if len(restarts) > MAX_TIME_RESTARTS:
            raise UserError(
                f"{path}: time t_s restarts {len(restarts)} times (line(s) "
                f"{_lines_text(restarts)}): a per-step time column? Map the test's total time "
                "to t_s (e.g. --columns t_s=Test_Time(s))"
            )
        t = t.copy()
        gap = max(RESTART_GAP_S, dt_med)
        for b in back.tolist():  # in file order: each offset carries over to all after it
            t[b + 1 :] += t[b] + gap - t[b + 1]
    # Equal times: keep the LAST row of each run. A tester logs the end of the old step and the
    # start of the new one at the same instant; the new step's current is what flows until the
    # next row (the engine holds a sample's current over the following interval), and its
    # voltage is the response to it. An average would invent a current that never flowed.
    keep = np.append(np.diff(t) != 0.0, True)
    return t, keep, tuple(restarts)


def read_tester_csv(
    path: str | Path,
    *,
    charge_positive: bool = False,
    columns: Mapping[str, ColumnMap] | None = None,
) -> TesterData:
    """Load a tester CSV (see the module docstring).

    Parameters
    ----------
    path : str or Path
        ``.csv`` or ``.csv.gz`` file.
    charge_positive : bool
        The file counts charge current positive: the current's sign is flipped.
    columns : mapping of canonical name to ColumnMap, or None
        Where ``t_s``, ``current_A``, ``voltage_V``, ``v_cell_NN`` or ``temperature_C`` come
        from in an export with other names (applied before the rules above), with a unit scale.

    Raises
    ------
    UserError
        A missing/empty file, missing columns, bad rows, time that goes back (other than a
        restart of the clock), and values that look like mV or mA.
    """
    p = Path(path)
    text = _read_text(p)
    lines = text.splitlines()
    while lines and not lines[-1].strip():
        lines.pop()
    if not lines:
        raise UserError(f"{p}: empty file")
    sep = _separator(lines[0])
    header = [h.strip().strip('"').strip() for h in lines[0].split(sep)]
    scales: dict[int, float] = {}
    if columns:
        header, scales = _apply_column_map(header, columns, p)
    keys = [h.lower() for h in header]
    body = lines[1:]
    if not body:
        raise UserError(f"{p}: header only, no data rows")

    cells = sorted(
        ((int(m.group(1)), j) for j, k in enumerate(keys) if (m := _CELL_RE.match(k))),
        key=lambda nj: nj[0],
    )
    missing = [c for c in ("t_s", "current_a") if c not in keys]
    if not cells and "voltage_v" not in keys:
        missing.append("voltage_V (or v_cell_01, v_cell_02, ...)")
    if missing:
        names = ", ".join(m.replace("current_a", "current_A") for m in missing)
        raise UserError(
            f"{p}: missing column(s) {names}; found: {', '.join(header)} "
            "(other names: --columns t_s=NAME,current_A=NAME,voltage_V=NAME)"
        )

    n_fields = len(header)
    rows: list[list[str]] = []
    bad_rows: list[int] = []
    for k, line in enumerate(body):
        parts = line.split(sep)
        if len(parts) != n_fields:
            bad_rows.append(k + 2)
        else:
            rows.append(parts)
    if bad_rows:
        raise UserError(
            f"{p}: line(s) {_lines_text(bad_rows)} are empty or do not have the "
            f"{n_fields} fields of the header"
        )
    columns_text = list(zip(*rows, strict=True))

    def cells_of(j: int) -> list[str]:
        return [s.strip().strip('"') for s in columns_text[j]]

    def required(name: str) -> FloatArray:
        j = keys.index(name.lower())
        arr = _parse_column(cells_of(j), header[j], p, 2, True)
        assert arr is not None
        return arr * scales[j] if j in scales else arr

    t, keep, restarts = _clean_time(required("t_s"), p)
    merged = int(keep.size - np.count_nonzero(keep))
    current = required("current_A")
    if charge_positive:
        current = -current
    if float(np.max(np.abs(current))) > MAX_PLAUSIBLE_CURRENT_A:
        raise UserError(
            f"{p}: |current_A| reaches {np.max(np.abs(current)):g} > {MAX_PLAUSIBLE_CURRENT_A:g}: "
            "looks like milliamperes; give the current in A"
        )

    cell_cols = [j for _, j in cells] if cells else [keys.index("voltage_v")]
    volts = np.column_stack([required(header[j]) for j in cell_cols])
    for c, j in enumerate(cell_cols):
        med = float(np.median(volts[:, c]))
        if med > MAX_PLAUSIBLE_CELL_VOLTAGE_V:
            raise UserError(
                f"{p}: column {header[j]!r} has median {med:g}: looks like millivolts; "
                "give cell voltages in V"
            )

    temperature = required("temperature_C") if "temperature_c" in keys else None
    used = {keys.index("t_s"), keys.index("current_a"), *cell_cols}
    if "temperature_c" in keys:
        used.add(keys.index("temperature_c"))
    extra: dict[str, FloatArray] = {}
    for j, name in enumerate(header):
        if j in used or not name:
            continue
        arr = _parse_column(cells_of(j), name, p, 2, False)
        if arr is not None:
            extra[name] = arr[keep]
    if merged:
        log.info("%s: merged %d rows with repeated timestamps", p, merged)
    return TesterData(
        t_s=t[keep],
        current_A=current[keep],
        cell_voltages_V=volts[keep],
        cell_names=[header[j] for j in cell_cols],
        temperature_C=None if temperature is None else temperature[keep],
        extra=extra,
        source=str(p),
        merged_repeats=merged,
        time_restarts=restarts,
    )


def write_tester_csv(data: TesterData, path: str | Path) -> None:
    """Write ``data`` in the format ``read_tester_csv`` reads (gzip when the name ends in .gz)."""
    names = ["t_s", "current_A", *data.cell_names]
    cols = [data.t_s, data.current_A, *data.cell_voltages_V.T]
    if data.temperature_C is not None:
        names.append("temperature_C")
        cols.append(data.temperature_C)
    for k, v in data.extra.items():
        names.append(k)
        cols.append(v)
    buf = io.StringIO()
    np.savetxt(buf, np.column_stack(cols), delimiter=",", fmt="%.10g")
    text = ",".join(names) + "\n" + buf.getvalue()
    p = Path(path)
    if p.name.lower().endswith(".gz"):
        with gzip.open(p, "wt", encoding="utf-8") as fh:
            fh.write(text)
    else:
        p.write_text(text, encoding="utf-8")


@dataclass(frozen=True)
class OcvPoints:
    """One (SOC, OCV) column pair of a rest-point table: SOC as a fraction, OCV in V.

    ``branch`` is "discharge" or "charge" when the column names say so, else None.
    """

    branch: str | None
    soc: FloatArray
    ocv_V: FloatArray


def read_ocv_points(path: str | Path) -> list[OcvPoints]:
    """Read a rest-point table: a header and column pairs (SOC, OCV), one pair per branch.

    A pair's branch comes from its names ("discharge"/"charge"); SOC is in percent when its name
    says "percent" or any value exceeds 1.5, else a fraction. A pair may be blank on some lines
    (branches of different lengths), but never only half of it.
    """
    p = Path(path)
    lines = [ln for ln in _read_text(p).splitlines()]
    while lines and not lines[-1].strip():
        lines.pop()
    if len(lines) < 2:
        raise UserError(f"{p}: no rest points (need a header and data lines)")
    header = [h.strip() for h in lines[0].split(",")]
    if len(header) % 2 or not all("soc" in h.lower() for h in header[::2]):
        raise UserError(
            f"{p}: expected column pairs SOC,OCV (e.g. SOC_percent,OCV_V); "
            f"found: {', '.join(header)}"
        )
    pairs: list[OcvPoints] = []
    for j in range(0, len(header), 2):
        names = (header[j] + " " + header[j + 1]).lower()
        branch = "discharge" if "discharge" in names else "charge" if "charge" in names else None
        zs: list[float] = []
        vs: list[float] = []
        for n, line in enumerate(lines[1:], start=2):
            parts = [s.strip() for s in line.split(",")]
            if len(parts) != len(header):
                raise UserError(f"{p}: line {n} does not have the {len(header)} header fields")
            a, b = parts[j], parts[j + 1]
            if not a and not b:
                continue
            try:
                z, v = float(a), float(b)
            except ValueError:
                raise UserError(f"{p}: line {n}: {header[j]}/{header[j + 1]} not numeric") from None
            if not (np.isfinite(z) and np.isfinite(v)):
                raise UserError(f"{p}: line {n}: NaN or infinite value")
            zs.append(z)
            vs.append(v)
        soc = np.asarray(zs, dtype=np.float64)
        ocv = np.asarray(vs, dtype=np.float64)
        if soc.size == 0:
            raise UserError(f"{p}: column pair {header[j]},{header[j + 1]} is empty")
        if "percent" in header[j].lower() or "%" in header[j] or float(np.max(soc)) > 1.5:
            soc = soc / 100.0
        if float(np.median(ocv)) > MAX_PLAUSIBLE_CELL_VOLTAGE_V:
            raise UserError(f"{p}: {header[j + 1]} looks like millivolts; give volts")
        pairs.append(OcvPoints(branch=branch, soc=soc, ocv_V=ocv))
    return pairs
