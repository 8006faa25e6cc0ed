"""The embedded time-series store: points in one SQLite file, no server needed.

The default destination of the gateway's time series when no InfluxDB is
configured, and a source for :func:`gateway.export.export_runs`. It keeps
InfluxDB's identity rule: a point is identified by measurement, tags and time, so
writing the same point again stores it once (its fields are merged, a field
written again takes the new value, as InfluxDB does).
"""

from __future__ import annotations

import json
import sqlite3
import threading
from collections.abc import Iterable
from pathlib import Path

from gateway.timeseries import Point

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
"""


def _tags_text(tags: dict[str, str]) -> str:
    return json.dumps(dict(sorted(tags.items())), separators=(",", ":"), ensure_ascii=False)


class LocalStore:
    """SQLite (WAL) table of points, indexed on (measurement, machine, time_ns)."""

    def __init__(self, path: str | Path, synchronous: str = "NORMAL") -> None:
        if synchronous.upper() not in {"OFF", "NORMAL", "FULL", "EXTRA"}:
            raise ValueError(f"unknown SQLite synchronous level {synchronous!r}")
        self.path = Path(path)
        self.path.parent.mkdir(parents=True, exist_ok=True)
        self._lock = threading.Lock()
        self._db = sqlite3.connect(self.path, check_same_thread=False, isolation_level=None)
        self._db.execute("PRAGMA journal_mode=WAL")
        self._db.execute(f"PRAGMA synchronous={synchronous.upper()}")
        self._db.executescript(SCHEMA)

    def write(self, points: Iterable[Point]) -> None:
        """Store points (one transaction); a point already stored has its fields merged."""
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
            return
        with self._lock:
            self._db.execute("BEGIN IMMEDIATE")
            try:
                self._db.executemany(
                    "INSERT INTO points (measurement, machine, tags, time_ns, fields) "
                    "VALUES (?, ?, ?, ?, ?) "
                    "ON CONFLICT (measurement, machine, tags, time_ns) "
                    "DO UPDATE SET fields = json_patch(fields, excluded.fields)",
                    rows,
                )
                self._db.execute("COMMIT")
            except BaseException:
                self._db.execute("ROLLBACK")
                raise

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

    def delete_before(self, time_ns: int) -> int:
        """Remove points older than ``time_ns`` (retention); return how many."""
        with self._lock:
            return self._db.execute("DELETE FROM points WHERE time_ns < ?", (time_ns,)).rowcount

    def __len__(self) -> int:
        with self._lock:
            return self._db.execute("SELECT COUNT(*) FROM points").fetchone()[0]

    def close(self) -> None:
        with self._lock:
            self._db.close()

    def __enter__(self) -> LocalStore:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
