"""A simulated machine compensated at a 1 s cycle over the real protocols, for tests.

The plant serves its transmitters over Modbus TCP and its CNC over Modbus TCP
(or OPC UA); the gateway's own loop, configured as :func:`tests.gateway_rig.machine_entry`
configures a machine, polls them every second of a manual clock, with the store the
demo fits. At a 1 s cycle the prediction rate bound allows 1.1 µm from one cycle to
the next: the noise of a fallback model with large coefficients comes close to it,
which a 30 s cycle (4 µm) hides.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from pathlib import Path

from drivers.clock import ManualClock
from gateway.config import MachineSection
from gateway.demo.compensate import open_loop
from gateway.live.record import CycleRecord
from simulator.closed_loop import ClosedLoop
from simulator.faults import SensorFault
from tests import gateway_rig as rig
from tests.test_plausibility_loop import BUSY_PROGRAM, stepped_plant

CYCLE_S = 1.0
SENSORS = rig.SENSORS
#: The faults measured on each sensor in turn: (kind, magnitude °C or °C/h).
FAULTS = {"spike +3 °C": ("spike", 3.0), "drift 20 °C/h": ("drift", 20.0)}


@dataclass
class Run:
    """One run: the closed loop and the records of the cycles after the fault started."""

    closed: ClosedLoop
    after: list[CycleRecord] = field(default_factory=list)

    @property
    def predicting(self) -> float:
        """Share of the cycles after the fault with a prediction."""
        return sum(r.predicted_um is not None for r in self.after) / len(self.after)

    @property
    def predicting_answered(self) -> float:
        """Share of the cycles after the fault in which every source answered, with a
        prediction (:func:`tests.gateway_rig.answered`: at most 1 % unanswered)."""
        answered = rig.answered(self.after)
        return sum(r.predicted_um is not None for r in answered) / len(answered)

    def held(self) -> list[str]:
        """Every sensor held as implausible at some cycle after the fault, sorted."""
        return sorted(
            {s for r in self.after for s, why in r.quality_reasons.items() if "implaus" in why}
        )


def machine(store: Path, plant, cnc: str = "modbus") -> MachineSection:
    return MachineSection.model_validate(
        rig.machine_entry("vmc", plant, store, cnc=cnc, cycle_s=CYCLE_S)
    )


async def run(
    store: Path,
    fault: SensorFault | None,
    before_s: float,
    cycles: int,
    seed: int = 6,
    warm: bool = False,
) -> Run:
    """The busy-day programme; the gateway's first cycle at rest (``warm``: 10 min into
    it), the fault ``before_s`` after that first cycle, then ``cycles`` cycles.

    ``fault.start_s`` and ``end_s`` count from the fault's start.
    """
    clock = ManualClock()
    plant = stepped_plant(clock, seed=seed)
    plant.machine.program = BUSY_PROGRAM
    plant.machine.schedule_program(0.0 if warm else math.inf)
    if warm:
        clock.advance(600.0)
    closed = await open_loop(plant, machine(store, plant), clock)
    async with rig.closing(closed, plant):
        await plant.update()
        await closed.loop.run_cycle()  # the reference: cold, or taken while turning
        if not warm:
            plant.machine.schedule_program(plant.machine.time_s + CYCLE_S)
        fault_at = plant.machine.time_s + before_s - 0.5 * CYCLE_S  # between two cycles
        if fault is not None:
            fault.end_s = None if fault.end_s is None else fault.end_s + fault_at
            fault.start_s = fault_at
            plant.machine.add_fault(fault)
        for _ in range(int(before_s / CYCLE_S) + cycles):
            await closed.step(clock)
    after = [r for r in closed.trace.records if r.time_s > fault_at][:cycles]
    return Run(closed, after)


def fault_of(name: str, sensor: str) -> SensorFault:
    """A fault of :data:`FAULTS` on ``sensor``; the spike lasts 60 s."""
    kind, magnitude = FAULTS[name]
    return SensorFault(
        sensor, kind, start_s=0.0, end_s=60.0 if kind == "spike" else None, magnitude_C=magnitude
    )
