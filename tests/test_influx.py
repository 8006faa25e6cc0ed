"""Store and forward to a real InfluxDB 2.7.12 (influxd on 127.0.0.1, no mocks).

The version deploy/docker-compose.yml ships: token, organisation and bucket, the v2
write API and Flux (tests/influx_server.py).

The server runs once for the module; every test has its own database. Machine time
runs fast: cycles 0.2 s of machine time apart are produced every ~20 ms of real
time, so a real outage of ~4 s is 40 s of machine time.
"""

from __future__ import annotations

import asyncio
import dataclasses
import itertools
from collections.abc import Iterator, Sequence
from pathlib import Path

import numpy as np
import pytest

from gateway.live.record import CycleRecord
from gateway.offline.export import export_runs
from gateway.outputs.disk_buffer import PointBuffer
from gateway.outputs.influx import Forwarder, InfluxReader, InfluxWriter
from gateway.outputs.local_store import LocalStore
from gateway.outputs.points import (
    CYCLE_MEASUREMENT,
    PROBE_MEASUREMENT,
    TEMPERATURE_MEASUREMENT,
    Point,
    points_from_record,
    probe_point,
)
from models.data.dataset import load_runs
from tests.influx_server import InfluxServer
from tests.test_timeseries import EPOCH_S, make_records, true_error_um

MEASUREMENTS = (CYCLE_MEASUREMENT, TEMPERATURE_MEASUREMENT, PROBE_MEASUREMENT)
_databases = itertools.count()


@pytest.fixture(scope="module")
def server(tmp_path_factory: pytest.TempPathFactory) -> Iterator[InfluxServer]:
    with InfluxServer(tmp_path_factory.mktemp("influxdb")) as influx:
        yield influx


@pytest.fixture
def bucket(server: InfluxServer) -> str:
    if not server.running:  # a failed outage test must not take the others down
        server.start()
    return server.create_database(f"gateway{next(_databases)}")


class RecordingWriter(InfluxWriter):
    """The real writer, remembering every batch InfluxDB acknowledged, in order."""

    def __init__(self, *args: object, **kwargs: object) -> None:
        super().__init__(*args, **kwargs)
        self.acknowledged: list[list[Point]] = []

    def write_sync(self, points: Sequence[Point]) -> None:
        super().write_sync(points)
        self.acknowledged.append(list(points))

    def sent(self) -> list[Point]:
        return [p for batch in self.acknowledged for p in batch]


def writer_for(server: InfluxServer, bucket: str) -> RecordingWriter:
    return RecordingWriter(server.url, server.token, server.org, bucket, timeout_s=2.0)


def forwarder_for(buffer: PointBuffer, writer: InfluxWriter, batch: int = 500) -> Forwarder:
    return Forwarder(buffer, writer, batch=batch, retry_s=0.1, max_retry_s=0.5, idle_s=0.05)


def read_all(server: InfluxServer, bucket: str) -> list[Point]:
    reader = InfluxReader(server.url, server.token, server.org, bucket)
    try:
        return [p for m in MEASUREMENTS for p in reader.query(m)]
    finally:
        reader.close()


def canonical(points: Sequence[Point]) -> list[tuple]:
    return sorted(
        (p.measurement, p.time_ns, sorted(p.tags.items()), sorted(p.fields.items())) for p in points
    )


def assert_stored_exactly(server: InfluxServer, bucket: str, expected: Sequence[Point]) -> None:
    stored = read_all(server, bucket)
    assert len(stored) == len(expected)
    assert canonical(stored) == canonical(expected)
    for measurement in MEASUREMENTS:  # read back in time order
        times = [p.time_ns for p in stored if p.measurement == measurement]
        assert times == sorted(times)


async def produce(
    buffer: PointBuffer, forwarder: Forwarder | None, records: Sequence[CycleRecord]
) -> list[Point]:
    """Append the points of ``records`` as a running gateway would, ~20 ms apart."""
    produced = []
    for record in records:
        points = points_from_record(record, EPOCH_S)
        buffer.append(points)
        produced += points
        if forwarder is not None:
            forwarder.wake()
        await asyncio.sleep(0.02)
    return produced


# --- a normal run ------------------------------------------------------------------------
def test_simulated_run_arrives_with_tags_fields_and_times(
    server: InfluxServer, bucket: str, tmp_path: Path
) -> None:
    records = make_records("vmc-1", 600) + make_records("vmc-2", 600, sensors=("T1", "T2", "T3"))
    points = [p for r in records for p in points_from_record(r, EPOCH_S)]
    points += [probe_point(r.machine, r.time_s, true_error_um(r), EPOCH_S) for r in records[::60]]

    async def scenario() -> dict:
        buffer = PointBuffer(tmp_path / "buffer.sqlite", max_points=100_000)
        writer = writer_for(server, bucket)
        forwarder = Forwarder(buffer, writer, batch=5000, retry_s=0.1)
        forwarder.start()
        buffer.append(points)
        assert await forwarder.flush(timeout=30)
        health = forwarder.health()
        await forwarder.stop()
        assert writer.sent() == points  # in buffer order, each once
        assert [len(b) for b in writer.acknowledged] == [5000, len(points) - 5000]
        writer.close()
        buffer.close()
        return health

    health = asyncio.run(scenario())
    assert health["buffered"] == 0 and health["sent"] == len(points)
    assert health["dropped"] == 0 and health["last_error"] is None

    assert_stored_exactly(server, bucket, points)
    reader = InfluxReader(server.url, server.token, server.org, bucket)
    cycles = reader.query(CYCLE_MEASUREMENT, machine="vmc-2")
    assert len(cycles) == 600
    assert cycles[0].tags == {"machine": "vmc-2"}  # before a model: no regime/model tags
    assert cycles[20].tags == {
        "machine": "vmc-2",
        "regime": "variable",
        "model_id": "mlr-error_um-all",
    }
    assert cycles[20].time_ns == 1_767_225_620_000_000_000
    assert cycles[20].fields["write_status"] == "ok: slew"
    assert isinstance(cycles[20].fields["link_errors"], int)
    assert isinstance(cycles[20].fields["speed_rpm"], float)
    window = reader.query(
        TEMPERATURE_MEASUREMENT,
        machine="vmc-1",
        start_ns=1_767_225_649_000_000_000,
        stop_ns=1_767_225_650_000_000_001,
    )
    assert {(p.tags["sensor"], p.time_ns) for p in window} == {
        *((s, 1_767_225_649_000_000_000) for s in ("T1", "T2", "T3", "ambient")),
        *((s, 1_767_225_650_000_000_000) for s in ("T1", "T2", "T3", "ambient")),
    }
    # T3 was silent in cycle 49: flagged bad, its point holds the reason and no value
    silent = {(p.tags["sensor"], p.time_ns): p for p in window}[("T3", 1_767_225_649 * 10**9)]
    assert silent.tags["quality"] == "bad" and silent.fields == {"reason": "no value"}
    reader.close()


# --- an outage of the server ---------------------------------------------------------------
def test_outage_loses_nothing_and_duplicates_nothing(
    server: InfluxServer, bucket: str, tmp_path: Path
) -> None:
    records = make_records("vmc-1", 400, cycle_s=0.2)

    async def scenario() -> list[Point]:
        buffer = PointBuffer(tmp_path / "buffer.sqlite", max_points=100_000)
        writer = writer_for(server, bucket)
        forwarder = forwarder_for(buffer, writer)
        forwarder.start()
        produced = await produce(buffer, forwarder, records[:100])
        assert await forwarder.flush(timeout=10)

        await asyncio.to_thread(server.stop)
        down = await produce(buffer, forwarder, records[100:300])  # 40 s of machine time
        produced += down
        health = forwarder.health()
        assert health["buffered"] == len(down)  # everything since the outage waits on disk
        assert not health["connected"] and "unreachable" in health["last_error"]
        assert health["failures"] >= 3

        await asyncio.to_thread(server.start)
        produced += await produce(buffer, forwarder, records[300:])
        assert await forwarder.flush(timeout=30)
        health = forwarder.health()
        assert health["connected"] and health["buffered"] == 0 and health["dropped"] == 0
        await forwarder.stop()
        assert writer.sent() == produced  # acknowledged in order, each point once
        writer.close()
        buffer.close()
        return produced

    produced = asyncio.run(scenario())
    assert_stored_exactly(server, bucket, produced)


def test_gateway_restart_during_outage_loses_nothing(
    server: InfluxServer, bucket: str, tmp_path: Path
) -> None:
    path = tmp_path / "buffer.sqlite"
    records = make_records("vmc-1", 300, cycle_s=0.2)

    async def before_restart() -> tuple[list[Point], list[Point]]:
        buffer = PointBuffer(path, max_points=100_000)
        writer = writer_for(server, bucket)
        forwarder = forwarder_for(buffer, writer)
        forwarder.start()
        produced = await produce(buffer, forwarder, records[:100])
        assert await forwarder.flush(timeout=10)
        await asyncio.to_thread(server.stop)
        produced += await produce(buffer, forwarder, records[100:200])
        await forwarder.stop()  # the gateway goes down in the middle of the outage
        writer.close()
        buffer.close()
        return produced, writer.sent()

    async def after_restart() -> tuple[list[Point], list[Point]]:
        buffer = PointBuffer(path, max_points=100_000)
        assert [p for _, p in buffer.peek(100_000)] == waiting  # reopened: all still there
        writer = writer_for(server, bucket)
        forwarder = forwarder_for(buffer, writer)
        forwarder.start()
        produced = await produce(buffer, forwarder, records[200:250])  # server still down
        await asyncio.to_thread(server.start)
        produced += await produce(buffer, forwarder, records[250:])
        assert await forwarder.flush(timeout=30)
        await forwarder.stop()
        writer.close()
        assert len(buffer) == 0
        buffer.close()
        return produced, writer.sent()

    produced_1, sent_1 = asyncio.run(before_restart())
    waiting = produced_1[len(sent_1) :]
    assert sent_1 == produced_1[: len(sent_1)] and len(waiting) > 0
    produced_2, sent_2 = asyncio.run(after_restart())
    assert sent_1 + sent_2 == produced_1 + produced_2
    assert_stored_exactly(server, bucket, produced_1 + produced_2)


def test_resent_batch_after_ack_is_stored_once(
    server: InfluxServer, bucket: str, tmp_path: Path
) -> None:
    """The process dies after InfluxDB acknowledged a batch but before removing it."""
    path = tmp_path / "buffer.sqlite"
    points = [p for r in make_records("vmc-1", 50) for p in points_from_record(r, EPOCH_S)]
    buffer = PointBuffer(path)
    buffer.append(points)
    writer = writer_for(server, bucket)
    writer.write_sync([p for _, p in buffer.peek(120)])  # acknowledged …
    buffer.close()  # … and the process ends before remove_through

    async def resend() -> None:
        again = PointBuffer(path)
        forwarder = forwarder_for(again, writer)
        forwarder.start()
        assert await forwarder.flush(timeout=10)
        await forwarder.stop()
        again.close()

    asyncio.run(resend())
    assert len(writer.sent()) == len(points) + 120  # sent twice …
    assert_stored_exactly(server, bucket, points)  # … stored once
    writer.close()


def test_refused_batch_is_dropped_counted_and_does_not_block(
    server: InfluxServer, bucket: str, tmp_path: Path
) -> None:
    good = [p for r in make_records("vmc-1", 10) for p in points_from_record(r, EPOCH_S)]
    # speed_rpm is a float field: a string in the same shard is a type conflict (HTTP 422)
    conflicting = Point(
        CYCLE_MEASUREMENT, {"machine": "vmc-1"}, {"speed_rpm": "fast"}, good[0].time_ns + 1
    )

    async def scenario() -> dict:
        buffer = PointBuffer(tmp_path / "buffer.sqlite")
        writer = writer_for(server, bucket)
        forwarder = forwarder_for(buffer, writer, batch=len(good))
        buffer.append(good)
        buffer.append([conflicting, *good[:3]])  # one batch: a partial write
        buffer.append(good[3:6])
        forwarder.start()
        assert await forwarder.flush(timeout=10)
        await forwarder.stop()
        writer.close()
        buffer.close()
        return forwarder.health()

    health = asyncio.run(scenario())
    # InfluxDB 2 answers a partial write with 422 (1.8 answered 400), naming the count
    assert health["rejected"] == 1 and "HTTP 422" in health["last_error"]
    assert "field type conflict" in health["last_error"]
    assert health["sent"] == len(good) and health["buffered"] == 0
    assert_stored_exactly(server, bucket, good)


# --- export from InfluxDB ----------------------------------------------------------------
def test_export_from_influxdb_matches_the_local_store(
    server: InfluxServer, bucket: str, tmp_path: Path
) -> None:
    records = make_records("vmc-1", 200) + make_records("vmc-1", 100, start_s=3000.0)
    points = [p for r in records for p in points_from_record(r, EPOCH_S)]
    points += [
        probe_point(r.machine, r.time_s + 0.3, true_error_um(r), EPOCH_S) for r in records[::2]
    ]
    writer = writer_for(server, bucket)
    writer.write_sync(points)
    writer.close()
    with LocalStore(tmp_path / "series.sqlite") as store:
        store.write(points)
        local = export_runs(store, "vmc-1", 50.0, None, tmp_path / "local.csv", epoch_s=EPOCH_S)
    reader = InfluxReader(server.url, server.token, server.org, bucket)
    remote = export_runs(reader, "vmc-1", 50.0, None, tmp_path / "influx.csv", epoch_s=EPOCH_S)
    reader.close()

    assert remote == dataclasses.replace(local, path=remote.path)
    text = (tmp_path / "influx.csv").read_text(encoding="utf-8")
    assert text == (tmp_path / "local.csv").read_text(encoding="utf-8")
    runs = load_runs(tmp_path / "influx.csv")
    assert len(runs.run_ids) == 2 and runs.time_s[0] == 50.0


def test_export_from_influxdb_in_slices_is_the_same_file(
    server: InfluxServer, bucket: str, tmp_path: Path
) -> None:
    """40 minutes of cycles and a pause, read with Flux in slices of about 2000 points
    (a few minutes each, slice boundaries inside the runs): the file of one local read."""
    records = make_records("vmc-2", 1500) + make_records("vmc-2", 900, start_s=2400.0)
    points = [p for r in records for p in points_from_record(r, EPOCH_S)]
    points += [probe_point(r.machine, r.time_s + 0.3, true_error_um(r), EPOCH_S) for r in records]
    writer = writer_for(server, bucket)
    writer.write_sync(points)
    writer.close()
    with LocalStore(tmp_path / "series.sqlite") as store:
        store.write(points)
        local = export_runs(store, "vmc-2", None, None, tmp_path / "local.csv", EPOCH_S,
                            slice_points=10**9)  # fmt: skip
    reader = InfluxReader(server.url, server.token, server.org, bucket)
    sliced = export_runs(reader, "vmc-2", None, None, tmp_path / "sliced.csv", EPOCH_S,
                         slice_points=2000)  # fmt: skip
    reader.close()
    assert sliced == dataclasses.replace(local, path=sliced.path) and len(sliced.runs) == 2
    assert (tmp_path / "sliced.csv").read_bytes() == (tmp_path / "local.csv").read_bytes()


KILLED_WRITER = """
import sys
sys.path.insert(0, {root!r})
from gateway.outputs.disk_buffer import PointBuffer
from gateway.outputs.points import points_from_record
from tests.test_timeseries import EPOCH_S, make_records

buffer = PointBuffer({path!r}, max_points=1_000_000)
for i, record in enumerate(make_records("vmc-1", 5000, cycle_s=0.2)):
    buffer.append(points_from_record(record, EPOCH_S))
    print(i, flush=True)  # this cycle's points are in the buffer file
"""


def test_gateway_killed_during_outage_loses_nothing(
    server: InfluxServer, bucket: str, tmp_path: Path
) -> None:
    """SIGKILL the process that buffers points (no clean shutdown), then replay."""
    import os
    import signal
    import subprocess
    import sys

    path = tmp_path / "buffer.sqlite"
    root = str(Path(__file__).resolve().parent.parent)
    child = subprocess.Popen(
        [sys.executable, "-c", KILLED_WRITER.format(root=root, path=str(path))],
        stdout=subprocess.PIPE,
        text=True,
    )
    acknowledged = -1
    assert child.stdout is not None
    for line in child.stdout:
        acknowledged = int(line)
        if acknowledged >= 400:
            os.kill(child.pid, signal.SIGKILL)  # mid-stream: no close, no flush
            break
    child.wait(timeout=10)
    assert child.returncode == -signal.SIGKILL

    records = make_records("vmc-1", 5000, cycle_s=0.2)
    buffer = PointBuffer(path, max_points=1_000_000)
    kept = [p for _, p in buffer.peek(1_000_000)]
    # Every acknowledged cycle survived the kill, and the file holds whole cycles only:
    # the child runs on after its last acknowledgement until the signal lands, so
    # more cycles than acknowledged may be kept, never part of one.
    whole_cycles = np.cumsum([0] + [len(points_from_record(r, EPOCH_S)) for r in records])
    acknowledged_points = int(whole_cycles[acknowledged + 1])
    assert len(kept) >= acknowledged_points
    assert len(kept) in set(whole_cycles.tolist())
    expected = [p for r in records for p in points_from_record(r, EPOCH_S)][: len(kept)]
    assert kept == expected

    async def replay() -> None:
        writer = writer_for(server, bucket)
        forwarder = forwarder_for(buffer, writer)
        forwarder.start()
        assert await forwarder.flush(timeout=30)
        await forwarder.stop()
        writer.close()

    asyncio.run(replay())
    assert len(buffer) == 0
    buffer.close()
    assert_stored_exactly(server, bucket, kept)
