"""``export`` reads the window in time slices: the file is the same as from one read of
the whole window, and the memory it takes does not grow with the window's length."""

from __future__ import annotations

import dataclasses
import statistics
import tracemalloc
from pathlib import Path

import numpy as np
import pytest

from gateway.offline.export import _IntervalCounts, export_runs
from gateway.outputs.local_store import LocalStore
from gateway.outputs.points import Point
from models.data.dataset import load_runs
from tests.long_store import DAY_S, EPOCH_S, write_long_store

DAYS = 4


@pytest.fixture(scope="module")
def long_store(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """4 days of two machines' 8-hour shifts, one cycle every 10 s (~150 000 points)."""
    return write_long_store(tmp_path_factory.mktemp("long") / "series.sqlite", days=DAYS)


class WholeWindow:
    """The store as a source that can only answer ``query``: the export reads the
    whole window of each measurement at once, as it did before it read in slices."""

    def __init__(self, store: LocalStore) -> None:
        self.store = store

    def query(
        self,
        measurement: str,
        machine: str | None = None,
        start_ns: int | None = None,
        stop_ns: int | None = None,
    ) -> list[Point]:
        return self.store.query(measurement, machine, start_ns, stop_ns)


def test_slices_write_the_same_file_as_one_read(long_store: Path, tmp_path: Path) -> None:
    with LocalStore(long_store, set_aside_damaged=False) as store:
        whole = export_runs(WholeWindow(store), "m1", None, None, tmp_path / "whole.csv",  # type: ignore[arg-type]
                            epoch_s=EPOCH_S)  # fmt: skip
        # default slices, and small ones (about an hour of points, boundaries mid-run)
        for points in (50_000, 4_000):
            out = tmp_path / f"{points}.csv"
            sliced = export_runs(store, "m1", None, None, out, EPOCH_S, slice_points=points)
            assert sliced == dataclasses.replace(whole, path=out)
            assert out.read_bytes() == (tmp_path / "whole.csv").read_bytes()
        window = export_runs(store, "m2", 30_000.0, 200_000.0, tmp_path / "w.csv", EPOCH_S)
        one = export_runs(WholeWindow(store), "m2", 30_000.0, 200_000.0,  # type: ignore[arg-type]
                          tmp_path / "w1.csv", EPOCH_S)  # fmt: skip
    assert (tmp_path / "w.csv").read_bytes() == (tmp_path / "w1.csv").read_bytes()
    assert window == dataclasses.replace(one, path=window.path)
    # two runs a day (the stop half-way through the shift), a probe in two cycles of three
    assert len(whole.runs) == 2 * DAYS and whole.cycle_s == pytest.approx(10.0, abs=0.01)
    assert whole.rows == 2 * whole.rows_without_probe == 2 * DAYS * 8 * 360 // 3
    assert load_runs(tmp_path / "whole.csv").run_ids == whole.runs


def peak_bytes(store: LocalStore, days: int, out: Path) -> tuple[int, int]:
    """The export's peak of Python memory (tracemalloc) for the first ``days``, and its rows."""
    tracemalloc.start()
    try:
        result = export_runs(store, "m1", None, days * DAY_S, out, epoch_s=EPOCH_S)
        return tracemalloc.get_traced_memory()[1], result.rows
    finally:
        tracemalloc.stop()


def test_memory_does_not_grow_with_the_window(long_store: Path, tmp_path: Path) -> None:
    with LocalStore(long_store, set_aside_damaged=False) as store:
        export_runs(store, "m1", None, 3600.0 * 7, tmp_path / "warm.csv", epoch_s=EPOCH_S)
        one_day, rows_1 = peak_bytes(store, 1, tmp_path / "1.csv")
        all_days, rows_4 = peak_bytes(store, DAYS, tmp_path / "4.csv")
    assert rows_4 == DAYS * rows_1
    # Read whole, the 4 days took 4 times the 1 day's peak (54 MB against 14 MB).
    assert all_days < 1.5 * one_day, (one_day, all_days)
    assert all_days < 16e6, all_days


@pytest.mark.parametrize("n", [1, 2, 7, 1000, 1001])
def test_interval_median_is_the_lists(n: int) -> None:
    rng = np.random.default_rng(n)
    intervals = [int(x) for x in rng.integers(999_000_000, 1_001_000_000, n)]
    intervals[: n // 3] = [1_000_000_000] * (n // 3)
    counts = _IntervalCounts()
    for interval in intervals:
        counts.add(interval)
    assert counts.median() == statistics.median(intervals)


def test_interval_median_stays_within_a_bin_past_the_limit() -> None:
    rng = np.random.default_rng(3)
    intervals = [
        int(x) for x in rng.integers(900_000_000, 1_100_000_000, 3 * _IntervalCounts.LIMIT)
    ]
    counts = _IntervalCounts()
    for interval in intervals:
        counts.add(interval)
    assert len(counts.counts) <= _IntervalCounts.LIMIT and counts.bin_ns > 1
    assert abs(counts.median() - statistics.median(intervals)) <= counts.bin_ns
