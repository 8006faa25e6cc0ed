"""What protocol endpoints see of a machine: a snapshot to publish, macro writes to apply.

Endpoints (Modbus transmitters, the CNC over OPC UA or Modbus) do not know the
physics. They publish ``snapshot()`` and forward a client's write of a macro
variable to ``write_macro()``. Anything with these two methods can stand behind an
endpoint: the simulated machine, or a fixed table of values in an endpoint's own
unit tests.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from enum import IntEnum
from typing import Protocol

MACRO_FIRST = 500
MACRO_LAST = 999


class ChannelStatus(IntEnum):
    """Status register codes of a temperature-transmitter channel."""

    OK = 0
    OPEN_CIRCUIT = 1
    SHORT_CIRCUIT = 2
    OUT_OF_RANGE = 3


class RunMode(IntEnum):
    """CNC run mode, FANUC-like (published as an integer)."""

    STOP = 0
    AUTO = 1  # running a programme from memory
    MDI = 2
    JOG = 3


@dataclass(frozen=True)
class ChannelReading:
    """One transmitter channel: the temperature it reports (°C) and its status.

    With ``status`` OPEN_CIRCUIT the value is meaningless (NaN here); a real
    module then shows its fault code in the value register too.
    """

    value_C: float
    status: ChannelStatus = ChannelStatus.OK


@dataclass(frozen=True)
class MachineSnapshot:
    """Everything the machine's endpoints publish at one instant (machine time)."""

    time_s: float
    channels: dict[str, ChannelReading]
    actual_speed_rpm: float
    commanded_speed_rpm: float
    run_mode: RunMode
    macros: dict[int, float] = field(default_factory=dict)
    probe_error_um: float | None = None


class MachineLink(Protocol):
    def snapshot(self) -> MachineSnapshot: ...

    def write_macro(self, number: int, value: float) -> None:
        """Apply a client's write of macro #number; ValueError outside #500–#999."""
        ...


def check_macro_number(number: int) -> None:
    if not MACRO_FIRST <= number <= MACRO_LAST:
        raise ValueError(
            f"macro variable #{number} is outside the retained common range "
            f"#{MACRO_FIRST}–#{MACRO_LAST}"
        )


class FixedLink:
    """A machine that stands still: fixed values, writable macros.

    For endpoint tests that need known values, and for serving a recorded state.
    """

    def __init__(self, snapshot: MachineSnapshot) -> None:
        self._snapshot = snapshot
        self.macros: dict[int, float] = dict(snapshot.macros)
        self.writes: list[tuple[int, float]] = []

    def snapshot(self) -> MachineSnapshot:
        s = self._snapshot
        return MachineSnapshot(
            time_s=s.time_s,
            channels=dict(s.channels),
            actual_speed_rpm=s.actual_speed_rpm,
            commanded_speed_rpm=s.commanded_speed_rpm,
            run_mode=s.run_mode,
            macros=dict(self.macros),
            probe_error_um=s.probe_error_um,
        )

    def set_snapshot(self, snapshot: MachineSnapshot) -> None:
        self._snapshot = snapshot
        self.macros.update(snapshot.macros)

    def write_macro(self, number: int, value: float) -> None:
        check_macro_number(number)
        self.macros[number] = float(value)
        self.writes.append((number, float(value)))
