"""One notion of time for the simulator and the gateway.

Machine time is in seconds. In the plant it is wall time. In tests and the demo,
an accelerated clock runs machine time ``speedup`` times faster than the wall
(an hour of machine time in seconds), and a manual clock moves only when told,
so a test never has to sleep for real. The gateway and the simulated machine
share one clock object, so they agree on what "now" is.

Two times, each for one job. ``now`` is machine time, and on the wall clock it
follows ``time.monotonic()``: the cycles are scheduled on it and every rate (slew,
lags, quality) is computed from it, so a step of the system clock (an NTP step, an
operator's ``date -s``) neither bunches nor stalls the cycles. ``stamp`` is the time
every output stamps a cycle with (the log's points, Sparkplug, the heartbeat): on the
wall clock the system's wall time (``time.time()``), taken once per cycle, so the
outputs agree with each other and with the rest of the plant even after a step, or
after a pause of the host that the monotonic clock did not count (a suspended virtual
machine: its wall clock is set right on resume, its monotonic clock stays behind).
A simulated clock stamps with machine time.

Every ``sleep`` takes an optional ``stop`` event and returns as soon as it is set:
a gateway asked to stop (SIGTERM) must not wait out a cycle of minutes first.
"""

from __future__ import annotations

import asyncio
import contextlib
import time
from typing import Protocol


class Clock(Protocol):
    def now(self) -> float:
        """Machine time, s."""
        ...

    async def sleep(self, seconds: float, stop: asyncio.Event | None = None) -> None:
        """Wait ``seconds`` of machine time, or less when ``stop`` is set meanwhile."""
        ...

    def stamp(self) -> float:
        """The time outputs stamp a cycle with, s (wall time on the wall clock)."""
        ...


async def wait_or_stop(wall_s: float, stop: asyncio.Event | None) -> None:
    """Sleep ``wall_s`` wall seconds, returning early (at once) when ``stop`` is set."""
    wall_s = max(0.0, wall_s)
    if stop is None:
        await asyncio.sleep(wall_s)
        return
    if stop.is_set():
        return
    # asyncio.timeout cancels this task's own wait when it expires: one timer, where
    # wait_for (3.11) adds a task for the wait and a second loop pass to cancel it
    # (the cycle scheduler sleeps here several times per cycle).
    with contextlib.suppress(TimeoutError):
        async with asyncio.timeout(wall_s):
            await stop.wait()


class WallClock:
    """Machine time = wall time (monotonic, from an origin)."""

    def __init__(self, origin_s: float = 0.0) -> None:
        self._start = time.monotonic()
        self._origin = origin_s

    def now(self) -> float:
        return self._origin + (time.monotonic() - self._start)

    async def sleep(self, seconds: float, stop: asyncio.Event | None = None) -> None:
        await wait_or_stop(seconds, stop)

    def stamp(self) -> float:
        """The system's wall time (Unix s): it follows NTP and steps, ``now`` does not."""
        return time.time()


class AcceleratedClock:
    """Machine time runs ``speedup`` × faster than the wall (speedup 3600: an hour a second)."""

    def __init__(self, speedup: float, origin_s: float = 0.0) -> None:
        if not speedup > 0:
            raise ValueError(f"speedup must be > 0, got {speedup}")
        self.speedup = float(speedup)
        self._start = time.monotonic()
        self._origin = origin_s

    def now(self) -> float:
        return self._origin + (time.monotonic() - self._start) * self.speedup

    async def sleep(self, seconds: float, stop: asyncio.Event | None = None) -> None:
        await wait_or_stop(max(0.0, seconds) / self.speedup, stop)

    def stamp(self) -> float:
        return self.now()


class ManualClock:
    """Machine time that moves only through ``advance``; ``sleep`` advances it at once
    (unless ``stop`` is already set: a stopped sleeper does not move time)."""

    def __init__(self, origin_s: float = 0.0) -> None:
        self._now = origin_s

    def now(self) -> float:
        return self._now

    def stamp(self) -> float:
        return self._now

    def advance(self, seconds: float) -> float:
        if seconds < 0:
            raise ValueError("time does not go backwards")
        self._now += seconds
        return self._now

    async def sleep(self, seconds: float, stop: asyncio.Event | None = None) -> None:
        if stop is None or not stop.is_set():
            self.advance(max(0.0, seconds))
        await asyncio.sleep(0)
