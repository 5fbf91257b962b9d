"""What offline identification reads: recordings as sample blocks, cell configs and options.

A recording is opened as an :class:`InputSource` that yields :class:`~bmsid.samples.SampleBlock`
columns in time order, whatever the file format: tester CSV (``.csv``, ``.csv.gz``, read by
:func:`~bmsid.offline.csvio.read_tester_csv`) or candump log (``.log``, decoded by
:func:`~bmsid.canbus.logs.samples_from_log` exactly as the daemon decodes the bus). Both readers
load the whole file today and slice it; a streaming reader (issue 12) only has to yield the same
blocks.

The option parsers take the text a user typed (``KEY=VALUE``, ``LO,HI``) and raise
:class:`~bmsid.errors.UserError` with one line that names the command-line option it came from,
so every front end (CLI, benches) reports a bad value the same way.
"""

from __future__ import annotations

import math
from collections.abc import Iterator, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Protocol

import numpy as np
import numpy.typing as npt
from pydantic import ValidationError

from bmsid.canbus.logs import samples_from_log
from bmsid.canbus.mapping import default_mapping, load_mapping
from bmsid.config.cell import CellConfig, OcvCurve, load_cell_config, paper_cell
from bmsid.errors import UserError
from bmsid.estimate.tuning import EstimatorTuning
from bmsid.offline.csvio import TesterData, read_tester_csv
from bmsid.offline.scoring import EvalWindow
from bmsid.samples import SampleBlock

FloatArray = npt.NDArray[np.float64]

#: Samples per block when a caller does not say (a few thousand: per-block overhead negligible,
#: a progress bar still moves every second or two).
DEFAULT_BLOCK_SIZE = 4096


class InputSource(Protocol):
    """A recording as a sequence of sample blocks.

    Attributes
    ----------
    source : str
        The path as the caller gave it (for messages and metrics.json).
    cell_names : list of str
        Name of each voltage column, in block column order.
    n_samples : int or None
        Number of samples, None when unknown before reading to the end.
    """

    @property
    def source(self) -> str: ...

    @property
    def cell_names(self) -> list[str]: ...

    @property
    def n_samples(self) -> int | None: ...

    @property
    def n_cells(self) -> int: ...

    def blocks(self, size: int = DEFAULT_BLOCK_SIZE) -> Iterator[SampleBlock]:
        """Consecutive blocks of at most ``size`` samples, in time order."""
        ...


@dataclass(frozen=True)
class LoadedInput:
    """A recording held in memory as one block, yielded in slices (views, no copies).

    ``temperature_C`` (degC, shape (n,)) is the tester file's temperature column, if any.
    """

    source: str
    samples: SampleBlock
    cell_names: list[str]
    temperature_C: FloatArray | None = None

    @property
    def n_samples(self) -> int:
        return len(self.samples)

    @property
    def n_cells(self) -> int:
        return self.samples.n_cells

    def blocks(self, size: int = DEFAULT_BLOCK_SIZE) -> Iterator[SampleBlock]:
        if size < 1:
            raise ValueError(f"block size must be >= 1, got {size}")
        for start in range(0, self.n_samples, size):
            yield self.samples.slice(start, start + size)

    @classmethod
    def from_tester(cls, data: TesterData, source: str | None = None) -> LoadedInput:
        """A tester file's columns as a source (cells named by their voltage columns)."""
        block = SampleBlock.from_arrays(data.t_s, data.current_A, data.cell_voltages_V)
        return cls(
            source=data.source if source is None else source,
            samples=block,
            cell_names=list(data.cell_names),
            temperature_C=data.temperature_C,
        )


def read_csv_input(path: str | Path, *, charge_positive: bool = False) -> LoadedInput:
    """A tester CSV as a source (format in :mod:`bmsid.offline.csvio`).

    Parameters
    ----------
    path : str or Path
        ``.csv`` or ``.csv.gz`` file.
    charge_positive : bool
        The file counts charge current positive (the engine counts discharge positive).

    Raises
    ------
    UserError
        A missing or malformed file (one line naming the file and the lines).
    """
    return LoadedInput.from_tester(read_tester_csv(path, charge_positive=charge_positive))


def read_log_input(
    path: str | Path,
    *,
    n_cells: int = 1,
    mapping: str | Path | None = None,
    charge_positive: bool = False,
) -> LoadedInput:
    """A candump log decoded as the daemon decodes the bus, as a source.

    Parameters
    ----------
    path : str or Path
        candump ``-l`` / ``-ta`` log.
    n_cells : int
        Cells of the pack on the bus.
    mapping : str, Path or None
        Bus mapping TOML; None uses the default mapping.
    charge_positive : bool
        The bus counts charge current positive.

    Raises
    ------
    UserError
        A missing file, a bad mapping, no decodable sample or no timestamps.
    """
    if n_cells < 1:
        raise UserError(f"--n-cells must be >= 1, got {n_cells}")
    if not Path(path).is_file():
        raise UserError(f"{path}: no such file")
    bus = load_mapping(mapping) if mapping else default_mapping()
    block = SampleBlock.from_samples(samples_from_log(path, bus, n_cells))
    if charge_positive:
        block = SampleBlock(block.t_s, -block.current_A, block.cell_voltages_V)
    names = [f"v_cell_{c + 1:02d}" for c in range(block.n_cells)]
    return LoadedInput(source=str(path), samples=block, cell_names=names)


def open_input(
    path: str | Path,
    *,
    charge_positive: bool = False,
    mapping: str | Path | None = None,
    n_cells: int = 1,
) -> LoadedInput:
    """The recording at ``path``: a candump log when it ends in ``.log``, else a tester CSV.

    ``mapping`` and ``n_cells`` apply to logs only (a mapping given for a CSV is an error: the
    user meant something else). Errors as :func:`read_csv_input` and :func:`read_log_input`.
    """
    if str(path).lower().endswith(".log"):
        return read_log_input(
            path, n_cells=n_cells, mapping=mapping, charge_positive=charge_positive
        )
    if mapping is not None:
        raise UserError("--mapping applies to candump .log inputs only")
    return read_csv_input(path, charge_positive=charge_positive)


# ----------------------------------------------------------------------------- cell config
def load_config(path: str | Path) -> CellConfig:
    """The cell config at ``path`` (.toml or .json); UserError naming the bad field."""
    try:
        return load_cell_config(path)
    except FileNotFoundError:
        raise UserError(f"cell config not found: {path}") from None
    except ValidationError as exc:
        err = exc.errors()[0]
        where = ".".join(str(x) for x in err["loc"])
        raise UserError(f"{path}: invalid cell config at {where}: {err['msg']}") from None
    except (OSError, ValueError) as exc:
        raise UserError(f"{path}: cannot read the cell config: {exc}".splitlines()[0]) from None


def cell_config(
    path: str | Path | None = None,
    capacity_Ah: float | None = None,
    ocv_coeffs: Sequence[float] | None = None,
) -> tuple[CellConfig, str]:
    """The cell config of a run and a note on where it came from (printed, and in metrics.json).

    Parameters
    ----------
    path : str, Path or None
        Cell config file; None takes the paper's cell (Table 1 OCV, 15 mV hysteresis).
    capacity_Ah : float or None
        Capacity override, Ah. Without a config file the paper's start values are dropped, so
        they scale with this capacity.
    ocv_coeffs : sequence of 6 floats or None
        Mean OCV curve override (Eq. 4 coefficients a0..a5, V); the SOC range is kept.
    """
    if path is not None:
        cell = load_config(path)
        note = f"cell config {path}"
    else:
        cell = paper_cell()
        note = "no --cell-config: the paper's cell (Table 1 OCV, 15 mV hysteresis)"
        if capacity_Ah is not None:
            cell = cell.model_copy(update={"initial": None})  # capacity-scaled start values
    update: dict[str, Any] = {}
    if capacity_Ah is not None:
        if not (math.isfinite(capacity_Ah) and 0 < capacity_Ah <= 10_000):
            raise UserError(f"--capacity-ah must lie in (0, 10000], got {capacity_Ah:g}")
        update["capacity_Ah"] = float(capacity_Ah)
        note += f", capacity {capacity_Ah:g} Ah"
    if ocv_coeffs is not None:
        coeffs = [float(c) for c in ocv_coeffs]
        if len(coeffs) != 6 or not all(math.isfinite(c) for c in coeffs):
            raise UserError("--ocv-coeffs needs six finite numbers a0,a1,a2,a3,a4,a5")
        update["ocv"] = OcvCurve(mean=coeffs, soc_min=cell.ocv.soc_min, soc_max=cell.ocv.soc_max)
        note += ", OCV from --ocv-coeffs"
    if update:
        cell = CellConfig.model_validate({**cell.model_dump(), **update})
    return cell, note


# ----------------------------------------------------------------------------- option text
def parse_tuning(items: Sequence[str]) -> EstimatorTuning:
    """``KEY=VALUE`` overrides of :class:`~bmsid.estimate.tuning.EstimatorTuning` fields."""
    values: dict[str, str] = {}
    for item in items:
        key, sep, val = item.partition("=")
        if not sep or not key.strip():
            raise UserError(f"--tuning: {item!r} is not KEY=VALUE")
        if key.strip() not in EstimatorTuning.model_fields:
            raise UserError(f"--tuning: unknown field {key.strip()!r} of EstimatorTuning")
        values[key.strip()] = val.strip()
    try:
        return EstimatorTuning.model_validate(values)
    except ValidationError as exc:
        err = exc.errors()[0]
        where = ".".join(str(x) for x in err["loc"]) or "tuning"
        raise UserError(f"--tuning {where}: {err['msg']}") from None


def tuning_overrides(items: Sequence[str]) -> dict[str, str]:
    """The ``KEY=VALUE`` overrides as given (text), for metrics.json and compare.json."""
    return dict(item.partition("=")[::2] for item in items)


def parse_window(soc_window: str | None, skip_fraction: float | None) -> EvalWindow:
    """The evaluation window from ``LO,HI`` SOC fractions and a skipped fraction of the ticks.

    Without a SOC window the first 10 % of the ticks are skipped by default, with one none.
    """
    lo = hi = None
    if soc_window is not None:
        parts = soc_window.split(",")
        try:
            lo, hi = (float(x) for x in parts)
        except ValueError:
            raise UserError(f"--soc-window: expected LO,HI fractions, got {soc_window!r}") from None
        if lo > 1.0 or hi > 1.0:
            raise UserError("--soc-window takes fractions (0.15,0.95), not percent")
    skip = skip_fraction if skip_fraction is not None else (0.1 if soc_window is None else 0.0)
    try:
        return EvalWindow(skip_fraction=skip, soc_lo=lo, soc_hi=hi)
    except ValueError as exc:
        raise UserError(str(exc)) from None


def check_soc0(soc0: float | None) -> None:
    """UserError unless ``soc0`` is None or a fraction in [0, 1]."""
    if soc0 is not None and not (math.isfinite(soc0) and 0.0 <= soc0 <= 1.0):
        raise UserError(f"--soc0 is a fraction in [0, 1], got {soc0:g}")
