"""A disk-backed FIFO of points waiting to be sent (store and forward).

The gateway appends the points of every cycle here; the forwarder
(:class:`gateway.outputs.influx.Forwarder`) reads the oldest ones with
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

Besides ``max_points`` the buffer is one bounded SQLite ring (:mod:`gateway.outputs.sqlite_ring`):
the file never grows past ``max_bytes`` (an append that meets the cap drops the
oldest points first), and :meth:`PointBuffer.enforce_retention` drops points older
than ``retention_s``. Every point lost either way is counted in ``dropped``. When
the disk itself is full an append is dropped and counted, logged once when it
starts and once when appends succeed again, and never raised into the loop.
"""

from __future__ import annotations

import functools
import json
import logging
import sqlite3
import time
from collections.abc import Iterable
from pathlib import Path

from gateway.outputs.points import Point
from gateway.outputs.sqlite_ring import SqliteRing, is_out_of_space

log = logging.getLogger(__name__)

DELETE_CHUNK_ROWS = 5000  # rows per DELETE: keeps one retention step short (ms)

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
        max_bytes: the largest the file may grow (None: unbounded).
        retention_s: the oldest point :meth:`enforce_retention` keeps, s (None: all).
    """

    def __init__(
        self,
        path: str | Path,
        max_points: int = 1_000_000,
        synchronous: str = "NORMAL",
        max_bytes: int | None = None,
        retention_s: float | None = None,
    ):
        if max_points < 1:
            raise ValueError(f"max_points must be at least 1, got {max_points}")
        self.max_points = max_points
        self.max_bytes = max_bytes
        self.retention_s = retention_s
        self._unrecorded = 0  # dropped while the file could not be written
        self._removed_through = 0  # sent points whose removal the full disk refused …
        self._hidden = 0  # … and how many they are
        counted: dict[str, int] = {}

        def inspect(db: sqlite3.Connection) -> None:
            counted["points"] = db.execute("SELECT COUNT(*) FROM points").fetchone()[0]
            dropped = db.execute("SELECT value FROM meta WHERE key='dropped'").fetchone()
            counted["dropped"] = dropped[0]

        self._ring = SqliteRing(
            path,
            SCHEMA,
            label="point buffer",
            cannot="cannot keep points",
            synchronous=synchronous,
            max_bytes=max_bytes,
            inspect=inspect,
        )
        self.path = self._ring.path
        self.set_aside_as = self._ring.set_aside_as
        self._db = self._ring.db
        self._lock = self._ring.lock
        self._count, self._dropped = counted["points"], counted["dropped"]
        if self._count > max_points:  # reopened with a smaller bound
            with self._lock:
                self._drop_oldest(self._count - max_points)

    # --- writing ------------------------------------------------------------------------
    def append(self, points: Iterable[Point]) -> bool:
        """Add points at the end (one transaction); drop the oldest when full.

        Returns False when the points could not be kept (the disk is full): they
        are counted in :attr:`dropped` and logged, nothing is raised.
        """
        rows = [(json.dumps(p.to_json(), separators=(",", ":")),) for p in points]
        if not rows:
            return True
        return self._ring.write(
            lambda: self._append(rows), self._make_room, self._count_lost, len(rows)
        )

    def _append(self, rows: list[tuple[str]]) -> None:
        skipped = max(0, len(rows) - self.max_points)
        if skipped:  # more new points than the buffer holds: keep the newest
            rows = rows[skipped:]
        overflow = self._count + len(rows) - self.max_points
        with self._ring.transaction() as db:
            removed = self._delete_oldest(overflow) if overflow > 0 else 0
            db.executemany("INSERT INTO points (point) VALUES (?)", rows)
            lost = removed + skipped
            recorded = lost + self._unrecorded
            if recorded:
                db.execute("UPDATE meta SET value = value + ? WHERE key='dropped'", (recorded,))
        self._unrecorded = 0
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

    def _count_lost(self, n: int) -> int:
        """Count ``n`` points the full disk refused (written to the file's count later)."""
        self._dropped += n
        self._unrecorded += n
        return self._dropped

    def _make_room(self) -> int:
        """Drop the oldest chunk at the size cap (lock held, counted); how many went."""
        return self._drop_oldest(min(DELETE_CHUNK_ROWS, self._count), reason="at its size cap")

    def _delete_oldest(self, n: int) -> int:
        cursor = self._db.execute(
            "DELETE FROM points WHERE id IN (SELECT id FROM points ORDER BY id LIMIT ?)", (n,)
        )
        return cursor.rowcount

    def _drop_oldest(self, n: int, reason: str = "") -> int:
        if n <= 0:
            return 0
        with self._ring.transaction() as db:
            removed = self._delete_oldest(n)
            db.execute("UPDATE meta SET value = value + ? WHERE key='dropped'", (removed,))
        self._count -= removed
        self._dropped += removed
        log.warning(
            "point buffer %s %s: dropped the %d oldest point(s), %d dropped in all",
            self.path,
            reason or f"holds more than {self.max_points} points",
            removed,
            self._dropped,
        )
        return removed

    def enforce_retention(self, now_ns: int | None = None, budget_s: float = 0.2) -> int:
        """Drop points older than ``retention_s``, then the oldest while over ``max_bytes``.

        Points are appended in time order, so the too-old ones are at the head of the
        FIFO. Works in chunks for about ``budget_s`` at most; returns the points dropped
        (counted in :attr:`dropped`). A full disk makes it do nothing.
        """
        now_ns = time.time_ns() if now_ns is None else now_ns
        expire = None
        if self.retention_s is not None:
            expire = functools.partial(self._expire_chunk, now_ns - round(self.retention_s * 1e9))
        return self._ring.enforce(
            expire,
            lambda: self._drop_oldest(min(DELETE_CHUNK_ROWS, self._count), "over size"),
            budget_s,
        )

    def _expire_chunk(self, cutoff_ns: int) -> tuple[int, bool]:
        """Drop the head's points older than ``cutoff_ns`` (one chunk): how many, and
        whether more may be."""
        head = self._db.execute(
            "SELECT id, json_extract(point, '$.ns') FROM points ORDER BY id LIMIT ?",
            (DELETE_CHUNK_ROWS,),
        ).fetchall()
        old = 0
        for _, ns in head:
            if ns >= cutoff_ns:
                break
            old += 1
        n = self._drop_oldest(old, reason="retention (age)")
        return n, bool(head) and old == len(head)

    def used_bytes(self) -> int:
        """Bytes of the file in use (the quantity ``max_bytes`` bounds)."""
        return self._ring.used_bytes()

    # --- reading ------------------------------------------------------------------------
    def peek(self, n: int) -> list[tuple[int, Point]]:
        """Up to ``n`` of the oldest points with their row ids, oldest first (nothing removed)."""
        with self._lock:
            rows = self._db.execute(
                "SELECT id, point FROM points WHERE id > ? ORDER BY id LIMIT ?",
                (self._removed_through, n),
            ).fetchall()
        return [(row_id, Point.from_json(json.loads(text))) for row_id, text in rows]

    def remove_through(self, row_id: int) -> int:
        """Remove every point with a row id ≤ ``row_id`` (a sent batch); return how many.

        When the full disk refuses the delete, the points are hidden from
        :meth:`peek` (they were sent) and removed by a later call.
        """
        with self._lock:
            through = max(row_id, self._removed_through)
            try:
                cursor = self._db.execute("DELETE FROM points WHERE id <= ?", (through,))
            except sqlite3.Error as exc:
                if not is_out_of_space(exc):
                    raise
                hidden = self._db.execute(
                    "SELECT COUNT(*) FROM points WHERE id > ? AND id <= ?",
                    (self._removed_through, through),
                ).fetchone()[0]
                self._removed_through = through
                self._hidden += hidden
                self._count -= hidden
                return hidden
            removed = cursor.rowcount - self._hidden
            self._removed_through = self._hidden = 0
            self._count -= removed
            return removed

    def __len__(self) -> int:
        return self._count

    @property
    def dropped(self) -> int:
        """Points dropped because the buffer was full, since the file was created."""
        return self._dropped

    def close(self) -> None:
        self._ring.close()

    def __enter__(self) -> PointBuffer:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
