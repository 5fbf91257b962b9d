"""The daemon's in-process replay of a candump log holding two packs on two CAN interfaces:
refused without ``can.replay.channel`` (as ``bmsid identify`` refuses it without --channel),
one pack's frames only with it. Measured before: both packs merged into one, R0 doubled."""

from __future__ import annotations

import asyncio
from pathlib import Path

import can
import pytest
from daemon_helpers import demo_frames, make_settings, offline_estimates, run_replay

from bmsid.canbus.logs import write_log
from bmsid.config.settings import Settings
from bmsid.daemon.core import Daemon
from bmsid.errors import UserError
from bmsid.estimate.types import Estimates

DURATION_S = 200.0


def _shifted(frames: list[can.Message], dt_s: float, channel: str) -> list[can.Message]:
    return [
        can.Message(
            timestamp=m.timestamp + dt_s,
            arbitration_id=m.arbitration_id,
            is_extended_id=m.is_extended_id,
            data=bytes(m.data),
            channel=channel,
        )
        for m in frames
    ]


def _two_pack_log(path: Path) -> tuple[list[can.Message], list[can.Message]]:
    """can0: the demo's first 200 s; can1: another pack (the demo 600 s on) on the same time
    axis, 0.5 ms behind. Written interleaved in time order, as candump records two buses."""
    head = demo_frames(DURATION_S)
    later = [m for m in demo_frames(600.0 + DURATION_S) if m.timestamp >= head[0].timestamp + 600]
    can0 = _shifted(head, 0.0, "can0")
    can1 = _shifted(later, head[0].timestamp - later[0].timestamp + 0.0005, "can1")
    merged = sorted(can0 + can1, key=lambda m: m.timestamp)
    with path.open("w", encoding="utf-8") as fh:  # write_log sets one channel on every frame
        for m in merged:
            fh.write(f"({m.timestamp:.6f}) {m.channel} {m.arbitration_id:03X}#{m.data.hex()}\n")
    return can0, can1


def _settings(tmp_path: Path, log: Path, **replay: str) -> Settings:
    return make_settings(
        tmp_path, None, can={"replay": {"log": str(log), "speed": 1000.0, **replay}}
    )


def test_two_channel_log_without_replay_channel_is_refused_at_start(tmp_path: Path) -> None:
    log = tmp_path / "two.log"
    _two_pack_log(log)
    with pytest.raises(UserError) as err:
        Daemon(_settings(tmp_path, log))
    msg = str(err.value)
    assert msg.startswith("can.replay.channel: ") and "(one of can0, can1)" in msg
    assert not (tmp_path / "state").exists()  # nothing started


def test_replay_channel_absent_from_the_log_is_refused(tmp_path: Path) -> None:
    log = tmp_path / "two.log"
    _two_pack_log(log)
    with pytest.raises(UserError, match=r"can.replay.channel: .*'can7' .*can0, can1"):
        Daemon(_settings(tmp_path, log, channel="can7"))


@pytest.mark.parametrize("channel", ["can0", "can1"])
def test_replay_channel_replays_that_pack_only(tmp_path: Path, channel: str) -> None:
    log = tmp_path / "two.log"
    packs = dict(zip(("can0", "can1"), _two_pack_log(log), strict=True))
    settings = _settings(tmp_path, log, channel=channel)
    ref = offline_estimates(packs[channel], settings)
    seen: dict[float, Estimates] = {}

    async def main() -> None:
        await run_replay(Daemon(settings, on_estimates=lambda e: seen.setdefault(e.t_s, e)))

    asyncio.run(main())
    assert ref and sorted(seen) == sorted(ref)
    for t, e in ref.items():
        assert list(seen[t].R0_ohm) == list(e.R0_ohm)


def test_single_channel_log_needs_no_replay_channel(tmp_path: Path) -> None:
    log = tmp_path / "one.log"
    frames = demo_frames(60.0)
    write_log(log, frames, channel="can1")
    assert Daemon(_settings(tmp_path, log)).replay_channel is None
