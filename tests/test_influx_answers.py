"""The forwarder reads InfluxDB's answers: 429/503 Retry-After, 413 too large, 500.

A reverse proxy (tests/influx_proxy.py) stands in front of the real InfluxDB and
answers some writes itself; the rest reach the server, and what the test reads
back is what the server stored.
"""

from __future__ import annotations

import asyncio
import dataclasses
import email.utils
import logging
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest

from gateway.outputs.disk_buffer import PointBuffer
from gateway.outputs.influx import Forwarder, retry_after_s
from gateway.outputs.oversized import OversizedPoints, line_bytes
from gateway.outputs.points import CYCLE_MEASUREMENT, Point, points_from_record
from tests.influx_proxy import AnsweringProxy
from tests.influx_server import InfluxServer
from tests.test_influx import RecordingWriter, assert_stored_exactly
from tests.test_timeseries import EPOCH_S, make_records

WRITER_LOG = "gateway.outputs.influx"


@pytest.fixture(scope="module")
def server(tmp_path_factory: pytest.TempPathFactory) -> Iterator[InfluxServer]:
    with InfluxServer(tmp_path_factory.mktemp("influxdb")) as influx:
        yield influx


def cycle_points(count: int) -> list[Point]:
    return [p for r in make_records("vmc-1", count) for p in points_from_record(r, EPOCH_S)]


async def forward_through(
    proxy: AnsweringProxy,
    server: InfluxServer,
    bucket: str,
    buffer_path: Path,
    batches: list[list[Point]],
    flush_timeout_s: float,
    **settings: Any,
) -> tuple[dict, RecordingWriter]:
    """Buffer ``batches`` and let a forwarder (``settings``) send them through ``proxy``
    until the buffer is empty: (its health after the flush, the writer it used)."""
    buffer = PointBuffer(buffer_path)
    writer = RecordingWriter(proxy.url, server.token, server.org, bucket, timeout_s=5.0)
    forwarder = Forwarder(buffer, writer, **settings)
    for batch in batches:
        buffer.append(batch)
    forwarder.start()
    assert await forwarder.flush(timeout=flush_timeout_s)
    health = forwarder.health()
    await forwarder.stop()
    writer.close()
    buffer.close()
    return health, writer


def warnings_naming(caplog: pytest.LogCaptureFixture, text: str) -> list[str]:
    return [
        r.getMessage()
        for r in caplog.records
        if r.name == WRITER_LOG and r.levelno == logging.WARNING and text in r.getMessage()
    ]


def test_retry_after_is_honoured_and_each_cause_is_logged_once(
    server: InfluxServer, tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    bucket = server.create_database("answers_retry")
    points = cycle_points(100)

    async def scenario() -> tuple[AnsweringProxy, dict, RecordingWriter]:
        async with AnsweringProxy(server.url) as proxy:
            proxy.script = [(500, {}), (500, {}), (429, {"Retry-After": "2"}), (503, {})]
            proxy.script += [(500, {})]
            health, writer = await forward_through(
                proxy, server, bucket, tmp_path / "buffer.sqlite", [points], 20,
                retry_s=0.1, max_retry_s=0.5, idle_s=0.05,
            )  # fmt: skip
            return proxy, health, writer

    with caplog.at_level(logging.INFO, logger=WRITER_LOG):
        proxy, health, writer = asyncio.run(scenario())

    assert proxy.statuses() == [500, 500, 429, 503, 500, 204]
    gaps_s = [b.time_s - a.time_s for a, b in zip(proxy.writes, proxy.writes[1:], strict=False)]
    print(f"gaps between attempts: {[round(g, 2) for g in gaps_s]} s")
    assert gaps_s[2] >= 2.0, "Retry-After: 2 waited for"  # the back-off alone: ≤ 0.4 s
    assert gaps_s[2] < 3.5
    # no Retry-After: the back-off (≤ 0.4 s); a Retry-After of 2 s wrongly applied is ≥ 2 s
    assert all(g < 2.0 for i, g in enumerate(gaps_s) if i != 2), gaps_s
    assert health["failures"] == 5 and health["sent"] == len(points)
    assert health["connected"] and "HTTP 500" in health["last_error"]
    # each distinct cause once, with its status code; the second 500 is not logged again
    assert len(warnings_naming(caplog, "HTTP 500")) == 1
    assert len(warnings_naming(caplog, "HTTP 429")) == 1
    assert len(warnings_naming(caplog, "HTTP 503")) == 1
    assert writer.sent() == points
    assert_stored_exactly(server, bucket, points)


def test_too_large_halves_the_batch_drops_a_lone_oversized_point_and_loses_nothing(
    server: InfluxServer, tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    bucket = server.create_database("answers_413")
    points = cycle_points(600)  # ~3000 points, ~320 kB of line protocol
    cycle = next(p for p in points[1000:] if p.measurement == CYCLE_MEASUREMENT)
    huge = dataclasses.replace(
        cycle, fields={"write_status": "x" * 30_000}, time_ns=cycle.time_ns + 1
    )
    limit_bytes = 20_000

    async def scenario() -> tuple[AnsweringProxy, dict, RecordingWriter]:
        async with AnsweringProxy(server.url, max_body_bytes=limit_bytes) as proxy:
            # A forwarder that resent the refused batch for ever would never flush.
            health, writer = await forward_through(
                proxy, server, bucket, tmp_path / "buffer.sqlite",
                [points[:1000], [huge], points[1000:]], 30,
                batch=5000, retry_s=0.1, max_retry_s=0.5,
            )  # fmt: skip
            return proxy, health, writer

    with caplog.at_level(logging.INFO, logger=WRITER_LOG):
        proxy, health, writer = asyncio.run(scenario())

    refused = [w for w in proxy.writes if w.status == 413]
    taken = [w for w in proxy.writes if w.status == 204]
    print(
        f"413: {len(refused)} answers; {len(taken)} writes of ≤ {max(w.lines for w in taken)} "
        f"points; batch_limit {health['batch_limit']}; {len(proxy.writes)} requests in all"
    )
    assert all(w.body_bytes <= limit_bytes for w in taken)
    assert health["too_large"] == 1 and health["rejected"] == 1
    assert health["buffered"] == 0 and health["sent"] == len(points)
    # halved until ~20 kB fit, and back to that size after the lone point was dropped
    assert 1 < health["batch_limit"] <= 5000 // 2**5
    assert max(w.lines for w in taken) == health["batch_limit"]
    # 5000 → ~150 takes 5 halvings; the lone point's search from there 8 more (and a
    # few where the halved batch still held it)
    assert len(refused) <= 2 * 13
    assert len(warnings_naming(caplog, "HTTP 413")) == 1
    dropped = [r for r in caplog.records if r.levelno == logging.ERROR and "too large" in r.msg]
    assert len(dropped) == 1 and "HTTP 413" in dropped[0].getMessage()
    assert writer.sent() == points  # in order, each once, without the oversized point
    assert_stored_exactly(server, bucket, points)


def test_oversized_point_every_few_cycles_is_one_error_episode_without_a_request_storm(
    server: InfluxServer, tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    """87 cycles each carry one point over the server's limit: the first is found by
    halving, the others are known by their size and dropped without a request, and
    the episode is one ERROR line (each point used to cost ~10 refused requests and
    one ERROR line)."""
    bucket = server.create_database("answers_413_many")
    points = cycle_points(600)
    huge_cycles = {100 + 5 * k for k in range(87)}  # up to cycle 530 of 600
    cycles = 0
    sent_points: list[Point] = []
    buffered: list[Point] = []
    for point in points:
        if point.measurement == CYCLE_MEASUREMENT:
            cycles += 1
            if cycles in huge_cycles:
                big = {**point.fields, "write_status": "x" * 30_000}
                buffered.append(dataclasses.replace(point, fields=big))
                continue
        buffered.append(point)
        sent_points.append(point)
    limit_bytes = 20_000

    async def scenario() -> tuple[AnsweringProxy, dict, RecordingWriter]:
        async with AnsweringProxy(server.url, max_body_bytes=limit_bytes) as proxy:
            health, writer = await forward_through(
                proxy, server, bucket, tmp_path / "buffer.sqlite", [buffered], 60,
                batch=5000, retry_s=0.1, max_retry_s=0.5,
            )  # fmt: skip
            return proxy, health, writer

    with caplog.at_level(logging.DEBUG, logger=WRITER_LOG):
        proxy, health, writer = asyncio.run(scenario())

    refused = [w for w in proxy.writes if w.status == 413]
    print(
        f"{len(huge_cycles)} oversized points: {len(refused)} answers 413, "
        f"{len(proxy.writes)} requests in all, batch_limit {health['batch_limit']}"
    )
    assert health["too_large"] == len(huge_cycles) == len(buffered) - len(sent_points)
    assert health["rejected"] == len(huge_cycles)
    assert health["buffered"] == 0 and health["sent"] == len(sent_points)
    # the first oversized point: 5 halvings and a search of ~8; none for the other 86
    assert len(refused) <= 2 * 13
    # every write the server took carried ~batch_limit points, none wasted on a lone point
    assert len(proxy.writes) - len(refused) <= 2 * len(sent_points) / health["batch_limit"] + 2
    errors = [r for r in caplog.records if r.name == WRITER_LOG and r.levelno >= logging.ERROR]
    assert len(errors) == 1, [r.getMessage()[:120] for r in errors]
    assert "too large" in errors[0].getMessage() and "HTTP 413" in errors[0].getMessage()
    assert writer.sent() == sent_points  # in order, each once, without the oversized points
    assert_stored_exactly(server, bucket, sent_points)


def test_retry_after_header_forms() -> None:
    now_s = 1_767_225_600.0
    assert retry_after_s("10") == 10.0
    assert retry_after_s(" 2.5 ") == 2.5
    assert retry_after_s(email.utils.formatdate(now_s + 30, usegmt=True), now_s) == 30.0
    assert retry_after_s(email.utils.formatdate(now_s - 30, usegmt=True), now_s) == 0.0
    assert retry_after_s("-5") == 0.0
    assert retry_after_s("999999") == 3600.0
    assert retry_after_s(None) is None
    assert retry_after_s("soon") is None
    assert retry_after_s("nan") is None


def test_oversized_episode_ends_after_a_quiet_minute_and_the_size_is_rechecked(
    caplog: pytest.LogCaptureFixture,
) -> None:
    """The episode's bookkeeping on a hand-moved clock: one ERROR per episode, INFO at its
    end, and the learned size forgotten after ``recheck_s`` (so a raised limit is seen)."""
    now = [0.0]
    tracker = OversizedPoints(quiet_s=60.0, recheck_s=600.0, clock=lambda: now[0])
    small, *_ = cycle_points(1)
    big = dataclasses.replace(small, fields={"write_status": "x" * 5000})
    rows = [(1, small), (2, big), (3, small)]
    assert tracker.split(rows) == (rows, [])  # nothing known yet: everything is sent
    tracker.refused_alone(big, "HTTP 413: too large")
    assert tracker.limit_bytes == line_bytes(big) > line_bytes(small)
    with caplog.at_level(logging.DEBUG, logger=WRITER_LOG):
        for _ in range(3):  # three drops 10 s apart: one episode
            send, drop = tracker.split(rows)
            assert send == [rows[0], rows[2]] and drop == [rows[1]]
            tracker.dropped(drop)
            now[0] += 10.0
        tracker.write_acknowledged()  # 10 s after the last drop: still the episode
        now[0] += 60.0
        tracker.write_acknowledged()  # a quiet minute: the episode ends
        tracker.dropped(tracker.split(rows)[1])  # a new episode, logged again
    levels = [(r.levelno, r.getMessage()) for r in caplog.records if r.name == WRITER_LOG]
    assert [level for level, _ in levels] == [
        logging.ERROR,
        logging.DEBUG,
        logging.DEBUG,
        logging.INFO,
        logging.ERROR,
    ]
    assert "HTTP 413" in levels[0][1] and "refused 3 point(s)" in levels[3][1]
    now[0] += 601.0
    assert tracker.split(rows) == (rows, [])  # rechecked: the big point is sent again
    assert tracker.limit_bytes is None
