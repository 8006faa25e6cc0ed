"""Points from cycle records; the disk-backed point buffer; the embedded SQLite store."""

from __future__ import annotations

import logging
import math
from pathlib import Path

import pytest

from gateway.live.record import CycleRecord
from gateway.outputs.disk_buffer import PointBuffer
from gateway.outputs.local_store import LocalStore
from gateway.outputs.points import (
    CYCLE_MEASUREMENT,
    PROBE_MEASUREMENT,
    TEMPERATURE_MEASUREMENT,
    Point,
    points_from_record,
    probe_point,
    record_sink,
    to_time_ns,
)

EPOCH_S = 1_767_225_600.0  # 2026-01-01T00:00:00Z: machine time 0


def make_records(
    machine: str,
    n: int,
    cycle_s: float = 1.0,
    start_s: float = 0.0,
    sensors: tuple[str, ...] = ("T1", "T2", "T3", "ambient"),
) -> list[CycleRecord]:
    """A synthetic run: warming sensors, a speed programme, occasional gaps and faults.

    Every 50th cycle lacks T3 (a silent transmitter); every 70th has T2 flagged bad;
    the first 10 cycles have no model (no regime, no prediction); every 90th cycle has
    a link error.
    """
    records = []
    for i in range(n):
        t = start_s + i * cycle_s
        temperatures: dict[str, float | None] = {
            name: round(20.0 + k + 0.01 * i * (k + 1), 4) for k, name in enumerate(sensors)
        }
        if "ambient" in temperatures:
            temperatures["ambient"] = round(20.0 + 0.001 * i, 4)
        if i % 50 == 49 and "T3" in temperatures:
            temperatures["T3"] = None
        quality = {
            name: "good" if value is not None else "bad" for name, value in temperatures.items()
        }
        reasons = {name: "no value" for name, value in temperatures.items() if value is None}
        if i % 70 == 69 and "T2" in quality:
            quality["T2"] = "bad"
            reasons["T2"] = "rate"
        warm = i >= 10
        records.append(
            CycleRecord(
                machine=machine,
                time_s=t,
                temperatures_C=temperatures,
                quality=quality,
                quality_reasons=reasons,
                speed_rpm=float((i // 100 % 3) * 2000),
                regime=("variable" if i < n // 2 else "constant") if warm else None,
                model_id="mlr-error_um-all" if warm else None,
                predicted_um=round(0.05 * i, 3) if warm else None,
                target_um=round(0.05 * i, 3) if warm else None,
                applied_um=round(0.05 * i - 0.1, 3) if warm else 0.0,
                written_cnc=round(-0.00005 * i, 6) if warm else None,
                write_status="ok: slew" if warm else "no write: no prediction",
                link_errors=["bus bus2: timeout"] if i % 90 == 89 else [],
            )
        )
    return records


def true_error_um(record: CycleRecord) -> float:
    """A 'measured' error for probe points: a known function of the record."""
    return round(0.8 * ((record.temperatures_C.get("T1") or 20.0) - 20.0) + 0.25, 4)


def sample_point(i: int, machine: str = "m1") -> Point:
    return Point(
        CYCLE_MEASUREMENT,
        {"machine": machine},
        {
            "speed_rpm": float(i),
            "write_status": f"ok {i}",
            "link_errors": i % 3,
            "flag": i % 2 == 0,
        },
        to_time_ns(i * 0.2, EPOCH_S),
    )


# --- points from records -------------------------------------------------------------------
def test_points_of_a_full_record() -> None:
    record = make_records("vmc-1", 20)[15]
    points = points_from_record(record, epoch_s=EPOCH_S)
    assert [p.measurement for p in points] == [CYCLE_MEASUREMENT] + [TEMPERATURE_MEASUREMENT] * 4
    assert all(p.time_ns == 1_767_225_615_000_000_000 for p in points)

    cycle = points[0]
    assert cycle.tags == {"machine": "vmc-1", "regime": "constant", "model_id": "mlr-error_um-all"}
    assert cycle.fields == {
        "speed_rpm": 0.0,
        "predicted_um": 0.75,
        "target_um": 0.75,
        "applied_um": 0.65,
        "written_cnc": -0.00075,
        "write_status": "ok: slew",
        "link_errors": 0,
    }
    # float fields stay floats even for whole numbers (InfluxDB refuses a type change)
    assert isinstance(cycle.fields["speed_rpm"], float)
    assert isinstance(cycle.fields["link_errors"], int)

    by_sensor = {p.tags["sensor"]: p for p in points[1:]}
    assert set(by_sensor) == {"T1", "T2", "T3", "ambient"}
    assert by_sensor["T2"].tags == {"machine": "vmc-1", "sensor": "T2", "quality": "good"}
    assert by_sensor["T2"].fields == {"value_C": pytest.approx(21.0 + 0.02 * 15)}
    assert by_sensor["ambient"].fields == {"value_C": 20.015}


def test_nones_are_omitted_not_zero() -> None:
    record = make_records("vmc-1", 50)[49]  # T3 silent; warm
    record.speed_rpm = None
    record.predicted_um = None
    record.written_cnc = float("nan")
    record.link_errors = ["CNC: timeout", "bus bus1: refused"]
    points = points_from_record(record)
    cycle = points[0]
    assert "speed_rpm" not in cycle.fields
    assert "predicted_um" not in cycle.fields
    assert "written_cnc" not in cycle.fields  # not finite: omitted
    assert cycle.fields["link_errors"] == 2
    assert cycle.time_ns == 49_000_000_000  # epoch_s defaults to 0
    by_sensor = {p.tags["sensor"]: p for p in points[1:]}
    assert set(by_sensor) == {"T1", "T2", "T3", "ambient"}
    # the missing T3 is flagged bad: its point says so, with no value (never a 0)
    assert by_sensor["T3"].tags["quality"] == "bad"
    assert by_sensor["T3"].fields == {"reason": "no value"}
    # a good sensor without a value (one missed read) gets no point at all
    record.quality["T3"] = "good"
    del record.quality_reasons["T3"]
    assert {p.tags["sensor"] for p in points_from_record(record)[1:]} == {"T1", "T2", "ambient"}

    cold = points_from_record(make_records("vmc-1", 1)[0])[0]
    assert cold.tags == {"machine": "vmc-1"}  # no regime/model yet: no empty tags
    assert "predicted_um" not in cold.fields and cold.fields["applied_um"] == 0.0


def test_bad_quality_is_a_tag() -> None:
    record = make_records("vmc-1", 70)[69]
    temps = {p.tags["sensor"]: p for p in points_from_record(record)[1:]}
    assert temps["T2"].tags["quality"] == "bad"
    assert temps["T2"].fields == {"value_C": pytest.approx(21.0 + 0.02 * 69), "reason": "rate"}
    assert temps["T1"].tags["quality"] == "good"
    assert "reason" not in temps["T1"].fields


def test_probe_point_and_sink() -> None:
    probe = probe_point("vmc-1", 12.5, 3.25, epoch_s=EPOCH_S)
    assert probe == Point(
        PROBE_MEASUREMENT, {"machine": "vmc-1"}, {"error_um": 3.25}, 1_767_225_612_500_000_000
    )
    with pytest.raises(ValueError, match="finite"):
        probe_point("vmc-1", 1.0, math.nan)

    got: list[list[Point]] = []
    sink = record_sink(got.append, epoch_s=EPOCH_S)
    records = make_records("vmc-1", 3)
    for record in records:
        sink(record)
    assert got == [points_from_record(r, EPOCH_S) for r in records]


def test_time_ns_keeps_sub_second_machine_time() -> None:
    assert to_time_ns(0.2, EPOCH_S) == 1_767_225_600_200_000_000
    assert to_time_ns(86_399.8, EPOCH_S) == 1_767_311_999_800_000_000


# --- the point buffer ----------------------------------------------------------------------
def test_buffer_is_fifo_with_row_ids(tmp_path: Path) -> None:
    buffer = PointBuffer(tmp_path / "buffer.sqlite", max_points=1000)
    points = [sample_point(i) for i in range(25)]
    buffer.append(points[:10])
    buffer.append(points[10:])
    assert len(buffer) == 25
    first = buffer.peek(10)
    assert [p for _, p in first] == points[:10]  # types survive: float, int, str, bool
    assert isinstance(first[0][1].fields["flag"], bool)
    assert isinstance(first[1][1].fields["link_errors"], int)
    assert [row_id for row_id, _ in first] == sorted(row_id for row_id, _ in first)
    assert buffer.peek(10) == first  # peek removes nothing

    assert buffer.remove_through(first[-1][0]) == 10
    assert len(buffer) == 15
    assert [p for _, p in buffer.peek(100)] == points[10:]
    buffer.remove_through(buffer.peek(100)[-1][0])
    assert len(buffer) == 0 and buffer.peek(5) == []

    # row ids never come back: a stale remove_through cannot remove newer points
    buffer.append([sample_point(99)])
    assert buffer.peek(1)[0][0] > first[-1][0]
    buffer.remove_through(first[-1][0])
    assert len(buffer) == 1
    buffer.close()


def test_buffer_bound_drops_oldest_and_says_so(
    tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    buffer = PointBuffer(tmp_path / "buffer.sqlite", max_points=100)
    points = [sample_point(i) for i in range(130)]
    buffer.append(points[:80])
    assert buffer.dropped == 0
    with caplog.at_level(logging.WARNING, logger="gateway.outputs.disk_buffer"):
        buffer.append(points[80:])
    assert len(buffer) == 100
    assert buffer.dropped == 30
    assert [p for _, p in buffer.peek(1000)] == points[30:]
    warnings = [r.getMessage() for r in caplog.records if r.levelno == logging.WARNING]
    assert len(warnings) == 1 and "dropped the 30 oldest" in warnings[0]

    # a single append larger than the buffer keeps its newest points
    big = [sample_point(1000 + i) for i in range(250)]
    buffer.append(big)
    assert [p for _, p in buffer.peek(1000)] == big[150:]
    assert buffer.dropped == 30 + 100 + 150
    buffer.close()


def test_buffer_survives_restart(tmp_path: Path) -> None:
    path = tmp_path / "state" / "buffer.sqlite"
    points = [sample_point(i) for i in range(40)]
    buffer = PointBuffer(path, max_points=30)
    buffer.append(points)
    buffer.remove_through(buffer.peek(5)[-1][0])
    before = buffer.peek(100)
    del buffer  # no close: as if the process died (the connection is not committed anew)

    again = PointBuffer(path, max_points=30)
    assert again.peek(100) == before
    assert len(again) == 25
    assert again.dropped == 10  # the count is kept in the file too
    again.append([sample_point(500)])
    assert again.peek(100)[-1][1] == sample_point(500)
    again.close()

    smaller = PointBuffer(path, max_points=20)  # reopened with a smaller bound
    assert len(smaller) == 20 and smaller.dropped == 16
    assert smaller.peek(100)[-1][1] == sample_point(500)
    smaller.close()


# --- the local store -----------------------------------------------------------------------
def test_local_store_round_trip(tmp_path: Path) -> None:
    path = tmp_path / "series.sqlite"
    store = LocalStore(path)
    records = make_records("m1", 120) + make_records("m2", 60)
    written = [p for r in records for p in points_from_record(r, EPOCH_S)]
    store.write(written)
    store.write([probe_point("m1", 30.0, 1.5, EPOCH_S)])
    store.close()

    store = LocalStore(path)  # reopened: everything is on disk
    assert store.machines() == ["m1", "m2"]
    cycles = store.query(CYCLE_MEASUREMENT, machine="m1")
    assert cycles == [
        p for p in written if p.measurement == CYCLE_MEASUREMENT and p.machine == "m1"
    ]
    temps = store.query(TEMPERATURE_MEASUREMENT)
    assert len(temps) == sum(1 for p in written if p.measurement == TEMPERATURE_MEASUREMENT)
    assert [p.time_ns for p in temps] == sorted(p.time_ns for p in temps)
    window = store.query(
        TEMPERATURE_MEASUREMENT,
        machine="m2",
        start_ns=to_time_ns(10.0, EPOCH_S),
        stop_ns=to_time_ns(20.0, EPOCH_S),
    )
    assert {p.time_ns for p in window} == {to_time_ns(float(s), EPOCH_S) for s in range(10, 20)}
    assert all(p.machine == "m2" for p in window)
    assert store.query(PROBE_MEASUREMENT, "m1") == [probe_point("m1", 30.0, 1.5, EPOCH_S)]
    assert store.query(PROBE_MEASUREMENT, "nobody") == []

    # the same point again is stored once (InfluxDB's rule); new fields merge in
    n = len(store)
    store.write(written[:50])
    assert len(store) == n
    first = written[0]
    store.write(
        [Point(first.measurement, first.tags, {"speed_rpm": 42.0, "extra": 1}, first.time_ns)]
    )
    assert len(store) == n
    merged = store.query(CYCLE_MEASUREMENT, "m1", stop_ns=first.time_ns + 1)[0]
    assert merged.fields == {**first.fields, "speed_rpm": 42.0, "extra": 1}

    assert store.delete_before(to_time_ns(100.0, EPOCH_S)) > 0
    assert min(p.time_ns for p in store.query(CYCLE_MEASUREMENT)) == to_time_ns(100.0, EPOCH_S)
    store.close()
