"""Where each cycle's record goes besides the loop: the time-series log and the heartbeat.

- Logging: with an InfluxDB configured, points are appended to a disk buffer and
  a forwarder task moves them to the database in order (store-and-forward);
  without one, they go to the embedded local store. Either way the runtime's
  sink only does a local disk append, so a slow or absent database never slows
  the compensation loop.
- Probe measurements of the real error, when the CNC publishes them, are logged
  as their own points.
- A heartbeat file per machine, which the container's health check reads.
"""

from __future__ import annotations

import logging
from pathlib import Path

from gateway.config import GatewayConfig
from gateway.health import write_heartbeat
from gateway.influx_writer import Forwarder, InfluxWriter
from gateway.local_store import LocalStore
from gateway.point_buffer import PointBuffer
from gateway.runtime import CycleRecord
from gateway.timeseries import Point, points_from_record, probe_point

log = logging.getLogger(__name__)


class Outputs:
    def __init__(self, config: GatewayConfig) -> None:
        self.config = config
        section = config.logging
        self.forwarder: Forwarder | None = None
        self.buffer: PointBuffer | None = None
        self.store: LocalStore | None = None
        if section.influxdb is not None:
            influx = section.influxdb
            section.buffer_path.parent.mkdir(parents=True, exist_ok=True)
            self.buffer = PointBuffer(section.buffer_path, section.buffer_max_points)
            writer = InfluxWriter(
                influx.url, influx.token(), influx.org, influx.bucket, influx.timeout_s
            )
            self.forwarder = Forwarder(self.buffer, writer)
        else:
            section.local_store.parent.mkdir(parents=True, exist_ok=True)
            self.store = LocalStore(section.local_store)
        self.state_dir = Path(config.state_dir)
        self._cycles: dict[str, int] = {}

    def _write(self, points: list[Point]) -> None:
        if self.buffer is not None:
            self.buffer.append(points)
        else:
            assert self.store is not None
            self.store.write(points)

    def sink(self, record: CycleRecord) -> None:
        """The runtime sink: log the record (and any probe value), beat the heart."""
        points = points_from_record(record)
        if record.probe_error_um is not None:
            points.append(probe_point(record.machine, record.time_s, record.probe_error_um))
        self._write(points)
        self._cycles[record.machine] = self._cycles.get(record.machine, 0) + 1
        write_heartbeat(
            self.state_dir, record.machine, record.time_s, cycles=self._cycles[record.machine]
        )

    def start(self) -> None:
        if self.forwarder is not None:
            self.forwarder.start()

    async def stop(self) -> None:
        if self.forwarder is not None:
            await self.forwarder.flush(timeout=5.0)
            await self.forwarder.stop()
        if self.buffer is not None:
            self.buffer.close()
        if self.store is not None:
            self.store.close()
