"""Link health and reconnect pacing shared by every protocol client of the gateway.

Field links fail in ordinary ways: a transmitter is unplugged, a cable is re-plugged,
the CNC restarts its OPC UA server. The gateway must keep running, report what is
wrong, and reconnect on its own without hammering the peer. That bookkeeping is the
same for Modbus and OPC UA, so it lives here and knows no protocol; the pacing of
reconnect attempts is :class:`drivers.backoff.Backoff`, shared with the forwarder.

Time is always passed in by the caller (``now``): the drivers decide which clock
counts (a monotonic clock in the plant), and tests step time without sleeping.
"""

from __future__ import annotations

from dataclasses import dataclass, field

from drivers.backoff import Backoff

__all__ = ["Backoff", "LinkHealth"]  # Backoff lives in drivers.backoff; kept importable here


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
