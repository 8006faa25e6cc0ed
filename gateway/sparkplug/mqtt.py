"""One MQTT connection (paho-mqtt 2.1) seen from asyncio.

paho runs its network loop in its own thread; its callbacks only hand events to the
gateway's event loop (``call_soon_threadsafe``), where everything else happens.
"""

from __future__ import annotations

import asyncio
import ssl
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any
from urllib.parse import urlsplit

import paho.mqtt.client as paho
from paho.mqtt.enums import CallbackAPIVersion

CONNECT_TIMEOUT_S = 10.0
DEFAULT_PORTS = {"mqtt": 1883, "mqtts": 8883}


@dataclass(frozen=True)
class MqttSettings:
    brokers: tuple[str, ...]  # mqtt://host:port or mqtts://host:port, tried in turn
    client_id: str
    username: str | None = None
    password: str | None = None
    ca_file: Path | None = None
    cert_file: Path | None = None
    key_file: Path | None = None
    qos: int = 0  # of births and data; Sparkplug 3.0 asks 0, 1 has the broker ack each
    keepalive_s: int = 30


def _tls_context(settings: MqttSettings) -> ssl.SSLContext:
    context = ssl.create_default_context(
        cafile=None if settings.ca_file is None else str(settings.ca_file)
    )
    if settings.cert_file is not None:
        context.load_cert_chain(
            str(settings.cert_file), None if settings.key_file is None else str(settings.key_file)
        )
    return context


class MqttLink:
    """A connected client with a will; messages and acknowledgements as awaitables."""

    def __init__(self, settings: MqttSettings, url: str, will_topic: str, will: bytes) -> None:
        self.settings = settings
        self.url = url
        self.loop = asyncio.get_running_loop()
        self.messages: asyncio.Queue[tuple[str, bytes]] = asyncio.Queue()
        self.connected = False
        self.connect_sent = False  # the CONNECT packet (with the will) went out
        self._connected = self.loop.create_future()
        client = paho.Client(
            CallbackAPIVersion.VERSION2,
            client_id=settings.client_id,
            clean_session=True,
            reconnect_on_failure=False,
        )
        client.will_set(will_topic, will, qos=1, retain=False)
        if settings.username is not None:
            client.username_pw_set(settings.username, settings.password)
        if urlsplit(url).scheme == "mqtts":
            client.tls_set_context(_tls_context(settings))
        client.on_connect = self._on_connect
        client.on_disconnect = self._on_disconnect
        client.on_message = self._on_message
        client.max_queued_messages_set(0)
        client.max_inflight_messages_set(1000)
        self.client = client

    # paho's thread ---------------------------------------------------------------------
    def _on_connect(self, _c: Any, _u: Any, _f: Any, reason: Any, _p: Any = None) -> None:
        self.loop.call_soon_threadsafe(self._connect_result, reason)

    def _on_disconnect(self, *_args: Any) -> None:
        self.loop.call_soon_threadsafe(self._lost)

    def _on_message(self, _c: Any, _u: Any, message: paho.MQTTMessage) -> None:
        self.loop.call_soon_threadsafe(
            self.messages.put_nowait, (message.topic, bytes(message.payload))
        )

    # the event loop --------------------------------------------------------------------
    def _connect_result(self, reason: Any) -> None:
        if self._connected.done():
            return
        if reason.is_failure:
            self._connected.set_exception(ConnectionError(f"{self.url} refused: {reason}"))
        else:
            self.connected = True
            self._connected.set_result(None)

    def _lost(self) -> None:
        self.connected = False
        if not self._connected.done():
            self._connected.set_exception(ConnectionError(f"{self.url} closed the connection"))

    async def connect(self) -> None:
        parts = urlsplit(self.url)
        port = parts.port or DEFAULT_PORTS.get(parts.scheme, 1883)
        try:
            await asyncio.to_thread(
                self.client.connect, parts.hostname or "", port, self.settings.keepalive_s
            )
        except (OSError, ssl.SSLError) as exc:
            raise ConnectionError(f"cannot connect to {self.url}: {exc}") from None
        self.connect_sent = True  # paho wrote it before returning (no network thread yet)
        self.client.loop_start()
        try:
            await asyncio.wait_for(asyncio.shield(self._connected), CONNECT_TIMEOUT_S)
        except TimeoutError:
            await asyncio.to_thread(self.close)
            raise ConnectionError(f"{self.url} did not answer the connect") from None
        except ConnectionError:
            await asyncio.to_thread(self.close)
            raise

    async def subscribe(self, topic_filters: Sequence[str]) -> None:
        for topic in topic_filters:
            self.client.subscribe(topic, qos=1)

    def publish(self, topic: str, payload: bytes, qos: int | None = None) -> paho.MQTTMessageInfo:
        """At ``qos``, by default the configured one (births and data), never retained."""
        return self.client.publish(
            topic, payload, qos=self.settings.qos if qos is None else qos, retain=False
        )

    async def acknowledged(self, infos: Sequence[paho.MQTTMessageInfo], timeout_s: float) -> bool:
        """Wait until the broker acknowledged every message (QoS 0: sent).

        Acknowledgements are looked at before the link's state: a broker that acked a
        batch and then died must not have that batch sent twice.
        """
        deadline = self.loop.time() + timeout_s
        while True:
            if any(i.rc != paho.MQTT_ERR_SUCCESS for i in infos):
                return False
            if all(i.is_published() for i in infos):
                return True
            if not self.connected or self.loop.time() >= deadline:
                return False
            await asyncio.sleep(0.002)

    async def flush(self, timeout_s: float) -> None:
        deadline = self.loop.time() + timeout_s
        while self.connected and self.client.want_write() and self.loop.time() < deadline:
            await asyncio.sleep(0.01)
        await asyncio.sleep(0.05)

    async def next_message(self, timeout_s: float) -> tuple[str, bytes] | None:
        try:
            return await asyncio.wait_for(self.messages.get(), timeout_s)
        except TimeoutError:
            return None

    def close(self) -> None:
        self.connected = False
        self.client.disconnect()
        self.client.loop_stop()
