"""A long window of a machine from the local store's per-minute history.

A plot is a fixed number of pixel columns wide, so a day (86 400 cycles, 777 600
temperature rows) or a month needs only each column's lowest and highest value. The
per-minute history beside the Parquet parts holds every number's minimum and maximum
per minute, so a window whose columns are whole minutes (its start on a minute) is cut
to exactly the envelope of reading every row: the history for the minutes it covers,
the 1-s rows for the rest (the open period, not yet in the history). The events need
every change of a cycle's write status and link state and every quality flip: those
come from the 1-s rows while they are kept (grouped in DuckDB, only the changes come
back), read only in the 10-minute stretches where the history's write states say one
may begin; once the 1-s rows have aged out, the plots still come from the history.
"""

from __future__ import annotations

import sqlite3
from dataclasses import dataclass, field
from pathlib import Path

import duckdb
import numpy as np

from gateway.outputs.local_store import history_folder, parts_folder, read_window
from gateway.outputs.points import CYCLE_MEASUREMENT, PROBE_MEASUREMENT, TEMPERATURE_MEASUREMENT
from gateway.outputs.store_parts import MINUTE_NS, WRITE_STATE, literal

Series = tuple[np.ndarray, np.ndarray]
#: The numbers the page draws, by measurement.
CYCLE_NUMBERS = (
    "speed_rpm",
    "predicted_um",
    "applied_um",
    "written_cnc",
    "correction_um",
    "interval_um",
)


@dataclass
class HistoryWindow:
    """Per tag set (a cycle's ``tags_extra``: its axis) each cycle number's column
    envelope ``(t_ns, value)``; per sensor its temperatures'; the cycles counted; the
    probes ``(t_ns, error_um)``; the raw cycle rows where a status or link state
    changed, as columns; the quality flips ``(t_ns, sensor, before, after)``."""

    cycle_lines: dict[object, dict[str, Series]]
    temperatures_C: dict[str, Series]
    cycles: dict[object, int]
    probes: Series
    predicted_minutes: dict[object, Series]
    changes: list[list] = field(default_factory=list)
    flips: list[tuple] = field(default_factory=list)


def column_width_ns(span_s: float, columns: int) -> int:
    """Whole minutes a column, at least ``span_s / columns``."""
    return int(-(-int(span_s * 1e9) // (columns * MINUTE_NS))) * MINUTE_NS


def minute_floor(t_ns: int) -> int:
    return t_ns // MINUTE_NS * MINUTE_NS


def _history_files(path: Path, start_ns: int, stop_ns: int) -> tuple[list[Path], int]:
    """The history parts overlapping the window, and the last time any history covers."""
    db = sqlite3.connect(f"file:{path}?mode=ro", uri=True, timeout=5.0)
    try:
        names = db.execute(
            "SELECT name FROM history WHERE last_ns >= ? AND first_ns < ? ORDER BY first_ns",
            (start_ns, stop_ns),
        ).fetchall()
        (covered,) = db.execute("SELECT max(last_ns) FROM history").fetchone()
    finally:
        db.close()
    folder = history_folder(path)
    return [folder / n for (n,) in names], -1 if covered is None else int(covered)


#: The history's columns the page reads: each cycle number's and the temperature's
#: lowest and highest, the probe's and the prediction's mean (the probes' residuals).
#: Materialising these alone (not all 30 count/min/mean/max columns) halves the time
#: a 30-day window takes to gather.
_KEPT = (
    *(f"{n}_{edge}" for n in CYCLE_NUMBERS for edge in ("min", "max")),
    "value_C_min",
    "value_C_max",
    "error_um_mean",
    "predicted_um_mean",
    "write_state_min",
    "write_state_max",
)


def _raw_as_minute(column: str) -> str:
    """A kept history column taken from a 1-s row (a minute of one sample)."""
    if column.startswith("write_state_"):
        return f"{WRITE_STATE} AS {column}"
    return f"{column.rsplit('_', 1)[0]} AS {column}"


def _minutes_sql(
    db: duckdb.DuckDBPyConnection, files: list[Path], machine: str, start_ns: int, covered_ns: int
) -> str:
    """One table of minutes: the history's, then the 1-s rows after ``covered_ns`` as
    minutes of one sample (the same columns). A history file written before the write
    state was kept gives it as NULL (its minutes' states unknown)."""
    numbers = ", ".join(_raw_as_minute(c) for c in _KEPT)
    raw = (
        "SELECT measurement, sensor, quality, tags_extra, time_ns, 1 AS samples, "
        f"{numbers} FROM w WHERE time_ns > {covered_ns}"
    )
    if not files:
        return raw
    source = f"read_parquet([{', '.join(literal(str(f)) for f in files)}], union_by_name = true)"
    present = {row[0] for row in db.execute(f"DESCRIBE SELECT * FROM {source}").fetchall()}
    kept = ", ".join(c if c in present else f"CAST(NULL AS VARCHAR) AS {c}" for c in _KEPT)
    history = (
        f"SELECT measurement, sensor, quality, tags_extra, time_ns, samples, {kept} "
        f"FROM {source} WHERE machine = {literal(machine)} "
        f"AND time_ns >= {start_ns} AND time_ns <= {covered_ns}"
    )
    return f"{history} UNION ALL {raw}"


_COLUMN = "(time_ns - {start}) // {width}"
_LINES = (
    "SELECT {key}, {column} AS k, min(time_ns), max(time_ns), {aggregates}, sum(samples) "
    "FROM m WHERE measurement = '{measurement}' GROUP BY ALL ORDER BY ALL"
)
#: A cycle row whose write status or link state differs from its series' row before.
_CHANGES = (
    "SELECT time_ns, {fields}, write_status, link_errors, tags_extra FROM (SELECT *, "
    "lag(write_status) OVER s AS before, lag(coalesce(link_errors, 0) > 0) OVER s AS down, "
    "row_number() OVER s AS n FROM w WHERE measurement = '{measurement}' AND {where} "
    "WINDOW s AS (PARTITION BY tags_extra ORDER BY time_ns)) WHERE n = 1 "
    "OR before IS DISTINCT FROM write_status OR down <> (coalesce(link_errors, 0) > 0) "
    "ORDER BY time_ns"
)
#: Each 10-minute bucket's write states (status and link down), from the minutes (the
#: history's lowest and highest state of each minute): only buckets where the state
#: changes, and the bucket before each, need the ordered scan above.
BUCKET_NS = 600 * 1_000_000_000
_STATES = (
    "SELECT DISTINCT time_ns // {bucket} AS b, tags_extra, write_state_min, write_state_max "
    "FROM m WHERE measurement = '{measurement}'"
)
#: The same from the 1-s rows, for the minutes of a history written without the states.
_RAW_STATES = (
    "SELECT b, tags_extra, {state} FROM (SELECT DISTINCT time_ns // {bucket} AS b, tags_extra, "
    "write_status, least(coalesce(link_errors, 0), 1) AS link_errors FROM w "
    "WHERE measurement = '{measurement}' AND {where})"
)
_FLIPS = (
    "SELECT time_ns, sensor, before, quality FROM (SELECT time_ns, sensor, quality, "
    "lag(quality) OVER (PARTITION BY sensor ORDER BY time_ns) AS before FROM w "
    "WHERE measurement = '{measurement}' AND sensor IN ({names})) "
    "WHERE before IS NOT NULL AND before <> quality ORDER BY time_ns, sensor"
)


def history_window(
    path: Path, machine: str, start_ns: int, stop_ns: int, width_ns: int
) -> HistoryWindow:
    """The window ``start_ns ≤ t < stop_ns`` (``start_ns`` on a minute) cut to columns
    of ``width_ns`` (whole minutes), from the history and the 1-s rows it lacks."""
    files, covered = _history_files(path, start_ns, stop_ns)
    db = sqlite3.connect(f"file:{path}?mode=ro", uri=True, timeout=5.0)
    try:
        found = read_window(db, parts_folder(path), None, machine, start_ns, stop_ns, "", "")
    finally:
        db.close()
    try:
        minutes = _minutes_sql(found, files, machine, start_ns, covered)
        found.execute(f"CREATE TEMP TABLE m AS {minutes}")
        return _grouped(found, start_ns, width_ns)
    finally:
        found.close()


def _grouped(db: duckdb.DuckDBPyConnection, start_ns: int, width_ns: int) -> HistoryWindow:
    column = _COLUMN.format(start=start_ns, width=width_ns)
    lows = ", ".join(f"min({n}_min), max({n}_max)" for n in CYCLE_NUMBERS)
    cycle_rows = db.execute(
        _LINES.format(
            key="tags_extra", column=column, aggregates=lows, measurement=CYCLE_MEASUREMENT
        )
    ).fetchall()
    temp_rows = db.execute(
        _LINES.format(
            key="sensor",
            column=column,
            aggregates="min(value_C_min), max(value_C_max), count(DISTINCT quality)",
            measurement=TEMPERATURE_MEASUREMENT,
        )
    ).fetchall()
    window = HistoryWindow(
        cycle_lines=_cycle_lines(cycle_rows),
        temperatures_C=_temperatures(temp_rows),
        cycles=_counts(cycle_rows),
        probes=_probes(db),
        predicted_minutes=_predicted_minutes(db),
    )
    fields = ", ".join(CYCLE_NUMBERS)
    where = _changing_buckets(db)
    changes = db.execute(_CHANGES.format(fields=fields, measurement=CYCLE_MEASUREMENT, where=where))
    window.changes = [list(c) for c in zip(*changes.fetchall(), strict=True)]
    flipping = db.execute(
        "SELECT sensor FROM m WHERE measurement = ? GROUP BY sensor "
        "HAVING count(DISTINCT quality) > 1",
        [TEMPERATURE_MEASUREMENT],
    ).fetchall()
    if flipping:
        names = ", ".join(literal(s) for (s,) in flipping)
        query = _FLIPS.format(measurement=TEMPERATURE_MEASUREMENT, names=names)
        window.flips = db.execute(query).fetchall()
    return window


def _changing_buckets(db: duckdb.DuckDBPyConnection) -> str:
    """SQL selecting the cycle rows of the buckets where a series' state may change
    (more than one state in it, or another than the bucket before) and the bucket
    before each: elsewhere the state stays as it was, so no event begins there."""
    states = _bucket_states(db)
    wanted: set[int] = set()
    last: dict[object, set] = {}
    for (tag, bucket), found in sorted(states.items(), key=lambda kv: kv[0][1]):
        if len(found) > 1 or last.get(tag) != found:
            wanted.update((bucket - 1, bucket))
        last[tag] = found
    if not wanted:
        return "FALSE"
    return _bucket_ranges(sorted(wanted))


def _bucket_states(db: duckdb.DuckDBPyConnection) -> dict[tuple[object, int], set]:
    """Each (series, bucket)'s write states, from the minutes; a bucket holding minutes of
    a history written before it kept them is read from its 1-s rows instead."""
    query = _STATES.format(bucket=BUCKET_NS, measurement=CYCLE_MEASUREMENT)
    states: dict[tuple[object, int], set] = {}
    unknown: set[int] = set()
    for bucket, tag, lowest, highest in db.execute(query).fetchall():
        if lowest is None:
            unknown.add(bucket)
        else:
            states.setdefault((tag, bucket), set()).update((lowest, highest))
    if unknown:
        where = _bucket_ranges(sorted(unknown))
        query = _RAW_STATES.format(
            bucket=BUCKET_NS, state=WRITE_STATE, measurement=CYCLE_MEASUREMENT, where=where
        )
        for bucket, tag, state in db.execute(query).fetchall():
            states.setdefault((tag, bucket), set()).add(state)
    return states


#: Up to this many runs of wanted buckets are read as time ranges (each pruned to
#: its own row groups by the Parquet reader); more, as one span and a bucket list.
MAX_RANGES = 64


def _bucket_ranges(buckets: list[int]) -> str:
    """SQL selecting the rows of ``buckets`` (sorted): contiguous runs as time ranges,
    which the Parquet reader prunes on each part's time statistics (a bucket number
    computed from the time, as ``IN`` would test, makes it read every row)."""
    runs: list[list[int]] = []
    for b in buckets:
        if runs and b == runs[-1][1] + 1:
            runs[-1][1] = b
        else:
            runs.append([b, b])
    span = f"time_ns >= {buckets[0] * BUCKET_NS} AND time_ns < {(buckets[-1] + 1) * BUCKET_NS}"
    if len(runs) > MAX_RANGES:
        listed = ", ".join(str(b) for b in buckets)
        return f"({span} AND time_ns // {BUCKET_NS} IN ({listed}))"
    ranges = (
        f"(time_ns >= {first * BUCKET_NS} AND time_ns < {(last + 1) * BUCKET_NS})"
        for first, last in runs
    )
    return "(" + " OR ".join(ranges) + ")"


def _pairs(rows: list, low: int) -> Series:
    """Each column's first time with its lowest value and last time with its highest."""
    t = np.array([(r[2], r[3]) for r in rows], dtype=np.int64).reshape(-1)
    y = np.array([(r[low], r[low + 1]) for r in rows], dtype=float).reshape(-1)
    keep = np.isfinite(y)
    return t[keep], y[keep]


def _by_key(rows: list) -> dict[object, list]:
    keyed: dict[object, list] = {}
    for row in rows:
        keyed.setdefault(row[0], []).append(row)
    return keyed


def _cycle_lines(rows: list) -> dict[object, dict[str, Series]]:
    return {
        key: {n: _pairs(kept, 4 + 2 * i) for i, n in enumerate(CYCLE_NUMBERS)}
        for key, kept in _by_key(rows).items()
    }


def _temperatures(rows: list) -> dict[str, Series]:
    return {str(sensor): _pairs(kept, 4) for sensor, kept in _by_key(rows).items()}


def _counts(rows: list) -> dict[object, int]:
    return {key: int(sum(r[-1] for r in kept)) for key, kept in _by_key(rows).items()}


def _probes(db: duckdb.DuckDBPyConnection) -> Series:
    """Each probe (a minute of the history: its mean at the minute's start)."""
    rows = db.execute(
        "SELECT time_ns, error_um_mean FROM m WHERE measurement = ? ORDER BY time_ns",
        [PROBE_MEASUREMENT],
    ).fetchall()
    return (
        np.array([r[0] for r in rows], dtype=np.int64),
        np.array([r[1] for r in rows], dtype=float),
    )


def _predicted_minutes(db: duckdb.DuckDBPyConnection) -> dict[object, Series]:
    """Per tag set, each minute's mean prediction (the probes' residuals are against it)."""
    rows = db.execute(
        f"SELECT tags_extra, time_ns // {MINUTE_NS} * {MINUTE_NS} AS t, "
        "sum(predicted_um_mean * samples) / sum(samples) FROM m WHERE measurement = ? "
        "AND predicted_um_mean IS NOT NULL GROUP BY ALL ORDER BY ALL",
        [CYCLE_MEASUREMENT],
    ).fetchall()
    return {
        key: (
            np.array([r[1] for r in kept], dtype=np.int64),
            np.array([r[2] for r in kept], dtype=float),
        )
        for key, kept in _by_key(rows).items()
    }
