"""A disk-backed FIFO of points waiting to be sent (store and forward).

The gateway appends the points of every cycle here; the forwarder
(:class:`gateway.influx_writer.Forwarder`) reads the oldest ones with
:meth:`PointBuffer.peek`, sends them, and only after the destination acknowledged
them removes them with :meth:`PointBuffer.remove_through`. The buffer is one
SQLite file in WAL mode, so its content survives a restart of the process: reopen
the same file and the same points are there, in the same order.

The buffer is bounded (``max_points``). When an append would overflow it, the
oldest points are dropped — the newest data is the most useful after a long
outage — and that is never silent: the count is logged at WARNING and added to
:attr:`PointBuffer.dropped`, which is kept in the file too.

Row ids increase for ever (SQLite ``AUTOINCREMENT``), so a ``remove_through`` for
a batch taken earlier can never remove points appended later.
"""

from __future__ import annotations

import json
import logging
import sqlite3
import threading
from collections.abc import Iterable
from pathlib import Path

from gateway.timeseries import Point

log = logging.getLogger(__name__)

SCHEMA = """
CREATE TABLE IF NOT EXISTS points (
    id INTEGER PRIMARY KEY AUTOINCREMENT,
    point TEXT NOT NULL
);
CREATE TABLE IF NOT EXISTS meta (
    key TEXT PRIMARY KEY,
    value INTEGER NOT NULL
);
INSERT OR IGNORE INTO meta (key, value) VALUES ('dropped', 0);
"""


class PointBuffer:
    """SQLite (WAL) FIFO of :class:`Point`, bounded to ``max_points``; thread-safe.

    Args:
        path: the database file (created with its folder when missing).
        max_points: the most points kept; older ones are dropped (and counted).
        synchronous: SQLite ``synchronous`` level. ``NORMAL`` (default) survives a
            crash of the process; ``FULL`` also the last commits of a power cut.
    """

    def __init__(self, path: str | Path, max_points: int = 1_000_000, synchronous: str = "NORMAL"):
        if max_points < 1:
            raise ValueError(f"max_points must be at least 1, got {max_points}")
        if synchronous.upper() not in {"OFF", "NORMAL", "FULL", "EXTRA"}:
            raise ValueError(f"unknown SQLite synchronous level {synchronous!r}")
        self.path = Path(path)
        self.path.parent.mkdir(parents=True, exist_ok=True)
        self.max_points = max_points
        self._lock = threading.Lock()
        self._db = sqlite3.connect(self.path, check_same_thread=False, isolation_level=None)
        self._db.execute("PRAGMA journal_mode=WAL")
        self._db.execute(f"PRAGMA synchronous={synchronous.upper()}")
        self._db.executescript(SCHEMA)
        self._count = self._db.execute("SELECT COUNT(*) FROM points").fetchone()[0]
        self._dropped = self._db.execute("SELECT value FROM meta WHERE key='dropped'").fetchone()[0]
        if self._count > max_points:  # reopened with a smaller bound
            with self._lock:
                self._drop_oldest(self._count - max_points)

    # --- writing ------------------------------------------------------------------------
    def append(self, points: Iterable[Point]) -> None:
        """Add points at the end (one transaction); drop the oldest when full."""
        rows = [(json.dumps(p.to_json(), separators=(",", ":")),) for p in points]
        if not rows:
            return
        with self._lock:
            skipped = max(0, len(rows) - self.max_points)
            if skipped:  # more new points than the buffer holds: keep the newest
                rows = rows[skipped:]
            overflow = self._count + len(rows) - self.max_points
            self._db.execute("BEGIN IMMEDIATE")
            try:
                removed = self._delete_oldest(overflow) if overflow > 0 else 0
                self._db.executemany("INSERT INTO points (point) VALUES (?)", rows)
                lost = removed + skipped
                if lost:
                    self._db.execute(
                        "UPDATE meta SET value = value + ? WHERE key='dropped'", (lost,)
                    )
                self._db.execute("COMMIT")
            except BaseException:
                self._db.execute("ROLLBACK")
                raise
            self._count += len(rows) - removed
            if lost:
                self._dropped += lost
                log.warning(
                    "point buffer %s full (%d points): dropped the %d oldest point(s), "
                    "%d dropped in all",
                    self.path,
                    self.max_points,
                    lost,
                    self._dropped,
                )

    def _delete_oldest(self, n: int) -> int:
        cursor = self._db.execute(
            "DELETE FROM points WHERE id IN (SELECT id FROM points ORDER BY id LIMIT ?)", (n,)
        )
        return cursor.rowcount

    def _drop_oldest(self, n: int) -> None:
        self._db.execute("BEGIN IMMEDIATE")
        removed = self._delete_oldest(n)
        self._db.execute("UPDATE meta SET value = value + ? WHERE key='dropped'", (removed,))
        self._db.execute("COMMIT")
        self._count -= removed
        self._dropped += removed
        log.warning(
            "point buffer %s holds more than %d points: dropped the %d oldest",
            self.path,
            self.max_points,
            removed,
        )

    # --- reading ------------------------------------------------------------------------
    def peek(self, n: int) -> list[tuple[int, Point]]:
        """Up to ``n`` of the oldest points with their row ids, oldest first (nothing removed)."""
        with self._lock:
            rows = self._db.execute(
                "SELECT id, point FROM points ORDER BY id LIMIT ?", (n,)
            ).fetchall()
        return [(row_id, Point.from_json(json.loads(text))) for row_id, text in rows]

    def remove_through(self, row_id: int) -> int:
        """Remove every point with a row id ≤ ``row_id`` (a sent batch); return how many."""
        with self._lock:
            cursor = self._db.execute("DELETE FROM points WHERE id <= ?", (row_id,))
            self._count -= cursor.rowcount
            return cursor.rowcount

    def __len__(self) -> int:
        return self._count

    @property
    def dropped(self) -> int:
        """Points dropped because the buffer was full, since the file was created."""
        return self._dropped

    def close(self) -> None:
        with self._lock:
            self._db.close()

    def __enter__(self) -> PointBuffer:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
