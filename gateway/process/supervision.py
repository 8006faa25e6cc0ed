"""Keeping each long-running task of the gateway alive on its own.

A gateway serves several machines and forwards their logs. One of those tasks
failing (a bug, a full disk, a library raising what it never raised before) must
not end the others: each machine keeps compensating while another is restarted.
:class:`Supervised` runs one task until the stop event, and when it raises:

- logs it: the traceback the first time a given error occurs, then one line per
  restart, so a task that fails every few seconds does not flood the log;
- counts it (``restarts``, ``last_error``), for the health published to SCADA
  and written to the heartbeat;
- starts it again after a :class:`drivers.backoff.Backoff` delay (0.5 s doubling
  to 30 s by default). The delay is cut short by the stop event, and goes back
  to its start once the task made progress (``progress`` grew since the start),
  so a task that fails rarely restarts quickly and one that fails at once does
  not spin.

Cancellation (the gateway shutting down) is not a failure and is not restarted.
"""

from __future__ import annotations

import asyncio
import logging
import time
from collections.abc import Awaitable, Callable
from dataclasses import dataclass, field

from drivers.backoff import Backoff
from drivers.clock import wait_or_stop

log = logging.getLogger(__name__)


def restart_backoff() -> Backoff:
    """The restart pacing of a supervised task: 0.5 s doubling to 30 s, 20 % jitter."""
    return Backoff(initial_s=0.5, factor=2.0, max_s=30.0, jitter=0.2)


@dataclass
class Supervised:
    """One supervised task: ``start`` runs ``run(stop)`` again after every failure.

    ``progress`` (optional) returns a count that grows while the task does its job
    (cycles run, points sent); when it grew before a failure, the back-off restarts
    from its first step.
    """

    name: str
    run: Callable[[asyncio.Event], Awaitable[None]]
    progress: Callable[[], int] | None = None
    backoff: Backoff = field(default_factory=restart_backoff)
    # Called when the task raised, before the back-off: who publishes the task's state
    # (the Sparkplug node's DDEATH of a machine) learns that it stopped.
    on_failure: Callable[[], None] | None = None
    restarts: int = 0
    last_error: str | None = None
    last_error_time: float | None = None
    _seen: set[str] = field(default_factory=set, init=False, repr=False)

    async def supervise(self, stop: asyncio.Event) -> None:
        """Run the task until ``stop`` is set or it returns; restart it when it raises."""
        while not stop.is_set():
            before = self.progress() if self.progress is not None else 0
            try:
                await self.run(stop)
                return
            except Exception as exc:  # any failure of the task is supervised
                after = self.progress() if self.progress is not None else 0
                if after > before:
                    self.backoff.reset()
                delay_s = self.backoff.failed(time.monotonic())
                self._record(exc, delay_s)
                self._tell_stopped()
            await wait_or_stop(delay_s, stop)
            if not stop.is_set():
                self.restarts += 1

    def _tell_stopped(self) -> None:
        if self.on_failure is None:
            return
        try:
            self.on_failure()
        except Exception:  # the listener's fault must not stop the restart
            log.exception("%s: telling that it stopped failed", self.name)

    def _record(self, exc: Exception, delay_s: float) -> None:
        text = f"{type(exc).__name__}: {exc}"
        self.last_error = text
        self.last_error_time = time.time()
        if text not in self._seen:
            self._seen.add(text)
            log.error("%s failed; restarting it in %.1f s", self.name, delay_s, exc_info=exc)
        else:
            log.error(
                "%s failed again (%s); restarting it in %.1f s (restarts so far: %d)",
                self.name,
                text,
                delay_s,
                self.restarts,
            )

    def health(self) -> dict[str, int | str | None]:
        return {"restarts": self.restarts, "last_error": self.last_error}
