"""Where each cycle's record goes besides the loop: the time-series log and the heartbeat.

- Logging: with an InfluxDB configured, points are appended to a disk buffer and
  a forwarder task moves them to the database in order (store-and-forward);
  without one, they go to the embedded local store. Either way the runtime's
  sink only does a local disk append, so a slow or absent database never slows
  the compensation loop.
- Probe measurements of the real error, when the CNC publishes them, are logged
  as their own points.
- A heartbeat file per machine, which the container's health check reads, with
  the machine's health counters when a ``health`` provider is given.

The two are separate sinks (:meth:`Outputs.log_points`, :meth:`Outputs.beat`):
a log write that fails (a full disk under the local store) is counted by the
loop and does not keep the heartbeat, and the failure count in it, from being
written.
- Retention: every ``logging.retention_interval_s`` the store (or buffer) deletes
  what is past its age or over its size (gateway/outputs/local_store.py: typed Parquet
  parts after a SQLite open period; disk_buffer.py: a bounded SQLite ring, sqlite_ring.py).
- Timestamps: every point, and the heartbeat's ``time_s``, carry the record's one
  stamp (:attr:`CycleRecord.stamped_s`): in the plant the wall time taken at the
  cycle's start, so an NTP correction or a step of the system clock is followed and
  the Sparkplug node stamps the same cycle with the same time; the loops keep
  scheduling on the monotonic clock.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import time
from collections.abc import Callable, Mapping
from pathlib import Path
from typing import Any

from gateway.config import GatewayConfig
from gateway.live.record import CycleRecord
from gateway.outputs.disk_buffer import PointBuffer
from gateway.outputs.heartbeat import submit_heartbeat
from gateway.outputs.influx import Forwarder, InfluxWriter
from gateway.outputs.local_store import LocalStore
from gateway.outputs.points import Point, points_from_record, probe_point
from gateway.process.file_writer import HEARTBEATS

log = logging.getLogger(__name__)

#: Wall seconds a stopping gateway waits for the forwarder to empty the buffer.
FLUSH_TIMEOUT_S = 0.3
#: How long a stop waits for the last heartbeats to reach the disk, s.
HEARTBEAT_FLUSH_S = 2.0


HealthProvider = Callable[[str], Mapping[str, Any]]


SECONDS_PER_DAY = 86_400.0
#: How often the local store commits the queued points (off the event loop): at most
#: this much is lost to a SIGKILL or a power cut.
STORE_COMMIT_S = 1.0
BYTES_PER_MB = 1_000_000


class Outputs:
    def __init__(
        self,
        config: GatewayConfig,
        health: HealthProvider | None = None,
    ) -> None:
        self.config = config
        self.health = health
        section = config.logging
        self.forwarder: Forwarder | None = None
        self.buffer: PointBuffer | None = None
        self.store: LocalStore | None = None
        if section.influxdb is not None:
            influx = section.influxdb
            section.buffer_path.parent.mkdir(parents=True, exist_ok=True)
            self.buffer = PointBuffer(
                section.buffer_path,
                section.buffer_max_points,
                max_bytes=round(section.buffer_max_mb * BYTES_PER_MB),
                retention_s=section.buffer_retention_days * SECONDS_PER_DAY,
            )
            writer = InfluxWriter(
                influx.url_value(),
                influx.token(),
                influx.org_value(),
                influx.bucket_value(),
                influx.timeout_s,
            )
            self.forwarder = Forwarder(self.buffer, writer)
        else:
            section.local_store.parent.mkdir(parents=True, exist_ok=True)
            self.store = LocalStore(
                section.local_store,
                max_bytes=round(section.local_store_max_mb * BYTES_PER_MB),
                retention_s=section.local_store_retention_days * SECONDS_PER_DAY,
                synchronous="FULL",
                commit_interval_s=STORE_COMMIT_S,
                history_retention_s=section.local_store_history_days * SECONDS_PER_DAY,
            )
        self.state_dir = Path(config.state_dir)
        self._cycles: dict[str, int] = {}
        self._next_retention = time.monotonic()
        self._heartbeat_failing = False

    def enforce_retention(self, now_ns: int | None = None) -> int:
        """Delete what is past its age or over its size; the points deleted.

        ``now_ns`` is the time the ages count from, in the points' own time base (the
        newest point's stamp: wall time in the plant, machine time in a simulation).
        """
        self._next_retention = time.monotonic() + self.config.logging.retention_interval_s
        if self.buffer is not None:
            return self.buffer.enforce_retention(now_ns)
        assert self.store is not None
        return self.store.enforce_retention(now_ns)

    def _write(self, points: list[Point]) -> None:
        if self.buffer is not None:
            self.buffer.append(points)
        else:
            assert self.store is not None
            self.store.write(points)

    def sink(self, record: CycleRecord) -> None:
        """The runtime sink: log the record (and any probe value), beat the heart."""
        try:
            self.log_points(record)
        finally:
            self.beat(record)

    def log_points(self, record: CycleRecord) -> None:
        """Log the record's points (and any probe value) to the buffer or the local store."""
        points = points_from_record(record)
        if record.probe_error_um is not None:
            points.append(probe_point(record.machine, record.stamped_s, record.probe_error_um))
        self._write(points)
        if time.monotonic() >= self._next_retention:
            self.enforce_retention(points[0].time_ns)

    def beat(self, record: CycleRecord) -> None:
        """Write the machine's heartbeat, with its health counters when known (by the
        heartbeat thread: the rename does not hold up the event loop)."""
        self._cycles[record.machine] = self._cycles.get(record.machine, 0) + 1
        submit_heartbeat(
            self.state_dir,
            record.machine,
            record.stamped_s,
            cycles=self._cycles[record.machine],
            health=None if self.health is None else self.health(record.machine),
            done=self._heartbeat_written,
        )

    def _heartbeat_written(self, path: Path, error: OSError | None) -> None:
        """In the heartbeat thread: one line when heartbeats start failing (a full disk:
        the health check will say so, the loop goes on)."""
        if error is not None and not self._heartbeat_failing:
            log.error("cannot write the heartbeat in %s: %s", path.parent, error)
        self._heartbeat_failing = error is not None

    def start(self) -> None:
        if self.forwarder is not None:
            self.forwarder.start()

    async def stop(self, flush_timeout_s: float = FLUSH_TIMEOUT_S) -> None:
        """Give the forwarder ``flush_timeout_s`` to empty the buffer, then stop it.

        Short on purpose: a stop must be quick (SIGTERM), and whatever is not sent
        stays in the on-disk buffer (committed at every append) for the next start.
        """
        if self.forwarder is not None:
            if self.forwarder.health()["connected"]:  # down: the points wait on disk anyway
                with contextlib.suppress(RuntimeError):  # a forwarder that is not running
                    await self.forwarder.flush(timeout=flush_timeout_s)
            await self.forwarder.stop()
        if self.buffer is not None:
            self.buffer.close()
        if self.store is not None:
            self.store.close()
        with contextlib.suppress(TimeoutError):  # a hung disk must not hang the stop
            async with asyncio.timeout(HEARTBEAT_FLUSH_S):
                await HEARTBEATS.drain()  # the last cycle's heartbeats
