"""The simulated plant and a compensation loop on one clock, with the error at the tool.

The demo and the integration tests both pair a :class:`~simulator.serve.SimulatedPlant`
with the gateway's loop and record, per cycle, the thermal error the tool would see
without compensation (the machine's own Z growth) and with it (growth minus what the
CNC applied), in Z and along every other axis the machine grows in. The loop is only
known through :class:`CompensationLoop`, the few members this pairing uses, so the simulator
stays below the gateway in the import order.
"""

from __future__ import annotations

import asyncio
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any, Generic, Protocol, TypeVar

import numpy as np

from drivers.clock import Clock, ManualClock
from simulator.serve import SimulatedPlant


class _HasCycle(Protocol):
    @property
    def cycle_s(self) -> float: ...


class _TimedRecord(Protocol):
    @property
    def time_s(self) -> float: ...


class CompensationLoop(Protocol):
    """What the pairing needs of a loop (``gateway.live.loop.MachineLoop`` has it)."""

    @property
    def config(self) -> _HasCycle: ...

    @property
    def clock(self) -> Clock: ...

    @property
    def sinks(self) -> list[Callable[[Any], None]]: ...

    async def run_cycle(self) -> Any: ...

    async def run(self, stop: asyncio.Event | None = None) -> None: ...


LoopT = TypeVar("LoopT", bound=CompensationLoop)


def error_figures(uncompensated_um: Any, compensated_um: Any) -> dict[str, float]:
    """Peak and RMS of the error at the tool without and with compensation, µm."""
    without = np.asarray(uncompensated_um, dtype=float)
    with_ = np.asarray(compensated_um, dtype=float)
    return {
        "uncompensated_peak_um": float(np.max(np.abs(without))),
        "compensated_peak_um": float(np.max(np.abs(with_))),
        "uncompensated_rmse_um": float(np.sqrt(np.mean(without**2))),
        "compensated_rmse_um": float(np.sqrt(np.mean(with_**2))),
        "reduction_pct": float(100.0 * (1 - np.max(np.abs(with_)) / np.max(np.abs(without)))),
    }


@dataclass
class Trace:
    """Per cycle: the error at the tool without and with compensation, µm, and the loop's record.

    ``uncompensated_um`` / ``compensated_um`` are Z's; ``axes_um`` holds every axis's
    pair of lists by axis name (Z included, the same values).
    """

    time_s: list[float] = field(default_factory=list)
    uncompensated_um: list[float] = field(default_factory=list)
    compensated_um: list[float] = field(default_factory=list)
    records: list[Any] = field(default_factory=list)
    axes_um: dict[str, tuple[list[float], list[float]]] = field(default_factory=dict)

    def summary(self) -> dict[str, float]:
        return {
            **error_figures(self.uncompensated_um, self.compensated_um),
            "cycles": len(self.time_s),
        }

    def axis_summary(self) -> dict[str, dict[str, float]]:
        """Peak, RMS and reduction of each axis's error at the tool (:func:`error_figures`)."""
        return {axis: error_figures(*pair) for axis, pair in self.axes_um.items()}


class ClosedLoop(Generic[LoopT]):
    """The simulated plant and a compensation loop on one clock."""

    def __init__(self, plant: SimulatedPlant, loop: LoopT) -> None:
        self.plant = plant
        self.loop = loop
        self.trace = Trace()
        loop.sinks.append(self._observe)

    def _observe(self, record: _TimedRecord) -> None:
        machine = self.plant.machine
        self.trace.time_s.append(record.time_s)
        self.trace.uncompensated_um.append(machine.growth_um())
        self.trace.compensated_um.append(machine.true_error_um())
        for axis in machine.axis_names:
            without, with_ = self.trace.axes_um.setdefault(axis, ([], []))
            without.append(machine.axis_growth_um(axis))
            with_.append(machine.axis_true_error_um(axis))
        self.trace.records.append(record)

    async def step(self, clock: ManualClock) -> Any:
        """One deterministic cycle: advance time, update the machine, run the loop."""
        clock.advance(self.loop.config.cycle_s)
        await self.plant.update()
        return await self.loop.run_cycle()

    async def run_until(self, end_s: float) -> None:
        """Run the loop on its own clock until the clock reaches ``end_s``."""
        stop = asyncio.Event()

        async def watch() -> None:
            while self.loop.clock.now() < end_s:
                await asyncio.sleep(0.05)
            stop.set()

        await asyncio.gather(self.loop.run(stop), watch())
