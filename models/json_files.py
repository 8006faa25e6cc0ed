"""Files written whole or not at all: the model store, proposals, state, the heartbeat, and
the CSV and JSON files the commands write for people and scripts."""

from __future__ import annotations

import json
import os
import tempfile
from collections.abc import Iterator, Mapping
from contextlib import contextmanager
from pathlib import Path
from typing import Any, TextIO


@contextmanager
def atomic_text(path: Path, *, durable: bool = True) -> Iterator[TextIO]:
    """A text file (UTF-8, line endings as written) that appears at ``path`` only whole.

    What is written goes to a temporary file beside ``path`` (``.<name>.<random>.tmp``,
    which matches no ``*.json`` or ``*.csv`` listing), renamed over ``path`` when the
    block ends without an error. The rename is atomic on one file system, so a reader,
    or a gateway restarted after a crash or a full disk, sees the old file or the new
    one, never half of one; on an error the temporary file is removed and ``path`` is
    as it was. An ``OSError`` without a file name (a full disk answers a write with
    ``ENOSPC`` and no name) is raised again naming ``path``.

    ``durable``: the data reach the disk before the rename (``fsync``), and the rename
    before the call returns (``fsync`` of the folder). Without the first, a power cut
    soon after a rename can leave the new name on an empty or partial file on file
    systems that do not order data before metadata (ext4 only guesses at it; an edge
    box's flash card may run f2fs or xfs). ``False`` for files rewritten every cycle
    whose loss costs nothing (the heartbeat): an ``fsync`` on a flash card can take
    tens of ms and wears it.
    """
    path.parent.mkdir(parents=True, exist_ok=True)
    handle, tmp = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.", suffix=".tmp")
    try:
        with os.fdopen(handle, "w", encoding="utf-8", newline="") as out:
            yield out
            if durable:
                out.flush()
                os.fsync(out.fileno())
        os.replace(tmp, path)
    except OSError as exc:
        Path(tmp).unlink(missing_ok=True)
        if exc.filename is None:
            raise OSError(exc.errno, exc.strerror, str(path)) from exc
        raise
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise
    if durable:
        fsync_folder(path.parent)


def write_json_atomic(
    path: Path,
    payload: Mapping[str, Any],
    *,
    indent: int | None = 2,
    sort_keys: bool = False,
    allow_nan: bool = True,
    durable: bool = True,
) -> Path:
    """Write ``payload`` as JSON through :func:`atomic_text` (see there for ``durable``)."""
    with atomic_text(path, durable=durable) as out:
        json.dump(
            payload,
            out,
            indent=indent,
            sort_keys=sort_keys,
            ensure_ascii=False,
            allow_nan=allow_nan,
        )
        out.write("\n")
    return path


def remove_temporaries(folder: Path, patterns: tuple[str, ...] = (".*.tmp",)) -> list[Path]:
    """Remove the temporary files a writer killed mid-write left in ``folder`` (``.*.tmp``,
    as :func:`atomic_text` names them); the caller makes sure no writer is at work there
    (a lock). Returns the files removed."""
    if not folder.is_dir():
        return []
    found = sorted({path for pattern in patterns for path in folder.glob(pattern)})
    for path in found:
        path.unlink(missing_ok=True)
    if found:
        fsync_folder(folder)
    return found


def fsync_folder(folder: Path) -> None:
    """Make a rename in ``folder`` durable (POSIX: an ``fsync`` of the folder itself)."""
    handle = os.open(folder, os.O_RDONLY)
    try:
        os.fsync(handle)
    finally:
        os.close(handle)
