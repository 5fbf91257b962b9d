"""Real SocketCAN: can-utils are the independent peers of bmsid's reader and writer."""

from __future__ import annotations

import asyncio
import shutil
import subprocess
import time
from pathlib import Path

import cantools
import numpy as np
import pytest
from can_helpers import synthetic
from test_can_encoder import estimates

from bmsid.canbus.bus import AsyncFrameReader, open_socketcan, send_frames
from bmsid.canbus.encoder import ParameterEncoder
from bmsid.canbus.frames_to_samples import FrameToSamples
from bmsid.canbus.logs import csv_to_messages, write_log
from bmsid.canbus.mapping import DEFAULT_DBC_PATH, load_mapping

pytestmark = pytest.mark.realcan
REPO = Path(__file__).resolve().parents[2]


def _tool(name: str) -> str:
    path = shutil.which(name)
    if path is None:
        pytest.fail(f"{name} (can-utils) is not installed")
    return path


@pytest.mark.parametrize("mapping_file", ["bmsid_mapping.toml", "example_bms_mapping.toml"])
def test_canplayer_replay_is_decoded(vcan_channel: str, tmp_path: Path, mapping_file: str) -> None:
    mapping = load_mapping(REPO / "dbc" / mapping_file)
    n, n_cells = 200, 8
    t, i, v = synthetic(n, n_cells)
    t = t * 0.02  # 50 ticks/s keeps the replay short and within UML's syscall speed
    msgs = list(csv_to_messages(t, i, v, mapping, t0_s=1.0))
    log = tmp_path / "replay.log"
    write_log(log, msgs, channel="can0")

    async def replay() -> list:
        bus = open_socketcan(vcan_channel)
        reader = AsyncFrameReader(bus)
        f2s = FrameToSamples(mapping, n_cells)
        samples: list = []
        player = await asyncio.create_subprocess_exec(
            _tool("canplayer"), "-I", str(log), f"{vcan_channel}=can0"
        )
        try:
            async with asyncio.timeout(60):
                while len(samples) < n:
                    samples += f2s.feed(await reader.get())
        finally:
            await player.wait()
            reader.close()
            bus.shutdown()
        assert reader.dropped == 0 and f2s.counters["frames"] == len(msgs)
        return samples

    samples = asyncio.run(replay())
    assert len(samples) == n and all(not s.flags for s in samples)
    tol_i = 0.05 if "example" in mapping_file else 5e-4
    np.testing.assert_allclose([s.current_A for s in samples], i, atol=tol_i * 1.0001)
    np.testing.assert_allclose(np.array([s.cell_voltages_V for s in samples]), v, atol=5.001e-4)
    dt = np.diff([s.t_s for s in samples])  # kernel timestamps of a real replay
    assert np.median(dt) == pytest.approx(0.02, abs=0.01)


@pytest.mark.parametrize("extended_id", [True, False])
def test_parameter_frames_reach_candump(
    vcan_channel: str, tmp_path: Path, extended_id: bool
) -> None:
    enc = ParameterEncoder(extended_id=extended_id)
    est = estimates(16)
    frames = [*enc.cell_frames(est, range(16)), enc.pack_frame(est, health=1)]
    out = tmp_path / "dump.txt"
    with out.open("w") as fh:
        dump = subprocess.Popen([_tool("candump"), "-L", vcan_channel], stdout=fh)
        try:
            time.sleep(0.5)  # let candump bind before we send
            bus = open_socketcan(vcan_channel)
            try:
                assert asyncio.run(send_frames(bus, frames)) == len(frames)
            finally:
                bus.shutdown()
            time.sleep(0.5)
        finally:
            dump.terminate()
            dump.wait(10)
    lines = out.read_text().split()
    captured = [x for x in lines if "#" in x]
    assert len(captured) == len(frames)
    db = cantools.database.load_file(str(DEFAULT_DBC_PATH))  # independent of bmsid's decoder
    seen_cells = set()
    for item in captured:
        ident, data = item.split("#")
        assert (len(ident) == 8) == extended_id
        decoded = db.decode_message(int(ident, 16), bytes.fromhex(data))
        if "CellIndex" in decoded:
            seen_cells.add(decoded["CellIndex"])
        if "R0" in decoded:
            assert decoded["R0"] == pytest.approx(1.2e-3, abs=1e-6)
        if "Tau2" in decoded:
            assert decoded["Tau2"] == pytest.approx(2400.0, abs=0.025)
        if "SOC" in decoded:
            assert decoded["SOC"] == pytest.approx(0.63, abs=1.25e-4)
            assert decoded["Saturated"] == 0
        if "WeakestCell" in decoded:
            assert decoded["Health"] == 1 and decoded["R0Max"] == pytest.approx(1.2e-3, abs=5e-6)
    assert seen_cells == set(range(16))
