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
from bmsid.estimate.types import Quality

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


#: bmsid 0.1's output frames (29-bit ids; the 11-bit twins are 0x300 + the low byte): id, bytes,
#: signal -> (start bit, length, scale). Receivers decode these: signals are added, never moved.
LAYOUT_0_1: dict[str, tuple[int, int, dict[str, tuple[int, int, float]]]] = {
    "BMSID_CellR": (0x18FF5101, 8, {"CellIndex": (0, 10, 1), "R0": (10, 18, 2e-06),
                    "R1": (28, 18, 2e-06), "R2": (46, 18, 2e-06)}),
    "BMSID_CellTau": (0x18FF5102, 8, {"CellIndex": (0, 10, 1), "Tau1": (10, 18, 0.001),
                      "Tau2": (28, 18, 0.05), "Lambda": (46, 16, 2e-05)}),
    "BMSID_CellState": (0x18FF5103, 8, {"CellIndex": (0, 10, 1), "H": (10, 12, 0.0005),
                        "SOC": (22, 12, 0.00025), "VError": (34, 16, 0.0001),
                        "Quality": (50, 3, 1), "Saturated": (53, 11, 1)}),
    "BMSID_PackSummary": (0x18FF5104, 8, {"R0Min": (0, 16, 1e-05), "R0Mean": (16, 16, 1e-05),
                          "R0Max": (32, 16, 1e-05), "WeakestCell": (48, 10, 1),
                          "Health": (58, 4, 1), "Saturated": (62, 1, 1)}),
    "BMSID_CellParamsFD": (0x18FF5110, 48, {"CellIndex": (0, 16, 1), "R0": (16, 32, 1e-07),
                           "R1": (48, 32, 1e-07), "R2": (80, 32, 1e-07),
                           "Tau1": (112, 32, 0.0001), "Tau2": (144, 32, 0.0001),
                           "C1": (176, 32, 0.01), "C2": (208, 32, 0.01),
                           "Lambda": (240, 32, 1e-09), "H": (272, 16, 5e-05),
                           "SOC": (288, 16, 2e-05), "VError": (304, 32, 1e-06),
                           "Quality": (336, 8, 1), "Saturated": (344, 16, 1)}),
}  # fmt: skip


@pytest.mark.parametrize("name", sorted(LAYOUT_0_1))
def test_existing_output_frames_keep_their_ids_and_signals(name: str) -> None:
    frame_id, length, signals = LAYOUT_0_1[name]
    twin = 0x300 + (frame_id & 0xFF)
    for m, ident in ((DB.get_message_by_name(name), frame_id),
                     (DB.get_message_by_name(name + "_11bit"), twin)):  # fmt: skip
        assert (m.frame_id, m.length) == (ident, length)
        for sig, (start, n_bits, scale) in signals.items():
            s = m.get_signal_by_name(sig)
            assert (s.start, s.length, s.scale) == (start, n_bits, scale), (name, sig)


def test_new_outputs_fit_without_overlap_and_name_the_quality_codes() -> None:
    ids = [m.frame_id for m in DB.messages]
    assert len(ids) == len(set(ids))
    assert DB.get_message_by_name("BMSID_CellCapacity").frame_id == 0x18FF5105
    assert DB.get_message_by_name("BMSID_PackState_11bit").frame_id == 0x306
    cap = DB.get_message_by_name("BMSID_CellParamsFD").get_signal_by_name("Capacity")
    assert cap.unit == "Ah" and cap.maximum >= 300  # large prismatic cells (280 Ah LFP)
    for name in ("BMSID_CellState", "BMSID_CellParamsFD"):
        quality = DB.get_message_by_name(name).get_signal_by_name("Quality")
        assert dict(quality.choices or {}) == {q.value: q.name.lower() for q in Quality}
    # strict loading above already rejected overlapping signals; every mask bit fits a mask
    fd_mask = DB.get_message_by_name("BMSID_CellParamsFD").get_signal_by_name("Saturated")
    assert max(dbcgen.SATURATION_BITS.values()) < fd_mask.length


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
