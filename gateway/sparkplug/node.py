"""The gateway as a Sparkplug B edge node: each machine a device, over paho-mqtt.

Every cycle's values go first to a disk buffer (the :class:`PointBuffer` class of the
InfluxDB path, its own file), from which a task publishes them in order once the
node is born and the primary host is online; a point is removed only when it was
delivered: written to the socket at QoS 0 (Sparkplug 3.0's, the default), acknowledged
by the broker at QoS 1. So a host offline costs nothing, nor a broker down at QoS 1:
the points wait and are delivered afterwards, marked historical (``is_historical``)
when births came between their cycle and their delivery. The sink itself only appends
to the buffer, so MQTT never slows the compensation loop.

Sessions: a random start-up delay (``startup_delay_max_s``) spreads births when many
nodes reconnect; each connection takes the next broker of the list. Every MQTT CONNECT
that goes out carries a new bdSeq (the previous one + 1, Sparkplug 3.0's rule), in the
NDEATH will and the NBIRTH; an attempt that fails before its CONNECT (no TCP, no TLS)
uses none. The node waits for the primary host's STATE ``online`` before its births.
A valid ``offline`` STATE while born ends the session: NDEATH, disconnect, and a new
connection (next broker, new bdSeq) that waits for ``online`` again. A STATE older than
the last one taken, or not ``{"online": bool, "timestamp": int}``, is ignored (logged).
``Node Control/Rebirth`` republishes NBIRTH and every DBIRTH on the same session with the
same bdSeq. The node's own metrics (the gateway's process-wide counters and the node's)
are in NBIRTH and, when they change, in NDATA, at most once every ``NODE_DATA_EVERY_S``.
"""

from __future__ import annotations

import asyncio
import contextlib
import json
import logging
import random
import time
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from gateway.live.record import CycleRecord
from gateway.outputs.disk_buffer import PointBuffer
from gateway.outputs.points import Point
from gateway.sparkplug import topics
from gateway.sparkplug.commands import CommandHandler
from gateway.sparkplug.metrics import (
    BD_SEQ,
    REBIRTH,
    changed,
    device_specs,
    node_specs,
    snapshot,
)
from gateway.sparkplug.mqtt import MqttLink, MqttSettings
from gateway.sparkplug.payload import Value, encode

log = logging.getLogger(__name__)

MEASUREMENT = "sparkplug"
BATCH = 200  # points published before waiting for their acknowledgements
# Points encoded and published between two yields to the event loop: a backlog of
# historical snapshots (0.96 kB each) held the machine loops up to 0.8 s per batch of
# 200 on a loaded 2-core box.
YIELD_EVERY = 10
ACK_TIMEOUT_S = 10.0
FINAL_DRAIN_S = 1.5  # at a stop; the gateway gives the node 3 s in all
NODE_DATA_EVERY_S = 1.0  # NDATA of the node's counters that changed, at most this often
DEATH_QOS = 1  # NDEATH, as the will (Sparkplug 3.0)


class HostOfflineError(ConnectionError):
    """The primary host said it is offline: the session ends (NDEATH, disconnect)."""


@dataclass(frozen=True)
class NodeSettings:
    group_id: str
    edge_node_id: str
    primary_host_id: str | None
    machines: Mapping[str, tuple[str, ...]]  # machine id → sensor names
    health_keys: tuple[str, ...]
    state_dir: Path
    startup_delay_max_s: float = 5.0
    reconnect_min_s: float = 0.5
    reconnect_max_s: float = 30.0
    #: machine id → its axes in configured order (a multi-axis machine only)
    axes: Mapping[str, tuple[str, ...]] = field(default_factory=dict)


class EdgeNode:
    def __init__(
        self,
        settings: NodeSettings,
        mqtt: MqttSettings,
        buffer: PointBuffer,
        commands: CommandHandler,
        health: Callable[[str], Mapping[str, Any]],
        gateway_health: Callable[[], Mapping[str, int]] = dict,
    ) -> None:
        self.settings = settings
        self.mqtt = mqtt
        self.buffer = buffer
        self.commands = commands
        self.health = health
        self.gateway_health = gateway_health
        self.specs = {
            machine: device_specs(i, sensors, settings.health_keys, settings.axes.get(machine, ()))
            for i, (machine, sensors) in enumerate(settings.machines.items())
        }
        self.published = 0
        self.node_specs = node_specs(list(self._node_counters()))
        self.latest: dict[str, dict[str, Value]] = {}
        self.sent: dict[str, dict[str, Value]] = {}  # last values published per device
        self.node_sent: dict[str, Value] = {}  # the node's own, as last published
        self.epoch = 0  # births published so far: a point of an older epoch is historical
        self.seq = 0
        self._bd_seq_sent = self._saved_bd_seq()  # of the last CONNECT that went out
        self.bd_seq = (self._bd_seq_sent + 1) % 256  # of the current (or next) CONNECT
        self.link: MqttLink | None = None
        self.born = False
        self.host_online = settings.primary_host_id is None
        self.host_state_ms: int | None = None  # the timestamp of the last STATE taken
        self.sessions = 0
        self._broker = 0
        self._linked = False
        self._node_data_due = 0.0

    # -- the runtime sink: a local append only -------------------------------------------
    def sink(self, record: CycleRecord) -> None:
        values = snapshot(record, self.health(record.machine))
        self.latest[record.machine] = values
        tags = {"machine": record.machine, "epoch": str(self.epoch if self.born else -1)}
        stamp_s = record.stamped_s  # the cycle's one time, as its logged points carry
        ms = round(time.time() * 1000) if stamp_s < 1e9 else round(stamp_s * 1000)
        self.buffer.append([Point(MEASUREMENT, tags, dict(values), ms * 1_000_000)])

    # -- bdSeq, one per CONNECT sent, kept across restarts --------------------------------
    def _bd_seq_path(self) -> Path:
        return self.settings.state_dir / "sparkplug-bdseq.json"

    def _saved_bd_seq(self) -> int:
        """The bdSeq of the last CONNECT sent (by this process or an earlier one); -1: none."""
        try:
            return int(json.loads(self._bd_seq_path().read_text(encoding="utf-8"))["bdSeq"])
        except (OSError, ValueError, KeyError, TypeError):
            return -1

    def _bd_seq_used(self, value: int) -> None:
        """A CONNECT with ``value`` in its will went out: the next one takes ``value + 1``."""
        self._bd_seq_sent = value
        path = self._bd_seq_path()
        try:
            path.parent.mkdir(parents=True, exist_ok=True)
            path.write_text(json.dumps({"bdSeq": value}), encoding="utf-8")
        except OSError as exc:
            log.warning("cannot save the Sparkplug bdSeq in %s: %s", path, exc)

    def _topic(self, kind: str, device: str | None = None) -> str:
        s = self.settings
        if device is None:
            return topics.node_topic(s.group_id, kind, s.edge_node_id)
        return topics.device_topic(s.group_id, kind, s.edge_node_id, device)

    def _next_seq(self) -> int:
        seq = self.seq
        self.seq = (self.seq + 1) % 256
        return seq

    def death_payload(self) -> bytes:
        """NDEATH: ``bdSeq`` by name (and alias), so that a host pairs it with the NBIRTH."""
        bd_seq = self.node_specs[:1]
        return encode(bd_seq, {BD_SEQ: self.bd_seq}, seq=None, timestamp_ms=_now_ms(), birth=True)

    # -- sessions ------------------------------------------------------------------------
    async def run(self, stop: asyncio.Event) -> None:
        """Connect, be born, publish, reconnect to the next broker when the link drops."""
        delay = random.uniform(0, self.settings.startup_delay_max_s)
        backoff = self.settings.reconnect_min_s
        if await _wait(stop, delay):
            return
        while not stop.is_set():
            try:
                await self._session(stop)
            except ConnectionError as exc:
                if self._linked:  # a session that was up: start the back-off afresh
                    backoff, self._linked = self.settings.reconnect_min_s, False
                log.warning("Sparkplug: %s; reconnecting in %.1f s", exc, backoff)
                if await _wait(stop, backoff * random.uniform(1.0, 1.5)):
                    return
                backoff = min(backoff * 2, self.settings.reconnect_max_s)

    async def _session(self, stop: asyncio.Event) -> None:
        self.bd_seq = (self._bd_seq_sent + 1) % 256
        self.sessions += 1
        self.born, self.host_online = False, self.settings.primary_host_id is None
        url = self.mqtt.brokers[self._broker % len(self.mqtt.brokers)]
        self._broker += 1  # the next session tries the next broker (fail-over)
        link = MqttLink(self.mqtt, url, self._topic("NDEATH"), self.death_payload())
        try:
            await link.connect()
        finally:
            if link.connect_sent:
                self._bd_seq_used(self.bd_seq)
        self.link, self._linked = link, True
        host_left = False
        try:
            subs = [self._topic("NCMD"), self._topic("DCMD", "+")]
            if self.settings.primary_host_id:
                subs.append(topics.state_topic(self.settings.primary_host_id))
            await link.subscribe(subs)
            await self._serve(link, stop)
        except HostOfflineError:
            host_left = True  # Sparkplug 3.0: NDEATH, then disconnect
            raise
        finally:
            if (stop.is_set() or host_left) and link.connected:
                await self._say_goodbye(link)
            self.link = None
            await asyncio.to_thread(link.close)  # joins paho's thread: not on the loop
            self.born = False

    async def _serve(self, link: MqttLink, stop: asyncio.Event) -> None:
        while not stop.is_set():
            if not link.connected:
                raise ConnectionError(f"lost the broker {link.url}")
            if self.host_online and not self.born:
                self.births()
            if self.born and not self.host_online:
                self.born = False  # births again on the next session, once it is back
                raise HostOfflineError(f"primary host {self.settings.primary_host_id} offline")
            backlog = self.born and await self._drain(link)
            if self.born:
                self._node_data(link)
            message = await link.next_message(0.01 if backlog else 0.2)
            if message is not None:
                self._on_message(*message)

    async def _say_goodbye(self, link: MqttLink) -> None:
        """The points still buffered (within ``FINAL_DRAIN_S``), then DDEATH for every
        machine born and alive, then NDEATH, as the loops stop: the last cycles of a
        run reach the host now, not at the next start."""
        if self.born:
            with contextlib.suppress(ConnectionError, TimeoutError):
                await asyncio.wait_for(self._drain_all(link), FINAL_DRAIN_S)
            for machine in list(self.sent):
                self._device_death(link, machine)
        link.publish(self._topic("NDEATH"), self.death_payload(), qos=DEATH_QOS)
        await link.flush(1.0)

    async def _drain_all(self, link: MqttLink) -> None:
        while await self._drain(link):
            pass

    def _device_death(self, link: MqttLink, machine: str) -> None:
        data = encode((), {}, seq=self._next_seq(), timestamp_ms=_now_ms())
        link.publish(self._topic("DDEATH", machine), data)
        self.sent.pop(machine, None)  # its next point gives a DBIRTH first

    def machine_stopped(self, machine: str) -> None:
        """A machine's loop stopped (it raised; its supervisor restarts it): DDEATH now,
        when it is born, and no DBIRTH for it until its loop runs a cycle again."""
        self.latest.pop(machine, None)
        link = self.link
        if link is None or not self.born or machine not in self.sent:
            self.sent.pop(machine, None)
            return
        self._device_death(link, machine)
        log.warning("Sparkplug: DDEATH of %s (its loop stopped)", machine)

    # -- births --------------------------------------------------------------------------
    def births(self) -> None:
        """NBIRTH (seq 0, the session's bdSeq) and a DBIRTH for every machine seen."""
        assert self.link is not None
        self.seq = 0
        self.epoch += 1
        self.node_sent = self._node_values()
        node = encode(
            self.node_specs,
            self.node_sent,
            seq=self._next_seq(),
            timestamp_ms=_now_ms(),
            birth=True,
        )
        self.link.publish(self._topic("NBIRTH"), node)
        self.sent.clear()
        for machine, values in self.latest.items():
            self._device_birth(machine, values)
        self.born = True
        log.info("Sparkplug: births published (bdSeq %d, %d machines)", self.bd_seq, len(self.sent))

    def _device_birth(self, machine: str, values: Mapping[str, Value]) -> None:
        assert self.link is not None
        data = encode(
            self.specs[machine], values, seq=self._next_seq(), timestamp_ms=_now_ms(), birth=True
        )
        self.link.publish(self._topic("DBIRTH", machine), data)
        self.sent[machine] = dict(values)

    # -- data ----------------------------------------------------------------------------
    def _node_counters(self) -> dict[str, int]:
        return {**self.gateway_health(), **self.health_counters()}

    def _node_values(self) -> dict[str, Value]:
        counters = {f"Health/{k}": v for k, v in self._node_counters().items()}
        return {BD_SEQ: self.bd_seq, REBIRTH: False, **counters}

    def _node_data(self, link: MqttLink) -> None:
        """NDATA with the node's counters that changed, at most every ``NODE_DATA_EVERY_S``."""
        now = time.monotonic()
        if now < self._node_data_due:
            return
        self._node_data_due = now + NODE_DATA_EVERY_S
        values = self._node_values()
        send = changed(self.node_specs, self.node_sent, values)
        if not send:
            return
        link.publish(
            self._topic("NDATA"), encode(send, values, seq=self._next_seq(), timestamp_ms=_now_ms())
        )
        self.node_sent = values

    async def _drain(self, link: MqttLink) -> bool:
        """Publish the oldest buffered points; True when more are waiting."""
        batch = self.buffer.peek(BATCH)
        if not batch:
            return False
        infos = []
        for i, (_, point) in enumerate(batch):
            if i and i % YIELD_EVERY == 0:  # a backlog must not hold up the machine loops
                await asyncio.sleep(0)
            infos.append(self._publish_point(link, point))
        if not await link.acknowledged([i for i in infos if i is not None], ACK_TIMEOUT_S):
            raise ConnectionError(f"no acknowledgement from {link.url}")
        self.buffer.remove_through(batch[-1][0])
        self.published += len(batch)
        return len(batch) == BATCH

    def _publish_point(self, link: MqttLink, point: Point) -> Any:
        machine = point.tags.get("machine", "")
        specs = self.specs.get(machine)
        if specs is None:  # a machine no longer configured: its points are dropped, named
            log.warning("Sparkplug: dropping a buffered point of unknown machine %s", machine)
            return None
        if machine not in self.sent:
            self._device_birth(machine, self.latest.get(machine, point.fields))
        historical = point.tags.get("epoch") != str(self.epoch)
        values: dict[str, Value] = dict(point.fields)
        send = specs if historical else changed(specs, self.sent[machine], values)
        data = encode(
            send,
            values,
            seq=self._next_seq(),
            timestamp_ms=point.time_ns // 1_000_000,
            historical=historical,
        )
        if not historical:
            self.sent[machine] = values
        return link.publish(self._topic("DDATA", machine), data)

    # -- commands and STATE ----------------------------------------------------------------
    def _on_message(self, topic: str, data: bytes) -> None:
        s = self.settings
        incoming = topics.parse(topic, s.group_id, s.edge_node_id)
        if incoming is None:
            return
        if incoming.kind == "STATE":
            self._on_state(incoming.host, data)
        elif incoming.kind == "NCMD":
            self.commands.handle(data, self.node_specs, None)
        elif incoming.device in self.specs:
            self.commands.handle(data, self.specs[incoming.device], incoming.device)
        else:
            self.commands.refused += 1
            log.warning("Sparkplug DCMD refused: unknown device %s", incoming.device)

    def _on_state(self, host: str | None, data: bytes) -> None:
        """The primary host's STATE: taken unless malformed or older than the last one
        taken (a late death of an earlier host session); an ``offline`` taken while born
        ends the session in :meth:`_serve`."""
        if host != self.settings.primary_host_id or host is None:
            return
        topic = topics.state_topic(host)
        try:
            online, timestamp_ms = state_of(data)
        except ValueError as exc:
            log.warning("Sparkplug: STATE on %s ignored: %s", topic, exc)
            return
        last = self.host_state_ms
        if last is not None and timestamp_ms < last:
            log.warning(
                "Sparkplug: STATE on %s ignored: timestamp %d is older than the last one "
                "taken (%d)",
                topic,
                timestamp_ms,
                last,
            )
            return
        self.host_state_ms = timestamp_ms
        if online != self.host_online:
            log.warning("Sparkplug: primary host %s %s", host, "online" if online else "offline")
        self.host_online = online

    def rebirth(self) -> None:
        """``Node Control/Rebirth``: births again on this session, bdSeq unchanged."""
        if self.link is not None and self.host_online:
            self.births()

    def health_counters(self) -> dict[str, int]:
        return {
            "sparkplug_backlog": len(self.buffer),
            "sparkplug_published": self.published,
            "sparkplug_commands_accepted": self.commands.accepted,
            "sparkplug_commands_refused": self.commands.refused,
        }


def state_of(data: bytes) -> tuple[bool, int]:
    """``(online, timestamp_ms)`` of a STATE payload; ValueError naming what is wrong."""
    expected = 'expected JSON {"online": true|false, "timestamp": <ms>}'
    try:
        state = json.loads(data.decode("utf-8"))
    except (ValueError, UnicodeDecodeError):
        raise ValueError(f"not JSON ({data[:80]!r}); {expected}") from None
    if not isinstance(state, dict):
        raise ValueError(f"{state!r}: {expected}")
    online, timestamp_ms = state.get("online"), state.get("timestamp")
    if not isinstance(online, bool):
        raise ValueError(f"online is {online!r}, not a boolean; {expected}")
    if not isinstance(timestamp_ms, int) or isinstance(timestamp_ms, bool):
        raise ValueError(f"timestamp is {timestamp_ms!r}, not an integer; {expected}")
    return online, timestamp_ms


def _now_ms() -> int:
    return round(time.time() * 1000)


async def _wait(stop: asyncio.Event, seconds: float) -> bool:
    """Sleep ``seconds`` unless ``stop`` is set first; True when stopping."""
    try:
        await asyncio.wait_for(stop.wait(), timeout=seconds)
    except TimeoutError:
        return False
    return True
