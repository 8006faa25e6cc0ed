"""Keeping an SQLite file within a size on a small edge disk, and surviving a full disk.

Both of the gateway's SQLite files (the local store and the InfluxDB disk buffer)
are bounded the same way:

* a hard cap: ``PRAGMA max_page_count`` makes SQLite refuse to grow the file past
  ``max_bytes`` (it answers ``SQLITE_FULL``, "database or disk is full", exactly as
  it does when the disk itself is full), and ``journal_size_limit`` keeps the WAL
  file from staying large after a checkpoint;
* the owner deletes its oldest rows when a write meets the cap, or when its used
  pages exceed the bound, so the file works as a ring: freed pages are reused, the
  file never grows past the cap;
* a write that fails because the disk is full (or the cap could not be made room
  under) is dropped and counted, never raised into the compensation loop.
"""

from __future__ import annotations

import math
import sqlite3
from collections.abc import Callable

SQLITE_FULL = 13
SQLITE_IOERR = 10
WAL_LIMIT_BYTES = 4_000_000  # what a checkpointed WAL file is truncated back to
BYTES_PER_MB = 1_000_000
MAX_ROUNDS = 50  # make-room-and-retry rounds a write at the size cap may take


def cap_size(db: sqlite3.Connection, max_bytes: int) -> None:
    """Refuse to let the database file grow past ``max_bytes`` (``SQLITE_FULL`` at the cap)."""
    page_size = db.execute("PRAGMA page_size").fetchone()[0]
    pages = max(16, math.floor(max_bytes / page_size))
    db.execute(f"PRAGMA max_page_count = {int(pages)}")
    db.execute(f"PRAGMA journal_size_limit = {WAL_LIMIT_BYTES}")


def used_bytes(db: sqlite3.Connection) -> int:
    """Bytes of the file that hold data (pages in use; free pages are reused first)."""
    page_count = db.execute("PRAGMA page_count").fetchone()[0]
    free = db.execute("PRAGMA freelist_count").fetchone()[0]
    page_size = db.execute("PRAGMA page_size").fetchone()[0]
    return (page_count - free) * page_size


def at_cap(db: sqlite3.Connection, max_bytes: int) -> bool:
    """True when the pages in use come within 8 pages of ``max_bytes`` (time to make room)."""
    page_size = db.execute("PRAGMA page_size").fetchone()[0]
    return used_bytes(db) + 8 * page_size >= max_bytes


def is_out_of_space(exc: sqlite3.Error) -> bool:
    """True when SQLite failed for want of space (the disk, or the file's cap), or on I/O.

    Python reports the primary code in ``sqlite_errorcode`` (extended codes carry it
    in their low byte, e.g. ``SQLITE_IOERR_WRITE``).
    """
    code = getattr(exc, "sqlite_errorcode", None)
    if code is None:
        text = str(exc).lower()
        return "disk is full" in text or "disk i/o error" in text
    return code & 0xFF in (SQLITE_FULL, SQLITE_IOERR)


def bounded_write(
    write: Callable[[], None],
    make_room: Callable[[], bool],
    lost: Callable[[sqlite3.Error], None],
) -> bool:
    """Run ``write``; when it fails for want of space, let ``make_room`` free the oldest
    rows (it returns False when it cannot: a full disk, not the file's cap) and retry.

    Returns False, after calling ``lost`` with the cause, when the write could not be
    kept; any other SQLite error is raised. Never more than ``MAX_ROUNDS`` attempts.
    """
    for _ in range(MAX_ROUNDS):
        try:
            write()
        except sqlite3.Error as exc:
            if not is_out_of_space(exc):
                raise
            if make_room():
                continue
            lost(exc)
            return False
        return True
    lost(sqlite3.OperationalError("no room made at the size cap"))
    return False
