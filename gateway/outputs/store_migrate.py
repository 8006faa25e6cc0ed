"""Converting a local store of the JSON-per-point layout to typed parts, every point counted.

The earlier layout kept each point as a row ``points(measurement, machine, tags,
time_ns, fields)`` with JSON text. On first open the rows are read in chunks of
``CHUNK_ROWS`` (by rowid); each chunk becomes one Parquet part, registered in the
transaction that deletes the chunk's old rows and adds it to the ``migrated`` count,
so a crash at any step resumes where it stopped and never counts a point twice.
The old table goes when it is empty; the log says how many points were moved.
"""

from __future__ import annotations

import json
import logging
import sqlite3
from collections.abc import Callable

from gateway.outputs.points import Point
from gateway.outputs.store_rows import Row, row_of

log = logging.getLogger(__name__)

CHUNK_ROWS = 200_000


def _has_old_table(db: sqlite3.Connection) -> bool:
    found = db.execute(
        "SELECT 1 FROM sqlite_master WHERE type = 'table' AND name = 'points'"
    ).fetchone()
    return found is not None


def _count(db: sqlite3.Connection, name: str) -> int:
    row = db.execute("SELECT value FROM counters WHERE name = ?", (name,)).fetchone()
    return 0 if row is None else int(row[0])


def migrate_json_points(db: sqlite3.Connection, write_part: Callable[[list[Row]], None]) -> int:
    """Move every row of the old ``points`` table into parts (``write_part`` writes and
    registers one); the points moved in all, over every start that took part."""
    if not _has_old_table(db):
        return _count(db, "migrated")
    total = db.execute("SELECT COUNT(*) FROM points").fetchone()[0]
    log.warning("local store: converting %d point(s) of the JSON layout to typed parts", total)
    while True:
        chunk = db.execute(
            "SELECT rowid, measurement, tags, time_ns, fields FROM points ORDER BY rowid LIMIT ?",
            (CHUNK_ROWS,),
        ).fetchall()
        if not chunk:
            break
        rows = [
            row_of(Point(m, json.loads(tags), json.loads(fields), int(t)))
            for _, m, tags, t, fields in chunk
        ]
        db.execute("BEGIN IMMEDIATE")
        try:
            write_part(rows)
            db.execute("DELETE FROM points WHERE rowid <= ?", (chunk[-1][0],))
            db.execute(
                "INSERT INTO counters VALUES ('migrated', ?) "
                "ON CONFLICT (name) DO UPDATE SET value = value + excluded.value",
                (len(rows),),
            )
            db.execute("COMMIT")
        except BaseException:
            db.execute("ROLLBACK")
            raise
    db.execute("DROP TABLE points")
    try:
        db.execute("VACUUM")  # give the old rows' pages back to the disk (a small copy now)
    except sqlite3.OperationalError as exc:  # a full disk: the pages are reused instead
        log.warning("local store: the converted file keeps its size (%s)", exc)
    migrated = _count(db, "migrated")
    log.warning("local store: %d point(s) converted to typed parts", migrated)
    return migrated
