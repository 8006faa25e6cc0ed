"""A multi-axis machine's cycles in the time series: one ``spindle_cycle`` point per axis.

Through the real store-and-forward path into a real InfluxDB (tests/influx_server.py)
and through the embedded local store (its open period in SQLite and its Parquet parts),
the three axes of a cycle come back as three points, each with its ``axis`` tag, its
model and its own values; a single-axis record keeps exactly its one untagged point.
"""

from __future__ import annotations

import asyncio
from collections.abc import Iterator
from pathlib import Path

import pytest
from influxdb_client import InfluxDBClient

from gateway.offline.export import export_runs
from gateway.outputs.disk_buffer import PointBuffer
from gateway.outputs.influx import Forwarder, InfluxReader, InfluxWriter
from gateway.outputs.local_store import LocalStore, parts_folder
from gateway.outputs.points import (
    CYCLE_MEASUREMENT,
    TEMPERATURE_MEASUREMENT,
    points_from_record,
    probe_point,
)
from gateway.web.series import machine_view
from tests.influx_server import InfluxServer
from tests.records import axes_record, written_record
from tests.test_timeseries import EPOCH_S

TEMPS = {"T1": 21.5, "T2": 23.25}
AXES = ("Z", "X", "Y")  # configured order: Z first (the primary axis)


def three_axis_records(machine: str, cycles: int) -> list:
    """Cycles 1 s apart; axis Z applies t µm, X 2t + 0.5, Y −t − 0.25 (all distinct)."""
    return [
        axes_record(
            machine,
            float(t),
            TEMPS,
            {"Z": float(t), "X": 2.0 * t + 0.5, "Y": -float(t) - 0.25},
            speed_rpm=1000.0 + t,
        )
        for t in range(cycles)
    ]


def expected_applied(axis: str, t: float) -> float:
    return {"Z": t, "X": 2.0 * t + 0.5, "Y": -t - 0.25}[axis]


def test_single_axis_record_keeps_its_one_untagged_point() -> None:
    record = written_record("vmc-1", 5.0, TEMPS, 3.5)
    points = points_from_record(record, EPOCH_S)
    cycles = [p for p in points if p.measurement == CYCLE_MEASUREMENT]
    assert len(cycles) == 1
    assert cycles[0].tags == {"machine": "vmc-1", "regime": "variable", "model_id": "m"}
    assert cycles[0].fields["applied_um"] == 3.5


def test_three_axis_record_gives_one_tagged_point_per_axis_and_temperatures_once() -> None:
    record = three_axis_records("vmc-3", 8)[7]
    record.link_errors = ["bus"]
    points = points_from_record(record, EPOCH_S)
    cycles = [p for p in points if p.measurement == CYCLE_MEASUREMENT]
    assert [p.tags for p in cycles] == [
        {"machine": "vmc-3", "regime": "variable", "axis": a, "model_id": f"lag-ridge-{a}"}
        for a in AXES
    ]
    for index, (axis, point) in enumerate(zip(AXES, cycles, strict=True)):
        applied = expected_applied(axis, 7.0)
        assert point.fields == {
            "speed_rpm": 1007.0,
            "predicted_um": applied,
            "target_um": applied,
            "applied_um": applied,
            "written_cnc": applied / 1000.0,
            "interval_um": 1.0 + 0.5 * index,
            "training_span": "inside",
            "write_status": "ok",
            "link_errors": 1,
        }
        assert point.time_ns == cycles[0].time_ns
    temperatures = [p for p in points if p.measurement == TEMPERATURE_MEASUREMENT]
    assert sorted(p.tags["sensor"] for p in temperatures) == ["T1", "T2"]
    assert len(points) == 3 + 2


# --- the real InfluxDB ------------------------------------------------------------------
@pytest.fixture(scope="module")
def server(tmp_path_factory: pytest.TempPathFactory) -> Iterator[InfluxServer]:
    with InfluxServer(tmp_path_factory.mktemp("influxdb")) as influx:
        yield influx


def _flux_axis(server: InfluxServer, bucket: str, axis: str) -> list[tuple[int, float]]:
    """(time ns, applied_um) of one axis's points, selected by the ``axis`` tag in Flux."""
    flux = (
        f'from(bucket: "{bucket}") |> range(start: 0)'
        f' |> filter(fn: (r) => r._measurement == "{CYCLE_MEASUREMENT}")'
        f' |> filter(fn: (r) => r.axis == "{axis}")'
        ' |> filter(fn: (r) => r._field == "applied_um")'
        " |> map(fn: (r) => ({r with t_ns: int(v: r._time)}))"
    )
    with InfluxDBClient(url=server.url, token=server.token, org=server.org) as client:
        tables = client.query_api().query(flux, org=server.org)
        return sorted((int(r.values["t_ns"]), float(r.get_value())) for t in tables for r in t)


def test_three_axis_cycles_land_in_influxdb_as_three_points_queryable_by_axis(
    server: InfluxServer, tmp_path: Path
) -> None:
    bucket = server.create_database("axes")
    records = [*three_axis_records("vmc-3", 30), written_record("vmc-1", 3.0, TEMPS, 9.0)]
    points = [p for r in records for p in points_from_record(r, EPOCH_S)]

    async def forward() -> None:
        buffer = PointBuffer(tmp_path / "buffer.sqlite", max_points=10_000)
        writer = InfluxWriter(server.url, server.token, server.org, bucket, timeout_s=2.0)
        forwarder = Forwarder(buffer, writer, batch=40, retry_s=0.1, idle_s=0.05)
        forwarder.start()
        for record in records:  # as the sink hands them over, one cycle at a time
            buffer.append(points_from_record(record, EPOCH_S))
            forwarder.wake()
        assert await forwarder.flush(timeout=30)
        await forwarder.stop()
        writer.close()
        buffer.close()

    asyncio.run(forward())
    reader = InfluxReader(server.url, server.token, server.org, bucket)
    try:
        stored = reader.query(CYCLE_MEASUREMENT, machine="vmc-3")
        single = reader.query(CYCLE_MEASUREMENT, machine="vmc-1")
    finally:
        reader.close()
    assert len(stored) == 3 * 30
    assert {p.tags["axis"] for p in stored} == set(AXES)
    assert sorted(
        (p.time_ns, sorted(p.tags.items()), sorted(p.fields.items())) for p in stored
    ) == sorted(
        (p.time_ns, sorted(p.tags.items()), sorted(p.fields.items()))
        for p in points
        if p.measurement == CYCLE_MEASUREMENT and p.tags["machine"] == "vmc-3"
    )
    for axis in AXES:
        found = _flux_axis(server, bucket, axis)
        assert len(found) == 30
        assert [v for _, v in found] == [expected_applied(axis, float(t)) for t in range(30)]
    assert len(single) == 1 and "axis" not in single[0].tags
    # the console reads InfluxDB too: the machine's lines are the first axis's, each apart
    spec = ("influx", server.url, server.token, server.org, bucket, 5.0)
    factors = {"Z": 1000.0, "X": 1000.0, "Y": 1000.0}
    view = machine_view(spec, "vmc-3", EPOCH_S, EPOCH_S + 30, 1000.0, 60, axes=factors)
    assert view.cycles == 30
    assert list(view.lines["applied_um"][1]) == [float(t) for t in range(30)]
    for axis in AXES:
        assert list(view.axis_lines[axis]["applied_um"][1]) == [
            expected_applied(axis, float(t)) for t in range(30)
        ]


# --- the embedded local store -------------------------------------------------------------
def _by_axis(points: list) -> dict[str, list[tuple[int, float]]]:
    found: dict[str, list[tuple[int, float]]] = {}
    for p in points:
        found.setdefault(p.tags.get("axis", ""), []).append((p.time_ns, p.fields["applied_um"]))
    return found


def test_three_axis_cycles_written_to_the_local_store_read_back_with_their_axes(
    tmp_path: Path,
) -> None:
    records = three_axis_records("vmc-3", 1500)  # 25 min: closed periods go to Parquet
    written = [p for r in records for p in points_from_record(r, EPOCH_S)]
    store = LocalStore(tmp_path / "store.sqlite")
    try:
        assert store.write(written)
        store.compact()  # the write closes the periods it passes; anything left now
        assert list(parts_folder(store.path).glob("*.parquet"))  # some periods in parts
        assert list(store.segments.glob("*.log"))  # the last one still open
        stored = store.query(CYCLE_MEASUREMENT, machine="vmc-3")
        minutes = store.history(CYCLE_MEASUREMENT, machine="vmc-3")
    finally:
        store.close()
    cycles = [p for p in written if p.measurement == CYCLE_MEASUREMENT]
    assert len(stored) == 3 * 1500
    assert sorted(
        (p.time_ns, sorted(p.tags.items()), sorted(p.fields.items())) for p in stored
    ) == (sorted((p.time_ns, sorted(p.tags.items()), sorted(p.fields.items())) for p in cycles))
    by_axis = _by_axis(stored)
    assert sorted(by_axis) == sorted(AXES)
    for axis in AXES:
        assert [v for _, v in sorted(by_axis[axis])] == [
            expected_applied(axis, float(t)) for t in range(1500)
        ]
    # the per-minute history of the parts keeps one series per axis
    axes_in_history = {str(m["tags_extra"]) for m in minutes}
    assert axes_in_history == {f'{{"axis":"{a}"}}' for a in AXES}


def test_export_of_a_three_axis_machine_is_one_row_per_cycle_as_for_one_axis(
    tmp_path: Path,
) -> None:
    """The measured-run CSV of a 3-axis machine equals that of the same cycles logged
    as a single-axis machine: one row per cycle, nothing of the other axes mixed in."""
    multi = three_axis_records("vmc-3", 120)
    single = three_axis_records("vmc-3", 120)
    for record in single:
        record.axes = {}
    files = {}
    for name, records in (("multi", multi), ("single", single)):
        points = [p for r in records for p in points_from_record(r, EPOCH_S)]
        points += [probe_point("vmc-3", r.time_s, 0.5 * r.time_s, EPOCH_S) for r in records]
        with LocalStore(tmp_path / f"{name}.sqlite") as store:
            store.write(points)
            result = export_runs(store, "vmc-3", None, None, tmp_path / f"{name}.csv", EPOCH_S)
        assert result.rows == 120 and result.rows_without_probe == 0
        files[name] = (tmp_path / f"{name}.csv").read_text()
    assert files["multi"] == files["single"]
    assert len(files["multi"].splitlines()) == 1 + 120
