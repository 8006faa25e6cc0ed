"""The local store's earlier layout (JSON text per point in SQLite), kept to make such stores.

Tests of the conversion (:mod:`gateway.outputs.store_migrate`) and the side-by-side
benchmark (``benchmarks/store_engines.py``) write stores in this layout with it. What
follows is its description as it shipped.

The embedded time-series store: points in one SQLite file, no server needed.

The default destination of the gateway's time series when no InfluxDB is
configured, and a source for :func:`gateway.offline.export.export_runs`. It keeps
InfluxDB's identity rule: a point is identified by measurement, tags and time, so
writing the same point again stores it once (its fields are merged, a field
written again takes the new value, as InfluxDB does).

The store is one bounded SQLite ring (:mod:`gateway.outputs.sqlite_ring`): by age, points older than
``retention_s`` are deleted by :meth:`LocalStore.enforce_retention` (the gateway
calls it every ``logging.retention_interval_s``); by size, the file never grows past
``max_bytes`` — a write that meets the cap first deletes the oldest points. A
write that fails because the disk is full is dropped and counted
(:attr:`LocalStore.dropped`), logged once when it starts and once when writes
succeed again, and never raised: compensation does not depend on its log.

Write cost: the gateway writes each machine's cycle (about 10 points) as one
transaction. Each point goes to the end of its own series in the primary key and the
machine/time index, so one write dirties many pages, each written whole to the WAL and
again at the checkpoint (about 40 MB/s for 200 machines, 0.64 MB/s of points). The CPU
of a second of 200 machines rises about 40 % from a new file to 0.5 GB, then stays flat
to 4 GB (``benchmarks/local_store_growth.py``, docs/benchmarks.md). The connection keeps
SQLite's defaults: a 64 MB page cache or memory-mapped reads changed it by less than the
spread between runs (the operating system already holds the file's pages), and a larger
WAL checkpoint made it dearer. The schema stays too: a WITHOUT ROWID table was no
cheaper, and the time index (8–23 % of the cost) is how retention and the size cap find
the oldest points.
"""

from __future__ import annotations

import functools
import json
import logging
import time
from collections.abc import Iterable
from pathlib import Path

from gateway.outputs.points import Point
from gateway.outputs.sqlite_ring import SqliteRing

log = logging.getLogger(__name__)

DELETE_CHUNK_ROWS = 5000  # rows per DELETE: keeps one retention step short (ms)

SCHEMA = """
CREATE TABLE IF NOT EXISTS points (
    measurement TEXT NOT NULL,
    machine TEXT NOT NULL,
    tags TEXT NOT NULL,
    time_ns INTEGER NOT NULL,
    fields TEXT NOT NULL,
    PRIMARY KEY (measurement, machine, tags, time_ns)
);
CREATE INDEX IF NOT EXISTS points_by_machine_time ON points (measurement, machine, time_ns);
CREATE INDEX IF NOT EXISTS points_by_time ON points (time_ns);
"""


def _tags_text(tags: dict[str, str]) -> str:
    return json.dumps(dict(sorted(tags.items())), separators=(",", ":"), ensure_ascii=False)


class JsonLocalStore:
    """SQLite (WAL) table of points, indexed on (measurement, machine, time_ns).

    Args:
        path: the database file (created with its folder when missing).
        synchronous: SQLite ``synchronous`` level.
        max_bytes: the largest the file may grow (None: unbounded); at the cap the
            oldest points make room for the newest.
        retention_s: the oldest point :meth:`enforce_retention` keeps, s (None: all).
        set_aside_damaged: a file SQLite cannot read is renamed aside and a new one
            started (the gateway); False refuses it with a ``ValueError`` (``export``).
    """

    def __init__(
        self,
        path: str | Path,
        synchronous: str = "NORMAL",
        max_bytes: int | None = None,
        retention_s: float | None = None,
        set_aside_damaged: bool = True,
    ) -> None:
        self._ring = SqliteRing(
            path,
            SCHEMA,
            label="local store",
            cannot="cannot store points",
            synchronous=synchronous,
            max_bytes=max_bytes,
            set_aside_damaged=set_aside_damaged,
        )
        self.path = self._ring.path
        self.set_aside_as = self._ring.set_aside_as
        self.max_bytes = max_bytes
        self.retention_s = retention_s
        self.dropped = 0  # points not stored because the disk was full
        self.expired = 0  # points deleted for age
        self.evicted = 0  # points deleted to stay within max_bytes
        self._db = self._ring.db
        self._lock = self._ring.lock

    def write(self, points: Iterable[Point]) -> bool:
        """Store points (one transaction); a point already stored has its fields merged.

        Returns False when the points could not be stored (disk full): they are
        counted in :attr:`dropped` and logged, nothing is raised. At the file's own
        cap the oldest points make room; a full disk is waited out (the pages freed
        are reused once space returns).
        """
        rows = [
            (
                p.measurement,
                p.tags.get("machine", ""),
                _tags_text(p.tags),
                p.time_ns,
                json.dumps(p.fields, separators=(",", ":"), ensure_ascii=False),
            )
            for p in points
        ]
        if not rows:
            return True
        return self._ring.write(
            lambda: self._insert(rows), self._evict_oldest, self._count_dropped, len(rows)
        )

    def _count_dropped(self, n: int) -> int:
        self.dropped += n
        return self.dropped

    def _insert(self, rows: list[tuple[str, str, str, int, str]]) -> None:
        with self._ring.transaction() as db:
            db.executemany(
                "INSERT INTO points (measurement, machine, tags, time_ns, fields) "
                "VALUES (?, ?, ?, ?, ?) "
                "ON CONFLICT (measurement, machine, tags, time_ns) "
                "DO UPDATE SET fields = json_patch(fields, excluded.fields)",
                rows,
            )

    def _evict_oldest(self) -> int:
        """Delete the oldest chunk of points (lock held); how many went."""
        removed = self._db.execute(
            "DELETE FROM points WHERE rowid IN (SELECT rowid FROM points ORDER BY time_ns LIMIT ?)",
            (DELETE_CHUNK_ROWS,),
        ).rowcount
        self.evicted += removed
        return removed

    def query(
        self,
        measurement: str,
        machine: str | None = None,
        start_ns: int | None = None,
        stop_ns: int | None = None,
    ) -> list[Point]:
        """Points of ``measurement`` (of ``machine``), ``start_ns ≤ time < stop_ns``, by time."""
        sql = "SELECT tags, fields, time_ns FROM points WHERE measurement = ?"
        args: list[object] = [measurement]
        if machine is not None:
            sql += " AND machine = ?"
            args.append(machine)
        if start_ns is not None:
            sql += " AND time_ns >= ?"
            args.append(int(start_ns))
        if stop_ns is not None:
            sql += " AND time_ns < ?"
            args.append(int(stop_ns))
        sql += " ORDER BY time_ns, tags"
        with self._lock:
            rows = self._db.execute(sql, args).fetchall()
        return [
            Point(measurement, json.loads(tags), json.loads(fields), time_ns)
            for tags, fields, time_ns in rows
        ]

    def machines(self) -> list[str]:
        with self._lock:
            rows = self._db.execute("SELECT DISTINCT machine FROM points ORDER BY machine")
            return [machine for (machine,) in rows.fetchall() if machine]

    def delete_before(self, time_ns: int, limit: int | None = None) -> int:
        """Remove points older than ``time_ns`` (retention), at most ``limit``; return how many."""
        with self._lock:
            return self._delete_before(time_ns, limit)

    def _delete_before(self, time_ns: int, limit: int | None) -> int:
        if limit is None:
            sql, args = "DELETE FROM points WHERE time_ns < ?", (time_ns,)
        else:
            sql = (
                "DELETE FROM points WHERE rowid IN (SELECT rowid FROM points "
                "WHERE time_ns < ? ORDER BY time_ns LIMIT ?)"
            )
            args = (time_ns, limit)
        return self._db.execute(sql, args).rowcount

    def enforce_retention(self, now_ns: int | None = None, budget_s: float = 0.2) -> int:
        """Delete points past ``retention_s``, then the oldest while over ``max_bytes``.

        Works in chunks for at most about ``budget_s`` (it runs between compensation
        cycles); what is left is taken on the next call. Returns the points deleted.
        A full disk makes it do nothing (and nothing is raised).
        """
        now_ns = time.time_ns() if now_ns is None else now_ns
        expire = None
        if self.retention_s is not None:
            cutoff = now_ns - round(self.retention_s * 1e9)
            expire = functools.partial(self._expire_chunk, cutoff)
        deleted = self._ring.enforce(
            expire, lambda: self._ring.make_room(self._evict_oldest), budget_s
        )
        if deleted:
            log.info("local store %s: retention deleted %d old point(s)", self.path, deleted)
        return deleted

    def _expire_chunk(self, cutoff_ns: int) -> tuple[int, bool]:
        """Delete a chunk of points older than ``cutoff_ns``: how many, and whether more may be."""
        n = self._delete_before(cutoff_ns, DELETE_CHUNK_ROWS)
        self.expired += n
        return n, n >= DELETE_CHUNK_ROWS

    def used_bytes(self) -> int:
        """Bytes of the file in use (the quantity ``max_bytes`` bounds)."""
        return self._ring.used_bytes()

    def __len__(self) -> int:
        with self._lock:
            return self._db.execute("SELECT COUNT(*) FROM points").fetchone()[0]

    def close(self) -> None:
        self._ring.close()

    def __enter__(self) -> JsonLocalStore:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
