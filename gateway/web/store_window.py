"""A machine's window from the local store as column arrays, temperatures cut per column.

A day of one machine at 1 Hz holds 777 600 temperature rows: moving each into
Python costs seconds. DuckDB groups them per sensor and plot column (first and last
time, lowest and highest value) and finds each quality flip with a window function,
so a few thousand rows come back, and the result is exactly that of reading every
row (:func:`gateway.web.series.machine_view` without aggregation).
"""

from __future__ import annotations

import sqlite3
from pathlib import Path

import numpy as np

from gateway.outputs.local_store import parts_folder, read_window
from gateway.outputs.points import NS_PER_S, TEMPERATURE_MEASUREMENT
from gateway.outputs.store_parts import literal

Series = tuple[np.ndarray, np.ndarray]
Change = tuple[float, str, str]


def connect(path: Path) -> sqlite3.Connection:
    """A read-only connection to the store file (the gateway may be writing it)."""
    return sqlite3.connect(f"file:{path}?mode=ro", uri=True, timeout=5.0)


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


def window_columns(
    path: Path, measurement: str, machine: str, window: tuple[int, int], select: str
) -> list[list]:
    """Columns ``select`` of one machine's measurement in ``start ≤ t < stop``, by time:
    one list per column (NULL as None), fetched as arrays, never row by row."""
    db = connect(path)
    try:
        found = read_window(
            db, parts_folder(path), measurement, machine, *window, select, "time_ns"
        )
    finally:
        db.close()
    try:
        arrays = found.fetchnumpy()
    finally:
        found.close()
    return [np.ma.asarray(a).tolist() for a in arrays.values()]


#: Valued rows per sensor; the envelope's columns; a few sensors' every row.
_READ = "CREATE TEMP TABLE t AS SELECT time_ns, sensor, quality, value_C FROM w"
_VALUED = "SELECT sensor, count(value_C), count(DISTINCT quality) FROM t GROUP BY sensor"
_COLUMNS = (
    "SELECT sensor, min(time_ns), max(time_ns), min(value_C), max(value_C) FROM t "
    "WHERE value_C IS NOT NULL AND sensor IN ({names}) "
    "GROUP BY sensor, (time_ns - {start}) * {columns} // {span} "
    "ORDER BY sensor, (time_ns - {start}) * {columns} // {span}"
)
_WHOLE = (
    "SELECT sensor, time_ns, value_C FROM t WHERE value_C IS NOT NULL "
    "AND sensor IN ({names}) ORDER BY sensor, time_ns"
)
#: A quality that differs from the sensor's row before: the flips (only sensors that
#: show more than one quality in the window can have any).
_FLIPS = (
    "SELECT time_ns, sensor, before, quality FROM (SELECT time_ns, sensor, quality, "
    "lag(quality) OVER (PARTITION BY sensor ORDER BY time_ns) AS before FROM t "
    "WHERE sensor IN ({names})) "
    "WHERE before IS NOT NULL AND before <> quality ORDER BY time_ns, sensor"
)


def _names(sensors: list[str]) -> str:
    return ", ".join(literal(s) for s in sensors) or "NULL"


def temperature_envelopes(
    path: Path, machine: str, start_ns: int, stop_ns: int, columns: int
) -> tuple[dict[str, Series], list[Change]]:
    """Per sensor ``(t_ns, value_C)`` cut to the window's column envelope — each
    column's first time with its lowest value and last time with its highest; a sensor
    of at most ``2 × columns`` valued rows whole — and the quality changes
    ``(Unix s, sensor, "before → after")`` in time order, all grouped in DuckDB."""
    db = connect(path)
    try:
        window = (start_ns, stop_ns)
        found = read_window(
            db, parts_folder(path), TEMPERATURE_MEASUREMENT, machine, *window, "", ""
        )
    finally:
        db.close()
    try:
        found.execute(_READ)  # the window read once, then grouped
        counts = found.execute(_VALUED).fetchall()
        valued = {s: n for s, n, _ in counts}
        flipping = sorted(s for s, _, qualities in counts if qualities > 1)
        big = sorted(s for s, n in valued.items() if n > 2 * columns)
        small = sorted(s for s, n in valued.items() if n <= 2 * columns)
        shape = {"start": start_ns, "columns": columns, "span": stop_ns - start_ns}
        grouped = found.execute(_COLUMNS.format(names=_names(big), **shape)).fetchall()
        whole = found.execute(_WHOLE.format(names=_names(small))).fetchall()
        flips = found.execute(_FLIPS.format(names=_names(flipping))).fetchall() if flipping else []
    finally:
        found.close()
    series: dict[str, Series] = {}
    for sensor in valued:
        t: list[tuple[object, ...]] = [(a, b) for s, a, b, _, _ in grouped if s == sensor]
        y: list[tuple[object, ...]] = [(lo, hi) for s, _, _, lo, hi in grouped if s == sensor]
        if sensor in small:
            t = [(r[1],) for r in whole if r[0] == sensor]
            y = [(r[2],) for r in whole if r[0] == sensor]
        series[str(sensor)] = (
            np.array([x for pair in t for x in pair], dtype=np.int64),
            np.array([x for pair in y for x in pair], dtype=float),
        )
    changes = [(t / NS_PER_S, str(s), f"{before} → {after}") for t, s, before, after in flips]
    return series, changes
