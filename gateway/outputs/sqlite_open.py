"""Opening the gateway's SQLite files when one of them is damaged.

The local store and the InfluxDB disk buffer are logs: the compensation does not
depend on them. A file that SQLite cannot read at all — not a database (another
file at that path, a header overwritten) or a damaged image (a flash card's bad
block, a copy cut short) — must neither stop the gateway nor be thrown away. It is
renamed aside with its ``-wal`` and ``-shm`` companions, as
``<name>.unreadable-<UTC time>``, logged at ERROR with both names, and a new file is
started at the configured path. Any other failure (no permission, a locked file, a
full disk) is raised as it was: moving a good file aside for those would hide it.
"""

from __future__ import annotations

import logging
import sqlite3
import time
from collections.abc import Callable
from pathlib import Path

log = logging.getLogger(__name__)

#: The SQLite result codes of a file it cannot read as a database.
UNREADABLE = (sqlite3.SQLITE_CORRUPT, sqlite3.SQLITE_NOTADB)
COMPANIONS = ("", "-wal", "-shm")
#: The first 16 bytes of every SQLite database file.
HEADER = b"SQLite format 3\x00"


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
