"""One running gateway per state folder.

A second ``run`` on the same configuration (a service started by hand while
systemd or the container already runs it) would poll the same CNC and write
the same compensation macros, each gateway taking the other's writes for an
operator's change, and both would overwrite the same reference and lag-state
files. ``run`` therefore holds an exclusive ``flock`` on
``<state_dir>/gateway.lock`` while it runs, and a second one is refused before it
opens any connection. The kernel drops the lock when the holder exits, however
it exits (``kill -9``, a power cut), so a stale lock never blocks a restart; the
file keeps the holder's process id only to say who holds it.
"""

from __future__ import annotations

import contextlib
import fcntl
import os
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

LOCK_NAME = "gateway.lock"


class StateDirInUseError(ValueError):
    """Another process holds the state folder's lock."""


@contextmanager
def hold_state_dir(state_dir: Path) -> Iterator[Path]:
    """Hold ``state_dir``'s lock for the ``with`` block; the lock file's path is yielded."""
    state_dir.mkdir(parents=True, exist_ok=True)
    path = state_dir / LOCK_NAME
    fd = os.open(path, os.O_RDWR | os.O_CREAT, 0o644)
    try:
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            holder = os.pread(fd, 32, 0).decode("ascii", "replace").strip() or "unknown"
            raise StateDirInUseError(
                f"state_dir {state_dir}: another gateway (pid {holder}) is running on it; "
                "two would write the same CNC macros and state files: stop that one, or give "
                "this one a state_dir of its own"
            ) from None
        # Only to name the holder: a full disk must not stop the gateway from starting.
        with contextlib.suppress(OSError):
            os.ftruncate(fd, 0)
            os.pwrite(fd, f"{os.getpid()}\n".encode("ascii"), 0)
        yield path
    finally:
        os.close(fd)  # closing the last descriptor releases the lock
