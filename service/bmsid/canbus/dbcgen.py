"""bmsid's own CAN database, written from one table so the DBC and its documentation agree.

Run ``python -m bmsid.canbus.dbcgen`` to regenerate ``dbc/bmsid.dbc`` and the packaged copy.

Conventions of every scaled signal here: ``physical = raw * scale + offset``. A signal marked
``sna`` reserves one raw value as "signal not available" (all ones when unsigned, the most negative
value when signed); the declared [minimum, maximum] excludes it, so any decoder that checks ranges
sees a NaN/out-of-range value instead of a number. Senders saturate at the declared range and set
a ``Saturated`` bit rather than wrap around.
"""

from __future__ import annotations

import argparse
from dataclasses import dataclass
from pathlib import Path

from bmsid.estimate.types import Quality

#: Bit positions of the ``Saturated`` mask in the per-cell frames (classic and FD).
SATURATION_BITS: dict[str, int] = {
    "R0": 0,
    "R1": 1,
    "R2": 2,
    "Tau1": 3,
    "Tau2": 4,
    "Lambda": 5,
    "H": 6,
    "SOC": 7,
    "VError": 8,
    "C1": 9,
    "C2": 10,
    "SOCStd": 11,
    "Capacity": 12,
}
#: Bits of ``SATURATION_BITS`` that ``CellState``'s 11-bit mask has room for (0..10); the
#: ``CellCapacity`` and ``CellParamsFD`` masks carry every bit.
CLASSIC_STATE_MASK_BITS = 11

#: ``Quality`` codes as value descriptions (``VAL_``), named as MQTT's ``quality_name``.
QUALITY_CHOICES: tuple[tuple[int, str], ...] = tuple((int(q), q.name.lower()) for q in Quality)
QUALITY_COMMENT = ", ".join(f"{int(q)} {q.name.lower().replace('_', ' ')}" for q in Quality)

#: Largest number of cells bmsid's own frames address (cell voltages and cell parameters).
MAX_CELLS = 512
CELLS_PER_VOLTAGE_FRAME = 4
TEMPS_PER_FRAME = 3
MAX_TEMP_GROUPS = 64


@dataclass(frozen=True, slots=True)
class SignalSpec:
    """One little-endian (Intel) signal."""

    name: str
    start: int
    length: int
    scale: float = 1.0
    offset: float = 0.0
    signed: bool = False
    unit: str = ""
    sna: bool = False
    mux: str = ""  # "M" for the multiplexer, "m" for a signal present under every mux value
    maximum: float | None = None  # overrides the raw-range maximum (multiplexers)
    comment: str = ""
    choices: tuple[tuple[int, str], ...] = ()  # raw value -> name (VAL_)

    def raw_range(self) -> tuple[int, int]:
        """Valid raw values (the SNA value excluded)."""
        if self.signed:
            lo, hi = -(1 << (self.length - 1)), (1 << (self.length - 1)) - 1
            return (lo + 1 if self.sna else lo), hi
        hi = (1 << self.length) - 1
        return 0, (hi - 1 if self.sna else hi)

    def phys_range(self) -> tuple[float, float]:
        lo, hi = self.raw_range()
        pmin, pmax = lo * self.scale + self.offset, hi * self.scale + self.offset
        if self.maximum is not None:
            pmax = self.maximum
        return pmin, pmax


@dataclass(frozen=True, slots=True)
class MessageSpec:
    name: str
    frame_id: int
    extended: bool
    length: int
    signals: tuple[SignalSpec, ...]
    direction: str  # "in" (bmsid reads) or "out" (bmsid writes)
    fd: bool = False
    comment: str = ""
    mux_range: tuple[int, int] | None = None


def _num(x: float) -> str:
    return f"{x:.12g}"


def _cell_voltages() -> tuple[SignalSpec, ...]:
    groups = MAX_CELLS // CELLS_PER_VOLTAGE_FRAME
    sigs = [
        SignalSpec(
            "CellGroup",
            0,
            8,
            mux="M",
            maximum=groups - 1,
            comment=f"cells 4*CellGroup .. 4*CellGroup+3 (0..{groups - 1})",
        )
    ]
    for k in range(CELLS_PER_VOLTAGE_FRAME):
        sigs.append(
            SignalSpec(
                f"CellVoltage{k}",
                8 + 14 * k,
                14,
                0.001,
                unit="V",
                sna=True,
                mux="m",
                comment=f"voltage of cell 4*CellGroup+{k}",
            )
        )
    return tuple(sigs)


def _temperatures() -> tuple[SignalSpec, ...]:
    sigs = [
        SignalSpec(
            "TempGroup",
            0,
            8,
            mux="M",
            maximum=MAX_TEMP_GROUPS - 1,
            comment="sensors 3*TempGroup .. 3*TempGroup+2",
        )
    ]
    for k in range(TEMPS_PER_FRAME):
        sigs.append(
            SignalSpec(
                f"Temperature{k}",
                8 + 16 * k,
                16,
                0.01,
                signed=True,
                unit="degC",
                sna=True,
                mux="m",
                comment=f"temperature of sensor 3*TempGroup+{k}",
            )
        )
    return tuple(sigs)


def _cell_index(length: int) -> SignalSpec:
    return SignalSpec(
        "CellIndex", 0, length, mux="M", maximum=MAX_CELLS - 1, comment="cell index, 0-based"
    )


def _cell_r() -> tuple[SignalSpec, ...]:
    return (
        _cell_index(10),
        SignalSpec("R0", 10, 18, 2e-6, unit="Ohm", sna=True, mux="m", comment="ohmic resistance"),
        SignalSpec("R1", 28, 18, 2e-6, unit="Ohm", sna=True, mux="m", comment="fast RC branch"),
        SignalSpec("R2", 46, 18, 2e-6, unit="Ohm", sna=True, mux="m", comment="slow RC branch"),
    )


def _cell_tau() -> tuple[SignalSpec, ...]:
    return (
        _cell_index(10),
        SignalSpec("Tau1", 10, 18, 0.001, unit="s", sna=True, mux="m", comment="R1*C1"),
        SignalSpec("Tau2", 28, 18, 0.05, unit="s", sna=True, mux="m", comment="R2*C2"),
        SignalSpec("Lambda", 46, 16, 2e-5, sna=True, mux="m", comment="forgetting factor"),
    )


def _cell_state() -> tuple[SignalSpec, ...]:
    return (
        _cell_index(10),
        SignalSpec(
            "H",
            10,
            12,
            0.0005,
            signed=True,
            sna=True,
            mux="m",
            comment="hysteresis state, -1 after discharge",
        ),
        SignalSpec("SOC", 22, 12, 0.00025, sna=True, mux="m", comment="state of charge, fraction"),
        SignalSpec(
            "VError",
            34,
            16,
            1e-4,
            signed=True,
            unit="V",
            sna=True,
            mux="m",
            comment="measured minus model terminal voltage",
        ),
        SignalSpec("Quality", 50, 3, mux="m", comment=QUALITY_COMMENT, choices=QUALITY_CHOICES),
        SignalSpec(
            "Saturated",
            53,
            11,
            mux="m",
            comment="bit i set: signal i saturated at its range (see dbc/README.md); bits 0-10",
        ),
    )


def _soc_std(start: int) -> SignalSpec:
    return SignalSpec(
        "SOCStd", start, 8, 0.001, sna=True, mux="m", comment="1-sigma uncertainty of SOC, fraction"
    )


def _capacity(start: int) -> SignalSpec:
    return SignalSpec(
        "Capacity", start, 16, 0.01, unit="Ah", sna=True, mux="m", comment="cell capacity"
    )


def _cell_capacity() -> tuple[SignalSpec, ...]:
    return (
        _cell_index(10),
        _capacity(10),
        _soc_std(26),
        SignalSpec(
            "Saturated",
            34,
            16,
            mux="m",
            comment="bit i set: signal i saturated at its range (see dbc/README.md); every bit",
        ),
    )


def _pack_summary() -> tuple[SignalSpec, ...]:
    return (
        SignalSpec("R0Min", 0, 16, 1e-5, unit="Ohm", sna=True, comment="smallest cell R0"),
        SignalSpec("R0Mean", 16, 16, 1e-5, unit="Ohm", sna=True, comment="mean cell R0"),
        SignalSpec("R0Max", 32, 16, 1e-5, unit="Ohm", sna=True, comment="largest cell R0"),
        SignalSpec("WeakestCell", 48, 10, sna=True, comment="index of the cell with largest R0"),
        SignalSpec(
            "Health", 58, 4, comment="health bits 1-8, 0 = ok (every bit: PackState Health)"
        ),
        SignalSpec("Saturated", 62, 1, comment="a summary value saturated at its range"),
        SignalSpec("Diverged", 63, 1, comment="a cell diverged (health bit 16)"),
    )


def _pack_state() -> tuple[SignalSpec, ...]:
    return (
        SignalSpec(
            "CurrentOffset",
            0,
            24,
            1e-5,
            signed=True,
            unit="A",
            sna=True,
            comment="pack current-sensor offset, positive = reads too much discharge",
        ),
        SignalSpec("Saturated", 24, 1, comment="a value saturated at its range"),
        # PackSummary's 8 bytes are full (Health holds bits 1-8, Diverged bit 16): every health
        # bit goes here, in bits old senders left 0, so PackSummary and its receivers stay as
        # they were and OR-ing both frames' health is right for old and new senders alike.
        SignalSpec(
            "Health",
            32,
            16,
            comment=(
                "every pack health bit (MQTT health): 1 converging, 2 poorly excited, "
                "4 out of bounds, 8 input stale or a cell without data, 16 a cell diverged, "
                "32 state directory failing; 0 = ok"
            ),
        ),
    )


def _cell_params_fd() -> tuple[SignalSpec, ...]:
    return (
        _cell_index(16),
        SignalSpec("R0", 16, 32, 1e-7, unit="Ohm", sna=True, mux="m"),
        SignalSpec("R1", 48, 32, 1e-7, unit="Ohm", sna=True, mux="m"),
        SignalSpec("R2", 80, 32, 1e-7, unit="Ohm", sna=True, mux="m"),
        SignalSpec("Tau1", 112, 32, 1e-4, unit="s", sna=True, mux="m"),
        SignalSpec("Tau2", 144, 32, 1e-4, unit="s", sna=True, mux="m"),
        SignalSpec("C1", 176, 32, 0.01, unit="F", sna=True, mux="m"),
        SignalSpec("C2", 208, 32, 0.01, unit="F", sna=True, mux="m"),
        SignalSpec("Lambda", 240, 32, 1e-9, sna=True, mux="m"),
        SignalSpec("H", 272, 16, 5e-5, signed=True, sna=True, mux="m"),
        SignalSpec("SOC", 288, 16, 2e-5, sna=True, mux="m"),
        SignalSpec("VError", 304, 32, 1e-6, signed=True, unit="V", sna=True, mux="m"),
        SignalSpec("Quality", 336, 8, mux="m", comment=QUALITY_COMMENT, choices=QUALITY_CHOICES),
        SignalSpec("Saturated", 344, 16, mux="m"),
        _soc_std(360),
        _capacity(368),
    )


#: Extended (29-bit) base and standard (11-bit) base of the output messages.
OUT_EXT_BASE = 0x18FF5100
OUT_STD_BASE = 0x300


def messages() -> tuple[MessageSpec, ...]:
    """Every message of ``bmsid.dbc`` (inputs standard ids; outputs in both id spaces)."""
    msgs = [
        MessageSpec(
            "BMSID_PackCurrent",
            0x100,
            False,
            8,
            (
                SignalSpec(
                    "PackCurrent",
                    0,
                    24,
                    0.001,
                    signed=True,
                    unit="A",
                    sna=True,
                    comment="pack current, positive = discharge",
                ),
                SignalSpec("SampleCounter", 24, 16, comment="increments once per sample tick"),
            ),
            "in",
            comment="pack current, sent first in every sample tick",
        ),
        MessageSpec(
            "BMSID_CellVoltages",
            0x110,
            False,
            8,
            _cell_voltages(),
            "in",
            comment="cell voltages, 4 cells per frame",
            mux_range=(0, 127),
        ),
        MessageSpec(
            "BMSID_Temperatures",
            0x120,
            False,
            8,
            _temperatures(),
            "in",
            comment="temperatures, 3 sensors per frame",
            mux_range=(0, 63),
        ),
    ]
    outputs = (
        ("CellR", 0x01, _cell_r(), "per-cell resistances", (0, 511), 8, False),
        (
            "CellTau",
            0x02,
            _cell_tau(),
            "per-cell time constants and forgetting factor",
            (0, 511),
            8,
            False,
        ),
        (
            "CellState",
            0x03,
            _cell_state(),
            "per-cell hysteresis, SOC, model error, quality",
            (0, 511),
            8,
            False,
        ),
        ("PackSummary", 0x04, _pack_summary(), "pack summary", None, 8, False),
        (
            "CellCapacity",
            0x05,
            _cell_capacity(),
            "per-cell capacity and SOC uncertainty",
            (0, 511),
            8,
            False,
        ),
        (
            "PackState",
            0x06,
            _pack_state(),
            "pack states: current-sensor offset, every health bit",
            None,
            8,
            False,
        ),
        (
            "CellParamsFD",
            0x10,
            _cell_params_fd(),
            "all parameters of one cell (CAN FD)",
            (0, 511),
            48,
            True,
        ),
    )
    for name, off, sigs, comment, mux_range, length, fd in outputs:
        msgs.append(
            MessageSpec(
                f"BMSID_{name}",
                OUT_EXT_BASE + off,
                True,
                length,
                sigs,
                "out",
                fd=fd,
                comment=comment + " (29-bit id)",
                mux_range=mux_range,
            )
        )
        msgs.append(
            MessageSpec(
                f"BMSID_{name}_11bit",
                OUT_STD_BASE + off,
                False,
                length,
                sigs,
                "out",
                fd=fd,
                comment=comment + " (11-bit id)",
                mux_range=mux_range,
            )
        )
    return tuple(msgs)


def _dbc_id(m: MessageSpec) -> int:
    return m.frame_id | 0x80000000 if m.extended else m.frame_id


def dbc_text() -> str:
    """The text of ``bmsid.dbc``."""
    out = [
        'VERSION "bmsid 1"',
        "",
        "NS_ :",
        "",
        "BS_:",
        "",
        "BU_: BMS BMSID",
        "",
    ]
    comments: list[str] = []
    mux_vals: list[str] = []
    value_tables: list[str] = []
    fd_attrs: list[str] = []
    for m in messages():
        sender = "BMS" if m.direction == "in" else "BMSID"
        receiver = "BMSID" if m.direction == "in" else "Vector__XXX"
        out.append(f"BO_ {_dbc_id(m)} {m.name}: {m.length} {sender}")
        for s in m.signals:
            mux = {"M": " M", "m": " m0", "": ""}[s.mux]
            lo, hi = s.phys_range()
            sign = "-" if s.signed else "+"
            out.append(
                f" SG_ {s.name}{mux} : {s.start}|{s.length}@1{sign} ({_num(s.scale)},"
                f'{_num(s.offset)}) [{_num(lo)}|{_num(hi)}] "{s.unit}" {receiver}'
            )
            if s.comment:
                comments.append(f'CM_ SG_ {_dbc_id(m)} {s.name} "{s.comment}";')
            if s.choices:
                names = " ".join(f'{v} "{name}"' for v, name in s.choices)
                value_tables.append(f"VAL_ {_dbc_id(m)} {s.name} {names} ;")
            if s.mux == "m" and m.mux_range is not None:
                mux_name = next(x.name for x in m.signals if x.mux == "M")
                mux_vals.append(
                    f"SG_MUL_VAL_ {_dbc_id(m)} {s.name} {mux_name} "
                    f"{m.mux_range[0]}-{m.mux_range[1]};"
                )
        out.append("")
        if m.comment:
            comments.append(f'CM_ BO_ {_dbc_id(m)} "{m.comment}";')
        if m.fd:
            fd_attrs.append(f'BA_ "VFrameFormat" BO_ {_dbc_id(m)} {15 if m.extended else 14};')
    formats = ",".join(
        ['"StandardCAN"', '"ExtendedCAN"']
        + ['"reserved"'] * 12
        + ['"StandardCAN_FD"', '"ExtendedCAN_FD"']
    )
    out += comments
    out.append(f'BA_DEF_ BO_ "VFrameFormat" ENUM {formats};')
    out.append('BA_DEF_DEF_ "VFrameFormat" "StandardCAN";')
    out += fd_attrs
    out += value_tables
    out += mux_vals
    return "\n".join(out) + "\n"


def markdown_table() -> str:
    """The resolution/range table of ``dbc/README.md``."""
    rows = [
        "| Message | Id | Signal | Bits | Resolution | Range | Unit | SNA |",
        "|---|---|---|---|---|---|---|---|",
    ]
    for m in messages():
        if m.name.endswith("_11bit"):
            continue
        for s in m.signals:
            lo, hi = s.phys_range()
            ident = f"0x{m.frame_id:08X}" if m.extended else f"0x{m.frame_id:03X}"
            rows.append(
                f"| {m.name} | {ident} | {s.name} | {s.length}{'s' if s.signed else ''} | "
                f"{_num(s.scale)} | {_num(lo)} .. {_num(hi)} | {s.unit} | "
                f"{'yes' if s.sna else ''} |"
            )
    return "\n".join(rows) + "\n"


def main() -> None:
    here = Path(__file__).resolve().parent.parent
    parser = argparse.ArgumentParser(description="write bmsid.dbc")
    parser.add_argument(
        "--out",
        type=Path,
        action="append",
        help="output file (default: the packaged copy and ../dbc/bmsid.dbc of a checkout)",
    )
    args = parser.parse_args()
    targets: list[Path] = args.out or [here / "dbc" / "bmsid.dbc"]
    if not args.out and (here.parent.parent / "dbc").is_dir():
        targets.append(here.parent.parent / "dbc" / "bmsid.dbc")
    text = dbc_text()
    for t in targets:
        t.write_text(text, encoding="utf-8")
        print(f"wrote {t}")


if __name__ == "__main__":
    main()
