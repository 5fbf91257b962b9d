"""The bundled 8-cell log with lost frames, replayed through the real daemon into a real Home
Assistant (issue 16, item 6's target): HA shows ``unknown`` exactly where bmsid has no value,
numbers again once it has, and its log stays clean.

The in-process ``Daemon`` runs on python-can's virtual bus (its loop in a thread: the test's
HA calls block) and publishes discovery and data to the test's Mosquitto, to which HA's MQTT
integration (added as a user adds it, ``ha_tools``) is connected. The test sends the log's
first ~260 one-second ticks itself, at full speed, pausing where HA is to be looked at:

1. start-up: the frames of cells 4-7 are lost for the first ticks (a late BMS board), and
   cell 3 reads 0 V (a sensor dropout the gates refuse). bmsid publishes nothing for cells
   4-7 (never on the bus yet) and cell 3 as ``no_data`` (every field null): HA shows every
   sensor of cells 3-7 ``unknown`` (not 0), cell 3's quality ``no_data``; cells 0-2 and the
   pack's aggregates (over cells 0-2 only) are numbers;
2. ~250 intact ticks: cells 3-7 from their own data, every sensor a number;
3. three times, the frame of cells 0-3 lost (until a tick without it is published: the next
   tick's first frame closes a cycle that lost a frame), then intact ticks: cell 0's model
   error (an internal, enabled here as a user does) ``unknown`` while bmsid has no voltage,
   not the stale value, while its SOC stays the counted number; then a number again.

At every pause every watched entity must show exactly what bmsid last published on its topic
(an independent ``mosquitto_sub`` records it), through the discovery config's template:
``unknown`` for null or for a topic bmsid never published. That rules out stale and invented
values alike. About 11 s (HA listens after 3-6 s, the replay and the looks take ~5 s); a reload
of HA's MQTT integration in the middle (HA's own, 30 s after an entity is enabled, on a slow
machine) costs one more tick, not the test.
"""

from __future__ import annotations

import asyncio
import json
import math
import re
import sys
import threading
import time
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any, TypeVar, cast

import can
import pytest
from dashboard_tools import Process, wait_until
from ha_tools import HomeAssistant, log_problems, running_home_assistant

from bmsid.canbus.mapping import MultiplexedGroup, default_mapping
from bmsid.daemon.core import Daemon
from bmsid.estimate.types import Estimates, Quality
from bmsid.publish.discovery import discovery_messages

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "daemon"))
from daemon_helpers import MqttCapture, all_published, demo_frames, make_settings

T = TypeVar("T")
PACK = "replay"
N_CELLS = 8
_CELLS = default_mapping().cells
assert isinstance(_CELLS, MultiplexedGroup)
#: the cell-voltage frame; multiplexer value g carries cells g*len(signals) + 0, 1, ...
CELL_MESSAGE = default_mapping().database().get_message_by_name(_CELLS.message)
CELL_SIGNALS: list[str] = _CELLS.signals
MUX: str = _CELLS.multiplexer
PER_FRAME = len(CELL_SIGNALS)
LATE_GROUP = 1  # cells 4-7: their frames lost at start-up
DROPOUT_CELL = 3  # reads 0 V at start-up: seen on the bus, refused by the gates
DROPPED_GROUP = 0  # cells 0-3: their frame lost now and then later
INTACT_UNTIL_S = 250  # phase 2 ends at this tick (s of the log, 1 Hz)
N_DROPS = 3
#: ticks one ``Replay.advance`` may send (one more each time HA does not agree within LOOK_S)
MAX_TICKS = 20
LOOK_S = 2.0
WAIT_S = 30.0
#: ``{{ (value_json.KEY * SCALE) | round(DIGITS) if ... }}`` (``discovery.number_template``)
_TEMPLATE = re.compile(
    r"\{\{ \(value_json(?:\.(\w+)|\['(\w+)'\])(?: \* ([0-9.e+-]+))?\) \| round\((\d+)\) "
)
Want = float | str | None  # a number, an enum state, or None: ``unknown``


def ticks(duration_s: float) -> list[list[can.Message]]:
    """The log's frames of its first ``duration_s`` seconds, one list per 1 s tick."""
    out: dict[int, list[can.Message]] = {}
    frames = demo_frames(duration_s)
    t0 = frames[0].timestamp
    for m in frames:
        out.setdefault(round(m.timestamp - t0), []).append(m)
    return [out[k] for k in sorted(out)]


def decoded(m: can.Message) -> dict[str, Any]:
    return dict(cast(dict[str, Any], CELL_MESSAGE.decode(bytes(m.data), decode_choices=False)))


def group_of(m: can.Message) -> int | None:
    """The cell group a frame carries, None for other frames."""
    return int(decoded(m)[MUX]) if m.arbitration_id == CELL_MESSAGE.frame_id else None


def without(tick: list[can.Message], group: int) -> list[can.Message]:
    """``tick`` with the cell-voltage frame of ``group`` lost."""
    return [m for m in tick if group_of(m) != group]


def reading_zero(tick: list[can.Message], cell: int) -> list[can.Message]:
    """``tick`` with ``cell`` reading 0 V."""
    out = []
    for m in tick:
        if group_of(m) != cell // PER_FRAME:
            out.append(m)
            continue
        signals = decoded(m)
        signals[CELL_SIGNALS[cell % PER_FRAME]] = 0.0
        out.append(can.Message(timestamp=m.timestamp, arbitration_id=m.arbitration_id,
                               is_extended_id=m.is_extended_id,
                               data=CELL_MESSAGE.encode(signals)))  # fmt: skip
    return out


class DaemonThread:
    """``Daemon.run()`` on an event loop of its own thread; ``call(fn)`` runs ``fn(daemon)`` on
    that loop, where the daemon's state is consistent between awaits."""

    def __init__(self, settings: Any) -> None:
        self.settings = settings
        self.daemon: Daemon | None = None
        self.rc: int | None = None
        self.error: BaseException | None = None
        self._loop: asyncio.AbstractEventLoop | None = None
        self._thread = threading.Thread(target=self._main, daemon=True)

    def _main(self) -> None:
        async def run() -> None:
            self._loop = asyncio.get_running_loop()
            self.daemon = Daemon(self.settings)
            self.rc = await self.daemon.run()

        try:
            asyncio.run(run())
        except BaseException as exc:  # handed to the test thread
            self.error = exc

    def call(self, fn: Callable[[Daemon], T]) -> T:
        if not self._thread.is_alive():
            raise AssertionError(f"the daemon stopped: rc {self.rc}, {self.error!r}")
        assert self._loop is not None and self.daemon is not None
        daemon = self.daemon

        async def on_loop() -> T:
            return fn(daemon)

        return asyncio.run_coroutine_threadsafe(on_loop(), self._loop).result(WAIT_S)

    def __enter__(self) -> DaemonThread:
        self._thread.start()
        wait_until(lambda: self.daemon is not None or not self._thread.is_alive(), WAIT_S, "start")
        wait_until(
            lambda: self.call(lambda d: d.can_state == "up" and bool(d.mqtt and d.mqtt.connected)),
            WAIT_S,
            "the daemon's bus and broker connection",
        )
        return self

    def __exit__(self, *exc: object) -> None:
        if self._loop is not None and self.daemon is not None and self._thread.is_alive():
            self._loop.call_soon_threadsafe(self.daemon.request_stop)
        self._thread.join(60)
        if exc[0] is None:
            assert not self._thread.is_alive() and self.error is None, self.error
            assert self.rc == 0


def entity(config: dict[str, Any]) -> str:
    return str(config["default_entity_id"])


def shown(config: dict[str, Any], payload: dict[str, Any] | None) -> Want:
    """What HA must show for ``payload`` (None: never published) through ``config``'s
    template."""
    if payload is None:
        return None
    if config.get("device_class") == "enum":
        name = payload["quality_name"]
        return str(name) if name in config["options"] else None
    match = _TEMPLATE.match(config["value_template"])
    assert match, config["value_template"]
    key, scale, digits = match[1] or match[2], float(match[3] or 1.0), int(match[4])
    value = payload[key]
    return round(value * scale, digits) if isinstance(value, int | float) else None


def agrees(state: str, want: Want) -> bool:
    if want is None or isinstance(want, str):
        return state == (want or "unknown")
    try:
        return math.isclose(float(state), want, rel_tol=1e-9, abs_tol=1e-12)
    except ValueError:  # "unknown", "unavailable": not the number bmsid has
        return False


class Replay:
    """The test's side of the bus, the log's ticks in order; what bmsid published last (an
    independent ``mosquitto_sub``) and what HA shows."""

    def __init__(
        self, daemon: DaemonThread, ha: HomeAssistant, hass: Process, capture: MqttCapture
    ) -> None:
        self.daemon, self.ha, self.hass, self.capture = daemon, ha, hass, capture
        self.bus = can.Bus(
            interface="virtual", channel=daemon.settings.can.channel, preserve_timestamps=True
        )
        self.log = ticks(INTACT_UNTIL_S + (2 + 2 * N_DROPS) * MAX_TICKS)  # each advance()
        self.k = 0  # the next tick
        self.sent = 0
        configs = discovery_messages("homeassistant", "bmsid", PACK, N_CELLS, "x")
        self.configs = [json.loads(p) for _, p in configs]
        self.watched = [c for c in self.configs if c.get("enabled_by_default", True)]

    def config(self, name: str) -> dict[str, Any]:
        (cfg,) = [c for c in self.configs if c["name"] == name]
        return cfg

    def send(self, frames: list[can.Message]) -> Estimates | None:
        """Send ``frames``; once the daemon published everything and the capture holds its
        latest tick, the estimates of that tick (None before the first: a tick that lost a
        frame is closed by the next tick's first frame)."""
        for m in frames:
            self.bus.send(m)
        self.sent += len(frames)
        wait_until(
            lambda: self.daemon.call(lambda d: all_published(d, self.sent)),
            WAIT_S,
            "the daemon to publish",
        )
        est = self.daemon.call(lambda d: d.latest)
        if est is not None:
            pack = f"bmsid/{PACK}/pack"
            wait_until(lambda: self.published().get(pack, {}).get("t_s") == est.t_s, WAIT_S,
                       "mosquitto_sub to receive the latest tick")  # fmt: skip
        return est

    def send_until(self, n_ticks: int) -> Estimates | None:
        """The log's ticks up to ``n_ticks`` (exclusive) intact, at once."""
        frames = [m for tick in self.log[self.k : n_ticks] for m in tick]
        self.k = n_ticks
        return self.send(frames)

    def published(self) -> dict[str, dict[str, Any]]:
        """Topic -> the payload bmsid published last."""
        last: dict[str, dict[str, Any]] = dict(self.capture.messages())
        return last

    def want(self) -> dict[str, Want]:
        """Entity id -> what HA must show for what bmsid published last."""
        last = self.published()
        return {entity(c): shown(c, last.get(c["state_topic"])) for c in self.watched}

    def differences(self, want: dict[str, Want]) -> list[str]:
        states = self.ha.states()
        return [
            f"{e}: {states[e]['state'] if e in states else 'no entity'}, bmsid {w!r}"
            for e, w in want.items()
            if e not in states or not agrees(states[e]["state"], w)
        ]

    def advance(
        self,
        done: Callable[[dict[str, Want]], bool],
        fault: Callable[[list[can.Message]], list[can.Message]] = list,
    ) -> dict[str, Want]:
        """Send the next ticks one at a time, each through ``fault``, until bmsid published
        what ``done`` looks for and HA shows it; that, by entity id. One more tick when HA
        does not agree within ``LOOK_S``: bmsid sends each tick once, and HA subscribes a
        moment after it lists an entity (and again after a reload of its MQTT integration)."""
        diff = ["bmsid never published what was looked for"]
        for _ in range(MAX_TICKS):
            est = self.send(fault(self.log[self.k]))
            self.k += 1
            if est is None or not done(want := self.want()):
                continue
            deadline = time.monotonic() + LOOK_S
            while diff := self.differences(want):
                if time.monotonic() > deadline:
                    break
                time.sleep(0.1)
            else:
                return want
        raise AssertionError(
            f"after {MAX_TICKS} ticks up to tick {self.k}, Home Assistant does not show what "
            "bmsid published:\n" + "\n".join(diff[:20]) + f"\n{self.hass.log()[-3000:]}"
        )

    def close(self) -> None:
        self.bus.shutdown()


@pytest.fixture
def capture(
    tmp_path: Path, mosquitto_broker: Any, require_tool: Callable[[str], str]
) -> Iterator[MqttCapture]:
    """What bmsid publishes, as an independent subscriber receives it."""
    cap = MqttCapture(require_tool("mosquitto_sub"), mosquitto_broker.port, tmp_path / "sub")
    try:
        cap.wait_ready(require_tool("mosquitto_pub"), mosquitto_broker.port)
        yield cap
    finally:
        cap.stop()


def test_replay_with_lost_frames_shows_unknown_where_bmsid_has_no_value(
    tmp_path: Path, mosquitto_broker: Any, capture: MqttCapture
) -> None:
    t_start = time.monotonic()
    settings = make_settings(
        tmp_path, mosquitto_broker.port, pack_id=PACK,
        estimator={"isolation": "thread"},  # a bank process would only add its start-up
        mqtt={"homeassistant": {"enabled": True}},
    )  # fmt: skip
    with (
        running_home_assistant(tmp_path, mosquitto_broker.port) as (ha, hass, started_s),
        DaemonThread(settings) as daemon,
    ):
        replay = Replay(daemon, ha, hass, capture)
        try:
            ids = {entity(c) for c in replay.watched}
            wait_until(lambda: ids <= set(ha.states()), 60, "the discovered entities", hass)
            # the user enables one internal: cell 0's model error, null while its voltage is lost
            verr0_cfg = replay.config("cell 0 model error")
            verr0 = entity(verr0_cfg)
            ha.enable_entity(verr0)
            wait_until(lambda: verr0 in ha.states(), 60, f"{verr0} enabled", hass)
            replay.watched.append(verr0_cfg)
            quality3 = entity(replay.config(f"cell {DROPOUT_CELL} quality"))

            # 1. start-up: cells 4-7 lost, cell 3 reads 0 V
            start = replay.advance(
                lambda w: w[quality3] == "no_data",
                lambda tick: reading_zero(without(tick, LATE_GROUP), DROPOUT_CELL),
            )
            start_published = replay.published()
            start_ticks = replay.k

            # 2. intact ticks: cells 3-7 from their own data
            est = replay.send_until(INTACT_UNTIL_S)
            assert est is not None and int(Quality.NO_DATA) not in est.quality.tolist()
            intact = replay.advance(lambda w: all(v is not None for v in w.values()))

            # 3. the frame of cells 0-3 lost (for two ticks: the second closes the first's
            # cycle), then intact again: cell 0's model error unknown, then a number
            soc0 = entity(replay.config("cell 0 SOC"))
            for _ in range(N_DROPS):
                lost = replay.advance(
                    lambda w: w[verr0] is None, lambda tick: without(tick, DROPPED_GROUP)
                )
                assert isinstance(lost[soc0], float)  # the counted SOC: bmsid has one
                replay.advance(lambda w: isinstance(w[verr0], float))
        finally:
            replay.close()

    # 1: nothing published for cells 4-7, cell 3 no_data with every field null
    assert not [t for t in start_published if t.rsplit("/", 1)[-1] in "4567" and "/cell/" in t]
    cell3 = start_published[f"bmsid/{PACK}/cell/{DROPOUT_CELL}"]
    assert cell3["quality_name"] == "no_data"
    assert not [k for k, v in cell3.items() if isinstance(v, float) and k != "t_s"]
    # HA: every sensor of cells 3-7 unknown (not 0), cell 3's quality no_data, cells 0-2 values
    for cfg in replay.watched:
        state = start[entity(cfg)]
        cell = int(m[1]) if (m := re.match(r"cell (\d+) ", cfg["name"])) else -1
        enum = cfg.get("device_class") == "enum"
        if cell >= DROPOUT_CELL:
            assert state == ("no_data" if enum and cell == DROPOUT_CELL else None), cfg["name"]
        elif cfg is not verr0_cfg:  # (no model error before the first estimate)
            assert state not in (None, "no_data"), (cfg["name"], state)
    # the pack's SOC mean over cells 0-2 only
    socs = [start[f"sensor.bmsid_{PACK}_cell{c}_soc"] for c in range(DROPOUT_CELL)]
    assert isinstance(soc_mean := start[f"sensor.bmsid_{PACK}_pack_soc_mean"], float)
    assert math.isclose(soc_mean, sum(s for s in socs if isinstance(s, float)) / 3, abs_tol=0.01)
    # 2: every entity shows a value
    assert all(w is not None for w in intact.values()), intact
    bad = log_problems(hass.log())
    assert not bad, "\n".join(bad)
    print(
        f"Home Assistant listening after {started_s:.1f} s; {start_ticks} start-up ticks, "
        f"{replay.k} in all; whole test {time.monotonic() - t_start:.1f} s"
    )
