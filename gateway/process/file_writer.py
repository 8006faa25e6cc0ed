"""Files written by one thread, so the event loop never waits for the disk.

Every machine writes its heartbeat each cycle and its lag states on its first cycle
(and every minute after): a rename, and for the lag states two ``fsync`` calls. On a
busy or slow disk each takes milliseconds, and on the event loop they added up to
seconds at a thousand machines: every other machine's cycle waited for them. Here the
loop only hands over the file's text (:meth:`FileWriter.submit`); one thread per
writer writes it, through :func:`models.json_files.atomic_text`, so a reader (or a
restart after a kill) still finds the old file or the new one, never half of one.

Per file, the newest text wins: a file handed over again before its turn is written
once, with the newest text (a machine that cycles faster than the disk writes loses
nothing but superseded states). Files are written in the order they were first
handed over, so every machine gets its turn. :meth:`FileWriter.drain` waits (on the
event loop, without a thread of its own) until what was handed over is on disk: a
stop flushes the last state that way. At interpreter exit whatever is still queued
is written too (bounded by :data:`EXIT_FLUSH_S`).
"""

from __future__ import annotations

import asyncio
import atexit
import contextlib
import logging
import threading
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

from models.json_files import atomic_text

log = logging.getLogger(__name__)

#: Called in the writer thread once a file is written (None) or failed (the error).
Done = Callable[[Path, OSError | None], None]
#: The longest the interpreter's exit waits for queued files.
EXIT_FLUSH_S = 5.0


@dataclass
class _Job:
    text: str
    done: Done | None


class FileWriter:
    """One thread writing files atomically (``durable``: with ``fsync``, see
    :func:`models.json_files.atomic_text`). The thread starts with the first file."""

    def __init__(self, name: str, *, durable: bool) -> None:
        self.name = name
        self.durable = durable
        #: Files written, and hand-overs that replaced a text still waiting.
        self.written = 0
        self.superseded = 0
        self._cond = threading.Condition()
        self._pending: dict[Path, _Job] = {}
        self._writing: Path | None = None
        self._waiters: list[tuple[asyncio.AbstractEventLoop, asyncio.Future[None]]] = []
        self._thread: threading.Thread | None = None

    @property
    def idle(self) -> bool:
        """Nothing waiting and nothing being written."""
        with self._cond:
            return not self._pending and self._writing is None

    def submit(self, path: Path, text: str, done: Done | None = None) -> None:
        """Have ``text`` written to ``path`` soon; a text for ``path`` still waiting is
        replaced (its ``done`` is not called). Never blocks on the disk."""
        with self._cond:
            if path in self._pending:
                self.superseded += 1
            self._pending[path] = _Job(text, done)  # a replaced one keeps its place
            if self._thread is None:
                self._thread = threading.Thread(target=self._run, name=self.name, daemon=True)
                self._thread.start()
                atexit.register(self.flush, EXIT_FLUSH_S)
            self._cond.notify_all()  # the thread, not only a flush() waiting on the same

    def flush(self, timeout_s: float | None = None) -> bool:
        """Block until everything handed over is written; False if ``timeout_s`` passed."""
        with self._cond:
            return self._cond.wait_for(
                lambda: not self._pending and self._writing is None, timeout_s
            )

    async def drain(self) -> None:
        """Wait, on the event loop, until everything handed over is written (the writer
        is idle: a stop, after the last cycle, waits for its last files this way)."""
        loop = asyncio.get_running_loop()
        future: asyncio.Future[None] = loop.create_future()
        with self._cond:
            if not self._pending and self._writing is None:
                return
            self._waiters.append((loop, future))
        await future

    def _run(self) -> None:
        while True:
            with self._cond:
                self._cond.wait_for(lambda: bool(self._pending))
                path = next(iter(self._pending))
                job = self._pending.pop(path)
                self._writing = path
            self._write(path, job)
            with self._cond:
                self._writing = None
                if self._pending:
                    continue
                self._cond.notify_all()
                waiters, self._waiters = self._waiters, []
            for loop, future in waiters:
                with contextlib.suppress(RuntimeError):  # that loop has closed meanwhile
                    loop.call_soon_threadsafe(_resolve, future)

    def _write(self, path: Path, job: _Job) -> None:
        error: OSError | None = None
        try:
            with atomic_text(path, durable=self.durable) as out:
                out.write(job.text)
            self.written += 1
        except OSError as exc:
            error = exc
        except Exception:  # not the disk (text it cannot encode): the thread goes on
            log.exception("%s: cannot write", path)
            return
        if job.done is None:
            if error is not None:
                log.error("%s: cannot write: %s", path, error)
            return
        try:
            job.done(path, error)
        except Exception:  # a caller's bug must not stop every later write
            log.exception("%s: the callback after writing failed", path)


def _resolve(future: asyncio.Future[None]) -> None:
    if not future.done():  # a waiter cancelled meanwhile
        future.set_result(None)


#: The heartbeats: replaced every cycle, not synced (their loss costs nothing).
HEARTBEATS = FileWriter("heartbeat-writer", durable=False)
#: Saved state that a restart carries on from (the lag states): synced.
STATE = FileWriter("state-writer", durable=True)
