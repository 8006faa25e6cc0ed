"""When to try again after a failure: capped exponential back-off with jitter.

One helper serves every link of the gateway (the CNC sessions, the transmitter
buses), the InfluxDB forwarder and the supervisor that restarts a failed loop.

Why capped low: a link that is down is retried only at the back-off's pace, so
the cap is also the longest the gateway can take to notice that a peer is back.
A 30 s cap made a 20 s CNC outage cost 14–15 s more after the server returned;
with the link defaults here (0.5 s doubling to 2 s) a returning peer is seen
within 2 s. An attempt against a dead peer on a local network costs one refused
connection, so a short cap does not hammer it.

Why jitter: several machines of one gateway, or several gateways, that lost the
same server at the same moment would otherwise retry in lock-step. Each delay
is drawn from ``[(1 − jitter) · d, d]``, where ``d`` is the exponential step, so
jitter only ever shortens a delay: the cap stays a hard upper bound, and the
lower bound ``(1 − jitter) · initial_s`` stays above zero (a zero delay turns a
dead peer into a busy loop, pymodbus #1794).

Time is passed in by the caller (``now``), so the drivers choose their clock and
tests step it without sleeping; ``rng`` makes the jitter reproducible.
"""

from __future__ import annotations

import random
from dataclasses import dataclass, field


@dataclass
class Backoff:
    """Delays ``initial_s · factor^n`` (n failures since the last success), capped at
    ``max_s``, each shortened by a random fraction of at most ``jitter``.

    Before the first failure, and after :meth:`reset`, an attempt is allowed at once.
    """

    initial_s: float = 0.5
    factor: float = 2.0
    max_s: float = 2.0
    jitter: float = 0.2
    rng: random.Random = field(default_factory=random.Random, repr=False, compare=False)
    failures: int = field(default=0, init=False)
    _step_s: float = field(init=False, repr=False)
    _next_attempt_s: float | None = field(default=None, init=False, repr=False)

    def __post_init__(self) -> None:
        if not self.initial_s > 0:
            raise ValueError(
                f"initial_s must be > 0 (a zero delay busy-loops), got {self.initial_s}"
            )
        if not self.factor >= 1:
            raise ValueError(f"factor must be >= 1, got {self.factor}")
        if not self.max_s >= self.initial_s:
            raise ValueError(f"max_s ({self.max_s}) must be >= initial_s ({self.initial_s})")
        if not 0 <= self.jitter < 1:
            raise ValueError(f"jitter must be in [0, 1), got {self.jitter}")
        self._step_s = self.initial_s

    @property
    def next_attempt_s(self) -> float | None:
        """Earliest time of the next attempt; None when an attempt is allowed at once."""
        return self._next_attempt_s

    def ready(self, now: float) -> bool:
        """True when an attempt may be made at ``now``."""
        return self._next_attempt_s is None or now >= self._next_attempt_s

    def wait_s(self, now: float) -> float:
        """Seconds from ``now`` until an attempt is allowed (0 when it is)."""
        if self._next_attempt_s is None:
            return 0.0
        return max(0.0, self._next_attempt_s - now)

    def failed(self, now: float) -> float:
        """Record a failure at ``now``; return the delay before the next attempt."""
        delay = self._step_s * (1.0 - self.jitter * self.rng.random())
        self._next_attempt_s = now + delay
        self._step_s = min(self._step_s * self.factor, self.max_s)
        self.failures += 1
        return delay

    def reset(self) -> None:
        """It works again: the next failure waits about ``initial_s`` only."""
        self._step_s = self.initial_s
        self._next_attempt_s = None
        self.failures = 0
