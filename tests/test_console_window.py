"""The machine page's window read from the local store: the temperatures grouped per
plot column in SQL give the same lines and events as reading every row.

Real parts: cycle records become points as the gateway makes them and go into the
local SQLite store; both reads run against that file. The same points written to a
real InfluxDB 2 (``tests/influx_server.py``) give the same page. The run has short spikes, a
sensor that breaks without a value every 50th cycle, another flagged bad every 70th,
link errors, quality changes on a column's first row and inside a column (there and
back within it), write refusals and an external macro change.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from gateway.live.record import CycleRecord
from gateway.outputs.influx import InfluxWriter
from gateway.outputs.local_store import LocalStore
from gateway.outputs.points import Point, points_from_record, probe_point
from gateway.web.series import MachineView, SourceSpec, machine_view
from tests.influx_server import InfluxServer
from tests.test_timeseries import EPOCH_S, make_records

CYCLES = 2400
COLUMNS = 60  # 40 s a column: 40 rows per sensor, far more than 2 × COLUMNS in all
SENSORS = ("T1", "T2", "T3")
SPIKES = {2201: 95.0, 2202: -40.0}  # T1, °C: one column, up then down
T1_BAD = (range(2000, 2002), range(2110, 2113))  # from a column's first row; mid-column
LATE = range(CYCLES - 90, CYCLES)  # T9 appears late: 90 rows, drawn whole
T2_BAD = range(2320, 2360)  # one whole column, its first and last rows without a value


def _run() -> list[CycleRecord]:
    records = make_records("m1", CYCLES, sensors=SENSORS)
    for i, value in SPIKES.items():
        records[i].temperatures_C["T1"] = value
    for cycles in T1_BAD:
        for i in cycles:
            records[i].quality["T1"] = "bad"
            records[i].quality_reasons["T1"] = "rate"
    for i in T2_BAD:
        records[i].quality["T2"] = "bad"
        records[i].quality_reasons["T2"] = "open circuit"
    for i in (T2_BAD.start, T2_BAD.stop - 1):
        records[i].temperatures_C["T2"] = None
    for i in LATE:
        records[i].temperatures_C["T9"] = 30.0 + (i % 7)
        records[i].quality["T9"] = "good"
    records[1500].write_status = "refused: readback differs"
    records[1501].write_status = "refused: readback differs"
    records[1800].write_status = "hold: external change of #500"
    return records


def _points() -> list[Point]:
    points = [p for record in _run() for p in points_from_record(record, EPOCH_S)]
    return points + [probe_point("m1", t, 5.0 + t / 1000, EPOCH_S) for t in range(0, CYCLES, 120)]


@pytest.fixture(scope="module")
def store(tmp_path_factory: pytest.TempPathFactory) -> Path:
    path = tmp_path_factory.mktemp("window") / "points.sqlite"
    with LocalStore(path) as local:
        local.write(_points())
    return path


def _view(store: Path | SourceSpec, aggregate: bool = True) -> MachineView:
    spec = ("local", str(store)) if isinstance(store, Path) else store
    return machine_view(spec, "m1", EPOCH_S, EPOCH_S + CYCLES, 1000.0, COLUMNS, aggregate)


def _same(a: tuple[np.ndarray, np.ndarray], b: tuple[np.ndarray, np.ndarray]) -> bool:
    return all(np.array_equal(x, y, equal_nan=True) for x, y in zip(a, b, strict=True))


def test_the_columns_grouped_in_sql_give_the_lines_and_events_of_every_row(store: Path) -> None:
    grouped, full = _view(store, aggregate=True), _view(store, aggregate=False)
    assert sorted(grouped.temperatures_C) == sorted(full.temperatures_C) == [*SENSORS, "T9"]
    for sensor, series in full.temperatures_C.items():
        assert _same(grouped.temperatures_C[sensor], series), sensor
    for name, series in full.lines.items():
        assert _same(grouped.lines[name], series), name
    assert grouped.events == full.events
    assert grouped.quality_changes == full.quality_changes
    assert grouped.cycles == full.cycles == CYCLES
    assert _same(
        (grouped.probe_t_s, grouped.probe_residual_um), (full.probe_t_s, full.probe_residual_um)
    )


def test_spikes_and_every_quality_change_are_kept(store: Path) -> None:
    view = _view(store, aggregate=True)
    t_s, value_C = view.temperatures_C["T1"]
    for value in SPIKES.values():
        assert value in value_C, value
    column = (t_s >= EPOCH_S + 2200) & (t_s < EPOCH_S + 2240)
    assert sorted(value_C[column]) == [-40.0, 95.0]
    flags = {(round(t - EPOCH_S), text) for t, kind, text in view.events if kind == "sensor flag"}
    for cycles in T1_BAD:
        assert (cycles.start, "T1: good → bad") in flags
        assert (cycles.stop, "T1: bad → good") in flags
    assert {(T2_BAD.start, "T2: good → bad"), (T2_BAD.stop, "T2: bad → good")} <= flags
    t_s, _ = view.temperatures_C["T2"]
    column = t_s[(t_s >= EPOCH_S + T2_BAD.start) & (t_s < EPOCH_S + T2_BAD.stop)]
    assert list(column - EPOCH_S) == [T2_BAD.start + 1, T2_BAD.stop - 2]  # the valued rows
    # T3 breaks without a value on every 50th cycle: the break and the recovery each time
    for i in range(1849, CYCLES - 1, 50):
        assert {(i, "T3: good → bad"), (i + 1, "T3: bad → good")} <= flags, i
    kinds = {(round(t - EPOCH_S), kind) for t, kind, _ in view.events}
    assert {(1500, "write"), (1800, "external macro change")} <= kinds
    assert (1501, "write") not in kinds  # the same refusal goes on: listed once
    links = [kind for t, kind, _ in view.events if kind in ("source fault", "reconnected")]
    assert links[:2] == ["reconnected", "source fault"] and len(links) % 2 == 0, links


def test_a_long_window_is_cut_to_two_points_a_column_and_a_short_series_kept_whole(
    store: Path,
) -> None:
    view = _view(store, aggregate=True)
    for sensor in SENSORS:
        assert 2 * COLUMNS - 2 <= len(view.temperatures_C[sensor][0]) <= 2 * COLUMNS, sensor
    for name, (t_s, _) in view.lines.items():
        assert len(t_s) <= 2 * COLUMNS, name
    t_s, value_C = view.temperatures_C["T9"]
    assert np.array_equal(t_s, [EPOCH_S + i for i in LATE])
    assert np.array_equal(value_C, [30.0 + (i % 7) for i in LATE])


def test_the_same_points_in_influxdb_give_the_same_page(store: Path, tmp_path: Path) -> None:
    with InfluxServer(tmp_path / "influxdb") as server:
        bucket = server.create_bucket("spindle")
        writer = InfluxWriter(server.url, server.token, server.org, bucket)
        try:
            writer.write_sync(_points())
        finally:
            writer.close()
        influx = _view(("influx", server.url, server.token, server.org, bucket, 30.0))
    local = _view(store)
    assert sorted(influx.temperatures_C) == sorted(local.temperatures_C)
    for sensor, series in local.temperatures_C.items():
        assert _same(influx.temperatures_C[sensor], series), sensor
    for name, series in local.lines.items():
        assert _same(influx.lines[name], series), name
    assert influx.events == local.events and influx.cycles == CYCLES
    assert influx.quality_changes == local.quality_changes
