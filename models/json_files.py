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
) -> Path:
    """Write ``payload`` to a temporary file beside ``path``, then rename it over ``path``.

    The rename is atomic on one file system, so a reader, or a gateway restarted after a
    crash or a full disk, sees the old file or the new one, never half of one. The
    temporary name (``.<name>.<random>.tmp``) matches no ``*.json`` listing.
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
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise
    return path
