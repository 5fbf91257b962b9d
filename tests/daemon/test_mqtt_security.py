"""MQTT security against a real Mosquitto: TLS, client certificates, passwords, secrets, topics.

Every broker here is configured by the test with a password file (``mosquitto_passwd``) and a
CA, server and client certificates made with trustme; the publisher runs in the test's event
loop with tiny reconnect delays, so a failing login is retried many times within a second.
A missing mosquitto fails these tests when real parts are required (conftest rule).
"""

from __future__ import annotations

import asyncio
import json
import logging
import os
import re
import ssl
import subprocess
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import aiomqtt
import pytest
import trustme
from daemon_helpers import demo_frames, make_settings, run_with_frames, wait_for
from paho.mqtt.packettypes import PacketTypes
from paho.mqtt.reasoncodes import ReasonCode

from bmsid.cli.main import main
from bmsid.config.settings import MqttSettings, load_settings
from bmsid.daemon.core import Daemon
from bmsid.errors import UserError
from bmsid.publish import mqtt as mqtt_mod
from bmsid.publish.mqtt import (
    TLS_FAILED,
    UNREACHABLE,
    ConnectFailure,
    MqttPublisher,
    classify_connect_error,
    explain_failure,
    tls_context,
)
from bmsid.publish.outbox import Outbox, OutMessage

USER = "bmsid-gw"
PASSWORD = "Tr0ub4dor-pw-7f3a9c"  # distinctive: searched for in every log and output
MQTT_LOGGER = "bmsid.publish.mqtt"
#: Tiny delays: a persistent failure is retried every ~10 ms.
FAST = {"reconnect_min_s": 0.005, "reconnect_max_s": 0.01, "publish_timeout_s": 2.0}

BrokerFactory = Callable[..., Any]


@dataclass(frozen=True)
class Pki:
    ca: Path
    other_ca: Path  # a CA that signed nothing the broker uses
    server_crt: Path  # for 127.0.0.1 and localhost
    server_key: Path
    wrong_host_crt: Path  # for wrong.example only
    wrong_host_key: Path
    client_crt: Path
    client_key: Path
    other_client_crt: Path  # signed by other_ca
    other_client_key: Path


@pytest.fixture(scope="module")
def pki(tmp_path_factory: pytest.TempPathFactory) -> Pki:
    d = tmp_path_factory.mktemp("pki")
    ca, other = trustme.CA(), trustme.CA()
    ca.cert_pem.write_to_path(str(d / "ca.pem"))
    other.cert_pem.write_to_path(str(d / "other-ca.pem"))

    def issue(issuer: trustme.CA, name: str, *hosts: str) -> tuple[Path, Path]:
        cert = issuer.issue_cert(*hosts)
        cert.cert_chain_pems[0].write_to_path(str(d / f"{name}.crt"))
        cert.private_key_pem.write_to_path(str(d / f"{name}.key"))
        (d / f"{name}.key").chmod(0o600)
        return d / f"{name}.crt", d / f"{name}.key"

    server = issue(ca, "server", "127.0.0.1", "localhost")
    wrong = issue(ca, "wrong-host", "wrong.example")
    client = issue(ca, "client", "bmsid-client")
    other_client = issue(other, "other-client", "bmsid-client")
    return Pki(d / "ca.pem", d / "other-ca.pem", *server, *wrong, *client, *other_client)


def _password_file(path: Path, tool: str, password: str = PASSWORD) -> Path:
    """A mosquitto password file with USER:password (re-created)."""
    subprocess.run([tool, "-b", "-c", str(path), USER, password], check=True, timeout=20)
    path.chmod(0o600)
    return path


@pytest.fixture
def broker_passwd(tmp_path: Path, require_tool: Callable[[str], str]) -> Path:
    return _password_file(tmp_path / "mosquitto.passwd", require_tool("mosquitto_passwd"))


def _tls_config(
    pki: Pki, passwd: Path, *, client_cert: bool = False, wrong_host: bool = False
) -> str:
    crt, key = (pki.wrong_host_crt, pki.wrong_host_key) if wrong_host else (
        pki.server_crt, pki.server_key)  # fmt: skip
    text = (
        f"allow_anonymous false\npassword_file {passwd}\n"
        f"cafile {pki.ca}\ncertfile {crt}\nkeyfile {key}\n"
    )
    if client_cert:
        text += "require_certificate true\nuse_identity_as_username false\n"
    return text


def _settings(port: int, pki: Pki | None, **kw: Any) -> MqttSettings:
    data: dict[str, Any] = {
        "url": f"mqtts://127.0.0.1:{port}" if pki else f"mqtt://127.0.0.1:{port}",
        "username": USER,
        "password": PASSWORD,
        **FAST,
    }
    if pki is not None:
        data["ca_file"] = pki.ca
    data.update(kw)
    return MqttSettings(**{k: v for k, v in data.items() if v is not None})


def _publisher(settings: MqttSettings, outbox: Outbox | None = None) -> MqttPublisher:
    return MqttPublisher(
        settings,
        f"sec-{os.getpid()}",
        outbox if outbox is not None else Outbox(100),
        "sec/status",
        lambda: b"online",
        b"offline",
    )


def _sub_context(pki: Pki, client_cert: bool = False) -> ssl.SSLContext:
    ctx = ssl.create_default_context(cafile=str(pki.ca))
    if client_cert:
        ctx.load_cert_chain(pki.client_crt, pki.client_key)
    return ctx


async def _delivered(
    settings: MqttSettings, port: int, sub_tls: ssl.SSLContext | None
) -> MqttPublisher:
    """Run a publisher with one message in its outbox until an independent subscriber
    (credentials, TLS) has received it; returns the stopped publisher."""
    async with aiomqtt.Client(
        "127.0.0.1", port, username=USER, password=PASSWORD, tls_context=sub_tls
    ) as sub:
        await sub.subscribe("sec/#", qos=1)
        outbox = Outbox(100)
        outbox.put(OutMessage("sec/data", b"hello", qos=1))
        pub = _publisher(settings, outbox)
        task = asyncio.create_task(pub.run())
        try:
            async with asyncio.timeout(10):
                async for msg in sub.messages:
                    if msg.topic.value == "sec/data":
                        assert msg.payload == b"hello"
                        break
            assert pub.state == "connected" and pub.connected
        finally:
            pub.stop()
            await asyncio.wait_for(task, 10)
    assert pub.state == "stopped"
    return pub


async def _failing(
    settings: MqttSettings, attempts: int, *, timeout_s: float = 10.0
) -> tuple[MqttPublisher, str]:
    """Run a publisher until ``attempts`` connects failed; it must still be running.
    Returns the stopped publisher and its state before the stop."""
    pub = _publisher(settings)
    task = asyncio.create_task(pub.run())
    try:
        await wait_for(lambda: pub.failed_attempts >= attempts or task.done(), timeout_s, "fails")
        assert not task.done(), f"the publisher ended: {task}"
        state = pub.state
    finally:
        pub.stop()
        await asyncio.wait_for(task, 10)
    assert pub.state == "stopped"
    return pub, state


def _records(caplog: pytest.LogCaptureFixture, level: int) -> list[str]:
    return [r.getMessage() for r in caplog.records if r.name == MQTT_LOGGER and r.levelno == level]


def _no_secret(caplog: pytest.LogCaptureFixture, *more: str) -> None:
    for text in (caplog.text, *more):
        assert PASSWORD not in text


@pytest.fixture(autouse=True)
def _debug_logs(caplog: pytest.LogCaptureFixture) -> Iterator[None]:
    caplog.set_level(logging.DEBUG)
    yield
    _no_secret(caplog)  # whatever a test did, the password was never logged


# ------------------------------------------------------------------ working connections


def test_tls_and_password_deliver(
    pki: Pki, broker_passwd: Path, mosquitto_factory: BrokerFactory
) -> None:
    broker = mosquitto_factory(_tls_config(pki, broker_passwd))
    for host in ("127.0.0.1", "localhost"):  # both names are in the server certificate
        s = _settings(broker.port, pki, url=f"mqtts://{host}:{broker.port}")
        pub = asyncio.run(_delivered(s, broker.port, _sub_context(pki)))
        assert pub.counters["publishes"] == 1 and pub.last_error is None


def test_client_certificate_required(
    pki: Pki,
    broker_passwd: Path,
    mosquitto_factory: BrokerFactory,
    caplog: pytest.LogCaptureFixture,
) -> None:
    broker = mosquitto_factory(_tls_config(pki, broker_passwd, client_cert=True))
    with_cert = _settings(broker.port, pki, cert_file=pki.client_crt, key_file=pki.client_key)
    asyncio.run(_delivered(with_cert, broker.port, _sub_context(pki, client_cert=True)))

    pub, state = asyncio.run(_failing(_settings(broker.port, pki), 3))
    assert state == "tls_failed"
    assert pub.last_error is not None
    assert "requires a client certificate" in pub.last_error
    assert "mqtt.cert_file" in pub.last_error
    errors = _records(caplog, logging.ERROR)
    assert len(errors) == 1 and "[tls_failed]" in errors[0], errors

    caplog.clear()
    foreign = _settings(
        broker.port, pki, cert_file=pki.other_client_crt, key_file=pki.other_client_key
    )
    pub, state = asyncio.run(_failing(foreign, 3))
    assert state == "tls_failed"
    assert pub.last_error is not None and "rejected the client certificate" in pub.last_error
    assert str(pki.other_client_crt) in pub.last_error
    assert len(_records(caplog, logging.ERROR)) == 1


def test_password_from_file_and_environment(
    pki: Pki,
    broker_passwd: Path,
    mosquitto_factory: BrokerFactory,
    tmp_path: Path,
    monkeypatch: pytest.MonkeyPatch,
    capsys: pytest.CaptureFixture[str],
) -> None:
    broker = mosquitto_factory(_tls_config(pki, broker_passwd))
    pw_file = tmp_path / "mqtt.password"
    pw_file.write_text(PASSWORD + "\n", encoding="utf-8")
    pw_file.chmod(0o600)
    config = tmp_path / "bmsid.toml"
    config.write_text(
        f'pack_id = "p1"\n[can]\nchannel = "vcan0"\nn_cells = 4\n[mqtt]\n'
        f'url = "mqtts://127.0.0.1:{broker.port}"\nusername = "{USER}"\n'
        f'password_file = "mqtt.password"\nca_file = "{pki.ca}"\n'
        f'cert_file = "c.crt"\nkey_file = "c.key"\n',
        encoding="utf-8",
    )
    (tmp_path / "c.crt").write_bytes(pki.client_crt.read_bytes())
    (tmp_path / "c.key").write_bytes(pki.client_key.read_bytes())
    s = load_settings(config)
    assert s.mqtt.password_file == pw_file  # relative paths: against the config's directory
    assert (s.mqtt.cert_file, s.mqtt.key_file) == (tmp_path / "c.crt", tmp_path / "c.key")
    asyncio.run(_delivered(s.mqtt, broker.port, _sub_context(pki)))
    assert main(["check-config", str(config)]) == 0
    out = capsys.readouterr().out
    assert f'password_file = "{pw_file}"' in out and PASSWORD not in out

    # the environment instead of the file: BMSID_MQTT__PASSWORD
    config.write_text(config.read_text().replace('password_file = "mqtt.password"\n', ""))
    monkeypatch.setenv("BMSID_MQTT__PASSWORD", PASSWORD)
    s = load_settings(config)
    assert s.mqtt.password_value() == PASSWORD and s.mqtt.password_file is None
    asyncio.run(_delivered(s.mqtt, broker.port, _sub_context(pki)))
    for text in (repr(s), str(s), repr(s.mqtt), s.model_dump_json(), json.dumps(s.redacted())):
        assert PASSWORD not in text
    assert main(["check-config", str(config)]) == 0
    out = capsys.readouterr().out
    assert PASSWORD not in out and 'password = "**********"' in out


def test_secret_never_in_daemon_status_or_log(
    pki: Pki,
    broker_passwd: Path,
    mosquitto_factory: BrokerFactory,
    tmp_path: Path,
    monkeypatch: pytest.MonkeyPatch,
    caplog: pytest.LogCaptureFixture,
) -> None:
    """The whole daemon with TLS and the password from the environment: the retained status
    (with its counters) reaches a subscriber, without the password in it or in the log."""
    broker = mosquitto_factory(_tls_config(pki, broker_passwd))
    monkeypatch.setenv("BMSID_MQTT__PASSWORD", PASSWORD)
    settings = make_settings(
        tmp_path,
        broker.port,
        mqtt={"url": f"mqtts://localhost:{broker.port}", "username": USER, "ca_file": pki.ca},
    )
    assert settings.mqtt.password_value() == PASSWORD
    statuses: list[bytes] = []

    async def run() -> None:
        async with aiomqtt.Client(
            "127.0.0.1", broker.port, username=USER, password=PASSWORD,
            tls_context=_sub_context(pki),
        ) as sub:  # fmt: skip
            await sub.subscribe("bmsid/testpack/status", qos=1)

            async def collect() -> None:
                async for msg in sub.messages:
                    assert isinstance(msg.payload, bytes)
                    statuses.append(msg.payload)

            collector = asyncio.create_task(collect())

            async def during(d: Daemon) -> None:
                await wait_for(lambda: len(statuses) >= 2, 20, "status messages")

            await run_with_frames(Daemon(settings), demo_frames(20.0), during=during)
            await wait_for(lambda: b'"offline"' in statuses[-1], 10, "the offline status")
            collector.cancel()

    asyncio.run(run())
    online = [json.loads(p) for p in statuses if b'"online"' in p]
    assert online and "counters" in online[-1]
    for payload in statuses:
        assert PASSWORD.encode() not in payload
    _no_secret(caplog)


# ------------------------------------------------------------------ failures: clear, bounded


def test_wrong_password_is_auth_failed_logged_once_then_recovers(
    pki: Pki,
    broker_passwd: Path,
    mosquitto_factory: BrokerFactory,
    caplog: pytest.LogCaptureFixture,
    require_tool: Callable[[str], str],
) -> None:
    # the broker accepts another password than the daemon's
    _password_file(broker_passwd, require_tool("mosquitto_passwd"), "something-else")
    broker = mosquitto_factory(_tls_config(pki, broker_passwd))
    settings = _settings(broker.port, pki)

    async def scenario() -> MqttPublisher:
        pub = _publisher(settings)
        task = asyncio.create_task(pub.run())
        await wait_for(lambda: pub.failed_attempts >= 12 or task.done(), 15, "12 failures")
        assert not task.done() and pub.state == "auth_failed" and not pub.connected
        assert pub.last_error is not None and "bad username or password" in pub.last_error
        # fix the broker's password file; the publisher keeps retrying and gets in
        await asyncio.to_thread(
            _password_file, broker_passwd, require_tool("mosquitto_passwd"), PASSWORD
        )
        await asyncio.to_thread(broker.restart)
        await wait_for(lambda: pub.connected or task.done(), 10, "the reconnect")
        pub.stop()
        await asyncio.wait_for(task, 10)
        return pub

    pub = asyncio.run(scenario())
    assert pub.counters["connect_failures"] >= 12 and pub.counters["connects"] == 1
    errors = _records(caplog, logging.ERROR)
    # the 1st and the 10th failure, not one line per attempt
    assert len(errors) == 2, errors
    first, tenth = errors
    assert "[auth_failed]" in first and "not authorised" in first and repr(USER) in first
    assert "mqtt.password_file" in first  # says what to check
    assert "still failing" in tenth and "10 times" in tenth
    infos = [m for m in _records(caplog, logging.INFO) if "failed attempt" in m]
    assert len(infos) == 1 and "after " in infos[0], infos


def test_anonymous_login_refused_says_set_username(
    pki: Pki, broker_passwd: Path, mosquitto_factory: BrokerFactory
) -> None:
    broker = mosquitto_factory(_tls_config(pki, broker_passwd))
    pub, state = asyncio.run(_failing(_settings(broker.port, pki, username=None, password=None), 2))
    assert state == "auth_failed"
    assert pub.last_error is not None and "set mqtt.username" in pub.last_error


@pytest.mark.parametrize(
    ("case", "state", "words"),
    [
        ("untrusted", "tls_failed", ("certificate verification", "mqtt.ca_file")),
        ("system-store", "tls_failed", ("certificate verification", "system trust store")),
        ("wrong-host", "tls_failed", ("not valid for host 'localhost'", "mqtt.url")),
        ("tls-to-plain-port", "unreachable", ("during the TLS handshake", "TLS listener")),
        ("plain-to-tls-port", "unreachable", ("closed the connection before CONNACK", "mqtts://")),
        ("refused", "unreachable", ("connection refused",)),
        ("dns", "unreachable", ("cannot resolve host 'no-such-host.invalid'",)),
    ],
)
def test_connect_failures_are_classified_and_logged_once(
    case: str,
    state: str,
    words: tuple[str, ...],
    pki: Pki,
    broker_passwd: Path,
    mosquitto_factory: BrokerFactory,
    caplog: pytest.LogCaptureFixture,
) -> None:
    tls = _tls_config(pki, broker_passwd, wrong_host=case == "wrong-host")
    port = mosquitto_factory(tls).port if case != "refused" else 1
    s: MqttSettings
    if case == "untrusted":
        s = _settings(port, pki, ca_file=pki.other_ca)
    elif case == "system-store":
        s = _settings(port, pki, ca_file=None)
    elif case == "wrong-host":
        s = _settings(port, pki, url=f"mqtts://localhost:{port}")
    elif case == "tls-to-plain-port":
        plain = mosquitto_factory(f"allow_anonymous false\npassword_file {broker_passwd}\n")
        s = _settings(plain.port, pki)
    elif case == "plain-to-tls-port":
        s = _settings(port, None, publish_timeout_s=0.3)
    elif case == "refused":
        s = _settings(port, None)
    else:
        s = _settings(port, None, url="mqtt://no-such-host.invalid:1883")
    # a resolver can be slow to say no: one lookup is enough there
    attempts, timeout_s = (1, 30.0) if case == "dns" else (3, 10.0)
    pub, got = asyncio.run(_failing(s, attempts, timeout_s=timeout_s))
    assert got == state, pub.last_error
    assert pub.last_error is not None
    for w in words:
        assert w in pub.last_error
    level = logging.ERROR if state == "tls_failed" else logging.WARNING
    lines = _records(caplog, level)
    assert len(lines) == 1 and f"[{state}]" in lines[0] and pub.last_error in lines[0], lines
    assert "Traceback" not in caplog.text


def test_repeats_are_logged_at_1_10_100(caplog: pytest.LogCaptureFixture) -> None:
    """A broker that stays away: 100+ fast retries give three log lines, all with the count."""
    s = _settings(1, None, reconnect_min_s=0.0005, reconnect_max_s=0.001)
    pub, _ = asyncio.run(_failing(s, 105, timeout_s=20))
    lines = _records(caplog, logging.WARNING)
    assert len(lines) == 3, lines
    assert "still failing" in lines[1] and "10 times" in lines[1] and "100 times" in lines[2]
    assert pub.counters["connect_failures"] == pub.failed_attempts >= 105


def test_password_file_problems_are_config_errors_not_crashes(
    pki: Pki,
    broker_passwd: Path,
    mosquitto_factory: BrokerFactory,
    tmp_path: Path,
    caplog: pytest.LogCaptureFixture,
) -> None:
    broker = mosquitto_factory(_tls_config(pki, broker_passwd))
    pw_file = tmp_path / "late.password"
    settings = _settings(broker.port, pki, password=None, password_file=pw_file)

    async def scenario() -> MqttPublisher:
        pub = _publisher(settings)
        task = asyncio.create_task(pub.run())
        await wait_for(lambda: pub.failed_attempts >= 3 or task.done(), 10, "missing file")
        assert pub.state == "config_error" and pub.last_error is not None
        assert "mqtt.password_file" in pub.last_error and str(pw_file) in pub.last_error
        pw_file.write_text("")
        n = pub.failed_attempts
        await wait_for(lambda: pub.failed_attempts > n + 2 or task.done(), 10, "empty file")
        assert pub.last_error is not None and "is empty" in pub.last_error
        pw_file.write_text(PASSWORD + "\n")  # the file appears: the next retry gets in
        await wait_for(lambda: pub.connected or task.done(), 10, "the connect")
        pub.stop()
        await asyncio.wait_for(task, 10)
        return pub

    pub = asyncio.run(scenario())
    assert pub.counters["connects"] == 1
    errors = _records(caplog, logging.ERROR)
    assert len(errors) == 2, errors  # one per kind (missing, empty), not one per attempt
    assert all("[config_error]" in e and "mqtt.password_file" in e for e in errors)


def test_duplicate_client_id_flapping_is_bounded(
    mosquitto_factory: BrokerFactory, caplog: pytest.LogCaptureFixture
) -> None:
    """Two publishers with one client id kick each other off: the log says so, briefly."""
    broker = mosquitto_factory()
    s = _settings(broker.port, None, username=None, password=None, reconnect_max_s=0.05)

    async def scenario() -> list[MqttPublisher]:
        pubs = [_publisher(s), _publisher(s)]
        tasks = [asyncio.create_task(p.run()) for p in pubs]
        await wait_for(lambda: sum(p.counters["connects"] for p in pubs) >= 25, 15, "flaps")
        for p in pubs:
            p.stop()
        await asyncio.wait_for(asyncio.gather(*tasks), 10)
        return pubs

    pubs = asyncio.run(scenario())
    lost = [m for m in _records(caplog, logging.WARNING) if "lost" in m]
    assert 1 <= len(lost) <= 4, lost  # 1st and 10th per publisher
    assert "another client with the same client id" in lost[0]
    assert all(p.last_error and "connection lost" in p.last_error for p in pubs)


def test_a_lost_broker_is_said_plainly_with_what_happens_next(
    mosquitto_factory: BrokerFactory, caplog: pytest.LogCaptureFixture, monkeypatch: Any
) -> None:
    """A broker that goes away: one WARNING in an operator's words (it was logged as
    "lost: [code:4] The client is not currently connected." or "Disconnected during message
    iteration"), saying that it reconnects and that the messages are held and delivered."""
    monkeypatch.setattr(mqtt_mod, "STABLE_SESSION_S", 0.0)  # no duplicate-client-id hint
    broker = mosquitto_factory()
    s = _settings(broker.port, None, username=None, password=None, reconnect_max_s=0.5)

    async def scenario() -> None:
        pub = _publisher(s)
        task = asyncio.create_task(pub.run())
        try:
            await wait_for(lambda: pub.connected, 10, "connected")
            broker.stop()
            await wait_for(lambda: pub.state != "connected", 10, "the loss")
        finally:
            pub.stop()
            await asyncio.wait_for(task, 10)

    asyncio.run(scenario())
    (lost,) = [m for m in _records(caplog, logging.WARNING) if " lost" in m]
    assert lost.startswith(
        f"MQTT connection to mqtt://127.0.0.1:{broker.port} lost: the broker closed it or the "
        "network dropped it"
    ), lost
    assert "; reconnecting (backoff 0.005-0.5 s); messages are held meanwhile (0 now" in lost
    assert lost.endswith("and delivered in order once connected again"), lost
    assert "[code:" not in lost and "message iteration" not in lost


def test_lost_reasons_are_worded_for_an_operator() -> None:
    """What aiomqtt raises for a loss (the words of the call that noticed it), reworded."""
    no_conn = aiomqtt.MqttCodeError(4, "Could not publish message")
    assert str(no_conn) == "[code:4] The client is not currently connected."
    assert mqtt_mod.lost_reason(no_conn, 10.0) == "the broker closed it or the network dropped it"
    iteration = aiomqtt.MqttError("Disconnected during message iteration")
    keepalive = ReasonCode(PacketTypes.DISCONNECT, "Keep alive timeout")
    iteration.__cause__ = aiomqtt.MqttCodeError(keepalive, "Unexpected disconnection")
    assert mqtt_mod.lost_reason(iteration, 10.0) == (
        "the broker stopped answering (no reply within the keep-alive interval)"
    )
    taken = ReasonCode(PacketTypes.DISCONNECT, "Session taken over")
    assert mqtt_mod.lost_reason(aiomqtt.MqttCodeError(taken), 10.0) == (
        "the broker disconnected it: session taken over"
    )
    assert mqtt_mod.lost_reason(aiomqtt.MqttError("Operation timed out"), 2.5) == (
        "the broker acknowledged nothing within mqtt.publish_timeout_s = 2.5 s"
    )


# ------------------------------------------------------------------ configuration


def test_tls_insecure_warns_and_connects_to_an_untrusted_broker(
    pki: Pki,
    broker_passwd: Path,
    mosquitto_factory: BrokerFactory,
    caplog: pytest.LogCaptureFixture,
) -> None:
    broker = mosquitto_factory(_tls_config(pki, broker_passwd))
    s = _settings(broker.port, pki, ca_file=pki.other_ca, tls_insecure=True)
    asyncio.run(_delivered(s, broker.port, _sub_context(pki)))
    assert any("NOT verified" in m for m in _records(caplog, logging.WARNING))


GOOD = """
pack_id = "p1"
[can]
channel = "vcan0"
n_cells = 4
[mqtt]
url = "mqtts://broker.example:8883"
username = "bmsid"
topic_prefix = "site/bms"
[mqtt.homeassistant]
prefix = "homeassistant"
"""


def _config(tmp_path: Path, text: str) -> Path:
    p = tmp_path / "bmsid.toml"
    p.write_text(text, encoding="utf-8")
    return p


@pytest.mark.parametrize(
    ("old", "new", "field"),
    [
        ('topic_prefix = "site/bms"', 'topic_prefix = "site/+/bms"', "mqtt.topic_prefix"),
        ('topic_prefix = "site/bms"', 'topic_prefix = "site/#"', "mqtt.topic_prefix"),
        ('topic_prefix = "site/bms"', 'topic_prefix = ""', "mqtt.topic_prefix"),
        ('topic_prefix = "site/bms"', 'topic_prefix = "site//bms"', "mqtt.topic_prefix"),
        ('topic_prefix = "site/bms"', 'topic_prefix = "/site"', "mqtt.topic_prefix"),
        ('topic_prefix = "site/bms"', 'topic_prefix = "site/"', "mqtt.topic_prefix"),
        ('topic_prefix = "site/bms"', 'topic_prefix = "$SYS/x"', "mqtt.topic_prefix"),
        ('prefix = "homeassistant"', 'prefix = "ha/+"', "mqtt.homeassistant.prefix"),
        ('prefix = "homeassistant"', 'prefix = "#"', "mqtt.homeassistant.prefix"),
        ('prefix = "homeassistant"', 'prefix = "ha//x"', "mqtt.homeassistant.prefix"),
        ('prefix = "homeassistant"', 'prefix = "ha/"', "mqtt.homeassistant.prefix"),
        ('prefix = "homeassistant"', 'prefix = "/ha"', "mqtt.homeassistant.prefix"),
        ('pack_id = "p1"', 'pack_id = "a/b"', "pack_id"),
        ('pack_id = "p1"', 'pack_id = "a+"', "pack_id"),
        ('pack_id = "p1"', 'pack_id = "#"', "pack_id"),
    ],
)
def test_topic_levels_are_validated(tmp_path: Path, old: str, new: str, field: str) -> None:
    assert old in GOOD
    with pytest.raises(UserError, match=rf"field {field}: "):
        load_settings(_config(tmp_path, GOOD.replace(old, new, 1)))


@pytest.mark.parametrize(
    ("extra", "words"),
    [
        ('cert_file = "c.crt"', "needs both cert_file and key_file"),
        ('key_file = "c.key"', "needs both cert_file and key_file"),
        ('password = "x"\npassword_file = "pw"', "not both"),
    ],
)
def test_mqtt_settings_combinations(tmp_path: Path, extra: str, words: str) -> None:
    text = GOOD.replace('username = "bmsid"', f'username = "bmsid"\n{extra}')
    with pytest.raises(UserError, match=rf"field mqtt: .*{words}"):
        load_settings(_config(tmp_path, text))


@pytest.mark.parametrize(
    ("url", "words"),
    [
        ("127.0.0.1:1883", "has no scheme: write mqtt://HOST"),
        ("localhost", "has no scheme: write mqtt://HOST"),
        ("mqtt://127.0.0.1:188400", "url port: Port out of range"),
        ("http://broker", "url scheme must be one of"),
    ],
)
def test_a_bad_url_names_mqtt_url_and_what_to_write(tmp_path: Path, url: str, words: str) -> None:
    """A sweep: a URL without a scheme or with a port out of range said "field mqtt", and for
    a bare host:port "got ''" as the scheme."""
    text = GOOD.replace("mqtts://broker.example:8883", url)
    with pytest.raises(UserError, match=rf"field mqtt\.url: .*{words}"):
        load_settings(_config(tmp_path, text))


def test_tls_files_need_mqtts_and_password_needs_username(tmp_path: Path) -> None:
    plain = GOOD.replace("mqtts://broker.example:8883", "mqtt://broker.example:1883")
    for extra in ('ca_file = "ca.pem"', "tls_insecure = true"):
        with pytest.raises(UserError, match=r"field mqtt: .*need\(s\) a TLS url"):
            load_settings(_config(tmp_path, plain.replace("[mqtt]", f"[mqtt]\n{extra}")))
    with pytest.raises(UserError, match=r"field mqtt: .*needs a username") as err:
        load_settings(
            _config(tmp_path, GOOD.replace('username = "bmsid"', f'password = "{PASSWORD}"'))
        )
    assert PASSWORD not in str(err.value)


def test_check_config_checks_mqtt_files_without_showing_secrets(
    tmp_path: Path, pki: Pki, capsys: pytest.CaptureFixture[str]
) -> None:
    def check(extra: str) -> tuple[int, str, str]:
        text = GOOD.replace('username = "bmsid"', f'username = "bmsid"\n{extra}')
        rc = main(["check-config", str(_config(tmp_path, text))])
        out, err = capsys.readouterr()
        assert PASSWORD not in out + err
        return rc, out, err.strip()

    (tmp_path / "pw").write_text(PASSWORD)
    (tmp_path / "empty").write_text("\n")
    (tmp_path / "garbage.pem").write_text("not a certificate\n")
    rc, out, _ = check('password_file = "pw"')
    assert rc == 0 and f'password_file = "{tmp_path / "pw"}"' in out
    rc, out, _ = check(f'password = "{PASSWORD}"\ntls_insecure = true')
    assert rc == 0 and 'password = "**********"' in out and "WARNING" in out
    files = f'cert_file = "{pki.client_crt}"\n'
    cases = [
        ('password_file = "nope"', "mqtt.password_file: cannot read"),
        ('password_file = "empty"', "mqtt.password_file:"),
        ('ca_file = "nope.pem"', "mqtt.ca_file: cannot read"),
        ('ca_file = "garbage.pem"', "mqtt.ca_file: no usable PEM CA certificate"),
        (files + 'key_file = "nope.key"', "mqtt.key_file: cannot read"),
        (files + 'key_file = "garbage.pem"', "mqtt.key_file: no PEM private key"),
        (files + f'key_file = "{pki.other_client_key}"', "mqtt.key_file: .* is not the key"),
        (f'cert_file = "garbage.pem"\nkey_file = "{pki.client_key}"', "mqtt.cert_file: no PEM"),
    ]
    for extra, want in cases:
        rc, _, err = check(extra)
        assert rc == 2 and len(err.splitlines()) == 1, (extra, err)
        assert re.search(want, err), (extra, err)
    assert "is empty" in check('password_file = "empty"')[2]


def test_encrypted_key_is_a_clear_config_error(tmp_path: Path, pki: Pki) -> None:
    from cryptography.hazmat.primitives import serialization

    key = serialization.load_pem_private_key(pki.client_key.read_bytes(), None)
    enc = tmp_path / "enc.key"
    enc.write_bytes(
        key.private_bytes(
            serialization.Encoding.PEM,
            serialization.PrivateFormat.PKCS8,
            serialization.BestAvailableEncryption(b"passphrase"),
        )
    )
    s = _settings(8883, pki, cert_file=pki.client_crt, key_file=enc)
    with pytest.raises(UserError, match=r"mqtt\.key_file: .* is encrypted"):
        tls_context(s)


def test_library_messages_are_redacted() -> None:
    """Belt and braces: a password a library might echo is replaced in every message."""
    pub = _publisher(_settings(1, None))
    pub._secret = PASSWORD
    pub._on_failure(mqtt_mod.ConnectFailure("unreachable", f"oops {PASSWORD} echoed"))
    assert pub.last_error == "oops ********** echoed"


def test_an_unexplained_tls_close_keeps_the_earlier_certificate_diagnosis() -> None:
    """TLS 1.3: a client certificate is rejected after the handshake, and the alert saying so
    can be lost to a reset (seen in CI). The next attempt's bare close must not replace the
    diagnosis with a vaguer one, but a different cause (refused) must."""
    rejected = ConnectFailure(TLS_FAILED, "rejected the client certificate")
    closed = ConnectFailure(UNREACHABLE, "closed during the TLS handshake", ambiguous=True)
    refused = ConnectFailure(UNREACHABLE, "connection refused")
    shown, kept = explain_failure(rejected, None)
    assert shown is rejected and kept is rejected
    shown, kept = explain_failure(closed, kept)
    assert shown is rejected and kept is rejected
    shown, kept = explain_failure(refused, kept)
    assert shown is refused and kept is None
    shown, kept = explain_failure(closed, kept)
    assert shown is closed and kept is None


def test_a_bare_ssl_eof_after_a_certificate_rejection_stays_a_tls_failure() -> None:
    """Seen in CI: the broker's UNKNOWN_CA alert came on one attempt, and the next attempt's
    socket logged only "EOF occurred in violation of protocol" (no "[SSL: ...]" tag). That
    close is ambiguous, so the earlier certificate diagnosis must be kept; on a plain mqtt://
    URL the same text is not a TLS matter."""
    s = _settings(8883, None, url="mqtts://127.0.0.1:8883")
    eof = "failed to receive on socket: EOF occurred in violation of protocol (_ssl.c:2427)"
    alert = "failed to receive on socket: [SSL: TLSV1_ALERT_UNKNOWN_CA] tlsv1 alert unknown ca"
    first = classify_connect_error(mqtt_mod._SocketFailedError(alert), s, [alert])
    assert first.state == TLS_FAILED and "rejected" in first.message
    bare = classify_connect_error(mqtt_mod._SocketFailedError(eof), s, [eof])
    assert bare.state == UNREACHABLE and bare.ambiguous
    shown, kept = explain_failure(bare, first)
    assert shown is first and kept is first
    plain = classify_connect_error(mqtt_mod._SocketFailedError(eof), _settings(1883, None), [eof])
    assert not plain.ambiguous
