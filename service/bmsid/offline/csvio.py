"""The one loader for battery-tester CSV files (``.csv`` or ``.csv.gz``).

Format: a header line, then one row per sample, comma separated. Columns (names are matched
case-insensitively, surrounding blanks ignored):

- ``t_s`` (s, strictly increasing) and ``current_A`` (A, positive = discharge) are required;
- the cell voltage(s) in volts: ``voltage_V`` for one cell, or ``v_cell_01, v_cell_02, ...`` for
  several (ordered by their number; when both exist the ``v_cell_*`` columns are the cells and
  ``voltage_V`` goes to ``extra``);
- ``temperature_C`` is optional; any other column that is numeric in every row lands in
  ``extra`` (e.g. ``soc_true``), non-numeric ones (step names, dates) are ignored.

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
import re
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import ClassVar

import numpy as np
import numpy.typing as npt

from bmsid.errors import UserError

FloatArray = npt.NDArray[np.float64]

MAX_PLAUSIBLE_CURRENT_A = 3000.0
MAX_PLAUSIBLE_CELL_VOLTAGE_V = 100.0
_MAX_LINES_LISTED = 5
_CELL_RE = re.compile(r"^v_cell_(\d+)$")


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


def read_tester_csv(path: str | Path, *, charge_positive: bool = False) -> TesterData:
    """Load a tester CSV (see the module docstring); ``charge_positive`` flips the current sign.

    Raises ``UserError`` for a missing/empty file, missing columns, bad rows, non-increasing time
    and values that look like mV or mA.
    """
    p = Path(path)
    text = _read_text(p)
    lines = text.splitlines()
    while lines and not lines[-1].strip():
        lines.pop()
    if not lines:
        raise UserError(f"{p}: empty file")
    header = [h.strip() for h in lines[0].split(",")]
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
        raise UserError(f"{p}: missing column(s) {names}; found: {', '.join(header)}")

    n_fields = len(header)
    rows: list[list[str]] = []
    bad_rows: list[int] = []
    for k, line in enumerate(body):
        parts = line.split(",")
        if len(parts) != n_fields:
            bad_rows.append(k + 2)
        else:
            rows.append(parts)
    if bad_rows:
        raise UserError(
            f"{p}: line(s) {_lines_text(bad_rows)} are empty or do not have the "
            f"{n_fields} fields of the header"
        )
    columns = list(zip(*rows, strict=True))

    def required(name: str) -> FloatArray:
        j = keys.index(name.lower())
        arr = _parse_column([s.strip() for s in columns[j]], header[j], p, 2, True)
        assert arr is not None
        return arr

    t = required("t_s")
    steps = np.diff(t)
    if np.any(steps <= 0):
        k = int(np.flatnonzero(steps <= 0)[0])
        raise UserError(
            f"{p}: time t_s is not increasing at line {k + 3} ({t[k + 1]:g} s after {t[k]:g} s)"
        )
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
        arr = _parse_column([s.strip() for s in columns[j]], name, p, 2, False)
        if arr is not None:
            extra[name] = arr
    return TesterData(
        t_s=t,
        current_A=current,
        cell_voltages_V=volts,
        cell_names=[header[j] for j in cell_cols],
        temperature_C=temperature,
        extra=extra,
        source=str(p),
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
