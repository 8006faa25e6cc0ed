"""JSON files written whole or not at all (model store, proposals, state, heartbeat)."""

from __future__ import annotations

import json
import os
import tempfile
from collections.abc import Mapping
from pathlib import Path
from typing import Any


def write_json_atomic(
    path: Path,
    payload: Mapping[str, Any],
    *,
    indent: int | None = 2,
    sort_keys: bool = False,
    allow_nan: bool = True,
    durable: bool = True,
) -> Path:
    """Write ``payload`` to a temporary file beside ``path``, then rename it over ``path``.

    The rename is atomic on one file system, so a reader, or a gateway restarted after a
    crash or a full disk, sees the old file or the new one, never half of one. The
    temporary name (``.<name>.<random>.tmp``) matches no ``*.json`` listing.

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
        with os.fdopen(handle, "w", encoding="utf-8") as out:
            json.dump(
                payload,
                out,
                indent=indent,
                sort_keys=sort_keys,
                ensure_ascii=False,
                allow_nan=allow_nan,
            )
            out.write("\n")
            if durable:
                out.flush()
                os.fsync(out.fileno())
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise
    if durable:
        _fsync_folder(path.parent)
    return path


def _fsync_folder(folder: Path) -> None:
    """Make a rename in ``folder`` durable (POSIX: an ``fsync`` of the folder itself)."""
    handle = os.open(folder, os.O_RDONLY)
    try:
        os.fsync(handle)
    finally:
        os.close(handle)
