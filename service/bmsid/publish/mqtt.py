"""The MQTT publisher: reconnects with backoff, drains the outbox in order, keeps the status.

aiomqtt does not reconnect by itself and its ``publish`` waits for the library's acknowledgement
(QoS >= 1: the broker's), so this task owns the connection and nothing upstream ever awaits it.
On connect: retained ``online`` status (the will is the retained ``offline``), Home Assistant
discovery if enabled (re-sent whenever ``<ha_prefix>/status`` says ``online``), then the backlog.
A message leaves the outbox only after its publish succeeded, so the backlog of an outage is
delivered in order; a publish that failed with the connection is sent again (at-least-once).
"""

from __future__ import annotations

import asyncio
import logging
import random
import ssl
from collections.abc import Callable

import aiomqtt

from bmsid.config.settings import MqttSettings
from bmsid.publish.outbox import Outbox, OutMessage

log = logging.getLogger(__name__)
#: aiomqtt warns once per publish while more than 10 are pending: noise, not news.
_CLIENT_LOG = logging.getLogger(f"{__name__}.client")
_CLIENT_LOG.setLevel(logging.ERROR)


class MqttPublisher:
    """Owns the broker connection; ``run()`` until ``stop()``.

    Args:
        settings: the ``[mqtt]`` section.
        client_id: unique MQTT client identifier.
        outbox: where the daemon puts data messages.
        status_topic: retained status topic; ``online_payload()`` is published on every connect,
            ``offline_payload`` is the will and the last word at shutdown.
        discovery: callable returning the (topic, payload) Home Assistant config messages.
        on_published: called with each delivered message (latency figures).
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
        on_published: Callable[[OutMessage], None] | None = None,
    ) -> None:
        self.settings = settings
        self.client_id = client_id
        self.outbox = outbox
        self.status_topic = status_topic
        self.online_payload = online_payload
        self.offline_payload = offline_payload
        self.discovery = discovery
        self.on_published = on_published
        self.connected = False
        self.counters: dict[str, int] = {
            "publishes": 0,
            "connects": 0,
            "reconnects": 0,
            "connect_failures": 0,
            "discovery_sent": 0,
        }
        self._stopping = False
        self._status_due = False
        self._wake = asyncio.Event()
        self._stop_event = asyncio.Event()

    @property
    def ha_status_topic(self) -> str:
        return f"{self.settings.homeassistant.prefix}/status"

    def _client(self) -> aiomqtt.Client:
        s = self.settings
        host, port, tls = s.endpoint()
        tls_context = None
        if tls:
            tls_context = ssl.create_default_context(
                cafile=str(s.ca_file) if s.ca_file is not None else None
            )
            if s.tls_insecure:
                tls_context.check_hostname = False
                tls_context.verify_mode = ssl.CERT_NONE
        return aiomqtt.Client(
            host,
            port,
            username=s.username,
            password=s.password_value(),
            identifier=self.client_id,
            will=aiomqtt.Will(self.status_topic, self.offline_payload, qos=1, retain=True),
            keepalive=s.keepalive_s,
            timeout=s.publish_timeout_s,
            tls_context=tls_context,
            max_inflight_messages=s.max_inflight,
            logger=_CLIENT_LOG,
        )

    async def run(self) -> None:
        """Connect, publish, reconnect with exponential backoff (with jitter) until stopped."""
        s = self.settings
        backoff = s.reconnect_min_s
        while True:
            connected_once = False
            try:
                async with self._client() as client:
                    connected_once = True
                    self.connected = True
                    self.counters["connects"] += 1
                    backoff = s.reconnect_min_s
                    log.info("MQTT connected to %s", s.url)
                    if await self._session(client):
                        return
            except aiomqtt.MqttError as exc:
                if not connected_once:
                    self.counters["connect_failures"] += 1
                log.warning("MQTT %s: %s", "connection lost" if connected_once else "connect", exc)
            finally:
                self.connected = False
            if self._stopping and not len(self.outbox):
                return  # nothing left to deliver; the broker publishes the will
            self.counters["reconnects"] += 1
            delay = backoff * random.uniform(0.8, 1.2)
            backoff = min(backoff * 2.0, s.reconnect_max_s)
            # asyncio.wait, not wait_for: 3.11's wait_for can swallow a cancellation that
            # arrives as its inner wait completes, and the daemon's shutdown would hang.
            stop_wait = asyncio.ensure_future(self._stop_event.wait())
            try:
                await asyncio.wait({stop_wait}, timeout=delay)
            finally:
                stop_wait.cancel()

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

    def stop(self) -> None:
        """Ask ``run()`` to deliver the outbox, publish ``offline`` and return."""
        self._stopping = True
        self._wake.set()
        self._stop_event.set()
