"""bmsid.dbc: generated from one table, loads strictly, dumps, and round-trips within resolution."""

from __future__ import annotations

import filecmp
import math
import subprocess
import sys
from pathlib import Path

import cantools
import pytest
from hypothesis import given
from hypothesis import strategies as st

from bmsid.canbus import dbcgen
from bmsid.canbus.codec import decode_raw, encode_saturating, raw_range
from bmsid.canbus.mapping import PACKAGE_DBC_DIR

REPO = Path(__file__).resolve().parents[2]
DB = cantools.database.load_file(str(PACKAGE_DBC_DIR / "bmsid.dbc"), strict=True)


def test_generated_text_is_the_shipped_file() -> None:
    assert (PACKAGE_DBC_DIR / "bmsid.dbc").read_text() == dbcgen.dbc_text()


@pytest.mark.parametrize(
    "name",
    ["bmsid.dbc", "example_bms_motorola.dbc", "bmsid_mapping.toml", "example_bms_mapping.toml"],
)
def test_repo_and_package_copies_are_identical(name: str) -> None:
    assert filecmp.cmp(REPO / "dbc" / name, PACKAGE_DBC_DIR / name, shallow=False)


def test_readme_table_is_current() -> None:
    assert dbcgen.markdown_table() in (REPO / "dbc" / "README.md").read_text()


@pytest.mark.parametrize("name", ["bmsid.dbc", "example_bms_motorola.dbc"])
def test_cantools_dump_accepts_the_dbc(name: str) -> None:
    res = subprocess.run(
        [sys.executable, "-m", "cantools", "dump", str(REPO / "dbc" / name)],
        capture_output=True,
        text=True,
        check=False,
    )
    assert res.returncode == 0, res.stderr
    assert "Messages" in res.stdout


def test_ids_fd_and_capacity() -> None:
    cur = DB.get_message_by_name("BMSID_PackCurrent")
    assert not cur.is_extended_frame
    assert DB.get_message_by_name("BMSID_CellR").is_extended_frame
    assert not DB.get_message_by_name("BMSID_CellR_11bit").is_extended_frame
    fd = DB.get_message_by_name("BMSID_CellParamsFD")
    assert fd.is_fd and fd.length == 48
    sig = cur.get_signal_by_name("PackCurrent")
    assert sig.scale <= 0.01 and sig.minimum <= -1000 and sig.maximum >= 1000
    groups = DB.get_message_by_name("BMSID_CellVoltages").get_signal_by_name("CellVoltage0")
    assert len(groups.multiplexer_ids) * dbcgen.CELLS_PER_VOLTAGE_FRAME >= 512
    assert groups.scale == 0.001


def test_ranges_serve_prismatic_and_18650_cells() -> None:
    r = DB.get_message_by_name("BMSID_CellR").get_signal_by_name("R0")
    assert r.scale <= 0.01 * 1e-3 and r.maximum >= 0.2  # 1 % of 1 mOhm .. 18650 and worse
    tau2 = DB.get_message_by_name("BMSID_CellTau").get_signal_by_name("Tau2")
    assert tau2.maximum >= 8000
    c = DB.get_message_by_name("BMSID_CellParamsFD").get_signal_by_name("C2")
    assert c.maximum >= 1e6


@st.composite
def message_and_values(draw: st.DrawFn) -> tuple[cantools.database.can.Message, dict[str, float]]:
    msg = draw(st.sampled_from(DB.messages))
    values: dict[str, float] = {}
    mux_value = None
    for sig in msg.signals:
        if sig.is_multiplexer:
            mux_value = draw(
                st.sampled_from(sorted({i for s in msg.signals for i in (s.multiplexer_ids or [])}))
            )
            values[sig.name] = float(mux_value)
    for sig in msg.signals:
        if sig.is_multiplexer:
            continue
        lo, hi = float(sig.minimum), float(sig.maximum)
        values[sig.name] = draw(st.floats(lo, hi, allow_nan=False))
    return msg, values


@given(message_and_values())
def test_encode_decode_round_trip_within_resolution(
    case: tuple[cantools.database.can.Message, dict[str, float]],
) -> None:
    msg, values = case
    data, saturated = encode_saturating(msg, values)
    assert saturated == []
    back = decode_raw(msg, data)
    for name, v in values.items():
        sig = msg.get_signal_by_name(name)
        assert math.isclose(back[name], v, abs_tol=sig.scale / 2 * (1 + 1e-9)), name
    # an independent decoder (plain cantools) agrees
    plain = msg.decode(data, decode_choices=False)
    for name in values:
        assert math.isclose(float(plain[name]), back[name], abs_tol=1e-9)


@given(st.sampled_from([m for m in DB.messages if not m.is_multiplexed()]), st.data())
def test_out_of_range_saturates_never_wraps(
    msg: cantools.database.can.Message, data: st.DataObject
) -> None:
    sig = data.draw(st.sampled_from([s for s in msg.signals if raw_range(s).sna is not None]))
    too_big = float(sig.maximum) + data.draw(st.floats(1.0, 1e9)) * sig.scale
    encoded, saturated = encode_saturating(msg, {sig.name: too_big})
    assert saturated == [sig.name]
    assert math.isclose(decode_raw(msg, encoded)[sig.name], float(sig.maximum), rel_tol=1e-9)
    encoded, _ = encode_saturating(msg, {sig.name: math.nan})
    assert math.isnan(decode_raw(msg, encoded)[sig.name])
