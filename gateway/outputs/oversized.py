"""Points InfluxDB refuses as too large even alone (HTTP 413), known by their size.

A body-size limit (nginx's ``client_max_body_size``, an API gateway's) refuses every
point over it, and a gateway that logs a large field every cycle makes one such point
per cycle. Finding each one again by halving the batch costs about ten refused
requests per point, and logging each one floods the log. So the size of the smallest
lone point the server refused is remembered, and every point at least that large is
dropped without a request (counted all the same). The size is forgotten after
``recheck_s``, so a limit raised on the server is noticed: the next large point is
then sent once more.

Drops are logged per episode: the first drop at ERROR, the others at DEBUG, and the
episode's end — ``quiet_s`` without a drop, seen at the next acknowledged write — at
INFO with how many points it dropped.
"""

from __future__ import annotations

import logging
import time
from collections.abc import Callable

from influxdb_client import Point as InfluxPoint
from influxdb_client import WritePrecision

from gateway.outputs.points import Point

log = logging.getLogger("gateway.outputs.influx")

Row = tuple[int, Point]


def to_influx(point: Point) -> InfluxPoint:
    """The influxdb-client point that is sent for ``point``."""
    influx = InfluxPoint(point.measurement)
    for key, tag in point.tags.items():
        influx.tag(key, tag)
    for key, value in point.fields.items():
        influx.field(key, value)
    return influx.time(point.time_ns, WritePrecision.NS)


def line_bytes(point: Point) -> int:
    """Bytes of the point's line protocol: its share of a write request's body."""
    return len(to_influx(point).to_line_protocol().encode("utf-8"))


class OversizedPoints:
    """The size the server refuses a lone point at, and the log of what it drops."""

    def __init__(
        self,
        quiet_s: float = 60.0,
        recheck_s: float = 600.0,
        clock: Callable[[], float] = time.monotonic,
    ) -> None:
        self.quiet_s = quiet_s
        self.recheck_s = recheck_s
        self.clock = clock
        self.limit_bytes: int | None = None  # the smallest lone point refused, bytes
        self._reason = ""  # the server's answer to that point
        self._learned_s = 0.0
        self._episode_points = 0
        self._episode_start_s = 0.0
        self._last_drop_s: float | None = None

    def refused_alone(self, point: Point, reason: str) -> None:
        """The server refused ``point`` alone as too large: points this size will be dropped."""
        size = line_bytes(point)
        if self.limit_bytes is None or size < self.limit_bytes:
            self.limit_bytes = size
        self._reason = reason
        self._learned_s = self.clock()

    def split(self, batch: list[Row]) -> tuple[list[Row], list[Row]]:
        """The batch's points to send, and those known to be too large (kept in order)."""
        if self.limit_bytes is not None and self.clock() - self._learned_s > self.recheck_s:
            self.limit_bytes = None  # send the next large point again: the limit may be raised
        if self.limit_bytes is None:
            return batch, []
        send: list[Row] = []
        drop: list[Row] = []
        for row in batch:
            (drop if line_bytes(row[1]) >= self.limit_bytes else send).append(row)
        return send, drop

    def dropped(self, rows: list[Row]) -> None:
        """Log a drop: at ERROR when it opens an episode, at DEBUG within one."""
        if not rows:
            return
        now_s = self.clock()
        first = rows[0][1]
        if self._episode_points == 0:
            self._episode_start_s = now_s
            log.error(
                "dropping %d %s point(s) (machine %s, first at %d ns) InfluxDB refuses as "
                "too large even alone (%d bytes or more): %s. Further points that large "
                "are dropped without a request and counted in too_large; the next is "
                "logged after %.0f s without one",
                len(rows),
                first.measurement,
                first.tags.get("machine", "?"),
                first.time_ns,
                self.limit_bytes or line_bytes(first),
                self._reason,
                self.quiet_s,
            )
        else:
            log.debug("dropping %d more point(s) too large for InfluxDB", len(rows))
        self._episode_points += len(rows)
        self._last_drop_s = now_s

    def write_acknowledged(self) -> None:
        """Close the episode once ``quiet_s`` passed without a drop (logged at INFO)."""
        if self._episode_points == 0 or self._last_drop_s is None:
            return
        if self.clock() - self._last_drop_s < self.quiet_s:
            return
        log.info(
            "InfluxDB refused %d point(s) as too large in %.0f s; none for %.0f s since",
            self._episode_points,
            self._last_drop_s - self._episode_start_s,
            self.quiet_s,
        )
        self._episode_points = 0
