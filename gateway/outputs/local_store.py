"""The embedded time-series store: typed columns, compressed, no server needed.

The default destination of the gateway's time series when no InfluxDB is
configured, and a source for :func:`gateway.offline.export.export_runs` and the
console. It keeps InfluxDB's identity rule: a point is identified by measurement,
tags and time, so writing the same point again stores it once (its fields are
merged, a field written again takes the new value, as InfluxDB does) — within the
open period; a point re-sent after its period was closed is stored again.

Layout (one row per point, typed columns: :mod:`gateway.outputs.store_rows`):

* the **open period** — the last ``PART_S`` seconds and a ``LATE_S`` margin — lives
  in append-only segment files in ``<file>.open/`` (:mod:`gateway.outputs.store_log`),
  one per 10-minute period: each commit appends one compact, CRC-framed record and
  flushes it to the disk before the next, so a SIGKILL or a power cut loses at most
  the points not yet committed (the gateway commits once a second, off the event
  loop: ``commit_interval_s``), and a record cut short is never read; a second costs
  about what it stores (1.8 bytes written per byte kept, parts and history
  included, against 140-170 with the period's rows in SQLite's WAL);
* each **closed period** is compacted into one immutable Parquet (zstd) file in
  ``<file>.parts/`` (:mod:`gateway.outputs.store_parts`), 1.3–1.8 bytes a value measured,
  registered in the SQLite file (``points.sqlite``: the registry of parts) in one
  transaction with the names of the segments it came from, which are removed after
  it (a crash before leaves an unregistered part, after it listed segments: both
  removed at the next start, and readers skip listed segments).
  The parts of a closed day are merged into one when they are small (a few machines:
  :meth:`LocalStore.merge_days`; a large fleet's parts compress as well alone);
  each part has its per-minute history beside it (``<file>.history/``: count, min,
  mean and max of every number), kept ``history_retention_s`` and dropped last at
  the size cap. Readers (``export``, the console's worker process) take the list of parts and the
  open rows from one SQLite snapshot and read the parts with DuckDB: any process may
  read while the gateway writes (the parts are listed again after the segments are
  read: a period closed meanwhile makes the read start over);
* a store written in the earlier JSON-per-point layout is converted on first open,
  in chunks that each commit with the deletion of their old rows (a crash resumes),
  every point counted (:attr:`LocalStore.migrated`); the open rows a store kept in
  its SQLite file (the layout before the segments) are closed into parts from there.

Bounds: by age, :meth:`LocalStore.enforce_retention` deletes the parts (and open
rows) older than ``retention_s``; by size, the oldest parts go while the store
(registry, segments, parts and history) holds more than ``max_bytes``. A write that fails because
the disk is full is dropped and counted (:attr:`LocalStore.dropped`), logged once
when it starts and once when writes succeed again, and never raised: compensation
does not depend on its log.
"""

from __future__ import annotations

import contextlib
import logging
import sqlite3
import threading
import time
from collections.abc import Iterable
from pathlib import Path

import duckdb
import numpy as np

from gateway.outputs import store_log, store_parts
from gateway.outputs.points import Point
from gateway.outputs.sqlite_ring import SqliteRing
from gateway.outputs.store_migrate import migrate_json_points
from gateway.outputs.store_rows import COLUMNS, TAGS, Row, point_of

log = logging.getLogger(__name__)

DELETE_CHUNK_ROWS = 5000  # rows per DELETE: keeps one retention step short (ms)
PART_S = 600  # seconds of points per Parquet part
LATE_S = 60  # a period is closed this long after its end (points of slower machines)
NS = 1_000_000_000
DAY_NS = 86_400 * NS  # the parts of a closed (UTC) day are merged into one
#: ... when they are small: 10 machines' hour took 1.48 bytes a value as one part
#: against 1.79 in 10-minute parts, but 200 machines' 20 minutes (2.9 MB parts) 1 %
#: less for 2.3 s of CPU and every byte written again.
MERGE_BELOW_BYTES = 1_000_000  # the mean size of a day's parts below which they merge
MAX_EVICTIONS = 100  # oldest parts one write may drop to get under the cap
READ_ATTEMPTS = 3  # a reader whose parts were merged or aged out meanwhile reads again
SNAPSHOT_ATTEMPTS = 10  # a reader whose segments were closed meanwhile reads again

_KEY = ("time_ns", "measurement", *TAGS, "tags_extra")
SCHEMA = f"""
CREATE TABLE IF NOT EXISTS samples (
    measurement TEXT NOT NULL,
    {", ".join(f"{t} TEXT NOT NULL" for t in TAGS)},
    tags_extra TEXT NOT NULL,
    time_ns INTEGER NOT NULL,
    speed_rpm REAL, predicted_um REAL, target_um REAL, applied_um REAL, written_cnc REAL,
    correction_um REAL, interval_um REAL, training_span TEXT, outside_inputs TEXT,
    write_status TEXT, link_errors INTEGER, value_C REAL, reason TEXT,
    error_um REAL, fields_extra TEXT,
    PRIMARY KEY ({", ".join(_KEY)})
) WITHOUT ROWID;
CREATE TABLE IF NOT EXISTS parts (
    name TEXT PRIMARY KEY,
    first_ns INTEGER NOT NULL,
    last_ns INTEGER NOT NULL,
    rows INTEGER NOT NULL,
    bytes INTEGER NOT NULL
);
CREATE TABLE IF NOT EXISTS history (
    name TEXT PRIMARY KEY,
    first_ns INTEGER NOT NULL,
    last_ns INTEGER NOT NULL,
    rows INTEGER NOT NULL,
    bytes INTEGER NOT NULL
);
CREATE TABLE IF NOT EXISTS counters (name TEXT PRIMARY KEY, value INTEGER NOT NULL);
CREATE TABLE IF NOT EXISTS closed_logs (name TEXT PRIMARY KEY);
"""
_STAGED = f"SELECT {', '.join(COLUMNS)} FROM samples"


def parts_folder(path: Path) -> Path:
    """Where the Parquet parts of the store file ``path`` live."""
    return path.with_name(path.name + ".parts")


def open_folder(path: Path) -> Path:
    """Where the open period's segment files of the store file ``path`` live."""
    return path.with_name(path.name + ".open")


def history_folder(path: Path) -> Path:
    """Where the per-minute history parts of the store file ``path`` live."""
    return path.with_name(path.name + ".history")


class LocalStore:
    """Typed points: the open period in SQLite, closed periods in Parquet parts.

    Args:
        path: the SQLite file (created with its folder when missing).
        synchronous: SQLite ``synchronous`` level ("FULL": each commit reaches the
            disk, so a power cut loses nothing committed).
        max_bytes: the most the store may hold (None: unbounded); the oldest parts
            make room for the newest.
        retention_s: the oldest point :meth:`enforce_retention` keeps, s (None: all).
        history_retention_s: the oldest minute of the per-minute history it keeps, s
            (None: all).
        set_aside_damaged: a file SQLite cannot read is renamed aside and a new one
            started (the gateway); False refuses it with a ``ValueError`` (``export``).
        commit_interval_s: None: each :meth:`write` commits before it returns;
            otherwise points are queued and a thread commits them (and compacts
            closed periods) this often, so the caller never waits on the disk.
    """

    def __init__(
        self,
        path: str | Path,
        synchronous: str = "NORMAL",
        max_bytes: int | None = None,
        retention_s: float | None = None,
        set_aside_damaged: bool = True,
        commit_interval_s: float | None = None,
        history_retention_s: float | None = None,
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
        self.parts = parts_folder(self.path)
        self.parts.mkdir(exist_ok=True)
        self.history_parts = history_folder(self.path)
        self.history_parts.mkdir(exist_ok=True)
        self.segments = open_folder(self.path)
        self.segments.mkdir(exist_ok=True)
        self._open: dict[str, store_log.Segment] = {}  # the writer's segments by file name
        self._sync = synchronous in ("FULL", "EXTRA")
        self._append_lock = threading.Lock()
        self._failing = False
        self.history_retention_s = history_retention_s
        self.set_aside_as = self._ring.set_aside_as
        self.max_bytes = max_bytes
        self.retention_s = retention_s
        self.expired = 0  # points deleted for age
        self.evicted = 0  # points deleted to stay within max_bytes
        self._db = self._ring.db
        self._lock = self._ring.lock
        with self._lock:
            if set_aside_damaged:  # the writer; a reader must not touch a part being made
                self._remove_strays()
            self.migrated = migrate_json_points(self._db, self._write_part)
        self.dropped = self._counter("dropped")  # points not stored (full disk)
        self._queue: list[Point] = []
        self._queue_lock = threading.Lock()
        self._newest_ns = 0
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        if commit_interval_s is not None:
            self._thread = threading.Thread(
                target=self._run, args=(commit_interval_s,), name="local-store", daemon=True
            )
            self._thread.start()

    def _remove_strays(self) -> None:
        """Delete the files of parts a crash left unregistered (lock held)."""
        named = {n for (n,) in self._db.execute("SELECT name FROM parts")}
        store_parts.remove_strays(self.parts, named)
        named = {n for (n,) in self._db.execute("SELECT name FROM history")}
        store_parts.remove_strays(self.history_parts, named)
        closed = [n for (n,) in self._db.execute("SELECT name FROM closed_logs")]
        for name in closed:  # compacted into a part before a crash let them be removed
            with contextlib.suppress(FileNotFoundError):
                (self.segments / name).unlink()
        with self._ring.transaction() as db:
            db.execute("DELETE FROM closed_logs")

    # --- writing ----------------------------------------------------------------------
    def write(self, points: Iterable[Point]) -> bool:
        """Store points; a point already stored in the open period has its fields merged.

        Queued for the commit thread when there is one (True unless the last commit
        failed). Otherwise one transaction; False when the points could not be stored
        (disk full): they are counted in :attr:`dropped` and logged, nothing raised.
        """
        points = list(points)
        if not points:
            return True
        newest = max(p.time_ns for p in points)
        if self._thread is not None:  # made into rows by the commit thread, not the caller
            with self._queue_lock:
                self._queue.extend(points)
                self._newest_ns = max(self._newest_ns, newest)
            return not self._ring.failing
        self._newest_ns = max(self._newest_ns, newest)
        kept = self._commit(store_log.columns_of(points))
        if kept and self.compact():
            self.merge_days()
            self._keep_within_cap()
        return kept

    def _commit(self, columns: store_log.Columns) -> bool:
        """Append ``columns`` to the open period's segments (one record per period),
        within the size cap; False when the disk refused them (counted, logged once)."""
        self._keep_within_cap()
        periods = np.array(columns["time_ns"], dtype=np.int64) // (PART_S * NS)
        try:
            with self._append_lock:
                for period in np.unique(periods):
                    if len(periods) and periods.min() == periods.max():
                        part = columns  # the usual commit: one period
                    else:
                        rows = np.nonzero(periods == period)[0]
                        part = {c: [v[i] for i in rows] for c, v in columns.items()}
                    self._segment(int(period) * PART_S * NS).append(part)
        except OSError as exc:
            self._lost(len(periods), exc)
            return False
        if self._failing:
            self._failing = self._ring.failing = False
            log.warning(
                "local store %s writable again; %d point(s) dropped in all",
                self.path,
                self._count_dropped(0),
            )
        return True

    def _lost(self, n: int, exc: OSError) -> None:
        with self._lock:
            self._count_dropped(n)
        if not self._failing:
            self._failing = self._ring.failing = True
            log.error(
                "local store %s cannot store points (%s): dropping and counting them "
                "until it can again",
                self.path,
                exc,
            )

    def _segment(self, start_ns: int) -> store_log.Segment:
        """The writer's open segment of the period starting at ``start_ns`` (append lock
        held): the one on the disk from before a restart, or a new one."""
        for name, segment in self._open.items():
            if name.startswith(f"{start_ns}-"):
                return segment
        found = sorted(self.segments.glob(f"{start_ns}-*.log"))
        name = found[-1].name if found else f"{start_ns}-{time.time_ns()}.log"
        segment = store_log.Segment(self.segments / name, self._sync)
        self._open[name] = segment
        return segment

    def _keep_within_cap(self) -> None:
        """Drop the oldest parts while the store holds more than 98 % of ``max_bytes``."""
        if self.max_bytes is None:
            return
        with self._lock, contextlib.suppress(sqlite3.Error):
            for _ in range(MAX_EVICTIONS):
                if not self._over_cap() or self._ring.make_room(self._evict_oldest) == 0:
                    break

    def flush(self) -> bool:
        """Commit the queued points now (the commit thread does it every interval)."""
        with self._queue_lock:
            points, self._queue = self._queue, []
        return self._commit(store_log.columns_of(points)) if points else True

    def _run(self, interval_s: float) -> None:
        """The commit thread: commit, then close any period due; a compaction that fails
        (a full disk) leaves the rows where they are, says so once, and is retried."""
        failing = False
        while not self._stop.wait(interval_s):
            try:
                self.flush()
                if self.compact():
                    self.merge_days()
                    self._keep_within_cap()
            except Exception as exc:
                if not failing:
                    log.error(
                        "local store %s: cannot close a period (%s); retrying", self.path, exc
                    )
                failing = True
            else:
                if failing:
                    log.warning("local store %s: periods close again", self.path)
                failing = False

    def _count_dropped(self, n: int) -> int:
        self.dropped += n
        with contextlib.suppress(sqlite3.Error):  # a full disk may refuse the count too
            self._db.execute(
                "INSERT INTO counters VALUES ('dropped', ?) "
                "ON CONFLICT (name) DO UPDATE SET value = excluded.value",
                (self.dropped,),
            )
        return self.dropped

    def _counter(self, name: str) -> int:
        with self._lock:
            row = self._db.execute("SELECT value FROM counters WHERE name = ?", (name,)).fetchone()
        return 0 if row is None else int(row[0])

    def _evict_oldest(self) -> int:
        """Make room at the cap (lock held): the oldest part of 1-s points, else the
        oldest history part, else the oldest open rows. The points deleted (a history
        part counts as 1: room was made)."""
        removed = self._drop_oldest_part()
        if removed == 0 and self._drop_oldest_history():
            return 1
        if removed == 0:
            removed = self._db.execute(
                "DELETE FROM samples WHERE time_ns IN (SELECT time_ns FROM samples "
                "ORDER BY time_ns LIMIT ?)",
                (DELETE_CHUNK_ROWS,),
            ).rowcount
        self.evicted += removed
        return removed

    # --- closing periods ----------------------------------------------------------------
    def _write_part(self, rows: list[Row] | dict[str, np.ndarray]) -> None:
        """Write ``rows`` (or their columns) as a part and register it (the caller deletes
        their source in the same transaction, lock held)."""
        columns = rows if isinstance(rows, dict) else store_parts.arrays_of(rows)
        times = columns["time_ns"]
        first, last = int(times.min()), int(times.max())
        name = f"{first}-{last}-{time.time_ns()}.parquet"
        size = store_parts.write_part(columns, self.parts / name)
        self._db.execute(
            "INSERT INTO parts VALUES (?, ?, ?, ?, ?)", (name, first, last, len(times), size)
        )
        minutes, size = store_parts.write_history(self.parts / name, self.history_parts / name)
        self._db.execute(
            "INSERT INTO history VALUES (?, ?, ?, ?, ?)", (name, first, last, minutes, size)
        )

    def compact(self, now_ns: int | None = None) -> int:
        """Move every closed period (ended ``LATE_S`` before the newest point, or
        ``now_ns``) from SQLite into Parquet parts; the points moved."""
        now_ns = self._newest_ns if now_ns is None else now_ns
        cut = (now_ns - LATE_S * NS) // (PART_S * NS) * (PART_S * NS)
        moved = self._compact_segments(cut)
        with self._lock:  # rows a store of the earlier SQLite open period still holds
            while True:
                oldest = self._db.execute("SELECT min(time_ns) FROM samples").fetchone()[0]
                if oldest is None or oldest >= cut:
                    return moved
                end = min(cut, (oldest // (PART_S * NS) + 1) * (PART_S * NS))
                moved += self._compact_period(end)

    def _compact_segments(self, cut_ns: int) -> int:
        """Each period's segment files that ended by ``cut_ns`` into one part, registered
        with their names in one transaction, then removed; the points moved."""
        with self._append_lock:  # no append to a segment while it is closed
            return self._compact_closed(cut_ns)

    def _compact_closed(self, cut_ns: int) -> int:
        periods: dict[int, list[Path]] = {}
        for path in sorted(self.segments.glob("*.log")):
            start = int(path.name.split("-", 1)[0])
            if start + PART_S * NS <= cut_ns:
                periods.setdefault(start, []).append(path)
        for paths in periods.values():
            for path in paths:
                segment = self._open.pop(path.name, None)
                if segment is not None:
                    segment.close()
        moved = 0
        for paths in periods.values():
            columns = read_segments(paths, ordered=True)
            with self._lock:
                if len(columns["time_ns"]):
                    with self._ring.transaction() as db:
                        self._write_part(columns)
                        db.executemany(
                            "INSERT OR IGNORE INTO closed_logs VALUES (?)",
                            [(p.name,) for p in paths],
                        )
                for path in paths:  # registered as a part: a crash here leaves them listed
                    with contextlib.suppress(FileNotFoundError):
                        path.unlink()
                with self._ring.transaction() as db:
                    db.executemany(
                        "DELETE FROM closed_logs WHERE name = ?", [(p.name,) for p in paths]
                    )
            moved += len(columns["time_ns"])
        return moved

    def merge_days(self, now_ns: int | None = None) -> int:
        """Merge the parts (and history parts) of each day closed before ``now_ns`` into
        one each (better compression, fewer files to open) when they average under
        :data:`MERGE_BELOW_BYTES`; the files merged."""
        now_ns = self._newest_ns if now_ns is None else now_ns
        before = (now_ns - LATE_S * NS) // DAY_NS * DAY_NS
        merged = 0
        with self._lock:
            for table, folder in (("parts", self.parts), ("history", self.history_parts)):
                merged += self._merge_table(table, folder, before)
        return merged

    def _merge_table(self, table: str, folder: Path, before_ns: int) -> int:
        found = self._db.execute(
            f"SELECT name, first_ns, last_ns, rows, bytes FROM {table} WHERE last_ns < ? "
            "ORDER BY first_ns",
            (before_ns,),
        ).fetchall()
        days: dict[int, list[tuple]] = {}
        for part in found:
            days.setdefault(part[1] // DAY_NS, []).append(part)
        merged = 0
        for parts in days.values():
            if len(parts) < 2 or sum(p[4] for p in parts) >= MERGE_BELOW_BYTES * len(parts):
                continue
            first, last = parts[0][1], max(p[2] for p in parts)
            name = f"{first}-{last}-{time.time_ns()}.parquet"
            size = store_parts.merge_parts([folder / p[0] for p in parts], folder / name)
            with self._ring.transaction() as db:
                db.executemany(f"DELETE FROM {table} WHERE name = ?", [(p[0],) for p in parts])
                db.execute(
                    f"INSERT INTO {table} VALUES (?, ?, ?, ?, ?)",
                    (name, first, last, sum(p[3] for p in parts), size),
                )
            for part in parts:  # unregistered now: a crash here leaves strays, removed later
                with contextlib.suppress(FileNotFoundError):
                    (folder / part[0]).unlink()
            merged += len(parts)
        return merged

    def _compact_period(self, end_ns: int) -> int:
        rows = self._db.execute(f"{_STAGED} WHERE time_ns < ?", (end_ns,)).fetchall()
        with self._ring.transaction() as db:
            self._write_part(rows)
            db.execute("DELETE FROM samples WHERE time_ns < ?", (end_ns,))
        return len(rows)

    # --- reading ------------------------------------------------------------------------
    def query(
        self,
        measurement: str,
        machine: str | None = None,
        start_ns: int | None = None,
        stop_ns: int | None = None,
    ) -> list[Point]:
        """Points of ``measurement`` (of ``machine``), ``start_ns ≤ time < stop_ns``, by time."""
        self.flush()
        with self._lock:
            db = read_window(self._db, self.parts, measurement, machine, start_ns, stop_ns)
        try:
            return [point_of(r) for r in db.fetchall()]
        finally:
            db.close()

    def time_span(
        self, machine: str | None = None, start_ns: int | None = None, stop_ns: int | None = None
    ) -> tuple[int, int] | None:
        """The first and last time of the points (of ``machine``) in the window
        ``start_ns ≤ time < stop_ns``, or None: where a reader in time slices starts and ends."""
        self.flush()
        with self._lock:
            select = "MIN(time_ns), MAX(time_ns)"
            db = read_window(self._db, self.parts, None, machine, start_ns, stop_ns, select, "")
        try:
            row = db.fetchone()
        finally:
            db.close()
        if row is None or row[0] is None:
            return None
        return int(row[0]), int(row[1])

    def machines(self) -> list[str]:
        self.flush()
        with self._lock:
            db = read_window(self._db, self.parts, None, None, None, None, "DISTINCT machine")
        try:
            return sorted(m for (m,) in db.fetchall() if m)
        finally:
            db.close()

    # --- bounds -------------------------------------------------------------------------
    def delete_before(self, time_ns: int, limit: int | None = None) -> int:
        """Remove points older than ``time_ns``: the open rows, and the parts wholly
        before it (at most ``limit`` open rows); how many points."""
        self.flush()
        with self._lock:
            return self._delete_before(time_ns, limit)

    def _delete_before(self, time_ns: int, limit: int | None) -> int:
        removed = 0
        for name, rows in self._db.execute(
            "SELECT name, rows FROM parts WHERE last_ns < ? ORDER BY first_ns", (time_ns,)
        ).fetchall():
            self._drop_part(name)
            removed += rows
        straddling = self._db.execute(
            "SELECT name, rows FROM parts WHERE first_ns < ? AND last_ns >= ?", (time_ns, time_ns)
        ).fetchall()
        for name, rows in straddling:
            removed += rows - self._trim_part(name, time_ns)
        removed += self._trim_segments(time_ns)
        sql = "DELETE FROM samples WHERE time_ns < ?"
        args: tuple[int, ...] = (time_ns,)
        if limit is not None:
            sql = (
                "DELETE FROM samples WHERE time_ns IN (SELECT time_ns FROM samples "
                "WHERE time_ns < ? ORDER BY time_ns LIMIT ?) AND time_ns < ?"
            )
            args = (time_ns, limit, time_ns)
        return removed + self._db.execute(sql, args).rowcount

    def _trim_segments(self, from_ns: int) -> int:
        """Rewrite the open period's segments that hold points before ``from_ns`` with
        the later ones only (a new file; the old one listed as closed, then removed, as
        a compaction does, lock held); the points removed."""
        removed = 0
        with self._append_lock:
            for path in sorted(self.segments.glob("*.log")):
                if int(path.name.split("-", 1)[0]) >= from_ns:
                    continue
                segment = self._open.pop(path.name, None)
                if segment is not None:
                    segment.close()
                columns = read_segments([path])
                keep = columns["time_ns"] >= from_ns
                removed += int((~keep).sum())
                if keep.any():
                    fresh = store_log.Segment(
                        path.with_name(f"{path.name.split('-', 1)[0]}-{time.time_ns()}.log"), True
                    )
                    fresh.append(
                        {c: [store_log.plain(v) for v in columns[c][keep]] for c in COLUMNS}
                    )
                    self._open[fresh.path.name] = fresh
                with self._ring.transaction() as db:
                    db.execute("INSERT OR IGNORE INTO closed_logs VALUES (?)", (path.name,))
                path.unlink()
                with self._ring.transaction() as db:
                    db.execute("DELETE FROM closed_logs WHERE name = ?", (path.name,))
        return removed

    def _trim_part(self, name: str, from_ns: int) -> int:
        """Replace part ``name`` by its rows at or after ``from_ns``; the rows kept."""
        new = f"{from_ns}-{name.split('-', 1)[1]}"
        rows, first, last, size = store_parts.trim_part(
            self.parts / name, self.parts / new, from_ns
        )
        self._db.execute(
            "UPDATE parts SET name = ?, first_ns = ?, last_ns = ?, rows = ?, bytes = ? "
            "WHERE name = ?",
            (new, first, last, rows, size, name),
        )
        with contextlib.suppress(FileNotFoundError):
            (self.parts / name).unlink()
        return rows

    def _drop_part(self, name: str) -> None:
        """Unregister a part (committed first: a reader's snapshot no longer lists it),
        then delete its file."""
        self._db.execute("DELETE FROM parts WHERE name = ?", (name,))
        with contextlib.suppress(FileNotFoundError):
            (self.parts / name).unlink()

    def _drop_oldest_history(self) -> bool:
        """Drop the oldest history part when no 1-s part is left; whether one went."""
        row = self._db.execute("SELECT name FROM history ORDER BY first_ns LIMIT 1").fetchone()
        if row is None:
            return False
        self._drop_history(row[0])
        return True

    def _drop_history(self, name: str) -> None:
        self._db.execute("DELETE FROM history WHERE name = ?", (name,))
        with contextlib.suppress(FileNotFoundError):
            (self.history_parts / name).unlink()

    def _expire_history(self, now_ns: int) -> None:
        if self.history_retention_s is None:
            return
        cutoff = now_ns - round(self.history_retention_s * 1e9)
        old = self._db.execute("SELECT name FROM history WHERE last_ns < ?", (cutoff,))
        for (name,) in old.fetchall():
            self._drop_history(name)

    def history(
        self,
        measurement: str,
        machine: str | None = None,
        start_ns: int | None = None,
        stop_ns: int | None = None,
    ) -> list[dict[str, object]]:
        """The per-minute history of ``measurement`` (of ``machine``): one dict per
        minute and series, with ``time_ns`` (the minute's start), ``samples`` and
        ``<field>_min``, ``_mean``, ``_max`` of every numeric field, and the lowest and
        highest write state (:data:`store_parts.WRITE_STATE`), by time."""
        self.flush()
        with self._lock:
            names = [n for (n,) in self._db.execute("SELECT name FROM history ORDER BY first_ns")]
        files = [self.history_parts / n for n in names]
        return store_parts.read_history(files, measurement, machine, start_ns, stop_ns)

    def _drop_oldest_part(self) -> int:
        row = self._db.execute("SELECT name, rows FROM parts ORDER BY first_ns LIMIT 1").fetchone()
        if row is None:
            return 0
        self._drop_part(row[0])
        return int(row[1])

    def enforce_retention(self, now_ns: int | None = None, budget_s: float = 0.2) -> int:
        """Delete points past ``retention_s``, then the oldest parts while over ``max_bytes``.

        Without a commit thread, closed periods are compacted first. Works for about
        ``budget_s`` at most; what is left is taken on the next call. Returns the points
        deleted. A full disk makes it do nothing (and nothing is raised).
        """
        now_ns = time.time_ns() if now_ns is None else now_ns
        self._newest_ns = max(self._newest_ns, now_ns)
        self.flush()  # the queued points count too (at most a second of them)
        if self._thread is None and self.compact():
            self.merge_days()
        deadline = time.monotonic() + budget_s
        deleted = 0
        with self._lock:
            try:
                if self.retention_s is not None:
                    cutoff = now_ns - round(self.retention_s * 1e9)
                    n = self._delete_before(cutoff, DELETE_CHUNK_ROWS)
                    self.expired += n
                    deleted += n
                self._expire_history(now_ns)
                while self._over_cap() and time.monotonic() < deadline:
                    n = self._evict_oldest()
                    deleted += n
                    if n == 0:
                        break
            except sqlite3.Error as exc:
                log.warning("local store %s: retention step failed (%s)", self.path, exc)
        if deleted:
            log.info("local store %s: retention deleted %d old point(s)", self.path, deleted)
        return deleted

    def _over_cap(self) -> bool:
        return self.max_bytes is not None and self._used_bytes() > 0.98 * self.max_bytes

    def _used_bytes(self) -> int:
        from gateway.outputs.sqlite_ring import used_bytes

        parts = self._db.execute(
            "SELECT (SELECT coalesce(sum(bytes), 0) FROM parts) "
            "+ (SELECT coalesce(sum(bytes), 0) FROM history)"
        ).fetchone()[0]
        logs = sum(p.stat().st_size for p in self.segments.glob("*.log"))
        return used_bytes(self._db) + int(parts) + logs

    def used_bytes(self) -> int:
        """Bytes the store holds: the SQLite file's pages in use, the open period's
        segments and the parts."""
        with self._lock:
            return self._used_bytes()

    def __len__(self) -> int:
        self.flush()
        with self._lock:
            staged = self._db.execute("SELECT COUNT(*) FROM samples").fetchone()[0]
            parts = self._db.execute("SELECT coalesce(sum(rows), 0) FROM parts").fetchone()[0]
            _, columns = _snapshot(self._db, self.parts, "FALSE", [], (-(2**63), 2**63 - 1))
        return int(staged) + int(parts) + len(columns["time_ns"])

    def close(self) -> None:
        if self._thread is not None:
            self._stop.set()
            self._thread.join()
            self._thread = None
        self.flush()
        with self._append_lock:
            for segment in self._open.values():
                segment.close()
            self._open.clear()
        self._ring.close()

    def __enter__(self) -> LocalStore:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


def read_window(
    db: sqlite3.Connection,
    parts: Path,
    measurement: str | None,
    machine: str | None,
    start_ns: int | None,
    stop_ns: int | None,
    select: str = ", ".join(COLUMNS),
    order: str | None = None,
) -> duckdb.DuckDBPyConnection:
    """The rows of a window from one snapshot of the store: the parts that overlap it
    and the open rows, read in one SQLite read transaction; a DuckDB connection with the
    result of ``SELECT select`` ordered by time (``select`` empty: none), and the
    window as the view ``w`` for further queries (the caller fetches and closes it)."""
    where, args, literals = ["TRUE"], [], ["TRUE"]
    for column, value, op in (
        ("measurement", measurement, "="),
        ("machine", machine, "="),
        ("time_ns", start_ns, ">="),
        ("time_ns", stop_ns, "<"),
    ):
        if value is not None:
            where.append(f"{column} {op} ?")
            args.append(value)
            literals.append(f"{column} {op} {store_parts.literal(value)}")
    clause = " AND ".join(where)
    lo = -(2**63) if start_ns is None else start_ns
    hi = 2**63 - 1 if stop_ns is None else stop_ns
    if order is None:
        order = (
            "" if select.startswith("DISTINCT") else "time_ns, " + ", ".join((*TAGS, "tags_extra"))
        )
    for attempt in range(READ_ATTEMPTS):
        names, staged = _snapshot(db, parts, clause, args, (lo, hi))
        files = [parts / n for (n,) in names]
        try:
            return store_parts.scan(files, staged, " AND ".join(literals), select, order)
        except duckdb.IOException:  # a part merged or aged out since the snapshot
            if attempt == READ_ATTEMPTS - 1:
                raise
    raise AssertionError("unreachable")


def _snapshot(
    db: sqlite3.Connection, parts: Path, clause: str, args: list, span: tuple[int, int]
) -> tuple[list, dict[str, np.ndarray]]:
    """The parts overlapping ``span``, and the open rows (legacy SQLite rows meeting
    ``clause`` and the open period's segments overlapping ``span``), as one consistent
    state of the store: read again if a period was closed into a part meanwhile."""
    segments = parts.with_name(parts.name.removesuffix(".parts") + ".open")
    for _ in range(SNAPSHOT_ATTEMPTS):
        names, staged, closed = _registry(db, clause, args, span)
        paths = [
            p
            for p in sorted(segments.glob("*.log"))
            if p.name not in closed
            and int(p.name.split("-", 1)[0]) < span[1]
            and int(p.name.split("-", 1)[0]) + PART_S * NS > span[0]
        ]
        try:
            columns = read_segments(paths)
        except FileNotFoundError:  # closed into a part since the registry was read
            continue
        if _registry(db, "FALSE", [], span)[0] == names:
            legacy = store_parts.arrays_of(staged)
            return names, store_log.concatenate([legacy, columns])
    raise duckdb.IOException("the store changed during every read attempt")


def _registry(
    db: sqlite3.Connection, clause: str, args: list, span: tuple[int, int]
) -> tuple[list, list, set[str]]:
    """In one SQLite read transaction: the parts overlapping ``span``, the legacy open
    rows meeting ``clause`` and the segment files already closed into parts."""
    in_transaction = db.in_transaction
    if not in_transaction:
        db.execute("BEGIN")
    try:
        names = db.execute(
            "SELECT name FROM parts WHERE last_ns >= ? AND first_ns < ? ORDER BY first_ns",
            span,
        ).fetchall()
        staged = db.execute(f"{_STAGED} WHERE {clause}", args).fetchall()
        closed = {n for (n,) in db.execute("SELECT name FROM closed_logs")}
    finally:
        if not in_transaction:
            db.execute("COMMIT")
    return names, staged, closed


def read_segments(paths: list[Path], ordered: bool = False) -> dict[str, np.ndarray]:
    """The rows of segment files as columns, rows of one identity merged; ``ordered``:
    sorted as a part is when that is cheap (:data:`ORDERED` in the result then)."""
    batches: list[dict[str, np.ndarray]] = []
    duplicates = False
    for path in paths:
        found, flagged, _, _ = store_log.read_segment(path)
        batches += found
        duplicates |= flagged
    if duplicates:
        return store_log.merge_duplicates(store_log.concatenate(batches))
    in_order = store_log.ordered_columns(batches) if ordered else None
    if in_order is None:
        return store_log.concatenate(batches)
    return {**in_order, store_parts.ORDERED: in_order["time_ns"][:0]}
