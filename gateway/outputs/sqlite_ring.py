"""One bounded SQLite file on a small edge disk: the ring both of the gateway's logs use.

The local store (:mod:`gateway.outputs.local_store`) and the disk buffer of points
waiting to be sent (:mod:`gateway.outputs.disk_buffer`, one for the InfluxDB forwarder
and one per Sparkplug node) are logs: the compensation never depends on them. Each
is one :class:`SqliteRing`, which owns what the two have in common:

* **opening with recovery**: a file SQLite cannot read at all — not a database
  (another file at that path, a header overwritten) or a damaged image (a flash
  card's bad block, a copy cut short) — neither stops the gateway nor is thrown away.
  It is renamed aside with its ``-wal`` and ``-shm`` companions, as
  ``<name>.unreadable-<UTC time>``, logged at ERROR with both names, and a new file is
  started at the configured path. Any other failure (no permission, a locked file, a
  full disk) is raised as it was: moving a good file aside for those would hide it.
  A reader (``export``) refuses a damaged file with a ``ValueError`` instead.
* **a hard size cap**: ``PRAGMA max_page_count`` makes SQLite refuse to grow the file
  past ``max_bytes`` (it answers ``SQLITE_FULL``, "database or disk is full", exactly
  as it does when the disk itself is full), and ``journal_size_limit`` keeps the WAL
  file from staying large after a checkpoint;
* **bounded writes**: a write that meets the cap first lets the owner delete its oldest
  rows (freed pages are reused, so the file works as a ring and never grows past the
  cap), then retries;
* **full-disk handling**: a write that fails because the disk is full (or the cap could
  not be made room under) is dropped and counted by the owner, logged once when it
  starts and once when writes succeed again, and never raised into the loop;
* **eviction by age and size** within a time budget (:meth:`SqliteRing.enforce`), the
  owner saying which rows are too old and which are the oldest.

The owners keep only their table and its order: the store's identity rule (a point is
measurement, tags and time), the buffer's FIFO with its persistent drop count.
"""

from __future__ import annotations

import contextlib
import logging
import math
import sqlite3
import threading
import time
from collections.abc import Callable, Iterator
from pathlib import Path

log = logging.getLogger(__name__)

SQLITE_FULL = 13
SQLITE_IOERR = 10
WAL_LIMIT_BYTES = 4_000_000  # what a checkpointed WAL file is truncated back to
MAX_ROUNDS = 50  # make-room-and-retry rounds a write at the size cap may take
SYNCHRONOUS_LEVELS = frozenset({"OFF", "NORMAL", "FULL", "EXTRA"})
#: The SQLite result codes of a file it cannot read as a database.
UNREADABLE = (sqlite3.SQLITE_CORRUPT, sqlite3.SQLITE_NOTADB)
COMPANIONS = ("", "-wal", "-shm")
#: The first 16 bytes of every SQLite database file.
HEADER = b"SQLite format 3\x00"


# --- opening, with a damaged file set aside ------------------------------------------------
def open_database(
    path: Path, prepare: Callable[[sqlite3.Connection], None], set_aside_damaged: bool = True
) -> tuple[sqlite3.Connection, Path | None]:
    """A connection to ``path`` readied by ``prepare``, and where a damaged file was put
    aside (None when the file opened as it was). With ``set_aside_damaged`` False (a
    reader such as ``export``) a damaged file is refused with a ``ValueError`` instead,
    and a file without SQLite's header is refused before SQLite touches it."""
    problem = header_problem(path)
    if problem is not None and not set_aside_damaged:
        raise ValueError(f"{path}: not a readable SQLite database ({problem})")
    db = _connect(path)
    try:
        prepare(db)
        return db, None
    except sqlite3.DatabaseError as exc:
        unreadable = getattr(exc, "sqlite_errorcode", None) in UNREADABLE
        if not (unreadable and set_aside_damaged):
            db.close()
            if unreadable:
                raise ValueError(f"{path}: not a readable SQLite database ({exc})") from None
            raise
        # Renamed while still open: closing a connection deletes the -wal and -shm files
        # at the names it opened, and the old -wal may hold the last points written.
        aside = set_aside(path)
        db.close()
        log.error(
            "%s: not a readable SQLite database (%s); kept as %s, a new one started",
            path,
            exc,
            aside,
        )
    except BaseException:
        db.close()
        raise
    db = _connect(path)
    try:
        prepare(db)
    except BaseException:
        db.close()
        raise
    return db, aside


def _connect(path: Path) -> sqlite3.Connection:
    """The gateway's connection settings: shared between threads, autocommit."""
    return sqlite3.connect(path, check_same_thread=False, isolation_level=None)


def header_problem(path: Path) -> str | None:
    """Why ``path`` cannot be an SQLite database from its first bytes, or None (missing,
    empty, starting with SQLite's header, or not readable: SQLite then says why)."""
    try:
        with path.open("rb") as stream:
            head = stream.read(len(HEADER))
    except OSError:
        return None
    if not head or head == HEADER:
        return None
    return "file is not a database"


def set_aside(path: Path) -> Path:
    """Rename ``path`` and its companions to ``<name>.unreadable-<UTC time>[-wal|-shm]``."""
    stamp = time.strftime("%Y%m%dT%H%M%SZ", time.gmtime())
    aside = path.with_name(f"{path.name}.unreadable-{stamp}")
    n = 1
    while any(Path(f"{aside}{c}").exists() for c in COMPANIONS):
        n += 1
        aside = path.with_name(f"{path.name}.unreadable-{stamp}-{n}")
    for companion in COMPANIONS:
        source = Path(f"{path}{companion}")
        if source.exists():
            source.rename(f"{aside}{companion}")
    return aside


# --- the size cap and the full disk ---------------------------------------------------------
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


# --- the ring --------------------------------------------------------------------------------
class SqliteRing:
    """One SQLite (WAL) file bounded by size, opened with recovery; thread-safe via :attr:`lock`.

    Args:
        path: the database file (created with its folder when missing).
        schema: the owner's tables (``CREATE … IF NOT EXISTS``).
        label: how log lines name the file's owner ("local store", "point buffer").
        cannot: what a log line says the owner cannot do on a full disk.
        synchronous: SQLite ``synchronous`` level.
        max_bytes: the largest the file may grow (None: unbounded).
        set_aside_damaged: a file SQLite cannot read is renamed aside and a new one
            started; False refuses it with a ``ValueError`` (a reader).
        inspect: run on the opened connection after the schema (e.g. to count rows).
    """

    def __init__(
        self,
        path: str | Path,
        schema: str,
        *,
        label: str,
        cannot: str,
        synchronous: str = "NORMAL",
        max_bytes: int | None = None,
        set_aside_damaged: bool = True,
        inspect: Callable[[sqlite3.Connection], None] | None = None,
    ) -> None:
        if synchronous.upper() not in SYNCHRONOUS_LEVELS:
            raise ValueError(f"unknown SQLite synchronous level {synchronous!r}")
        self.path = Path(path)
        self.path.parent.mkdir(parents=True, exist_ok=True)
        self.label = label
        self.cannot = cannot
        self.max_bytes = max_bytes
        self.failing = False  # the last write was lost (full disk): say when they work again
        self.lock = threading.Lock()

        def prepare(db: sqlite3.Connection) -> None:
            db.execute("PRAGMA journal_mode=WAL")
            db.execute(f"PRAGMA synchronous={synchronous.upper()}")
            db.executescript(schema)
            if inspect is not None:
                inspect(db)

        self.db, self.set_aside_as = open_database(self.path, prepare, set_aside_damaged)
        if max_bytes is not None:
            cap_size(self.db, max_bytes)

    @contextlib.contextmanager
    def transaction(self) -> Iterator[sqlite3.Connection]:
        """``BEGIN IMMEDIATE`` … ``COMMIT``, rolled back when the body raises."""
        self.db.execute("BEGIN IMMEDIATE")
        try:
            yield self.db
            self.db.execute("COMMIT")
        except BaseException:
            with contextlib.suppress(sqlite3.Error):
                self.db.execute("ROLLBACK")
            raise

    def write(
        self,
        write: Callable[[], None],
        evict_oldest: Callable[[], int],
        count_lost: Callable[[int], int],
        n: int,
    ) -> bool:
        """Run ``write`` (``n`` rows) under the lock, within the size cap.

        At the cap ``evict_oldest`` deletes the oldest rows and the write is retried;
        when no room can be made (a full disk) ``count_lost(n)`` counts the rows lost
        and returns the owner's total, logged once per episode. Returns False then;
        nothing is raised for want of space.
        """

        def make_room() -> bool:
            return (
                self.max_bytes is not None
                and at_cap(self.db, self.max_bytes)
                and self.make_room(evict_oldest) > 0
            )

        with self.lock:
            kept = bounded_write(write, make_room, lambda exc: self._lost(n, exc, count_lost))
            if kept and self.failing:
                self.failing = False
                log.warning(
                    "%s %s writable again; %d point(s) dropped in all",
                    self.label,
                    self.path,
                    count_lost(0),
                )
            return kept

    def _lost(self, n: int, exc: sqlite3.Error, count_lost: Callable[[int], int]) -> None:
        count_lost(n)
        if not self.failing:
            self.failing = True
            log.error(
                "%s %s %s (%s): dropping and counting them until it can again",
                self.label,
                self.path,
                self.cannot,
                exc,
            )

    @staticmethod
    def make_room(evict_oldest: Callable[[], int]) -> int:
        """``evict_oldest()``, or 0 when the full disk refuses even the delete."""
        try:
            return evict_oldest()
        except sqlite3.Error as exc:
            if not is_out_of_space(exc):
                raise
            return 0

    def enforce(
        self,
        expire: Callable[[], tuple[int, bool]] | None,
        evict_oldest: Callable[[], int],
        budget_s: float,
    ) -> int:
        """Delete rows past their age, then the oldest while over 98 % of ``max_bytes``.

        ``expire`` deletes one chunk of too-old rows and says how many and whether more
        may be left; ``evict_oldest`` deletes one chunk of the oldest. Works for at most
        about ``budget_s`` (it runs between compensation cycles); what is left is taken
        on the next call. A full disk makes it stop with a warning, nothing raised.
        """
        deadline = time.monotonic() + budget_s
        deleted = 0
        with self.lock:
            try:
                while expire is not None and time.monotonic() < deadline:
                    n, more = expire()
                    deleted += n
                    if not more:
                        break
                if self.max_bytes is not None:
                    target = 0.98 * self.max_bytes
                    while used_bytes(self.db) > target and time.monotonic() < deadline:
                        n = evict_oldest()
                        deleted += n
                        if n == 0:
                            break
            except sqlite3.Error as exc:
                if not is_out_of_space(exc):
                    raise
                log.warning("%s %s: retention step failed (%s)", self.label, self.path, exc)
        return deleted

    def used_bytes(self) -> int:
        """Bytes of the file in use (the quantity ``max_bytes`` bounds)."""
        with self.lock:
            return used_bytes(self.db)

    def close(self) -> None:
        with self.lock:
            self.db.close()
