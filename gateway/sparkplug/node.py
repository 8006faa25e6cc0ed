"""The gateway as a Sparkplug B edge node: each machine a device, over paho-mqtt.

Every cycle's values go first to a disk buffer (the :class:`PointBuffer` class of the
InfluxDB path, its own file), from which a task publishes them in order once the
node is born and the primary host is online; a point is removed only when the broker
acknowledged it (QoS 1). So a broker down or a host offline costs nothing: the points
wait and are delivered afterwards, marked historical (``is_historical``) when births
came between their cycle and their delivery. The sink itself only appends to the
buffer, so MQTT never slows the compensation loop.

Sessions: a random start-up delay (``startup_delay_max_s``) spreads births when many
nodes reconnect; each connection takes the next broker of the list and a new bdSeq,
carried in the NDEATH will and the NBIRTH. The node waits for the primary host's
STATE ``online`` before its births; ``Node Control/Rebirth`` republishes NBIRTH and
every DBIRTH on the same session with the same bdSeq.
"""

from __future__ import annotations

import asyncio
import contextlib
import json
import logging
import random
import time
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from gateway.live.record import CycleRecord
from gateway.outputs.disk_buffer import PointBuffer
from gateway.outputs.points import Point
from gateway.sparkplug import topics
from gateway.sparkplug.commands import CommandHandler
from gateway.sparkplug.metrics import BD_SEQ, NODE_METRICS, REBIRTH, changed, device_specs, snapshot
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


class EdgeNode:
    def __init__(
        self,
        settings: NodeSettings,
        mqtt: MqttSettings,
        buffer: PointBuffer,
        commands: CommandHandler,
        health: Callable[[str], Mapping[str, Any]],
    ) -> None:
        self.settings = settings
        self.mqtt = mqtt
        self.buffer = buffer
        self.commands = commands
        self.health = health
        self.specs = {
            machine: device_specs(i, sensors, settings.health_keys)
            for i, (machine, sensors) in enumerate(settings.machines.items())
        }
        self.latest: dict[str, dict[str, Value]] = {}
        self.sent: dict[str, dict[str, Value]] = {}  # last values published per device
        self.epoch = 0  # births published so far: a point of an older epoch is historical
        self.seq = 0
        self.bd_seq = self._next_bd_seq()
        self.link: MqttLink | None = None
        self.born = False
        self.host_online = settings.primary_host_id is None
        self.published = 0
        self.sessions = 0
        self._broker = 0
        self._linked = False

    # -- the runtime sink: a local append only -------------------------------------------
    def sink(self, record: CycleRecord) -> None:
        values = snapshot(record, self.health(record.machine))
        self.latest[record.machine] = values
        tags = {"machine": record.machine, "epoch": str(self.epoch if self.born else -1)}
        stamp_s = record.stamped_s  # the cycle's one time, as its logged points carry
        ms = round(time.time() * 1000) if stamp_s < 1e9 else round(stamp_s * 1000)
        self.buffer.append([Point(MEASUREMENT, tags, dict(values), ms * 1_000_000)])

    # -- bdSeq, kept across restarts -----------------------------------------------------
    def _next_bd_seq(self) -> int:
        path = self.settings.state_dir / "sparkplug-bdseq.json"
        try:
            last = int(json.loads(path.read_text(encoding="utf-8"))["bdSeq"])
        except (OSError, ValueError, KeyError, TypeError):
            last = -1
        value = (last + 1) % 256
        try:
            path.parent.mkdir(parents=True, exist_ok=True)
            path.write_text(json.dumps({"bdSeq": value}), encoding="utf-8")
        except OSError as exc:
            log.warning("cannot save the Sparkplug bdSeq in %s: %s", path, exc)
        return value

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
        return encode(NODE_METRICS[:1], {BD_SEQ: self.bd_seq}, seq=None, timestamp_ms=_now_ms())

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
        self.bd_seq = self._next_bd_seq() if self.sessions else self.bd_seq
        self.sessions += 1
        self.born, self.host_online = False, self.settings.primary_host_id is None
        url = self.mqtt.brokers[self._broker % len(self.mqtt.brokers)]
        self._broker += 1  # the next session tries the next broker (fail-over)
        link = MqttLink(self.mqtt, url, self._topic("NDEATH"), self.death_payload())
        await link.connect()
        self.link, self._linked = link, True
        try:
            subs = [self._topic("NCMD"), self._topic("DCMD", "+")]
            if self.settings.primary_host_id:
                subs.append(topics.state_topic(self.settings.primary_host_id))
            await link.subscribe(subs)
            await self._serve(link, stop)
        finally:
            if stop.is_set() and link.connected:
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
            backlog = self.born and await self._drain(link)
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
        link.publish(self._topic("NDEATH"), self.death_payload())
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
        node = encode(
            NODE_METRICS,
            {BD_SEQ: self.bd_seq, REBIRTH: False},
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
            self.commands.handle(data, NODE_METRICS, None)
        elif incoming.device in self.specs:
            self.commands.handle(data, self.specs[incoming.device], incoming.device)
        else:
            self.commands.refused += 1
            log.warning("Sparkplug DCMD refused: unknown device %s", incoming.device)

    def _on_state(self, host: str | None, data: bytes) -> None:
        if host != self.settings.primary_host_id:
            return
        try:
            online = json.loads(data.decode("utf-8"))["online"] is True
        except (ValueError, KeyError, TypeError, UnicodeDecodeError):
            log.warning("Sparkplug: STATE of %s not understood: %r", host, data[:80])
            return
        if online != self.host_online:
            log.warning("Sparkplug: primary host %s %s", host, "online" if online else "offline")
        self.host_online = online
        if not online:
            self.born = False  # births again when it is back; the data waits in the buffer

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


def _now_ms() -> int:
    return round(time.time() * 1000)


async def _wait(stop: asyncio.Event, seconds: float) -> bool:
    """Sleep ``seconds`` unless ``stop`` is set first; True when stopping."""
    try:
        await asyncio.wait_for(stop.wait(), timeout=seconds)
    except TimeoutError:
        return False
    return True
