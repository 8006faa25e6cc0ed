"""A window of temperature points from the local store, cut to per-column envelopes in SQL.

A day of one machine at 1 Hz holds 777 600 temperature rows. Moving each into
Python costs seconds; grouping them in SQLite by plot column and tags returns a few
thousand rows: each group's row count, first and last time, lowest and highest
value. One query per column, each a short walk of the time index sorting the
column's rows by tags (one query grouping the whole day sorts 777 600 rows and
took a third longer). The tags text holds the sensor and its quality, so a group
never mixes two qualities, and a column where a sensor shows a single group holds
a single run of one quality. The few columns that do not (a quality change inside
the column, or rows logged without a value) are read row by row, so the envelope
and every quality change come out exactly as from the full read
(:func:`gateway.web.series.window_envelope` and the change list of
:func:`gateway.web.series.machine_view` without aggregation).
"""

from __future__ import annotations

import json
import sqlite3
from dataclasses import dataclass, field

import numpy as np

from gateway.outputs.points import NS_PER_S, TEMPERATURE_MEASUREMENT

Series = tuple[np.ndarray, np.ndarray]
Change = tuple[float, str, str]

#: One column's groups: rows, rows holding a value, first and last time, lowest and
#: highest value. Only temperature points with a value carry the ``value_C`` key (a
#: number: :mod:`gateway.outputs.points` omits missing and non-finite values), so the
#: key's presence counts the valued rows without parsing the JSON a third time. The
#: index is named: a query per column must walk the time index, never the whole machine.
_COLUMN = (
    "SELECT tags, count(*), sum(instr(fields, '\"value_C\":') > 0), min(time_ns), "
    "max(time_ns), min(fields->>'value_C'), max(fields->>'value_C') "
    "FROM points INDEXED BY points_by_machine_time WHERE measurement = ? AND machine = ? "
    "AND time_ns >= ? AND time_ns < ? GROUP BY tags"
)


@dataclass
class _Sensor:
    """One sensor's groups: tags text → quality, and per column its groups
    ``(rows, valued rows, first ns, last ns, lowest, highest, quality)``."""

    qualities: dict[str, str] = field(default_factory=dict)
    columns: dict[int, list[tuple]] = field(default_factory=dict)

    def valued(self) -> int:
        return sum(g[1] for groups in self.columns.values() for g in groups)


def column_start_ns(k: int, start_ns: int, stop_ns: int, columns: int) -> int:
    """First nanosecond of column ``k``: ``(t - start) * columns // span == k`` from here."""
    return start_ns - (-k * (stop_ns - start_ns) // columns)


def temperature_envelopes(
    db: sqlite3.Connection, machine: str, start_ns: int, stop_ns: int, columns: int
) -> tuple[dict[str, Series], list[Change]]:
    """Per sensor ``(t_ns, value_C)`` cut to the window's column envelope (a series of at
    most ``2 × columns`` valued rows comes back whole), and the quality changes
    ``(Unix s, sensor, "before → after")`` in time order."""
    sensors: dict[str, _Sensor] = {}
    labels: dict[str, tuple[str, str]] = {}
    for k in range(columns):
        lo = column_start_ns(k, start_ns, stop_ns, columns)
        hi = column_start_ns(k + 1, start_ns, stop_ns, columns)
        found = db.execute(_COLUMN, (TEMPERATURE_MEASUREMENT, machine, lo, hi))
        for tags, rows, valued, first, last, low, high in found:
            if tags not in labels:
                parsed = json.loads(tags)
                labels[tags] = (str(parsed.get("sensor")), str(parsed.get("quality")))
            sensor, quality = labels[tags]
            one = sensors.setdefault(sensor, _Sensor())
            one.qualities[tags] = quality
            one.columns.setdefault(k, []).append((rows, valued, first, last, low, high, quality))
    reader = _RowReader(db, machine)
    series: dict[str, Series] = {}
    changes: list[Change] = []
    for name, one in sensors.items():
        if one.valued() <= 2 * columns:
            window = (start_ns, stop_ns)
            t, y, runs = _points_and_runs(reader.rows(one.qualities, *window), keep_all=True)
        else:
            t, y, runs = _sensor_envelope(one, reader, (start_ns, stop_ns, columns))
        series[name] = (np.array(t, dtype=np.int64), np.array(y, dtype=float))
        changes += _changes(name, runs)
    changes.sort(key=lambda c: (c[0], c[1]))
    return series, changes


class _RowReader:
    """Rows of one sensor (its tags texts) in a time range, in time order."""

    def __init__(self, db: sqlite3.Connection, machine: str) -> None:
        self._db, self._machine = db, machine

    def rows(self, qualities: dict[str, str], start_ns: int, stop_ns: int) -> list[tuple]:
        tags = list(qualities)
        marks = ", ".join("?" * len(tags))
        found = self._db.execute(
            "SELECT time_ns, tags, fields->>'value_C' FROM points WHERE measurement = ? "
            f"AND machine = ? AND tags IN ({marks}) AND time_ns >= ? AND time_ns < ? "
            "ORDER BY time_ns",
            (TEMPERATURE_MEASUREMENT, self._machine, *tags, start_ns, stop_ns),
        ).fetchall()
        return [(t, qualities[g], v) for t, g, v in found]


def _points_and_runs(rows: list[tuple], keep_all: bool) -> tuple[list, list, list]:
    """Rows ``(t_ns, quality, value)`` → their valued points (all of them, or the
    column's first/lowest and last/highest) and the quality at each row."""
    valued = [(t, v) for t, _, v in rows if v is not None]
    runs = [(t, q) for t, q, _ in rows]
    if keep_all or not valued:
        return [t for t, _ in valued], [v for _, v in valued], runs
    values = [v for _, v in valued]
    return [valued[0][0], valued[-1][0]], [min(values), max(values)], runs


def _sensor_envelope(
    one: _Sensor, reader: _RowReader, window: tuple[int, int, int]
) -> tuple[list, list, list]:
    """Two points per column (first time with the lowest value, last time with the
    highest) and the runs of quality; a column with more than one group, or with rows
    without a value, is read row by row."""
    start_ns, stop_ns, columns = window
    t: list[int] = []
    y: list[float] = []
    runs: list[tuple[int, str]] = []
    for k in sorted(one.columns):
        groups = one.columns[k]
        rows, valued, first, last, low, high, quality = groups[0]
        if len(groups) == 1 and valued == rows:
            t += [first, last]
            y += [low, high]
            runs.append((first, quality))
            continue
        lo = column_start_ns(k, start_ns, stop_ns, columns)
        hi = column_start_ns(k + 1, start_ns, stop_ns, columns)
        bt, by, bruns = _points_and_runs(reader.rows(one.qualities, lo, hi), keep_all=False)
        t += bt
        y += by
        runs += bruns
    return t, y, runs


def _changes(sensor: str, runs: list[tuple[int, str]]) -> list[Change]:
    found = []
    before = None
    for time_ns, quality in runs:
        if before is not None and before != quality:
            found.append((time_ns / NS_PER_S, sensor, f"{before} → {quality}"))
        before = quality
    return found
