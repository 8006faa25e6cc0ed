"""Link health and reconnect pacing shared by every protocol client of the gateway.

Field links fail in ordinary ways: a transmitter is unplugged, a cable is re-plugged,
the CNC restarts its OPC UA server. The gateway must keep running, report what is
wrong, and reconnect on its own without hammering the peer. That bookkeeping is the
same for Modbus and OPC UA, so it lives here and knows no protocol.

Time is always passed in by the caller (``now``): the drivers decide which clock
counts (a monotonic clock in the plant), and tests step time without sleeping.
"""

from __future__ import annotations

from dataclasses import dataclass, field


@dataclass
class LinkHealth:
    """What the gateway knows about one link (a bus, a device on it, a CNC session).

    ``connected`` is True while the link delivers data. ``consecutive_failures``
    resets on the next success, ``total_failures`` never does, so a flapping link is
    visible even when it currently works. ``last_error`` keeps the latest failure's
    text after recovery (the diagnosis is still useful); ``last_ok_s`` is the
    caller's time of the latest success.
    """

    connected: bool = False
    consecutive_failures: int = 0
    total_failures: int = 0
    reconnects: int = 0
    last_error: str | None = None
    last_ok_s: float | None = None
    #: Set on the first connection, so later connections count as reconnects.
    ever_connected: bool = field(default=False, repr=False)

    def record_ok(self, now: float) -> None:
        """The link delivered data at ``now``."""
        self.connected = True
        self.consecutive_failures = 0
        self.last_ok_s = now

    def record_failure(self, error: str) -> None:
        """The link failed to deliver (no answer, connection lost, cannot connect)."""
        self.connected = False
        self.consecutive_failures += 1
        self.total_failures += 1
        self.last_error = error

    def record_connect(self) -> None:
        """A connection was established; every one after the first is a reconnect."""
        if self.ever_connected:
            self.reconnects += 1
        self.ever_connected = True


@dataclass
class Backoff:
    """When the next reconnect attempt may happen: exponential, capped, never zero.

    A zero delay turns a dead peer into a busy loop (pymodbus #1794), so the delay
    starts at ``initial_s`` > 0, grows by ``factor`` after each failed attempt up to
    ``max_s``, and returns to ``initial_s`` only after ``reset()`` (a link that
    delivered data again). Before the first failure an attempt is allowed at once.
    """

    initial_s: float = 0.5
    factor: float = 2.0
    max_s: float = 30.0
    _delay_s: float = field(init=False, repr=False)
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
        self._delay_s = self.initial_s

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
        delay = self._delay_s
        self._next_attempt_s = now + delay
        self._delay_s = min(self._delay_s * self.factor, self.max_s)
        return delay

    def reset(self) -> None:
        """The link works again: the next failure waits ``initial_s`` only."""
        self._delay_s = self.initial_s
        self._next_attempt_s = None
