"""Sending points to InfluxDB, and the store-and-forward task that does it.

:class:`InfluxWriter` writes a batch with influxdb-client's synchronous write API
(the async client needs aiohttp, which the gateway does not ship), run in a
worker thread so the event loop never waits for the network. Only the write and
query APIs are used, so InfluxDB 1.8 (its v2 compatibility API; bucket
``"db/retention"``, org ``"-"``), 2.x and 3.x all work.

:class:`Forwarder` is the asyncio task between the :class:`PointBuffer` on disk
and the writer::

    peek the oldest batch → write it → remove it from the buffer → next batch

On a failure it waits (:class:`drivers.backoff.Backoff`: from ``retry_s``
doubling up to ``max_retry_s``, with jitter, back to the start after a success)
and retries the *same* batch, so points reach InfluxDB in buffer order and none
is skipped, however long the outage. The task is supervised
(:class:`gateway.process.supervision.Supervised`): should it raise anyway (the buffer's
disk failing, a bug), it is logged, counted in ``restarts`` and started again,
and the points stay in the buffer for it.

Why there are no duplicates: a batch is removed from the buffer only after
InfluxDB acknowledged it (HTTP 204). If the gateway dies after the
acknowledgement but before the removal, the same batch is sent again after the
restart — with the same measurement, tags and timestamp for every point, since
points are stored with their final timestamps. InfluxDB identifies a point by its
series (measurement + tag set) and time; a second write of the same point
overwrites the first with identical field values, so it is stored once. The same
holds for a write that timed out on the gateway's side although the server
stored it.

A batch the server refuses as invalid (HTTP 400/422, e.g. a field whose type
conflicts with what the bucket holds) would fail for ever: it is removed, logged
at ERROR with the server's reason and counted in :meth:`Forwarder.health`
``rejected``, so it cannot block the points behind it. Such a refusal is
usually a partial write: the server kept the valid points of the batch and
dropped the others; ``rejected`` counts the points it says it dropped
(``dropped=N`` in its reason), or the whole batch when it does not say.

The server's other answers are read too (docs/reliability/influxdb.md):

- ``429 Too Many Requests`` / ``503 Service Unavailable`` with ``Retry-After``
  (seconds or an HTTP date): the next attempt waits at least that long — the
  back-off's jitter only ever shortens a wait, so without this a ``Retry-After: 10``
  was retried after 8–9 s.
- ``413 Payload Too Large``: resending the same batch cannot help, so the batch is
  halved at once (no wait) until the server takes it, down to one point; the
  smaller size is kept for the rest of the run (``batch_limit`` in
  :meth:`Forwarder.health`). A single point the server still refuses as too large
  is dropped and counted in ``too_large`` (and ``rejected``), and the batch size goes
  back to the last one the server took. Its size is remembered
  (:mod:`gateway.outputs.oversized`): later points that large are dropped without a
  request, and a run of such drops is one episode, logged once at ERROR.
- Every other failure (5xx, 401/403/404, timeouts, refused connections) keeps the
  batch and retries after the back-off. Each distinct cause of an outage (its HTTP
  status, or the kind of connection error) is logged once at WARNING with its
  status code; the outage's end is logged once at INFO.
"""

from __future__ import annotations

import asyncio
import contextlib
import datetime
import email.utils
import json
import logging
import re
import time
from collections.abc import Sequence
from typing import Protocol

from influxdb_client import InfluxDBClient
from influxdb_client.client.write_api import SYNCHRONOUS
from influxdb_client.rest import ApiException

from drivers.backoff import Backoff
from gateway.outputs.disk_buffer import PointBuffer
from gateway.outputs.oversized import OversizedPoints, Row, to_influx
from gateway.outputs.points import Point
from gateway.process.supervision import Supervised

log = logging.getLogger(__name__)

REJECTED_STATUS = {400, 422}  # the request itself is wrong: retrying cannot help
TOO_LARGE_STATUS = 413  # the request body is over the server's (or a proxy's) limit
MAX_TIME_NS = 9_223_372_036_854_775_806  # the largest time InfluxDB stores
MAX_RETRY_AFTER_S = 3600.0  # a longer Retry-After is taken as this (a wrong clock, a typo)


class WriteError(RuntimeError):
    """A write did not reach InfluxDB (server down, timeout, 5xx, auth): retry later.

    ``status`` is the HTTP status when the server answered (None: no answer);
    ``retry_after_s`` the wait its ``Retry-After`` header asked for, if any.
    """

    def __init__(
        self, message: str, status: int | None = None, retry_after_s: float | None = None
    ) -> None:
        super().__init__(message)
        self.status = status
        self.retry_after_s = retry_after_s

    @property
    def cause(self) -> str:
        """What went wrong, for logging each distinct cause once: "HTTP 429", "timeout"."""
        if self.status is not None:
            return f"HTTP {self.status}"
        origin = self.__cause__
        return type(origin).__name__ if origin is not None else "unreachable"


class WriteTooLargeError(WriteError):
    """InfluxDB (or a proxy in front) refused the request body as too large (HTTP 413)."""


class WriteRejectedError(WriteError):
    """InfluxDB refused the points themselves (HTTP 400/422): retrying cannot help.

    ``dropped`` is how many points of the batch the server dropped, when it says
    (a partial write: it stored the others); ``None`` when it does not.
    """

    def __init__(self, message: str, status: int, dropped: int | None = None) -> None:
        super().__init__(message, status)
        self.dropped = dropped


def _describe(exc: BaseException) -> str:
    """The status and the server's reason: InfluxDB 1.8 puts it in a header, 2.x in the
    JSON body's ``message`` (e.g. ``partial write: field type conflict … dropped=1``)."""
    if isinstance(exc, ApiException):
        reason = exc.headers.get("X-Influxdb-Error") if exc.headers else None
        return f"HTTP {exc.status}: {reason or _body_message(exc.body) or exc.reason}"
    return f"{type(exc).__name__}: {exc}"


def _body_message(body: object) -> str | None:
    if isinstance(body, bytes):
        body = body.decode("utf-8", errors="replace")
    if not isinstance(body, str) or not body.strip():
        return None
    try:
        message = json.loads(body).get("message")
    except (ValueError, AttributeError):
        return body.strip()[:500]
    return str(message) if message else body.strip()[:500]


def retry_after_s(value: str | None, now_s: float | None = None) -> float | None:
    """The wait a ``Retry-After`` header asks for, s: delay-seconds or an HTTP date.

    None when absent or unreadable; never negative; at most ``MAX_RETRY_AFTER_S``.
    """
    if value is None or not value.strip():
        return None
    text = value.strip()
    try:
        seconds = float(text)
    except ValueError:
        try:
            moment = email.utils.parsedate_to_datetime(text)
        except (TypeError, ValueError):
            return None
        if moment.tzinfo is None:
            moment = moment.replace(tzinfo=datetime.UTC)
        seconds = moment.timestamp() - (time.time() if now_s is None else now_s)
    if seconds != seconds:  # NaN
        return None
    return min(max(seconds, 0.0), MAX_RETRY_AFTER_S)


def _api_error(exc: ApiException, url: str, count: int) -> WriteError:
    """The WriteError (or subclass) an HTTP error answer stands for."""
    message = f"InfluxDB {url} refused {count} point(s): {_describe(exc)}"
    if exc.status in REJECTED_STATUS:
        found = re.search(r"dropped=(\d+)", message)
        return WriteRejectedError(message, exc.status, int(found.group(1)) if found else None)
    if exc.status == TOO_LARGE_STATUS:
        return WriteTooLargeError(message, exc.status)
    wait_s = retry_after_s(exc.headers.get("Retry-After") if exc.headers else None)
    return WriteError(message, exc.status, wait_s)


class InfluxWriter:
    """Writes points to one InfluxDB bucket; :meth:`write` raises :class:`WriteError`."""

    def __init__(
        self, url: str, token: str, org: str, bucket: str, timeout_s: float = 10.0
    ) -> None:
        self.url = url
        self.org = org
        self.bucket = bucket
        self.timeout_s = timeout_s
        # retries=False: no hidden urllib3 retries; the Forwarder decides when to retry.
        self._client = InfluxDBClient(
            url=url, token=token, org=org, timeout=int(timeout_s * 1000), retries=False
        )
        self._write_api = self._client.write_api(write_options=SYNCHRONOUS)

    def write_sync(self, points: Sequence[Point]) -> None:
        """Write a batch, blocking; return only once InfluxDB acknowledged it."""
        if not points:
            return
        records = [to_influx(p) for p in points]
        try:
            # Each point carries its precision (ns), which the client groups points by.
            self._write_api.write(bucket=self.bucket, org=self.org, record=records)
        except ApiException as exc:
            raise _api_error(exc, self.url, len(points)) from exc
        except Exception as exc:  # urllib3 connection errors, timeouts, …
            raise WriteError(
                f"InfluxDB {self.url} unreachable ({len(points)} point(s)): {_describe(exc)}"
            ) from exc

    async def write(self, points: Sequence[Point]) -> None:
        """:meth:`write_sync` in a worker thread."""
        await asyncio.to_thread(self.write_sync, list(points))

    def close(self) -> None:
        self._write_api.close()
        self._client.close()


class InfluxReader:
    """Reads points back with Flux (the same ``query`` as ``LocalStore``)."""

    def __init__(
        self, url: str, token: str, org: str, bucket: str, timeout_s: float = 30.0
    ) -> None:
        self.bucket = bucket
        self.org = org
        self._client = InfluxDBClient(url=url, token=token, org=org, timeout=int(timeout_s * 1000))
        self._query_api = self._client.query_api()

    def flux(
        self,
        measurement: str,
        machine: str | None = None,
        start_ns: int | None = None,
        stop_ns: int | None = None,
    ) -> str:
        # int(v: r._time) keeps the nanoseconds (the client parses _time to µs datetimes).
        return (
            self._range_flux(machine, start_ns, stop_ns) + "\n"
            f"  |> filter(fn: (r) => r._measurement == {_flux_string(measurement)})\n"
            '  |> pivot(rowKey: ["_time"], columnKey: ["_field"], valueColumn: "_value")\n'
            "  |> map(fn: (r) => ({r with _time_ns: int(v: r._time)}))"
        )

    def query(
        self,
        measurement: str,
        machine: str | None = None,
        start_ns: int | None = None,
        stop_ns: int | None = None,
    ) -> list[Point]:
        """Points of ``measurement`` (of ``machine``), ``start_ns ≤ time < stop_ns``, by time."""
        tables = self._query_api.query(
            self.flux(measurement, machine, start_ns, stop_ns), org=self.org
        )
        points = []
        for table in tables:
            tag_names = [
                c.label
                for c in table.columns
                if c.group and not c.label.startswith("_") and c.label not in ("result", "table")
            ]
            for record in table.records:
                values = record.values
                tags = {
                    name: str(values[name]) for name in tag_names if values.get(name) is not None
                }
                fields = {
                    k: v
                    for k, v in values.items()
                    if v is not None
                    and not k.startswith("_")
                    and k not in ("result", "table")
                    and k not in tag_names
                }
                points.append(Point(measurement, tags, fields, int(values["_time_ns"])))
        points.sort(key=lambda p: (p.time_ns, sorted(p.tags.items())))
        return points

    def time_span(
        self, machine: str | None = None, start_ns: int | None = None, stop_ns: int | None = None
    ) -> tuple[int, int] | None:
        """The first and last time of the points (of ``machine``) in the window, or None:
        each series' first and last point (Flux ``first``/``last``), the extremes of those."""
        times = []
        for selector in ("first", "last"):
            flux = self._range_flux(machine, start_ns, stop_ns) + (
                f"\n  |> {selector}()\n  |> map(fn: (r) => ({{_time_ns: int(v: r._time)}}))"
            )
            for table in self._query_api.query(flux, org=self.org):
                times += [int(record.values["_time_ns"]) for record in table.records]
        return (min(times), max(times)) if times else None

    def _range_flux(self, machine: str | None, start_ns: int | None, stop_ns: int | None) -> str:
        start = 0 if start_ns is None else int(start_ns)
        stop = MAX_TIME_NS if stop_ns is None else int(stop_ns)
        machine_filter = (
            ""
            if machine is None
            else f"\n  |> filter(fn: (r) => r.machine == {_flux_string(machine)})"
        )
        return (
            f"from(bucket: {_flux_string(self.bucket)})\n"
            f"  |> range(start: time(v: {start}), stop: time(v: {stop}))"
            f"{machine_filter}"
        )

    def close(self) -> None:
        self._client.close()


def _flux_string(text: str) -> str:
    escaped = text.replace("\\", "\\\\").replace('"', '\\"').replace("${", "\\${")
    return f'"{escaped}"'


class PointWriter(Protocol):
    async def write(self, points: Sequence[Point]) -> None: ...


class Forwarder:
    """Moves points from a :class:`PointBuffer` to a writer, in order, until stopped.

    Args:
        buffer: the store-and-forward buffer.
        writer: anything with ``async write(points)`` that raises on failure
            (:class:`InfluxWriter`); :class:`WriteRejectedError` drops the batch.
        batch: the most points per write (halved on HTTP 413, see ``batch_limit``).
        retry_s: the first wait after a failure; doubled per failure up to
            ``max_retry_s`` (each shortened by up to 20 % jitter); back to
            ``retry_s`` after a success. The cap is also the longest the
            forwarder can take to notice that InfluxDB is back.
        idle_s: how often an empty buffer is looked at (or call :meth:`wake`).
    """

    def __init__(
        self,
        buffer: PointBuffer,
        writer: PointWriter,
        batch: int = 5000,
        retry_s: float = 1.0,
        max_retry_s: float = 10.0,
        idle_s: float = 1.0,
    ) -> None:
        if batch < 1:
            raise ValueError(f"batch must be at least 1, got {batch}")
        self.buffer = buffer
        self.writer = writer
        self.batch = batch
        self.retry_s = retry_s
        self.max_retry_s = max_retry_s
        self.backoff = Backoff(initial_s=retry_s, max_s=max_retry_s)
        self.idle_s = idle_s
        self.batch_limit = batch  # halved on HTTP 413 (and kept): the most points per write
        self.sent = 0
        self.rejected = 0  # points InfluxDB refused and that were dropped (invalid or too large)
        self.too_large = 0  # of those, single points refused as too large (HTTP 413)
        self.failures = 0
        self.last_retry_delay_s: float | None = None
        self._causes: set[str] = set()  # the causes of this outage already logged
        # HTTP 413: batch_limit becomes "stable" after two acknowledged writes in a row at
        # that limit; a lone oversized point's binary search ends back at the stable one.
        self._stable_limit = batch
        self._last_ok_limit: int | None = None  # limit of the last write, if acknowledged
        self._told_too_large = False  # the first 413 is logged at WARNING, the rest at DEBUG
        self.oversized = OversizedPoints()  # lone points refused as too large, by size
        self.last_error: str | None = None
        self.last_error_time: float | None = None
        self.last_success_time: float | None = None
        self._wake = asyncio.Event()
        self._task: asyncio.Task[None] | None = None
        self._down = False
        self.supervisor = Supervised(
            "InfluxDB forwarder", lambda _stop: self.run(), progress=lambda: self.sent
        )

    # --- lifecycle ----------------------------------------------------------------------
    def start(self) -> asyncio.Task[None]:
        if self._task is None or self._task.done():
            self._task = asyncio.create_task(
                self.supervisor.supervise(asyncio.Event()), name="influx-forwarder"
            )
        return self._task

    async def stop(self) -> None:
        """Cancel the task; an unacknowledged batch stays in the buffer for the next start."""
        task, self._task = self._task, None
        if task is not None:
            task.cancel()
            with contextlib.suppress(asyncio.CancelledError):
                await task

    def wake(self) -> None:
        """Look at the buffer now (e.g. after an append) instead of after ``idle_s``."""
        self._wake.set()

    async def flush(self, timeout: float) -> bool:
        """Wait until the buffer is empty; False after ``timeout`` seconds (nothing lost)."""
        deadline = time.monotonic() + timeout
        while len(self.buffer):
            if self._task is None or self._task.done():
                raise RuntimeError("the forwarder is not running")
            if time.monotonic() >= deadline:
                return False
            self.wake()
            await asyncio.sleep(min(0.05, max(0.0, deadline - time.monotonic())))
        return True

    def health(self) -> dict:
        return {
            "running": self._task is not None and not self._task.done(),
            "connected": not self._down,
            "buffered": len(self.buffer),
            "dropped": self.buffer.dropped,
            "rejected": self.rejected,
            "too_large": self.too_large,
            "batch_limit": self.batch_limit,
            "sent": self.sent,
            "failures": self.failures,
            "last_error": self.last_error,
            "last_error_time": self.last_error_time,
            "last_success_time": self.last_success_time,
            "restarts": self.supervisor.restarts,
        }

    # --- the task -----------------------------------------------------------------------
    async def run(self) -> None:
        """Forward until cancelled (``start`` runs this under a supervisor)."""
        while True:
            batch = self.buffer.peek(self.batch_limit)
            if not batch:
                await self._idle(self.idle_s)
                continue
            send, oversized = self.oversized.split(batch)
            try:
                if send:
                    await self.writer.write([point for _, point in send])
            except WriteRejectedError as exc:
                self._refused(batch, oversized, exc)
            except WriteTooLargeError as exc:
                self._too_large(send, exc)
            except Exception as exc:
                await self._failed(exc)
            else:
                self._acknowledged(batch, len(send), oversized)

    def _remove(self, batch: list[Row], oversized: list[Row]) -> None:
        """Remove a batch that is done with; count and log its points known to be too large."""
        self.buffer.remove_through(batch[-1][0])
        self.too_large += len(oversized)
        self.rejected += len(oversized)
        self.oversized.dropped(oversized)

    def _acknowledged(self, batch: list[Row], sent: int, oversized: list[Row]) -> None:
        self._remove(batch, oversized)
        self.sent += sent
        self.oversized.write_acknowledged()
        self.last_success_time = time.time()
        self.backoff.reset()
        if sent:
            self._settle(self.batch_limit)
        if self._down:
            log.info("InfluxDB writes succeed again; %d point(s) buffered", len(self.buffer))
            self._down = False
            self._causes.clear()

    def _settle(self, limit: int) -> None:
        """Two acknowledged writes in a row at ``limit``: the server takes that size."""
        if self._last_ok_limit == limit and self._stable_limit != limit:
            log.info("InfluxDB takes batches of %d point(s); keeping that size", limit)
            self._stable_limit = limit
        self._last_ok_limit = limit

    def _refused(self, batch: list[Row], oversized: list[Row], exc: WriteRejectedError) -> None:
        """Invalid points (HTTP 400/422): drop the batch, it would fail for ever."""
        sent = len(batch) - len(oversized)
        self.rejected += sent if exc.dropped is None else exc.dropped
        self._record_error(exc)
        log.error("dropping %d point(s) InfluxDB refused: %s", sent, exc)
        self._remove(batch, oversized)

    def _too_large(self, send: list[Row], exc: WriteTooLargeError) -> None:
        """HTTP 413: halve the batch at once; a single point still too large is remembered
        by its size, and dropped with the others that large by the next :meth:`run` pass."""
        self._record_error(exc)
        self._last_ok_limit = None
        if len(send) > 1:
            log.log(
                logging.DEBUG if self._told_too_large else logging.WARNING,
                "InfluxDB refused a batch of %d point(s) as too large (%s); halving it",
                len(send),
                exc,
            )
            self._told_too_large = True
            self.batch_limit = max(1, len(send) // 2)
            return
        self.oversized.refused_alone(send[0][1], str(exc))
        self.batch_limit = self._stable_limit  # the points behind it fit as before

    async def _failed(self, exc: Exception) -> None:
        """Keep the batch; wait the back-off, or the server's Retry-After when longer."""
        self.failures += 1
        self._record_error(exc)
        cause = exc.cause if isinstance(exc, WriteError) else type(exc).__name__
        if cause not in self._causes:  # each distinct cause of an outage, once
            self._causes.add(cause)
            log.warning(
                "InfluxDB write failed (%s), keeping %d point(s) buffered, retrying: %s",
                cause,
                len(self.buffer),
                exc,
            )
        self._down = True
        delay_s = self.backoff.failed(time.monotonic())
        asked_s = exc.retry_after_s if isinstance(exc, WriteError) else None
        if asked_s is not None and asked_s > delay_s:
            delay_s = asked_s
        self.last_retry_delay_s = delay_s
        await asyncio.sleep(delay_s)  # not cut short by wake(): the back-off holds

    def _record_error(self, exc: BaseException) -> None:
        self.last_error = str(exc)
        self.last_error_time = time.time()

    async def _idle(self, seconds: float) -> None:
        self._wake.clear()
        with contextlib.suppress(TimeoutError):
            await asyncio.wait_for(self._wake.wait(), timeout=seconds)
