"""A machine's window from the local store as column arrays, temperatures cut per column.

A day of one machine at 1 Hz holds 777 600 temperature rows: moving each into
Python as a tuple costs seconds. DuckDB hands the typed columns over as numpy
arrays (sorted by sensor, then time) and each sensor is cut to the window's column
envelope with :func:`envelope` and its quality flips found by comparing neighbours,
so the result is exactly that of reading every row
(:func:`gateway.web.series.machine_view` without aggregation).
"""

from __future__ import annotations

import sqlite3
from collections.abc import Callable
from pathlib import Path

import numpy as np

from gateway.outputs.local_store import parts_folder, read_window
from gateway.outputs.points import NS_PER_S, TEMPERATURE_MEASUREMENT

Series = tuple[np.ndarray, np.ndarray]
Change = tuple[float, str, str]
Envelope = Callable[[np.ndarray, np.ndarray, int, int, int], Series]


def connect(path: Path) -> sqlite3.Connection:
    """A read-only connection to the store file (the gateway may be writing it)."""
    return sqlite3.connect(f"file:{path}?mode=ro", uri=True, timeout=5.0)


def _numbers(column: np.ndarray) -> np.ndarray:
    """A fetched numeric column as floats, NULL as NaN."""
    return np.ma.filled(np.ma.asarray(column).astype(float), np.nan)


def window_rows(
    path: Path, measurement: str, machine: str, window: tuple[int, int], select: str, order: str
) -> list[tuple]:
    """Rows ``SELECT select`` of one machine's measurement in ``start ≤ t < stop``."""
    db = connect(path)
    try:
        found = read_window(db, parts_folder(path), measurement, machine, *window, select, order)
    finally:
        db.close()
    try:
        return found.fetchall()
    finally:
        found.close()


def temperature_envelopes(
    path: Path, machine: str, start_ns: int, stop_ns: int, columns: int, envelope: Envelope
) -> tuple[dict[str, Series], list[Change]]:
    """Per sensor ``(t_ns, value_C)`` cut to the window's column envelope, and the
    quality changes ``(Unix s, sensor, "before → after")`` in time order."""
    db = connect(path)
    try:
        found = read_window(
            db,
            parts_folder(path),
            TEMPERATURE_MEASUREMENT,
            machine,
            start_ns,
            stop_ns,
            "time_ns, sensor, quality, value_C",
            "sensor, time_ns",
        )
    finally:
        db.close()
    try:
        arrays = found.fetchnumpy()
    finally:
        found.close()
    t = np.asarray(arrays["time_ns"], dtype=np.int64)
    sensors = np.asarray(arrays["sensor"], dtype=object)
    qualities = np.asarray(arrays["quality"], dtype=object)
    values = _numbers(arrays["value_C"])
    series: dict[str, Series] = {}
    changes: list[Change] = []
    starts = np.flatnonzero(np.r_[True, sensors[1:] != sensors[:-1]]) if len(t) else []
    ends = [*list(starts[1:]), len(t)]
    for a, b in zip(starts, ends, strict=True):
        name = str(sensors[a])
        series[name] = envelope(t[a:b], values[a:b], start_ns, stop_ns, columns)
        q = qualities[a:b]
        for i in np.flatnonzero(q[1:] != q[:-1]) + 1:
            changes.append((int(t[a + i]) / NS_PER_S, name, f"{q[i - 1]} → {q[i]}"))
    changes.sort(key=lambda c: (c[0], c[1]))
    return series, changes
