"""Run ``python -m gateway ARGS`` and SIGKILL it just before its Nth change under a folder.

``python -m tests.kill_at_write N FOLDER ARGS…``: an audit hook (:func:`sys.addaudithook`)
counts the file-system changes the command makes under FOLDER (a file opened for
writing, a rename or replace, a link, a removal) and sends the process a real
``SIGKILL`` as the Nth begins, so every step of a writer can be cut, whatever code
does the writing. Fewer than N changes: the command ends as it would.
"""

from __future__ import annotations

import os
import runpy
import signal
import sys
from typing import Any

WRITE_FLAGS = os.O_WRONLY | os.O_RDWR | os.O_CREAT | os.O_APPEND | os.O_TRUNC


def is_change(event: str, args: tuple[Any, ...]) -> str | None:
    """The path an audit event changes, or None."""
    if event == "open":
        path, mode, flags = args
        writing = any(c in mode for c in "wax+") if isinstance(mode, str) else False
        if writing or (isinstance(flags, int) and flags & WRITE_FLAGS):
            return os.fsdecode(path) if isinstance(path, str | bytes) else None
        return None
    if event in ("os.rename", "os.link", "os.remove", "os.unlink"):
        return os.fsdecode(args[0])
    return None


def main() -> None:
    limit, folder = int(sys.argv[1]), os.path.realpath(sys.argv[2])
    seen = [0]

    def hook(event: str, args: tuple[Any, ...]) -> None:
        path = is_change(event, args)
        if path is None or not os.path.realpath(path).startswith(folder + os.sep):
            return
        seen[0] += 1
        if seen[0] >= limit:
            os.kill(os.getpid(), signal.SIGKILL)

    sys.argv = ["gateway", *sys.argv[3:]]
    sys.addaudithook(hook)
    runpy.run_module("gateway", run_name="__main__", alter_sys=True)


if __name__ == "__main__":
    main()
