"""Parameter frames: round trip within resolution, saturation flags, NaN as not available."""

from __future__ import annotations

import functools
import math
from pathlib import Path

import can
import cantools
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from bmsid.canbus.dbcgen import CLASSIC_STATE_MASK_BITS, SATURATION_BITS
from bmsid.canbus.encoder import CLASSIC_PAGES, PACK_PAGES, ParameterEncoder
from bmsid.canbus.mapping import PACKAGE_DBC_DIR
from bmsid.estimate.types import Estimates, Quality
from bmsid.publish import payloads

REPO = Path(__file__).resolve().parents[2]


def estimates(n: int = 3, **over: float) -> Estimates:
    def arr(v: float) -> np.ndarray:
        return np.full(n, v, dtype=np.float64)

    base = dict(
        R0_ohm=1.2e-3,
        R1_ohm=0.4e-3,
        R2_ohm=0.8e-3,
        tau1_s=12.0,
        tau2_s=2400.0,
        M_V=0.01,
        ocv_offset_V=0.0,
        lambda_=0.995,
        h=-0.7,
        soc=0.63,
        soc_std=0.021,
        capacity_Ah=2.43,
        capacity_std_Ah=0.05,
        current_offset_A=-0.0123,
        v_model_V=3.30,
        v_meas_V=3.3021,
        arx_error_V=0.0,
    )
    base.update(over)
    fields = {k: arr(v) for k, v in base.items()}
    fields["C1_F"] = fields["tau1_s"] / fields["R1_ohm"]
    fields["C2_F"] = fields["tau2_s"] / fields["R2_ohm"]
    fields["v_error_V"] = fields["v_meas_V"] - fields["v_model_V"]
    return Estimates(t_s=5.0, current_A=1.0, cells=fields, quality=np.full(n, 1, dtype=np.int64))


EXPECT = {
    "R0_ohm": 1.2e-3,
    "R1_ohm": 0.4e-3,
    "R2_ohm": 0.8e-3,
    "tau1_s": 12.0,
    "tau2_s": 2400.0,
    "lambda": 0.995,
    "h": -0.7,
    "soc": 0.63,
    "soc_std": 0.021,
    "capacity_Ah": 2.43,
    "v_error_V": 0.0021,
    "quality": 1.0,
}


def _merged(enc: ParameterEncoder, est: Estimates, cell: int) -> dict[str, float]:
    out: dict[str, float] = {}
    for f in enc.cell_frames(est, [cell]):
        d = enc.decode(f)
        assert d is not None and d["cell"] == cell
        out |= d
    return out


@pytest.mark.parametrize(
    ("ext", "fd", "n_frames"), [(True, False, 4), (False, False, 4), (True, True, 1)]
)
def test_cell_frames_round_trip(ext: bool, fd: bool, n_frames: int) -> None:
    enc = ParameterEncoder(extended_id=ext, fd=fd)
    est = estimates()
    frames = enc.cell_frames(est, [0, 2])
    assert len(frames) == 2 * n_frames
    assert all(f.is_extended_id == ext and f.is_fd == fd for f in frames)
    got = _merged(enc, est, 2)
    for k, v in EXPECT.items():
        assert got[k] == pytest.approx(v, rel=2e-3, abs=1e-4), k
    assert got["saturated_mask"] == 0


def test_out_of_range_saturates_and_flags() -> None:
    enc = ParameterEncoder()
    got = _merged(enc, estimates(R0_ohm=2.0, tau2_s=1e6, h=-3.0), 0)
    assert got["R0_ohm"] == pytest.approx(0.524284)
    assert got["tau2_s"] == pytest.approx(13107.1)
    assert got["h"] == pytest.approx(-1.0235)
    mask = int(got["saturated_mask"])
    assert mask == (1 << SATURATION_BITS["R0"]) | (1 << SATURATION_BITS["Tau2"]) | (
        1 << SATURATION_BITS["H"]
    )


@pytest.mark.parametrize("fd", [False, True])
def test_new_signals_saturate_into_the_masks_that_have_room(fd: bool) -> None:
    """Capacity (bit 12) and SOCStd (bit 11) saturate like the others; in classic CAN only the
    16-bit mask of ``CellCapacity`` has room for them, ``CellState``'s 11 bits keep bits 0-10."""
    enc = ParameterEncoder(fd=fd)
    est = estimates(capacity_Ah=1000.0, soc_std=0.4, R0_ohm=2.0 if not fd else 1e-3)
    new_bits = (1 << SATURATION_BITS["Capacity"]) | (1 << SATURATION_BITS["SOCStd"])
    masks = {}
    for f in enc.cell_frames(est, [0]):
        d = enc.decode(f)
        assert d is not None
        if "saturated_mask" in d:
            masks[f.arbitration_id & 0xFF] = int(d["saturated_mask"])
        if "capacity_Ah" in d:
            assert d["capacity_Ah"] == pytest.approx(655.34)
            assert d["soc_std"] == pytest.approx(0.254)
    if fd:
        assert masks == {0x10: new_bits}
    else:
        r0_bit = 1 << SATURATION_BITS["R0"]
        assert masks == {0x03: r0_bit, 0x05: r0_bit | new_bits}
        assert max(SATURATION_BITS.values()) >= CLASSIC_STATE_MASK_BITS  # why two masks


def test_classic_and_fd_send_the_same_new_fields() -> None:
    est = estimates(soc_std=0.0123, capacity_Ah=280.17)
    for fd in (False, True):
        got = _merged(ParameterEncoder(fd=fd), est, 1)
        assert got["soc_std"] == pytest.approx(0.012, abs=5e-4)
        assert got["capacity_Ah"] == pytest.approx(280.17, abs=5e-3)
        assert "capacity_std_Ah" not in got and "current_offset_A" not in got  # not cell signals
    assert CLASSIC_PAGES[:3] == ("CellR", "CellTau", "CellState")  # the old pages keep their order


def test_nan_is_sent_as_not_available() -> None:
    enc = ParameterEncoder()
    got = _merged(enc, estimates(R1_ohm=math.nan), 1)
    assert math.isnan(got["R1_ohm"]) and got["saturated_mask"] == 0


def test_pack_frame() -> None:
    enc = ParameterEncoder()
    est = estimates(4)
    r0 = np.array([1e-3, 3e-3, np.nan, 2e-3])
    est = Estimates(est.t_s, est.current_A, {**est.cells, "R0_ohm": r0}, est.quality)
    d = enc.decode(enc.pack_frame(est, health=2))
    assert d is not None
    assert d["R0_min_ohm"] == pytest.approx(1e-3) and d["R0_max_ohm"] == pytest.approx(3e-3)
    assert d["R0_mean_ohm"] == pytest.approx(2e-3) and d["weakest_cell"] == 1 and d["health"] == 2


@pytest.mark.parametrize("ext", [True, False])
def test_pack_frames_carry_the_current_offset_and_every_health_bit(ext: bool) -> None:
    enc = ParameterEncoder(extended_id=ext)
    est = estimates(4, current_offset_A=0.0421)
    quality = np.array([1, 4, 3, 0])
    est = Estimates(est.t_s, est.current_A, est.cells, quality)
    health = payloads.health_bits(est) | payloads.HEALTH_INPUT_STALE
    assert health == 1 | 4 | 8 | payloads.HEALTH_DIVERGED
    frames = enc.pack_frames(est, health)
    assert len(frames) == len(PACK_PAGES) == 2
    summary, state = (enc.decode(f) for f in frames)
    assert summary is not None and state is not None
    assert summary["health"] == health
    assert summary["R0_mean_ohm"] == pytest.approx(1.2e-3)
    assert state == {
        "current_offset_A": pytest.approx(0.0421, abs=5e-6),
        "saturated_mask": 0,
        "health": health,
    }
    assert enc.decode(enc.pack_frame(est, health)) == summary  # the first of the pack frames
    # MQTT says the same
    body = payloads.pack_payload(est, "p", 0, health)
    assert body["current_offset_A"] == pytest.approx(0.0421)
    assert body["health"] == health and body["quality_counts"]["diverged"] == 1


@pytest.mark.parametrize("health", [0, 1, 15, 16, 17, 31])
def test_health_round_trips_through_both_signals(health: int) -> None:
    enc = ParameterEncoder()
    d = enc.decode(enc.pack_frame(estimates(), health))
    assert d is not None and d["health"] == health


ALL_HEALTH_BITS = (
    payloads.HEALTH_CONVERGING
    | payloads.HEALTH_POORLY_EXCITED
    | payloads.HEALTH_OUT_OF_BOUNDS
    | payloads.HEALTH_INPUT_STALE
    | payloads.HEALTH_DIVERGED
    | payloads.HEALTH_STATE_DIR
)


@functools.cache
def _cantools_db(path: Path) -> cantools.database.can.Database:
    """A DBC as a receiver loads it: plain cantools (~0.8 s a load here, hence the cache)."""
    db = cantools.database.load_file(str(path), strict=True)
    assert isinstance(db, cantools.database.can.Database)
    return db


def _cantools_pack_health(db: cantools.database.Database, frames: list[can.Message]) -> int:
    """Health as a receiver with only cantools and a DBC reads it: the OR of both pack frames
    (dbc/README.md), PackState's ``Health`` absent from a DBC older than it."""
    summary, state = (db.decode_message(f.arbitration_id, bytes(f.data)) for f in frames)
    assert isinstance(summary, dict) and isinstance(state, dict)
    return int(summary["Health"]) | int(summary["Diverged"]) << 4 | int(state.get("Health", 0))


@pytest.mark.parametrize("ext", [True, False])
@pytest.mark.parametrize(
    "health", [payloads.HEALTH_STATE_DIR, payloads.HEALTH_STATE_DIR | 16 | 1, ALL_HEALTH_BITS]
)
def test_health_bit_32_round_trips_through_cantools(ext: bool, health: int) -> None:
    frames = ParameterEncoder(extended_id=ext).pack_frames(estimates(), health)
    db = _cantools_db(REPO / "dbc" / "bmsid.dbc")  # the shipped copies are identical (test_can_dbc)
    state = db.decode_message(frames[1].arbitration_id, bytes(frames[1].data))
    assert isinstance(state, dict) and state["Health"] == health
    assert _cantools_pack_health(db, frames) == health


def test_every_health_bit_fits_the_pack_state_signal() -> None:
    enc = ParameterEncoder()
    assert ALL_HEALTH_BITS & enc.state_health_mask == ALL_HEALTH_BITS
    d = enc.decode(enc.pack_frames(estimates(), ALL_HEALTH_BITS)[1])
    assert d is not None and d["health"] == ALL_HEALTH_BITS


def _old_dbc(tmp_path: Path) -> Path:
    """bmsid.dbc as it was before PackState carried ``Health``."""
    text = (PACKAGE_DBC_DIR / "bmsid.dbc").read_text(encoding="utf-8")
    old = "\n".join(
        line
        for line in text.splitlines()
        if not line.startswith(" SG_ Health : 32|16")
        and not (line.startswith("CM_ SG_ ") and ' Health "every pack health bit' in line)
    )
    assert old.count("SG_ Health") == text.count("SG_ Health") - 2  # 29- and 11-bit PackState
    path = tmp_path / "bmsid-old.dbc"
    path.write_text(old + "\n", encoding="utf-8")
    return path


def test_old_receivers_decode_the_new_pack_frames_as_before(tmp_path: Path) -> None:
    old_dbc = _old_dbc(tmp_path)
    old_db = _cantools_db(old_dbc)
    est = estimates(current_offset_A=0.0421)
    new_frames = ParameterEncoder().pack_frames(est, 63)
    old_frames = ParameterEncoder(old_dbc).pack_frames(est, 63)  # an old sender
    assert bytes(new_frames[0].data) == bytes(old_frames[0].data)  # PackSummary unchanged
    for frames in (new_frames, old_frames):
        state = old_db.decode_message(frames[1].arbitration_id, bytes(frames[1].data))
        assert state == {"CurrentOffset": pytest.approx(0.0421, abs=5e-6), "Saturated": 0}
        assert _cantools_pack_health(old_db, frames) == 31  # what an old receiver always saw
    # a new receiver hearing an old sender: the bits that sender could carry, bit 32 absent
    new_db = _cantools_db(REPO / "dbc" / "bmsid.dbc")
    assert _cantools_pack_health(new_db, old_frames) == 31
    assert _cantools_pack_health(new_db, new_frames) == 63


def test_pack_state_sends_nan_offset_as_not_available_and_saturates() -> None:
    enc = ParameterEncoder()
    nan = enc.decode(enc.pack_frames(estimates(current_offset_A=math.nan), 0)[1])
    assert nan is not None and math.isnan(nan["current_offset_A"]) and nan["saturated_mask"] == 0
    big = enc.decode(enc.pack_frames(estimates(current_offset_A=-500.0), 0)[1])
    assert big is not None and big["saturated_mask"] == 1
    assert big["current_offset_A"] == pytest.approx(-83.88607)


def test_diverged_quality_is_sent_as_its_code() -> None:
    est = estimates(2)
    est = Estimates(est.t_s, est.current_A, est.cells, np.array([Quality.DIVERGED, 1]))
    for fd in (False, True):
        enc = ParameterEncoder(fd=fd)
        assert _merged(enc, est, 0)["quality"] == Quality.DIVERGED == 4
        assert _merged(enc, est, 1)["quality"] == 1


def test_decode_rejects_foreign_and_malformed_frames() -> None:
    import can

    enc = ParameterEncoder()
    assert (
        enc.decode(can.Message(arbitration_id=0x100, is_extended_id=False, data=bytes(8))) is None
    )
    f = enc.cell_frames(estimates(), [0])[0]
    f.data = f.data[:5]
    assert enc.decode(f) is None


@settings(max_examples=60, deadline=None)
@given(
    r0=st.floats(1e-5, 0.5),
    tau1=st.floats(0.5, 200.0),
    tau2=st.floats(20.0, 8000.0),
    lam=st.floats(0.9, 1.0),
    h=st.floats(-1.0, 1.0),
    soc=st.floats(0.0, 1.0),
    fd=st.booleans(),
)
def test_round_trip_within_resolution(
    *, r0: float, tau1: float, tau2: float, lam: float, h: float, soc: float, fd: bool
) -> None:
    enc = ParameterEncoder(fd=fd)
    got = _merged(
        enc, estimates(1, R0_ohm=r0, tau1_s=tau1, tau2_s=tau2, lambda_=lam, h=h, soc=soc), 0
    )
    assert abs(got["R0_ohm"] - r0) <= (1e-7 if fd else 2e-6) / 2 + 1e-12
    assert abs(got["tau1_s"] - tau1) <= (1e-4 if fd else 1e-3) / 2 + 1e-9
    assert abs(got["tau2_s"] - tau2) <= (1e-4 if fd else 0.05) / 2 + 1e-9
    assert abs(got["lambda"] - lam) <= (1e-9 if fd else 2e-5) / 2 + 1e-12
    assert abs(got["h"] - h) <= (5e-5 if fd else 5e-4) / 2 + 1e-12
    assert abs(got["soc"] - soc) <= (2e-5 if fd else 2.5e-4) / 2 + 1e-12
    assert got["saturated_mask"] == 0
