"""The local store's closed periods: immutable Parquet (zstd) files, written and read by DuckDB.

A part holds the typed rows (:mod:`gateway.outputs.store_rows`) of one closed period,
sorted by measurement, machine, sensor and time, so each column compresses to a few
bytes per value and a machine's rows are contiguous (DuckDB skips the row groups of
the others from their statistics). A part is written to a temporary name, flushed to
the disk and renamed, so a reader never sees half a file and a crash leaves at most a
temporary file, which the next start removes. Any process may read the parts while
the gateway writes new ones: they never change once named.
"""

from __future__ import annotations

import contextlib
import os
from collections.abc import Sequence
from pathlib import Path

import duckdb
import numpy as np

from gateway.outputs.store_rows import COLUMNS, FLOAT_FIELDS, INT_FIELDS, Row

#: Rows per Parquet row group: a machine-day at 1 Hz spans a few groups.
ROW_GROUP_ROWS = 100_000
_FLOATS = frozenset(FLOAT_FIELDS)
_INTS = frozenset(INT_FIELDS)


def _typed(column: str) -> str:
    """The SQL that turns a scanned numpy column back into its typed, nullable column."""
    if column in _FLOATS:
        return f"CASE WHEN isnan({column}) THEN NULL ELSE {column} END AS {column}"
    if column in _INTS:
        return f"CAST(CASE WHEN isnan({column}) THEN NULL ELSE {column} END AS BIGINT) AS {column}"
    if column == "time_ns":
        return "CAST(time_ns AS BIGINT) AS time_ns"
    return f"CAST({column} AS VARCHAR) AS {column}"


TYPED_SELECT = ", ".join(_typed(c) for c in COLUMNS)
SORT = "measurement, machine, sensor, quality, regime, model_id, tags_extra, time_ns"
ORDERED = "__ordered__"  # a key of columns already in SORT's order (no sort needed)


def arrays_of(rows: Sequence[Row]) -> dict[str, np.ndarray]:
    """Rows as one numpy array per column (NULL numbers as NaN), for DuckDB to scan."""
    columns = list(zip(*rows, strict=True)) if rows else [()] * len(COLUMNS)
    arrays = {}
    for name, values in zip(COLUMNS, columns, strict=True):
        if name == "time_ns":
            arrays[name] = np.array(values, dtype=np.int64)
        elif name in _FLOATS or name in _INTS:
            arrays[name] = np.array(values, dtype=float)
        else:
            arrays[name] = np.array(values, dtype=object)
    return arrays


def write_part(rows: Sequence[Row] | dict[str, np.ndarray], path: Path) -> int:
    """Write ``rows`` (or their columns) as the Parquet file ``path`` (atomically,
    flushed); its size in bytes. On failure (a full disk) nothing is left behind."""
    batch = dict(rows) if isinstance(rows, dict) else arrays_of(rows)
    ordered = batch.pop(ORDERED, None) is not None  # already in the part's order
    sql = f"SELECT {TYPED_SELECT} FROM batch" + ("" if ordered else f" ORDER BY {SORT}")
    _copy(sql, path, f"ROW_GROUP_SIZE {ROW_GROUP_ROWS}", batch)
    return path.stat().st_size


def _copy(sql: str, path: Path, options: str, batch: dict[str, np.ndarray] | None = None) -> None:
    """``COPY (sql) TO`` a temporary file, flushed and renamed ``path``; ``batch`` is the
    table the SQL may name (DuckDB finds it by name among this frame's locals). A
    failure (a full disk) removes the temporary file, so none piles up."""
    tmp = path.with_name(path.name + ".tmp")
    db = duckdb.connect()
    try:
        db.execute("SET threads = 1")
        db.execute(f"COPY ({sql}) TO '{tmp}' (FORMAT parquet, COMPRESSION zstd, {options})")
        with tmp.open("rb+") as stream:
            os.fsync(stream.fileno())
        tmp.replace(path)
        sync_folder(path.parent)
    except BaseException:
        with contextlib.suppress(OSError):
            tmp.unlink()
        raise
    finally:
        db.close()


def _summary(path: Path) -> tuple[int, int | None, int | None]:
    """Rows, first and last time of a written part."""
    db = duckdb.connect()
    try:
        found = db.execute(
            f"SELECT count(*), min(time_ns), max(time_ns) FROM read_parquet('{path}')"
        ).fetchone()
        assert found is not None  # an aggregate always has its one row
        rows, first, last = found
    finally:
        db.close()
    return int(rows), first, last


def sync_folder(folder: Path) -> None:
    """Flush a folder's entries (a rename or removal) to the disk."""
    fd = os.open(folder, os.O_RDONLY)
    try:
        os.fsync(fd)
    finally:
        os.close(fd)


def remove_strays(folder: Path, named: set[str]) -> int:
    """Delete files in ``folder`` no registry names (a crash's leftovers); how many."""
    removed = 0
    for path in folder.glob("*"):
        if path.name not in named:
            with contextlib.suppress(FileNotFoundError):
                path.unlink()
            removed += 1
    return removed


def literal(value: object) -> str:
    """``value`` (text or integer) as an SQL literal."""
    if isinstance(value, int):
        return str(int(value))
    return "'" + str(value).replace("'", "''") + "'"


def scan(
    files: Sequence[Path],
    staged: Sequence[Row] | dict[str, np.ndarray],
    where: str,
    select: str,
    order: str,
) -> duckdb.DuckDBPyConnection:
    """A DuckDB connection holding the view ``w``: the rows of the parts ``files`` and
    the ``staged`` rows that meet ``where`` (SQL with literals). With ``select`` it has
    also executed ``SELECT select FROM w`` ordered by ``order``, to fetch from; the
    caller runs any other query on ``w`` and closes it."""
    staged_batch = staged if isinstance(staged, dict) else arrays_of(staged)  # noqa: F841
    db = duckdb.connect()
    try:
        db.execute("SET threads = 1")
        db.execute("SET parquet_metadata_cache = true")
        db.execute(f"CREATE TEMP TABLE staged AS SELECT {TYPED_SELECT} FROM staged_batch")
        sources = ["SELECT * FROM staged"]
        if files:
            listed = ", ".join(literal(str(f)) for f in files)
            sources.append(f"SELECT {', '.join(COLUMNS)} FROM read_parquet([{listed}])")
        union = " UNION ALL ".join(sources)
        db.execute(f"CREATE TEMP VIEW w AS SELECT * FROM ({union}) WHERE {where}")
        if select:
            db.execute(f"SELECT {select} FROM w" + (f" ORDER BY {order}" if order else ""))
    except BaseException:
        db.close()
        raise
    return db


def trim_part(source: Path, path: Path, from_ns: int) -> tuple[int, int, int, int]:
    """Write the rows of part ``source`` at or after ``from_ns`` as the part ``path``
    (atomically, flushed): its rows, first and last time, and size in bytes."""
    sql = f"SELECT * FROM read_parquet('{source}') WHERE time_ns >= {int(from_ns)} ORDER BY {SORT}"
    _copy(sql, path, f"ROW_GROUP_SIZE {ROW_GROUP_ROWS}")
    rows, first, last = _summary(path)
    return rows, int(first or 0), int(last or 0), path.stat().st_size


#: The per-minute history of a part: count, lowest, mean and highest of every number.
MINUTE_NS = 60_000_000_000
_KEYS = "measurement, machine, sensor, quality, regime, model_id, tags_extra"
_AGGREGATES = ", ".join(
    f"min({f}) AS {f}_min, avg({f}) AS {f}_mean, max({f}) AS {f}_max"
    for f in (*FLOAT_FIELDS, *INT_FIELDS)
)
#: A cycle row's write state as one text: its write status (NULL kept apart from any
#: text) and whether a source was failing. The history keeps each minute's lowest and
#: highest (``write_state_min``, ``_max``): equal where the state held all minute, so a
#: reader finds the minutes where it changed without reading every row.
WRITE_STATE = (
    "(CASE WHEN write_status IS NULL THEN 'n' ELSE 's' || write_status END) || "
    "(CASE WHEN coalesce(link_errors, 0) > 0 THEN '|down' ELSE '|up' END)"
)
HISTORY_SELECT = (
    f"SELECT {_KEYS}, time_ns // {MINUTE_NS} * {MINUTE_NS} AS time_ns, "
    f"count(*) AS samples, {_AGGREGATES}, "
    f"min({WRITE_STATE}) AS write_state_min, max({WRITE_STATE}) AS write_state_max"
)


def write_history(part: Path, path: Path) -> tuple[int, int]:
    """Write the per-minute history of part ``part`` as the Parquet file ``path``
    (atomically, flushed): its rows and size in bytes."""
    sql = f"{HISTORY_SELECT} FROM read_parquet('{part}') GROUP BY ALL ORDER BY {SORT}"
    _copy(sql, path, f"ROW_GROUP_SIZE {ROW_GROUP_ROWS}")
    return _summary(path)[0], path.stat().st_size


def read_history(
    files: Sequence[Path],
    measurement: str,
    machine: str | None,
    start_ns: int | None,
    stop_ns: int | None,
) -> list[dict[str, object]]:
    """The history rows of ``files`` for one measurement (and machine), by time (a file
    written before a column was added gives it as None)."""
    if not files:
        return []
    where: list[str] = ["measurement = ?"]
    params: list[object] = [measurement]
    for clause, value in (("machine = ?", machine), ("time_ns >= ?", start_ns)):
        if value is not None:
            where.append(clause)
            params.append(value)
    if stop_ns is not None:
        where.append("time_ns < ?")
        params.append(stop_ns)
    listed = ", ".join("'" + str(f).replace("'", "''") + "'" for f in files)
    db = duckdb.connect()
    try:
        found = db.execute(
            f"SELECT * FROM read_parquet([{listed}], union_by_name = true) "
            f"WHERE {' AND '.join(where)} "
            "ORDER BY time_ns, machine, sensor, quality",
            params,
        )
        names = [d[0] for d in found.description]
        return [dict(zip(names, row, strict=True)) for row in found.fetchall()]
    finally:
        db.close()


def merge_parts(sources: Sequence[Path], path: Path) -> int:
    """Write the rows of ``sources`` as one part ``path`` (atomically, flushed), sorted
    as a part is: a day in one file compresses better than in 144. Its size in bytes."""
    listed = ", ".join(literal(str(f)) for f in sources)
    _copy(
        f"SELECT * FROM read_parquet([{listed}]) ORDER BY {SORT}",
        path,
        f"ROW_GROUP_SIZE {ROW_GROUP_ROWS}",
    )
    return path.stat().st_size
