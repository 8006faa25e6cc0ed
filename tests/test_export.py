"""Logged time series → the measured-run CSV of contract §1, which
models.data.dataset.load_runs accepts."""

from __future__ import annotations

import csv
from pathlib import Path

import numpy as np
import pytest

from gateway.live.record import CycleRecord
from gateway.offline.export import ExportError, export_runs
from gateway.outputs.local_store import LocalStore
from gateway.outputs.points import points_from_record, probe_point
from models.data.dataset import load_runs
from tests.test_timeseries import EPOCH_S, make_records, true_error_um

RUN_B_START_S = 5000.0  # a gap of ~4700 cycles after run A: a new run


def logged_records() -> list[CycleRecord]:
    """Machine m1: run A (300 cycles from 0 s) and run B (200 cycles from 5000 s)."""
    return make_records("m1", 300) + make_records("m1", 200, start_s=RUN_B_START_S)


def has_probe(i: int) -> bool:
    return i % 10 != 3  # no probe reading in every 10th cycle


def fill_store(store: LocalStore, records: list[CycleRecord]) -> int:
    """Write the records' points and a probe 0.3 s into most cycles; return the probe count."""
    probes = [
        probe_point(r.machine, r.time_s + 0.3, true_error_um(r), EPOCH_S)
        for i, r in enumerate(records)
        if has_probe(i)
    ]
    probes.append(probe_point("m1", 1000.0, 99.0, EPOCH_S))  # in the gap: no cycle, not used
    store.write([p for r in records for p in points_from_record(r, EPOCH_S)])
    store.write(probes)
    store.write([p for r in make_records("m2", 100) for p in points_from_record(r, EPOCH_S)])
    return len(probes) - 1


@pytest.fixture
def store(tmp_path: Path):
    with LocalStore(tmp_path / "series.sqlite") as local:
        yield local


def test_export_passes_load_runs_with_runs_from_gaps(store: LocalStore, tmp_path: Path) -> None:
    records = logged_records()
    n_probes = fill_store(store, records)
    out = tmp_path / "export" / "m1.csv"

    result = export_runs(store, "m1", None, None, out, epoch_s=EPOCH_S)

    assert result.columns == (
        "run",
        "time_s",
        "speed_rpm",
        "T1",
        "T2",
        "T3",
        "ambient_C",
        "error_um",
    )
    assert result.runs == ("m1-20260101T000000Z", "m1-20260101T012320Z")
    assert result.rows == n_probes
    assert result.rows_without_probe == len(records) - n_probes
    assert result.cycle_s == 1.0
    assert result.ignored_sensors == ()

    runs = load_runs(out)
    assert runs.run_ids == result.runs
    assert runs.sensors == ("T1", "T2", "T3")
    # rows with a silent T3 or a bad T2 keep an empty cell; load_runs skips and counts them
    kept = [
        (i, r)
        for i, r in enumerate(records)
        if has_probe(i) and r.temperatures_C["T3"] is not None and r.quality["T2"] == "good"
    ]
    assert result.rows_incomplete == n_probes - len(kept)
    assert sum(s.count for s in runs.skipped) == result.rows_incomplete
    assert runs.n_samples == len(kept)

    np.testing.assert_array_equal(runs.time_s, [r.time_s for _, r in kept])
    np.testing.assert_array_equal(runs.speed_rpm, [r.speed_rpm for _, r in kept])
    np.testing.assert_array_equal(runs.error_um, [true_error_um(r) for _, r in kept])
    np.testing.assert_array_equal(runs.column("T1"), [r.temperatures_C["T1"] for _, r in kept])
    np.testing.assert_array_equal(runs.ambient_C, [r.temperatures_C["ambient"] for _, r in kept])
    first_b = next(k for k, (_, r) in enumerate(kept) if r.time_s >= RUN_B_START_S)
    assert set(runs.run[:first_b]) == {"m1-20260101T000000Z"}
    assert set(runs.run[first_b:]) == {"m1-20260101T012320Z"}


def test_export_rows_and_cells(store: LocalStore, tmp_path: Path) -> None:
    records = logged_records()
    fill_store(store, records)
    out = tmp_path / "window.csv"

    result = export_runs(store, "m1", 0.0, 100.0, out, epoch_s=EPOCH_S, good_only=False)

    with out.open(newline="", encoding="utf-8") as handle:
        rows = list(csv.DictReader(handle))
    expected = [(i, r) for i, r in enumerate(records[:100]) if has_probe(i)]
    assert len(rows) == result.rows == len(expected) == 90
    assert result.rows_without_probe == 10 and result.runs == ("m1-20260101T000000Z",)
    row_by_time = {float(row["time_s"]): row for row in rows}
    assert 3.0 not in row_by_time  # cycle 3 had no probe value: left out
    row = row_by_time[69.0]  # T2 flagged bad: kept with good_only=False
    record = records[69]
    assert row["run"] == "m1-20260101T000000Z"
    assert float(row["T2"]) == record.temperatures_C["T2"]
    assert float(row["error_um"]) == true_error_um(record)
    assert float(row["speed_rpm"]) == record.speed_rpm
    assert row_by_time[49.0]["T3"] == ""  # no reading: an empty cell, never 0
    assert result.rows_incomplete == 2  # cycles 49 and 99

    strict = export_runs(store, "m1", 0.0, 100.0, tmp_path / "good.csv", epoch_s=EPOCH_S)
    with (tmp_path / "good.csv").open(newline="", encoding="utf-8") as handle:
        good_rows = {float(r["time_s"]): r for r in csv.DictReader(handle)}
    assert good_rows[69.0]["T2"] == "" and strict.rows_incomplete == 3
    assert load_runs(tmp_path / "good.csv").n_samples == 87


def test_export_fast_cycles_split_runs_by_gap(store: LocalStore, tmp_path: Path) -> None:
    """0.2 s cycles; a gap of 1.8 s (9 cycles) does not cut a run, one of 2.2 s does."""
    records = (
        make_records("fast", 20, cycle_s=0.2)
        + make_records("fast", 20, cycle_s=0.2, start_s=5.6)  # 1.8 s after 3.8 s
        + make_records("fast", 20, cycle_s=0.2, start_s=11.6)  # 2.2 s after 9.4 s
    )
    store.write([p for r in records for p in points_from_record(r, EPOCH_S)])
    store.write(
        [probe_point(r.machine, r.time_s + 0.1, true_error_um(r), EPOCH_S) for r in records]
    )
    out = tmp_path / "fast.csv"
    result = export_runs(store, "fast", None, None, out, epoch_s=EPOCH_S)
    assert result.cycle_s == pytest.approx(0.2)
    assert result.runs == ("fast-20260101T000000Z", "fast-20260101T000011Z")
    runs = load_runs(out)
    assert [(name, s.stop - s.start) for name, s in runs.run_slices()] == [
        ("fast-20260101T000000Z", 40),
        ("fast-20260101T000011Z", 20),
    ]


def test_nothing_to_export_is_an_error(store: LocalStore, tmp_path: Path) -> None:
    with pytest.raises(ExportError, match="no cycles"):
        export_runs(store, "m1", None, None, tmp_path / "x.csv")
    store.write([p for r in make_records("m1", 5) for p in points_from_record(r)])
    with pytest.raises(ExportError, match="probe"):
        export_runs(store, "m1", None, None, tmp_path / "x.csv")
