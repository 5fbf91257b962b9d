"""The real parts work: SocketCAN vcan with python-can and can-utils, mosquitto with aiomqtt.

`realcan` tests run on a kernel with vcan, or inside User-Mode Linux via scripts/uml-run; the
last test checks the host-side broker fixture, including a restart on the same port.
"""

from __future__ import annotations

import asyncio
import socket
import subprocess
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import aiomqtt
import can
import pytest

# (host, port) as the mosquitto_broker fixture yields it. Not imported from conftest on purpose:
# another tests/**/conftest.py can shadow the module name "conftest".
BrokerAddress = tuple[str, int]

TOOL_TIMEOUT_S = 20.0  # generous: every syscall is slow inside UML
RECV_TIMEOUT_S = 5.0


def socketcan_bus(channel: str) -> can.BusABC:
    return can.Bus(interface="socketcan", channel=channel, receive_own_messages=False)


@pytest.mark.realcan
def test_python_can_receives_frame_sent_by_cansend(
    vcan_channel: str, require_tool: Callable[[str], str]
) -> None:
    cansend = require_tool("cansend")
    with socketcan_bus(vcan_channel) as bus:
        subprocess.run([cansend, vcan_channel, "123#DEADBEEF"], check=True, timeout=TOOL_TIMEOUT_S)
        message = bus.recv(timeout=RECV_TIMEOUT_S)
    assert message is not None, "no frame received from cansend"
    assert (message.arbitration_id, message.is_extended_id) == (0x123, False)
    assert bytes(message.data) == bytes.fromhex("DEADBEEF")


@pytest.mark.realcan
def test_candump_captures_frame_sent_by_python_can(
    vcan_channel: str, require_tool: Callable[[str], str]
) -> None:
    candump = require_tool("candump")
    frame = can.Message(arbitration_id=0x1ABCDE01, is_extended_id=True, data=bytes(range(1, 9)))
    dump = subprocess.Popen(
        [candump, "-L", "-n", "1", vcan_channel],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )
    # candump binds its socket at some unknown moment after start: repeat the frame until it
    # has captured one (-n 1), instead of guessing a sleep.
    deadline = time.monotonic() + TOOL_TIMEOUT_S
    with socketcan_bus(vcan_channel) as bus:
        while dump.poll() is None and time.monotonic() < deadline:
            bus.send(frame)
            time.sleep(0.05)
    if dump.poll() is None:
        dump.kill()
    stdout, stderr = dump.communicate(timeout=TOOL_TIMEOUT_S)
    assert dump.returncode == 0, f"candump failed: {stderr}"
    # candump -L: "(1700000000.123456) vcan0 1ABCDE01#0102030405060708"
    timestamp, interface, payload = stdout.split()
    assert timestamp.startswith("(") and timestamp.endswith(")")
    assert interface == vcan_channel
    assert payload == "1ABCDE01#0102030405060708"


@pytest.mark.realcan
def test_the_two_buses_are_independent(vcan_channels: tuple[str, str]) -> None:
    first, second = vcan_channels
    frame = can.Message(arbitration_id=0x321, is_extended_id=False, data=b"\x01")
    with (
        socketcan_bus(first) as listener0,
        socketcan_bus(second) as listener1,
        socketcan_bus(second) as sender1,
    ):
        sender1.send(frame)
        on_second = listener1.recv(timeout=RECV_TIMEOUT_S)
        on_first = listener0.recv(timeout=0.5)
    assert on_second is not None and on_second.arbitration_id == 0x321
    assert on_first is None, f"{first} saw a frame sent on {second}: {on_first}"


REPLAY_FRAMES = [
    # (arbitration id, extended id, data)
    (0x100, False, b""),
    (0x101, False, b"\x11"),
    (0x7FF, False, bytes.fromhex("0011223344556677")),
    (0x18FF50E5, True, bytes.fromhex("FFEE")),
    (0x1FFFFFFF, True, bytes.fromhex("0102030405060708")),
    (0x000, False, bytes.fromhex("AA55")),
]


def candump_log_line(time_s: float, channel: str, can_id: int, extended: bool, data: bytes) -> str:
    id_text = f"{can_id:08X}" if extended else f"{can_id:03X}"
    return f"({time_s:.6f}) {channel} {id_text}#{data.hex().upper()}"


@pytest.mark.realcan
def test_canplayer_replays_candump_log_into_python_can(
    vcan_channel: str, require_tool: Callable[[str], str], tmp_path: Path
) -> None:
    canplayer = require_tool("canplayer")
    log = tmp_path / "replay.log"
    frames = REPLAY_FRAMES * 3
    log.write_text(
        "".join(
            candump_log_line(1_700_000_000 + 0.002 * i, "logbus0", can_id, ext, data) + "\n"
            for i, (can_id, ext, data) in enumerate(frames)
        ),
        encoding="ascii",
    )
    with socketcan_bus(vcan_channel) as bus:
        # "vcan0=logbus0": canplayer maps the log's interface name onto the test bus.
        subprocess.run(
            [canplayer, "-I", str(log), f"{vcan_channel}=logbus0"],
            check=True,
            timeout=TOOL_TIMEOUT_S,
        )
        received = []
        while (message := bus.recv(timeout=1.0)) is not None:
            received.append((message.arbitration_id, message.is_extended_id, bytes(message.data)))
    assert received == frames


def port_accepts(host: str, port: int) -> bool:
    try:
        with socket.create_connection((host, port), timeout=1.0):
            return True
    except OSError:
        return False


async def publish_retained(broker: BrokerAddress, topic: str, payload: bytes) -> None:
    host, port = broker
    async with aiomqtt.Client(host, port) as client:
        await client.publish(topic, payload, qos=1, retain=True)


async def first_message(broker: BrokerAddress, topic: str) -> tuple[str, bytes]:
    host, port = broker
    async with aiomqtt.Client(host, port) as client:
        await client.subscribe(topic, qos=1)
        async for message in client.messages:
            payload = message.payload
            assert isinstance(payload, bytes)
            return str(message.topic), payload
    raise AssertionError("message stream ended without a message")


def mosquitto_sub_first(
    mosquitto_sub: str, broker: BrokerAddress, topic: str
) -> subprocess.CompletedProcess[str]:
    host, port = broker
    return subprocess.run(
        [
            *(mosquitto_sub, "-h", host, "-p", str(port)),
            *("-t", topic, "-v", "-C", "1", "-W", str(int(TOOL_TIMEOUT_S))),
        ],
        capture_output=True,
        text=True,
        timeout=TOOL_TIMEOUT_S + 5,
        check=False,
    )


@pytest.mark.realcan
def test_mosquitto_sub_receives_what_aiomqtt_publishes(
    mosquitto_broker: BrokerAddress, require_tool: Callable[[str], str]
) -> None:
    mosquitto_sub = require_tool("mosquitto_sub")
    # Retained, so the subscriber that starts afterwards gets it without a timing race.
    asyncio.run(publish_retained(mosquitto_broker, "bmsid/test/cell/3", b"3.712"))
    result = mosquitto_sub_first(mosquitto_sub, mosquitto_broker, "bmsid/test/#")
    assert result.returncode == 0, result.stderr
    assert result.stdout == "bmsid/test/cell/3 3.712\n"


@pytest.mark.realcan
def test_aiomqtt_receives_what_mosquitto_pub_publishes(
    mosquitto_broker: BrokerAddress, require_tool: Callable[[str], str]
) -> None:
    mosquitto_pub = require_tool("mosquitto_pub")
    host, port = mosquitto_broker
    subprocess.run(
        [
            *(mosquitto_pub, "-h", host, "-p", str(port)),
            *("-t", "bmsid/test/pack", "-m", '{"current_A": -1.5}', "-q", "1", "-r"),
        ],
        check=True,
        timeout=TOOL_TIMEOUT_S,
    )
    topic, payload = asyncio.run(
        asyncio.wait_for(first_message(mosquitto_broker, "bmsid/test/#"), TOOL_TIMEOUT_S)
    )
    assert (topic, payload) == ("bmsid/test/pack", b'{"current_A": -1.5}')


def test_host_broker_serves_clients_and_restarts_on_the_same_port(
    mosquitto_factory: Callable[..., Any], require_tool: Callable[[str], str]
) -> None:
    mosquitto_sub = require_tool("mosquitto_sub")
    broker = mosquitto_factory()
    asyncio.run(publish_retained(broker.address, "bmsid/test/up", b"1"))
    assert mosquitto_sub_first(mosquitto_sub, broker.address, "bmsid/test/up").stdout == (
        "bmsid/test/up 1\n"
    )

    broker.stop()
    assert not port_accepts(*broker.address), "port still accepts after stop()"
    broker.start()
    # persistence is off, so the restarted broker has forgotten the retained message.
    asyncio.run(publish_retained(broker.address, "bmsid/test/up", b"2"))
    assert mosquitto_sub_first(mosquitto_sub, broker.address, "bmsid/test/up").stdout == (
        "bmsid/test/up 2\n"
    )


def test_host_broker_from_config_text_enforces_a_password_file(
    mosquitto_factory: Callable[..., Any], require_tool: Callable[[str], str], tmp_path: Path
) -> None:
    mosquitto_passwd = require_tool("mosquitto_passwd")
    mosquitto_pub = require_tool("mosquitto_pub")
    password_file = tmp_path / "passwords"
    subprocess.run(
        [mosquitto_passwd, "-b", "-c", str(password_file), "gateway", "s3cret"],
        check=True,
        timeout=TOOL_TIMEOUT_S,
    )
    password_file.chmod(0o600)
    broker = mosquitto_factory(f"allow_anonymous false\npassword_file {password_file}\n")
    host, port = broker.address

    def publish_as(password: str) -> int:
        command = [mosquitto_pub, "-h", host, "-p", str(port), "-t", "bmsid/test/auth"]
        command += ["-m", "x", "-u", "gateway", "-P", password]
        result = subprocess.run(command, capture_output=True, timeout=TOOL_TIMEOUT_S, check=False)
        return result.returncode

    assert publish_as("s3cret") == 0, broker.log_text()
    assert publish_as("wrong") != 0
