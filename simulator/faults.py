"""Injectable sensor faults, as a transmitter would report them.

- ``open_circuit``: a broken Pt100 lead; the channel's status register shows the
  open-circuit code and the value is meaningless.
- ``stuck``: the reading freezes at its value when the fault starts.
- ``spike``: the reading jumps by ``magnitude_C`` (default +40 °C) while active.
- ``drift``: the reading creeps by ``magnitude_C`` per hour (default 2 °C/h);
  :meth:`SensorFault.drift_C_per_s` states a fast drift in °C/s.
- ``offset``: the reading steps by ``magnitude_C`` (default +3 °C) and stays
  there while active: a loosened probe, a re-wired channel, a wrong calibration.
- ``bias``: the reading moves away by ``magnitude_C`` (default +2 °C) spread
  evenly over ``ramp_s`` (default 2 h), then holds that bias: a transmitter
  ageing, a probe slowly losing contact. Too slow for any rate check.

A fault is active from ``start_s`` until ``end_s`` (machine time; None: for ever).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

from simulator.link import ChannelReading, ChannelStatus

KINDS = ("open_circuit", "stuck", "spike", "drift", "offset", "bias")
DEFAULT_MAGNITUDE = {
    "spike": 40.0,
    "drift": 2.0,
    "open_circuit": 0.0,
    "stuck": 0.0,
    "offset": 3.0,
    "bias": 2.0,
}
DEFAULT_BIAS_RAMP_S = 7200.0


@dataclass
class SensorFault:
    sensor: str
    kind: str
    start_s: float
    end_s: float | None = None
    magnitude_C: float | None = None
    ramp_s: float | None = None  # ``bias`` only: how long the bias takes to build up, s
    _held_C: float | None = field(default=None, repr=False)

    def __post_init__(self) -> None:
        if self.kind not in KINDS:
            raise ValueError(f"unknown fault '{self.kind}'; expected one of {KINDS}")
        if self.end_s is not None and self.end_s <= self.start_s:
            raise ValueError("a fault must end after it starts")
        if self.magnitude_C is None:
            self.magnitude_C = DEFAULT_MAGNITUDE[self.kind]
        if self.ramp_s is not None and self.kind != "bias":
            raise ValueError(f"ramp_s applies to a 'bias' fault only, not to '{self.kind}'")
        if self.kind == "bias":
            self.ramp_s = DEFAULT_BIAS_RAMP_S if self.ramp_s is None else self.ramp_s
            if not self.ramp_s > 0:
                raise ValueError(f"a bias needs ramp_s > 0, got {self.ramp_s}")

    @classmethod
    def drift_C_per_s(
        cls, sensor: str, rate_C_per_s: float, start_s: float, end_s: float | None = None
    ) -> SensorFault:
        """A ``drift`` stated in °C per second (stored as °C per hour)."""
        return cls(sensor, "drift", start_s, end_s, magnitude_C=rate_C_per_s * 3600.0)

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
        magnitude_C = self.magnitude_C
        assert magnitude_C is not None  # every kind's default is set in __post_init__
        if self.kind in ("spike", "offset"):
            return ChannelReading(reading.value_C + magnitude_C, reading.status)
        if self.kind == "bias":
            assert self.ramp_s is not None
            share = min(1.0, (time_s - self.start_s) / self.ramp_s)
            return ChannelReading(reading.value_C + magnitude_C * share, reading.status)
        hours = (time_s - self.start_s) / 3600.0
        return ChannelReading(reading.value_C + magnitude_C * hours, reading.status)
