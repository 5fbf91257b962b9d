"""Which signals of a BMS's DBC carry the pack current, the cell voltages and the temperatures.

A mapping is a TOML file validated by pydantic and checked against the DBC it names, so bmsid can
listen to an existing BMS without changing it. Two layouts describe a group of values:

- ``multiplexed``: one message whose multiplexer selects a group; value ``k`` of group ``g`` is
  item ``g * len(signals) + k`` (bmsid's own layout);
- ``listed``: one (message, signal) per item, in item order (e.g. one signal per cell).

Every value is converted as ``SI = scale * decoded + offset`` (decoded = the DBC's physical value),
and the current additionally by its sign convention (bmsid: positive = discharge).
"""

from __future__ import annotations

import functools
import tomllib
from pathlib import Path
from typing import Annotated, Literal

import cantools
from pydantic import BaseModel, ConfigDict, Field, ValidationError

from bmsid.errors import UserError

PACKAGE_DBC_DIR = Path(__file__).resolve().parent.parent / "dbc"
DEFAULT_MAPPING_PATH = PACKAGE_DBC_DIR / "bmsid_mapping.toml"
DEFAULT_DBC_PATH = PACKAGE_DBC_DIR / "bmsid.dbc"


class _Strict(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True)


class SignalRef(_Strict):
    """One signal of one message; ``SI = scale * decoded + offset``."""

    message: str
    signal: str
    scale: float = 1.0
    offset: float = 0.0


class CurrentMap(SignalRef):
    """Pack current; ``positive`` is the sign convention of the BMS (bmsid's is discharge)."""

    positive: Literal["discharge", "charge"] = "discharge"


class CounterMap(_Strict):
    """A sample counter; a change of its value ends the open cycle (see frames_to_samples)."""

    message: str
    signal: str


class MultiplexedGroup(_Strict):
    layout: Literal["multiplexed"]
    message: str
    multiplexer: str
    signals: list[str] = Field(min_length=1)
    scale: float = 1.0
    offset: float = 0.0
    #: Items present on this bus (default: every item the multiplexer can address).
    count: int | None = Field(None, ge=1)


class ListedGroup(_Strict):
    layout: Literal["listed"]
    signals: list[SignalRef] = Field(min_length=1)


Group = Annotated[MultiplexedGroup | ListedGroup, Field(discriminator="layout")]


class BusMapping(_Strict):
    """A validated mapping. ``dbc`` is absolute after :func:`load_mapping`."""

    name: str = "mapping"
    dbc: Path
    current: CurrentMap
    counter: CounterMap | None = None
    cells: Group
    temperatures: Group | None = None

    def database(self) -> cantools.database.can.Database:
        """The DBC named by ``dbc`` (loaded once per path)."""
        return load_dbc(str(self.dbc))

    def max_cells(self) -> int:
        """How many cells this mapping can address."""
        return _group_capacity(self.cells, self.database())

    def max_temperatures(self) -> int:
        if self.temperatures is None:
            return 0
        return _group_capacity(self.temperatures, self.database())


@functools.lru_cache(maxsize=16)
def load_dbc(path: str) -> cantools.database.can.Database:
    try:
        db = cantools.database.load_file(path, strict=True)
    except FileNotFoundError as exc:
        raise UserError(f"dbc: file not found: {path}") from exc
    except Exception as exc:  # cantools raises several parser exception types
        raise UserError(f"dbc: cannot read {path}: {exc}") from exc
    if not isinstance(db, cantools.database.can.Database):
        raise UserError(f"dbc: {path} is not a CAN database")
    return db


def _mux_values(db: cantools.database.can.Database, message: str, mux: str) -> list[int]:
    msg = db.get_message_by_name(message)
    values: set[int] = set()
    for s in msg.signals:
        if s.multiplexer_signal == mux and s.multiplexer_ids:
            values.update(s.multiplexer_ids)
    return sorted(values)


def _group_capacity(
    group: MultiplexedGroup | ListedGroup, db: cantools.database.can.Database
) -> int:
    if isinstance(group, ListedGroup):
        return len(group.signals)
    values = _mux_values(db, group.message, group.multiplexer)
    capacity = (max(values) + 1) * len(group.signals) if values else 0
    return min(capacity, group.count) if group.count is not None else capacity


def _check_signal(
    db: cantools.database.can.Database, where: str, message: str, signal: str
) -> None:
    try:
        msg = db.get_message_by_name(message)
    except KeyError:
        raise UserError(f"{where}.message: no message {message!r} in the DBC") from None
    if signal not in {s.name for s in msg.signals}:
        raise UserError(f"{where}.signal: message {message!r} has no signal {signal!r}")


def _check_group(
    db: cantools.database.can.Database, where: str, group: MultiplexedGroup | ListedGroup
) -> None:
    if isinstance(group, ListedGroup):
        seen: set[tuple[str, str]] = set()
        for i, ref in enumerate(group.signals):
            _check_signal(db, f"{where}.signals[{i}]", ref.message, ref.signal)
            if (ref.message, ref.signal) in seen:
                raise UserError(f"{where}.signals[{i}]: {ref.message}.{ref.signal} listed twice")
            seen.add((ref.message, ref.signal))
        return
    _check_signal(db, where, group.message, group.multiplexer)
    msg = db.get_message_by_name(group.message)
    mux = msg.get_signal_by_name(group.multiplexer)
    if not mux.is_multiplexer:
        raise UserError(f"{where}.multiplexer: {group.multiplexer!r} is not a multiplexer signal")
    for name in group.signals:
        _check_signal(db, where, group.message, name)
    values = _mux_values(db, group.message, group.multiplexer)
    if not values:
        raise UserError(f"{where}.signals: none is multiplexed by {group.multiplexer!r}")
    capacity = (max(values) + 1) * len(group.signals)
    if group.count is not None and group.count > capacity:
        raise UserError(f"{where}.count: {group.count} > {capacity} items the DBC can address")


def validate_against_dbc(mapping: BusMapping) -> None:
    """Raise :class:`UserError` naming the field when the mapping does not fit its DBC."""
    db = mapping.database()
    _check_signal(db, "current", mapping.current.message, mapping.current.signal)
    if mapping.counter is not None:
        _check_signal(db, "counter", mapping.counter.message, mapping.counter.signal)
    _check_group(db, "cells", mapping.cells)
    if mapping.temperatures is not None:
        _check_group(db, "temperatures", mapping.temperatures)


def _format_validation_error(path: Path, exc: ValidationError) -> str:
    err = exc.errors()[0]
    field = ".".join(str(p) for p in err["loc"]) or "(top level)"
    return f"{path}: mapping field {field}: {err['msg']}"


def load_mapping(path: str | Path) -> BusMapping:
    """Read and validate a mapping TOML; ``dbc`` is resolved relative to the mapping file."""
    p = Path(path)
    try:
        data = tomllib.loads(p.read_text(encoding="utf-8"))
    except FileNotFoundError:
        raise UserError(f"mapping file not found: {p}") from None
    except (OSError, UnicodeDecodeError, tomllib.TOMLDecodeError) as exc:
        raise UserError(f"{p}: not a readable TOML mapping: {exc}") from None
    if isinstance(data.get("dbc"), str):
        data["dbc"] = str((p.resolve().parent / data["dbc"]).resolve())
    try:
        mapping = BusMapping.model_validate(data)
    except ValidationError as exc:
        raise UserError(_format_validation_error(p, exc)) from None
    try:
        validate_against_dbc(mapping)
    except UserError as exc:
        raise UserError(f"{p}: mapping field {exc}") from None
    return mapping


def default_mapping() -> BusMapping:
    """bmsid's own DBC layout (the packaged ``bmsid_mapping.toml``)."""
    return load_mapping(DEFAULT_MAPPING_PATH)
