"""One notion of time for the simulator and the gateway.

Machine time is in seconds. In the plant it is wall time. In tests and the demo,
an accelerated clock runs machine time ``speedup`` times faster than the wall
(an hour of machine time in seconds), and a manual clock moves only when told,
so a test never has to sleep for real. The gateway and the simulated machine
share one clock object, so they agree on what "now" is.
"""

from __future__ import annotations

import asyncio
import time
from typing import Protocol


class Clock(Protocol):
    def now(self) -> float:
        """Machine time, s."""
        ...

    async def sleep(self, seconds: float) -> None:
        """Wait ``seconds`` of machine time."""
        ...


class WallClock:
    """Machine time = wall time (monotonic, from an origin)."""

    def __init__(self, origin_s: float = 0.0) -> None:
        self._start = time.monotonic()
        self._origin = origin_s

    def now(self) -> float:
        return self._origin + (time.monotonic() - self._start)

    async def sleep(self, seconds: float) -> None:
        await asyncio.sleep(max(0.0, seconds))


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

    async def sleep(self, seconds: float) -> None:
        await asyncio.sleep(max(0.0, seconds) / self.speedup)


class ManualClock:
    """Machine time that moves only through ``advance``; ``sleep`` advances it at once."""

    def __init__(self, origin_s: float = 0.0) -> None:
        self._now = origin_s

    def now(self) -> float:
        return self._now

    def advance(self, seconds: float) -> float:
        if seconds < 0:
            raise ValueError("time does not go backwards")
        self._now += seconds
        return self._now

    async def sleep(self, seconds: float) -> None:
        self.advance(max(0.0, seconds))
        await asyncio.sleep(0)
