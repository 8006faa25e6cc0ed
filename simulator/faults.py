"""Injectable sensor faults, as a transmitter would report them.

- ``open_circuit``: a broken Pt100 lead; the channel's status register shows the
  open-circuit code and the value is meaningless.
- ``stuck``: the reading freezes at its value when the fault starts.
- ``spike``: the reading jumps by ``magnitude_C`` (default +40 °C) while active.
- ``drift``: the reading creeps by ``magnitude_C`` per hour (default 2 °C/h).

A fault is active from ``start_s`` until ``end_s`` (machine time; None: for ever).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

from simulator.link import ChannelReading, ChannelStatus

KINDS = ("open_circuit", "stuck", "spike", "drift")
DEFAULT_MAGNITUDE = {"spike": 40.0, "drift": 2.0, "open_circuit": 0.0, "stuck": 0.0}


@dataclass
class SensorFault:
    sensor: str
    kind: str
    start_s: float
    end_s: float | None = None
    magnitude_C: float | None = None
    _held_C: float | None = field(default=None, repr=False)

    def __post_init__(self) -> None:
        if self.kind not in KINDS:
            raise ValueError(f"unknown fault '{self.kind}'; expected one of {KINDS}")
        if self.end_s is not None and self.end_s <= self.start_s:
            raise ValueError("a fault must end after it starts")
        if self.magnitude_C is None:
            self.magnitude_C = DEFAULT_MAGNITUDE[self.kind]

    @property
    def held_C(self) -> float | None:
        """The value a stuck sensor shows (None until the machine took it)."""
        return self._held_C

    def hold(self, value_C: float) -> None:
        self._held_C = value_C

    def active(self, time_s: float) -> bool:
        return time_s >= self.start_s and (self.end_s is None or time_s < self.end_s)

    def apply(self, reading: ChannelReading, time_s: float) -> ChannelReading:
        if not self.active(time_s):
            self._held_C = None
            return reading
        if self.kind == "open_circuit":
            return ChannelReading(math.nan, ChannelStatus.OPEN_CIRCUIT)
        if self.kind == "stuck":
            if self._held_C is None:
                self._held_C = reading.value_C
            return ChannelReading(self._held_C, reading.status)
        if self.kind == "spike":
            return ChannelReading(reading.value_C + self.magnitude_C, reading.status)
        hours = (time_s - self.start_s) / 3600.0
        return ChannelReading(reading.value_C + self.magnitude_C * hours, reading.status)
