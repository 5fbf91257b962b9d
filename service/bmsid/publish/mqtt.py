"""The MQTT publisher: reconnects with backoff, drains the outbox in order, keeps the status.

aiomqtt does not reconnect by itself and its ``publish`` waits for the library's acknowledgement
(QoS >= 1: the broker's), so this task owns the connection and nothing upstream ever awaits it.
On connect: retained ``online`` status (the will is the retained ``offline``), Home Assistant
discovery if enabled (re-sent whenever ``<ha_prefix>/status`` says ``online``), then the backlog.
A message leaves the outbox only after its publish succeeded, so the backlog of an outage is
delivered in order; a publish that failed with the connection is sent again (at-least-once).

A failed connect is classified (:func:`classify_connect_error`) into a ``state``
(``auth_failed``, ``tls_failed``, ``config_error``, ``rejected``, ``unreachable``) and one
secret-free line saying what to check. The first failure of each kind is logged, repeats only
at the 10th, 100th, ... occurrence (or after an hour), so a wrong password or an untrusted
certificate cannot flood the log; login, TLS and local-file failures back off to
``reconnect_max_s`` after one quick retry. aiomqtt's and paho's own error lines ("failed to
receive on socket: ...") are folded into these messages instead of being logged per attempt.
Sessions that keep ending within seconds (typically two daemons with one client id kicking each
other off) do not reset the backoff and are logged the same bounded way.

``stop(timeout_s)`` flushes within a time limit and keeps the backoff: a stop while the broker
is unreachable or refuses the login makes only the attempts that the backoff schedule places
before the limit (measured before: 43,167 connects in 10 s against a closed port, 18,269
against a wrong password), and what is still in the outbox at the limit stays there for the
daemon to spool.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import random
import re
import socket
import ssl
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import aiomqtt
from paho.mqtt.reasoncodes import ReasonCode

from bmsid.config.settings import MqttSettings
from bmsid.errors import UserError
from bmsid.publish.outbox import Outbox, OutMessage

log = logging.getLogger(__name__)
#: aiomqtt warns once per publish while more than 10 are pending: noise, not news. Its (and
#: paho's) errors reach the publisher through :class:`_ClientLog`, never this logger directly.
_CLIENT_LOG = logging.getLogger(f"{__name__}.client")
_CLIENT_LOG.setLevel(logging.ERROR)

# Values of MqttPublisher.state
CONNECTING = "connecting"  #: started, no connect attempt finished yet
CONNECTED = "connected"
DISCONNECTED = "disconnected"  #: the connection was lost; reconnecting
UNREACHABLE = "unreachable"  #: refused, DNS, timeout, reset: the network or the broker is down
AUTH_FAILED = "auth_failed"  #: the broker refused the login (user name, password, permission)
TLS_FAILED = "tls_failed"  #: certificate verification, client certificate, TLS handshake
REJECTED = "rejected"  #: CONNACK refused for another reason (client id, server unavailable, ...)
CONFIG_ERROR = "config_error"  #: password_file / ca_file / cert_file / key_file unusable
STOPPED = "stopped"

#: Failures that will not fix themselves soon: after one quick retry, wait reconnect_max_s.
PERSISTENT_STATES = frozenset({AUTH_FAILED, TLS_FAILED, CONFIG_ERROR})
#: Failures logged at ERROR (the others, a broker outage, at WARNING).
ERROR_STATES = PERSISTENT_STATES | {REJECTED}
#: A repeated failure is logged again at the 10th, 100th, ... occurrence or after this long, s.
REPEAT_LOG_S = 3600.0
#: A session shorter than this, s, does not reset the backoff (a client kicking us off).
STABLE_SESSION_S = 10.0

#: CONNACK codes for a refused login: MQTT 3.1.1 4 (bad user name or password), 5 (not
#: authorised); MQTT 5 / paho reason codes 134, 135, 138 (banned), 140 (bad auth method).
_AUTH_CODES = frozenset({4, 5, 134, 135, 138, 140})
_CLIENT_ID_CODES = {2, 133}
_SSL_REASON = re.compile(r"\[SSL: ([A-Z0-9_]+)\]")
#: ssl.SSLEOFError: the peer closed the TLS connection without a close_notify or alert.
_SSL_EOF = "EOF occurred in violation of protocol"
#: TLS alerts/reasons meaning the broker did not accept our client certificate.
_CLIENT_CERT_REJECTED = (
    "UNKNOWN_CA",
    "BAD_CERTIFICATE",
    "CERTIFICATE_UNKNOWN",
    "CERTIFICATE_EXPIRED",
    "CERTIFICATE_REVOKED",
    "UNSUPPORTED_CERTIFICATE",
    "ACCESS_DENIED",
    "DECRYPT_ERROR",
)
#: TLS reasons typical of talking TLS to a port that does not speak it.
_NOT_TLS = ("WRONG_VERSION_NUMBER", "RECORD_LAYER", "PACKET_LENGTH", "HTTP")
#: X509_V_ERR_HOSTNAME_MISMATCH, X509_V_ERR_IP_ADDRESS_MISMATCH
_X509_V_ERR_HOST_MISMATCH = frozenset({62, 64})
_REDACTED = "**********"


@dataclass(frozen=True)
class ConnectFailure:
    """Why one connect attempt failed: a ``state`` and one secret-free line."""

    state: str
    message: str
    #: the broker closed the TLS connection without saying why (see :func:`explain_failure`)
    ambiguous: bool = False

    @property
    def persistent(self) -> bool:
        return self.state in PERSISTENT_STATES


def explain_failure(
    failure: ConnectFailure, tls_diagnosis: ConnectFailure | None
) -> tuple[ConnectFailure, ConnectFailure | None]:
    """The failure to report for an attempt, and the TLS diagnosis to keep for the next one.

    TLS 1.3 checks the client certificate after the client's side of the handshake is done;
    the broker's alert that says why can be lost to a TCP reset, and the same rejection then
    looks like an unexplained close. Until a connect succeeds, or another cause shows, an
    ambiguous close keeps the definite TLS diagnosis of an earlier attempt.
    """
    if failure.state == TLS_FAILED:
        return failure, failure
    if failure.ambiguous and tls_diagnosis is not None:
        return tls_diagnosis, tls_diagnosis
    return failure, None


class _SocketFailedError(Exception):
    """The client's socket failed before CONNACK (aiomqtt would only time out later)."""


class _ClientLog(logging.Logger):
    """The logger one aiomqtt client (and its paho client) gets.

    Its errors (normally the only records reaching it: its parent's level is ERROR) set
    ``failed``: before CONNACK that means the connect attempt is over. Socket failures
    ("failed to receive on socket: [SSL: TLSV13_ALERT_CERTIFICATE_REQUIRED] ...") are kept
    for the publisher's own one-line messages and logged at DEBUG only, so they do not repeat
    on every attempt; other errors (a callback raising: a bug) are logged as usual.
    """

    def __init__(self, loop: asyncio.AbstractEventLoop) -> None:
        super().__init__(_CLIENT_LOG.name)
        self.parent = _CLIENT_LOG
        self.errors: list[str] = []
        self.failed = asyncio.Event()
        self._loop = loop

    def handle(self, record: logging.LogRecord) -> None:
        if record.levelno < logging.ERROR:  # someone lowered the client logger's level
            super().handle(record)
            return
        text = record.getMessage()
        self.errors.append(text)
        del self.errors[:-5]
        self._loop.call_soon_threadsafe(self.failed.set)
        if " on socket" in text:
            log.debug("client: %s", text)
        else:
            super().handle(record)


class _Repeats:
    """When to log a repeated message: the 1st, 10th, 100th, ... time, or after REPEAT_LOG_S."""

    def __init__(self) -> None:
        self.counts: dict[str, int] = {}
        self._logged_at: dict[str, float] = {}

    def note(self, key: str) -> tuple[int, bool]:
        """(occurrences so far, log this one?)."""
        n = self.counts[key] = self.counts.get(key, 0) + 1
        now = time.monotonic()
        due = n == 10 ** (len(str(n)) - 1) or now - self._logged_at.get(key, now) >= REPEAT_LOG_S
        if due:
            self._logged_at[key] = now
        return n, due

    def clear(self) -> None:
        self.counts.clear()
        self._logged_at.clear()


def _read_file(path: Path, field: str) -> bytes:
    try:
        return path.read_bytes()
    except OSError as exc:
        raise UserError(
            f"mqtt.{field}: cannot read {path}: {exc.strerror or type(exc).__name__}"
        ) from None


def _no_passphrase() -> bytes:
    raise UserError("encrypted key")


def tls_context(settings: MqttSettings) -> ssl.SSLContext | None:
    """The TLS context for ``settings`` (None for a plain ``mqtt://`` url), files read now.

    Server verification against ``ca_file`` (None: the system trust store) with host name
    check unless ``tls_insecure``; the client certificate ``cert_file``/``key_file`` if set.

    Raises:
        UserError: naming the field (``mqtt.ca_file``, ``mqtt.cert_file``, ``mqtt.key_file``)
            of a file that is missing, unreadable or not what it should be.
    """
    s = settings
    if not s.endpoint()[2]:
        return None
    cafile = None
    if s.ca_file is not None:
        _read_file(s.ca_file, "ca_file")
        cafile = str(s.ca_file)
    try:
        ctx = ssl.create_default_context(cafile=cafile)
    except (ssl.SSLError, OSError) as exc:
        reason = getattr(exc, "reason", None) or exc.strerror or exc
        raise UserError(
            f"mqtt.ca_file: no usable PEM CA certificate in {s.ca_file} ({reason})"
        ) from None
    if s.tls_insecure:
        ctx.check_hostname = False
        ctx.verify_mode = ssl.CERT_NONE
    if s.cert_file is not None and s.key_file is not None:
        cert, key = _read_file(s.cert_file, "cert_file"), _read_file(s.key_file, "key_file")
        if b"-----BEGIN CERTIFICATE-----" not in cert:
            raise UserError(f"mqtt.cert_file: no PEM certificate in {s.cert_file}")
        if b"PRIVATE KEY-----" not in key:
            raise UserError(f"mqtt.key_file: no PEM private key in {s.key_file}")
        encrypted = (
            f"mqtt.key_file: {s.key_file} is encrypted (passphrase-protected), which bmsid "
            "cannot use: store the key unencrypted, readable only by the daemon's user"
        )
        if b"ENCRYPTED" in key:
            raise UserError(encrypted)
        try:
            ctx.load_cert_chain(s.cert_file, s.key_file, password=_no_passphrase)
        except UserError:
            raise UserError(encrypted) from None
        except ssl.SSLError as exc:
            if exc.reason == "KEY_VALUES_MISMATCH":
                raise UserError(
                    f"mqtt.key_file: {s.key_file} is not the key of the certificate in "
                    f"mqtt.cert_file ({s.cert_file})"
                ) from None
            raise UserError(
                f"mqtt.cert_file/key_file: cannot load {s.cert_file} with {s.key_file}: "
                f"{exc.reason or exc}"
            ) from None
        except OSError as exc:
            raise UserError(
                f"mqtt.cert_file/key_file: cannot load {s.cert_file} with {s.key_file}: "
                f"{exc.strerror or exc}"
            ) from None
    return ctx


def _closed_during_handshake(settings: MqttSettings) -> ConnectFailure:
    # Ambiguous (a plain MQTT port, a rejected client, a broker restarting): not persistent.
    host, port, _ = settings.endpoint()
    return ConnectFailure(
        UNREACHABLE,
        f"the broker {host}:{port} closed the connection during the TLS handshake: is that "
        "port a TLS listener (mqtt:// for a plain one)? does it require a client certificate "
        "(mqtt.cert_file)?",
        ambiguous=True,
    )


def _tls_reason_failure(reason: str, settings: MqttSettings) -> ConnectFailure:
    """The failure for an OpenSSL reason seen in the handshake (ours or the broker's alert)."""
    host, port, _ = settings.endpoint()
    if "CERTIFICATE_REQUIRED" in reason:
        if settings.cert_file is None:
            msg = (
                f"TLS: the broker {host}:{port} requires a client certificate ({reason}); "
                "set mqtt.cert_file and mqtt.key_file"
            )
        else:
            msg = (
                f"TLS: the broker {host}:{port} did not get a usable client certificate "
                f"({reason}); check mqtt.cert_file {settings.cert_file}"
            )
        return ConnectFailure(TLS_FAILED, msg)
    if any(k in reason for k in _CLIENT_CERT_REJECTED):
        which = (
            f"the client certificate mqtt.cert_file {settings.cert_file}"
            if settings.cert_file is not None
            else "the connection (no client certificate is configured: mqtt.cert_file)"
        )
        return ConnectFailure(
            TLS_FAILED,
            f"TLS: the broker {host}:{port} rejected {which} ({reason}); is it signed by a CA "
            "the broker trusts (its cafile), and still valid?",
        )
    if "EOF" in reason:
        return _closed_during_handshake(settings)
    if any(k in reason for k in _NOT_TLS):
        return ConnectFailure(
            TLS_FAILED,
            f"TLS handshake with {host}:{port} failed ({reason}): is that port a TLS listener? "
            "(use mqtt:// for a plain MQTT port)",
        )
    return ConnectFailure(TLS_FAILED, f"TLS handshake with {host}:{port} failed: {reason}")


def _code(rc: int | ReasonCode | None) -> tuple[int | None, str]:
    if isinstance(rc, ReasonCode):
        return int(rc.value), str(rc)
    return rc, ""


def classify_connect_error(
    exc: BaseException, settings: MqttSettings, client_errors: list[str] | None = None
) -> ConnectFailure:
    """What a failed connect attempt means, as a state and one line saying what to check.

    ``exc`` is what the attempt raised (``aiomqtt.MqttError`` wraps the socket/TLS error of
    paho's connect as its ``__context__``); ``client_errors`` are the client's logged errors
    of this attempt (the only trace of a TLS alert that arrives after the handshake).
    """
    s = settings
    host, port, tls = s.endpoint()
    where = f"{host}:{port}"
    errors = client_errors or []
    if isinstance(exc, UserError):
        return ConnectFailure(CONFIG_ERROR, str(exc))
    if isinstance(exc, aiomqtt.MqttCodeError) and exc.rc is not None:
        value, name = _code(exc.rc)
        shown = f"CONNACK {value}" + (f" '{name}'" if name else "")
        if value in _AUTH_CODES:
            if s.username is None:
                who = "an anonymous login; set mqtt.username and a password"
            else:
                who = (
                    f"user {s.username!r}; check mqtt.username and the password (mqtt.password, "
                    "mqtt.password_file or BMSID_MQTT__PASSWORD) against the broker's "
                    "password file and ACL"
                )
            return ConnectFailure(
                AUTH_FAILED,
                f"login refused, bad username or password / not authorised ({shown}): the "
                f"broker {where} refused {who}",
            )
        if value in _CLIENT_ID_CODES:
            return ConnectFailure(
                REJECTED,
                f"the broker {where} rejected the client id ({shown}); check mqtt.client_id",
            )
        return ConnectFailure(REJECTED, f"the broker {where} refused the connection ({shown})")
    cause = exc.__context__ if isinstance(exc, aiomqtt.MqttError) else exc
    if isinstance(cause, ssl.SSLCertVerificationError):
        detail = cause.verify_message or cause.reason or str(cause)
        if cause.verify_code in _X509_V_ERR_HOST_MISMATCH:
            return ConnectFailure(
                TLS_FAILED,
                f"TLS: the certificate of {where} is not valid for host {host!r} ({detail}); "
                "put a host name its certificate names in mqtt.url",
            )
        trust = f"mqtt.ca_file ({s.ca_file})" if s.ca_file else "the system trust store"
        return ConnectFailure(
            TLS_FAILED,
            f"TLS: certificate verification of {where} failed ({detail}); check that {trust} "
            "holds the CA that signed the broker's certificate",
        )
    if isinstance(cause, ssl.SSLError):
        return _tls_reason_failure(cause.reason or str(cause), s)
    for text in reversed(errors):  # the client's own record of a dead socket
        if m := _SSL_REASON.search(text):
            return _tls_reason_failure(m.group(1), s)
        if tls and _SSL_EOF in text:  # ssl.SSLEOFError's text carries no "[SSL: ...]" tag
            return _closed_during_handshake(s)
    if isinstance(cause, socket.gaierror):
        return ConnectFailure(
            UNREACHABLE, f"cannot resolve host {host!r} ({cause.strerror}); check mqtt.url and DNS"
        )
    if isinstance(cause, ConnectionRefusedError):
        return ConnectFailure(
            UNREACHABLE, f"connection refused by {where}: is the broker running on that port?"
        )
    reset = isinstance(cause, ConnectionError) or any("reset by peer" in t for t in errors)
    if reset and tls:
        return _closed_during_handshake(s)
    if reset:
        return ConnectFailure(
            UNREACHABLE,
            f"the broker {where} closed the connection before CONNACK: is that port a TLS "
            "listener (then use mqtts://)?",
        )
    # aiomqtt wraps the OSError of paho's connect as MqttError(str(oserror)); its own CONNACK
    # timeout is MqttError("Operation timed out") with asyncio's TimeoutError as the context.
    if isinstance(cause, OSError) and str(exc) == str(cause):
        if isinstance(cause, TimeoutError):
            return ConnectFailure(
                UNREACHABLE, f"no TCP connection to {where}: timed out (host down or filtered?)"
            )
        return ConnectFailure(UNREACHABLE, f"cannot connect to {where}: {cause.strerror or cause}")
    if "timed out" in str(exc):
        hint = "" if tls else " (a TLS listener needs mqtts://)"
        return ConnectFailure(
            UNREACHABLE,
            f"no CONNACK from {where} within {s.publish_timeout_s:g} s: is it an MQTT "
            f"broker{hint}?",
        )
    return ConnectFailure(UNREACHABLE, f"connect to {where} failed: {exc}")


def lost_reason(exc: aiomqtt.MqttError, publish_timeout_s: float) -> str:
    """Why an established connection ended, in an operator's words.

    aiomqtt and paho word a loss by the call that noticed it ("[code:4] The client is not
    currently connected." from a publish, "Disconnected during message iteration" from the
    receiver); the disconnect reason they chain below it says more when there is one.
    """
    if str(exc) == "Operation timed out":  # aiomqtt's wording of publish_timeout_s passing
        return (
            "the broker acknowledged nothing within mqtt.publish_timeout_s = "
            f"{publish_timeout_s:g} s"
        )
    cause: BaseException | None = exc
    while cause is not None:
        rc = getattr(cause, "rc", None)
        if isinstance(rc, ReasonCode) and str(rc) == "Keep alive timeout":
            return "the broker stopped answering (no reply within the keep-alive interval)"
        if isinstance(rc, ReasonCode) and rc.value not in (0, 128):  # 128: paho's "no reason"
            return f"the broker disconnected it: {str(rc).lower()}"
        cause = cause.__cause__
    return "the broker closed it or the network dropped it"


def _retrieve_disconnect_reason(client: aiomqtt.Client) -> None:
    """Mark the reason of an unexpected disconnection as seen.

    aiomqtt 2 keeps it in a future only its message iterator reads; when a publish noticed the
    loss first, asyncio would log "Future exception was never retrieved" at garbage collection.
    """
    fut = getattr(client, "_disconnected", None)
    if isinstance(fut, asyncio.Future) and fut.done() and not fut.cancelled():
        fut.exception()


class MqttPublisher:
    """Owns the broker connection; ``run()`` until ``stop()``.

    Args:
        settings: the ``[mqtt]`` section.
        client_id: unique MQTT client identifier.
        outbox: where the daemon puts data messages.
        status_topic: retained status topic; ``online_payload()`` is published on every connect,
            ``offline_payload`` is the will and the last word at shutdown.
        discovery: callable returning the (topic, payload) Home Assistant config messages.
        on_discovery_sent: called (in a thread) once the broker acknowledged all of them.
        on_published: called with each delivered message (latency figures).

    Attributes for the status (all secret-free):
        state: ``connecting``, ``connected``, ``disconnected``, ``unreachable``,
            ``auth_failed``, ``tls_failed``, ``rejected``, ``config_error`` or ``stopped``.
        last_error: the latest connect failure or connection loss as one line (kept after a
            reconnect; ``state`` says whether it is current), None before any.
        failed_attempts: connect attempts failed since the last successful connect.
    """

    def __init__(
        self,
        settings: MqttSettings,
        client_id: str,
        outbox: Outbox,
        status_topic: str,
        online_payload: Callable[[], bytes],
        offline_payload: bytes,
        discovery: Callable[[], list[tuple[str, bytes]]] | None = None,
        on_discovery_sent: Callable[[], None] | None = None,
        on_published: Callable[[OutMessage], None] | None = None,
    ) -> None:
        self.settings = settings
        self.client_id = client_id
        self.outbox = outbox
        self.status_topic = status_topic
        self.online_payload = online_payload
        self.offline_payload = offline_payload
        self.discovery = discovery
        self.on_discovery_sent = on_discovery_sent
        self.on_published = on_published
        self.connected = False
        self.state = CONNECTING
        self.last_error: str | None = None
        self.failed_attempts = 0
        #: the last definite TLS failure since the last connect (see explain_failure)
        self._tls_diagnosis: ConnectFailure | None = None
        self.counters: dict[str, int] = {
            "publishes": 0,
            "connects": 0,
            "reconnects": 0,
            "connect_failures": 0,
            "discovery_sent": 0,
        }
        self._stopping = False
        #: monotonic time by which a stopping publisher gives up (stop())
        self._stop_deadline = float("inf")
        self._status_due = False
        self._wake = asyncio.Event()
        self._stop_event = asyncio.Event()
        self._failures = _Repeats()
        self._short_sessions = _Repeats()
        self._secret: str | None = None

    @property
    def ha_status_topic(self) -> str:
        return f"{self.settings.homeassistant.prefix}/status"

    def _redact(self, text: str) -> str:
        """``text`` with the password replaced, in case a library ever echoes it."""
        if self._secret:
            text = text.replace(self._secret, _REDACTED)
        return text

    def _client(self, client_log: _ClientLog) -> aiomqtt.Client:
        """A new client; UserError (naming the field) when a password/TLS file is unusable."""
        s = self.settings
        host, port, _ = s.endpoint()
        tls = tls_context(s)
        password = s.password_value()
        self._secret = password
        return aiomqtt.Client(
            host,
            port,
            username=s.username,
            password=password,
            identifier=self.client_id,
            will=aiomqtt.Will(self.status_topic, self.offline_payload, qos=1, retain=True),
            keepalive=s.keepalive_s,
            timeout=s.publish_timeout_s,
            tls_context=tls,
            max_inflight_messages=s.max_inflight,
            logger=client_log,
        )

    async def _connect(self, client: aiomqtt.Client, client_log: _ClientLog) -> None:
        """Enter ``client``; give up as soon as its socket fails (aiomqtt would wait for
        CONNACK until the timeout, e.g. after the broker's TLS alert "certificate required")."""
        enter = asyncio.ensure_future(client.__aenter__())
        broken = asyncio.ensure_future(client_log.failed.wait())
        try:
            await asyncio.wait({enter, broken}, return_when=asyncio.FIRST_COMPLETED)
        finally:
            broken.cancel()
            if not enter.done():
                enter.cancel()
                await asyncio.gather(enter, return_exceptions=True)
        if enter.cancelled():
            raise _SocketFailedError(
                client_log.errors[-1] if client_log.errors else "socket failed"
            )
        enter.result()

    async def run(self) -> None:
        """Connect, publish, reconnect with exponential backoff (with jitter) until stopped."""
        s = self.settings
        if s.tls_insecure:
            log.warning(
                "MQTT tls_insecure = true: the broker's certificate and host name are NOT "
                "verified, anyone on the path can read and forge the traffic (tests only)"
            )
        backoff = s.reconnect_min_s
        try:
            while True:
                failure: ConnectFailure | None = None
                client_log = _ClientLog(asyncio.get_running_loop())
                try:
                    client = self._client(client_log)
                    await self._connect(client, client_log)
                except (UserError, aiomqtt.MqttError, _SocketFailedError) as exc:
                    failure, self._tls_diagnosis = explain_failure(
                        classify_connect_error(exc, s, client_log.errors), self._tls_diagnosis
                    )
                    self._on_failure(failure)
                else:
                    t_connect = self._on_connected()
                    try:
                        async with contextlib.AsyncExitStack() as stack:
                            stack.push_async_exit(client)
                            if await self._session(client):
                                return
                    except aiomqtt.MqttError as exc:
                        stable = time.monotonic() - t_connect >= STABLE_SESSION_S
                        if stable:
                            backoff = s.reconnect_min_s
                        self._on_lost(exc, client_log, stable)
                    finally:
                        self.connected = False
                        _retrieve_disconnect_reason(client)
                if self._stopping and not len(self.outbox):
                    return  # nothing left to deliver; the broker publishes the will
                delay = backoff * random.uniform(0.8, 1.2)
                if failure is not None and failure.persistent:
                    backoff = s.reconnect_max_s  # it will not fix itself within seconds
                else:
                    backoff = min(backoff * 2.0, s.reconnect_max_s)
                if not await self._backoff(delay):
                    return  # stopping, and the next attempt would come after the time limit
                self.counters["reconnects"] += 1
        finally:
            self.connected = False
            self.state = STOPPED

    async def _backoff(self, delay: float) -> bool:
        """Wait ``delay`` s before the next attempt; False: do not attempt (stopping).

        A stop does not cut the wait short (a stop while the broker is away would otherwise
        reconnect in a tight loop); it ends it when nothing is left to deliver, or when the
        next attempt would come after the stop's time limit.
        """
        wake_at = time.monotonic() + delay
        if not self._stopping:
            # asyncio.wait, not wait_for: 3.11's wait_for can swallow a cancellation that
            # arrives as its inner wait completes, and the daemon's shutdown would hang.
            stop_wait = asyncio.ensure_future(self._stop_event.wait())
            try:
                await asyncio.wait({stop_wait}, timeout=delay)
            finally:
                stop_wait.cancel()
        if not self._stopping:
            return True
        if not len(self.outbox) or wake_at >= self._stop_deadline:
            return False
        await asyncio.sleep(max(0.0, wake_at - time.monotonic()))
        return True

    def _on_failure(self, failure: ConnectFailure) -> None:
        message = self._redact(failure.message)
        self.counters["connect_failures"] += 1
        self.failed_attempts += 1
        self.state = failure.state
        self.last_error = message
        n, due = self._failures.note(message)
        if not due:
            return
        level = logging.ERROR if failure.state in ERROR_STATES else logging.WARNING
        if n == 1:
            log.log(
                level,
                "MQTT connect to %s failed [%s]: %s (retrying up to every %g s; repeats are "
                "logged at the 10th, 100th, ... failure)",
                self.settings.url,
                failure.state,
                message,
                self.settings.reconnect_max_s,
            )
        else:
            log.log(
                level,
                "MQTT connect to %s still failing [%s], %d times: %s",
                self.settings.url,
                failure.state,
                n,
                message,
            )

    def _on_connected(self) -> float:
        self.connected = True
        self.state = CONNECTED
        self._tls_diagnosis = None
        self.counters["connects"] += 1
        n_short = self._short_sessions.counts.get("", 0)
        if self.failed_attempts:
            log.info(
                "MQTT connected to %s after %d failed attempt(s) (last: %s)",
                self.settings.url,
                self.failed_attempts,
                self.last_error,
            )
        elif n_short == 0 or n_short == 10 ** (len(str(n_short)) - 1):
            log.info("MQTT connected to %s", self.settings.url)
        self.failed_attempts = 0
        self._failures.clear()
        return time.monotonic()

    def _on_lost(self, exc: aiomqtt.MqttError, client_log: _ClientLog, stable: bool) -> None:
        s = self.settings
        detail = lost_reason(exc, s.publish_timeout_s)
        if client_log.errors:  # the socket's own words ("Connection reset by peer")
            detail += f" ({self._redact(client_log.errors[-1])})"
        log.debug("MQTT connection lost: %s", self._redact(repr(exc)))
        self.state = DISCONNECTED
        self.last_error = f"connection lost: {detail}"
        # What happens next, so that the line alone tells an operator nothing is lost yet.
        then = (
            f"reconnecting (backoff {s.reconnect_min_s:g}-{s.reconnect_max_s:g} s); "
            f"messages are held meanwhile ({len(self.outbox)} now, the oldest dropped beyond "
            f"mqtt.outbox_size = {s.outbox_size}; spooled to the state directory at a stop) "
            "and delivered in order once connected again"
        )
        if stable:
            self._short_sessions.clear()
            log.warning("MQTT connection to %s lost: %s; %s", s.url, detail, then)
            return
        # Sessions that keep ending within seconds: typically a second client with the same
        # client id (the broker kicks the older one off). Log the 1st, 10th, 100th, ...
        n, due = self._short_sessions.note("")
        if due:
            log.warning(
                "MQTT connection to %s lost after less than %g s (%d such in a row): %s "
                "(another client with the same client id %r?); %s",
                s.url,
                STABLE_SESSION_S,
                n,
                detail,
                self.client_id,
                then,
            )

    async def _session(self, client: aiomqtt.Client) -> bool:
        """One connection; True when it ended because the daemon stops (offline published)."""
        await client.publish(self.status_topic, self.online_payload(), qos=1, retain=True)
        if self.discovery is not None:
            await client.subscribe(self.ha_status_topic, qos=1)
            await self._send_discovery(client)
        recv = asyncio.create_task(self._receive(client))
        send = asyncio.create_task(self._send(client))
        try:
            done, _ = await asyncio.wait({recv, send}, return_when=asyncio.FIRST_COMPLETED)
        finally:
            for t in (recv, send):
                t.cancel()
            await asyncio.gather(recv, send, return_exceptions=True)
        for t in done:
            if not t.cancelled() and (exc := t.exception()) is not None:
                raise exc
        # send returned: stopping with an empty outbox
        await client.publish(self.status_topic, self.offline_payload, qos=1, retain=True)
        return True

    async def _send_discovery(self, client: aiomqtt.Client) -> None:
        assert self.discovery is not None
        # ~1000 JSON documents for a 96-cell pack: built off the loop
        for topic, payload in await asyncio.to_thread(self.discovery):
            await client.publish(topic, payload, qos=1, retain=True)
            self.counters["discovery_sent"] += 1
        if self.on_discovery_sent is not None:
            await asyncio.to_thread(self.on_discovery_sent)

    async def _receive(self, client: aiomqtt.Client) -> None:
        async for msg in client.messages:
            if (
                self.discovery is not None
                and msg.topic.matches(self.ha_status_topic)
                and msg.payload == b"online"
            ):
                log.info("Home Assistant came online: re-publishing discovery")
                await self._send_discovery(client)

    async def _send(self, client: aiomqtt.Client) -> None:
        # One publish at a time: measured faster with aiomqtt 2.5 than gathered batches
        # (~1000-1600 QoS 1 messages/s on loopback), and the order on the wire is the outbox's.
        while True:
            if self._stopping and time.monotonic() >= self._stop_deadline:
                return  # out of time: the rest stays in the outbox (the daemon spools it)
            batch = self.outbox.peek(1)
            if not batch:
                if self._stopping:
                    return
                waiter = asyncio.create_task(self.outbox.wait())
                stopper = asyncio.create_task(self._wake.wait())
                await asyncio.wait({waiter, stopper}, return_when=asyncio.FIRST_COMPLETED)
                waiter.cancel()
                stopper.cancel()
                if not self._stopping:
                    self._wake.clear()
                await self._publish_status_if_due(client)
                continue
            if self._status_due:
                await self._publish_status_if_due(client)
            m = batch[0]
            await client.publish(m.topic, m.payload, qos=m.qos, retain=m.retain)
            self.outbox.remove_delivered(batch)
            self.counters["publishes"] += 1
            if self.on_published is not None:
                self.on_published(m)

    async def _publish_status_if_due(self, client: aiomqtt.Client) -> None:
        if self._status_due:
            self._status_due = False
            await client.publish(self.status_topic, self.online_payload(), qos=1, retain=True)

    def publish_status(self) -> None:
        """Publish a fresh retained status (counters, CAN state) as soon as connected."""
        self._status_due = True
        self._wake.set()

    def stop(self, timeout_s: float = float("inf")) -> None:
        """Ask ``run()`` to deliver the outbox within ``timeout_s``, publish ``offline`` and
        return; reconnects keep their backoff meanwhile (see :meth:`_backoff`)."""
        self._stop_deadline = time.monotonic() + timeout_s
        self._stopping = True
        self._wake.set()
        self._stop_event.set()
