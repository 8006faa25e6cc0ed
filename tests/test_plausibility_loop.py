"""Slow sensor faults caught by plausibility, over the real protocols.

The simulated machine serves its transmitters as Modbus TCP slaves and its CNC
over Modbus TCP (one scenario over OPC UA); the gateway's own loop compensates
it on a manual clock, with the store the demo fits (per-regime models, one on
all runs, one without each sensor, every file carrying the sensor relations).
Each fault scenario is run twice, with the fault and without it, on the same
seed and programme: the fault-free run is what the machine needed. The
simulator publishes only when a cycle steps it, so both runs draw the same
noise and differ by the fault alone.
"""

from __future__ import annotations

import asyncio
import math
from pathlib import Path

import numpy as np
import pytest

from drivers.clock import ManualClock
from gateway.config import MachineSection
from gateway.demo.compensate import machine_config, open_loop
from gateway.live.record import CycleRecord
from simulator.closed_loop import ClosedLoop
from simulator.faults import SensorFault
from simulator.programs import SpeedProgram, production_program
from simulator.serve import SimulatedPlant, SimulatorConfig
from tests import gateway_rig as rig
from tests.ports import free_tcp_port

CYCLE_S = 30.0
MARGIN_UM = 2.0  # the applied value may differ from what the fault-free machine needed by this
# An hour warming at 6000 r/min, then speed changes every 20 minutes: the sensors
# keep moving, as on a working day.
BUSY_PROGRAM = SpeedProgram(
    "busy-day",
    (
        (3600.0, 6000.0),
        *((1200.0, float(s)) for s in (2000, 7000, 1500, 6500, 3000, 7500, 2000, 6000, 4000)),
        (3600.0, 3000.0),
    ),
)
# Machine time after cycle start when the fault begins: 20 s before a cycle, as a fault
# does not wait for the loop.
FAULT_AT_S = 3610.0


@pytest.fixture(scope="module")
def store(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return rig.fit_store(tmp_path_factory.mktemp("plausibility"))


def stepped_plant(clock: ManualClock, cnc: str = "modbus", seed: int = 5) -> SimulatedPlant:
    """A simulated machine that publishes only when a cycle steps it; its CNC over ``cnc``."""
    return SimulatedPlant(
        SimulatorConfig.model_validate(
            {
                "seed": seed,
                "publish_period_s": 1e6,
                "transmitters": {"tcp": {"port": free_tcp_port(), "devices": rig.DEVICES}},
                "cnc": {cnc: {"port": free_tcp_port()}},
            }
        ),
        clock=clock,
    )


def stepped_machine(store: Path, plant: SimulatedPlant, cnc: str = "modbus") -> MachineSection:
    """The gateway's configuration of ``plant``: a cycle every CYCLE_S, the models of ``store``."""
    assert plant.tcp_transmitters is not None
    host, port = plant.tcp_transmitters.address
    if cnc == "opcua":
        assert plant.cnc_opcua is not None
        link = {"opcua": {"endpoint": plant.cnc_opcua.endpoint, "timeout_s": 1.0}}
    else:
        assert plant.cnc_modbus is not None
        link = {"modbus": {"host": "127.0.0.1", "port": plant.cnc_modbus.address[1]}}
    return machine_config(
        store,
        transmitters=[rig.tcp_bus(host, port, timeout_s=0.5)],
        cnc=link,
        cycle_s=CYCLE_S,
    )


async def run_machine(
    store: Path,
    program: SpeedProgram,
    seconds: float,
    fault: SensorFault | None = None,
    cnc: str = "modbus",
    seed: int = 5,
) -> ClosedLoop:
    """The plant and the gateway on one manual clock, ``seconds`` after cycle start.

    ``fault.start_s`` and ``end_s`` count from cycle start.
    """
    clock = ManualClock()
    plant = stepped_plant(clock, cnc, seed)
    plant.machine.program = program
    plant.machine.schedule_program(math.inf)
    machine = stepped_machine(store, plant, cnc)
    closed = await open_loop(plant, machine, clock)
    async with rig.closing(closed, plant):
        await closed.loop.run_cycle()  # the cold reference, before cycle start
        start_s = plant.machine.time_s + CYCLE_S
        plant.machine.schedule_program(start_s)
        if fault is not None:
            fault.start_s += start_s
            fault.end_s = None if fault.end_s is None else fault.end_s + start_s
            plant.machine.add_fault(fault)
        closed.start_s = start_s  # type: ignore[attr-defined]
        await step_for(closed, clock, seconds)
    return closed


async def step_for(closed: ClosedLoop, clock: ManualClock, seconds: float) -> None:
    """One cycle every CYCLE_S for ``seconds`` of machine time."""
    for _ in range(int(seconds // CYCLE_S)):
        await closed.step(clock)


def implausible(record: CycleRecord, sensor: str) -> bool:
    return record.quality[sensor] == "bad" and "implausible" in record.quality_reasons.get(
        sensor, ""
    )


def false_flags(records: list[CycleRecord]) -> int:
    return sum(1 for r in records for s in r.quality if implausible(r, s))


def applied_um(records: list[CycleRecord]) -> np.ndarray:
    return np.array([np.nan if r.applied_um is None else r.applied_um for r in records])


def run_pair(
    store: Path, fault: SensorFault, seconds: float, cnc: str = "modbus"
) -> tuple[ClosedLoop, ClosedLoop]:
    """The same scenario without and with ``fault``."""
    reference = asyncio.run(run_machine(store, BUSY_PROGRAM, seconds, cnc=cnc))
    faulty = asyncio.run(run_machine(store, BUSY_PROGRAM, seconds, fault, cnc=cnc))
    return reference, faulty


def check_fault_caught(
    reference: ClosedLoop, faulty: ClosedLoop, sensor: str, fault_start_s: float
) -> dict[str, float]:
    """Flagged, the model without it used, the applied value within the margin; the figures."""
    fault_at = faulty.start_s + fault_start_s  # type: ignore[attr-defined]
    records = faulty.trace.records
    assert [r.time_s for r in records] == [r.time_s for r in reference.trace.records]
    after = [i for i, r in enumerate(records) if r.time_s > fault_at]  # cycles that see it
    flagged = next(i for i in after if records[i].quality[sensor] == "bad")
    first_bad = records[flagged]
    assert "implausible" in first_bad.quality_reasons[sensor], first_bad.quality_reasons
    difference = np.abs(applied_um(records) - applied_um(reference.trace.records))
    return {
        "flagged_after_cycles": float(flagged - after[0] + 1),
        "flagged_after_s": first_bad.time_s - fault_at,
        "max_applied_difference_um": float(np.nanmax(difference)),
        "false_flags_reference": float(false_flags(reference.trace.records)),
        "flagged_index": float(flagged),
    }


def test_fast_drift_is_flagged_at_once_and_the_model_without_it_takes_over(store: Path) -> None:
    sensor = "T1"
    fault = SensorFault.drift_C_per_s(sensor, 0.056, start_s=FAULT_AT_S)
    reference, faulty = run_pair(store, fault, FAULT_AT_S + 3600.0)
    figures = check_fault_caught(reference, faulty, sensor, FAULT_AT_S)
    print("\nFIGURES drift", figures)
    records = faulty.trace.records
    flagged = int(figures["flagged_index"])
    assert figures["flagged_after_cycles"] <= 1, figures
    assert all(r.quality[sensor] == "bad" for r in records[flagged:])
    assert all(r.model_id == f"mlr-error_um-all-without-{sensor}" for r in records[flagged:])
    assert all(r.predicted_um is not None for r in rig.answered(records[flagged:]))
    assert figures["max_applied_difference_um"] <= MARGIN_UM, figures
    assert figures["false_flags_reference"] == 0


def test_offset_step_on_t5_stays_flagged_until_it_agrees_again(store: Path) -> None:
    sensor = "T5"
    fault = SensorFault(sensor, "offset", start_s=FAULT_AT_S, end_s=FAULT_AT_S + 2 * 3600.0)
    reference, faulty = run_pair(store, fault, FAULT_AT_S + 3 * 3600.0, cnc="opcua")
    figures = check_fault_caught(reference, faulty, sensor, FAULT_AT_S)
    print("\nFIGURES offset", figures)
    records = faulty.trace.records
    flagged = int(figures["flagged_index"])
    cleared_s = faulty.start_s + FAULT_AT_S + 2 * 3600.0  # type: ignore[attr-defined]
    during = [r for r in records[flagged:] if r.time_s < cleared_s]
    assert figures["flagged_after_cycles"] <= 1, figures
    assert len(during) > 200 and all(implausible(r, sensor) for r in during)  # no flapping
    assert all(r.model_id == f"mlr-error_um-all-without-{sensor}" for r in during)
    back = next(r.time_s for r in records if r.time_s >= cleared_s and r.quality[sensor] == "good")
    # Trusted again once it has agreed for plausibility_recover_s (900 s), not before.
    assert 900.0 <= back - cleared_s <= 900.0 + 3 * CYCLE_S, back - cleared_s
    assert figures["max_applied_difference_um"] <= MARGIN_UM, figures
    assert figures["false_flags_reference"] == 0


def test_slow_bias_is_flagged_before_it_costs_2_um(store: Path) -> None:
    sensor = "T9"
    fault = SensorFault(sensor, "bias", start_s=FAULT_AT_S, magnitude_C=2.0, ramp_s=2 * 3600.0)
    reference, faulty = run_pair(store, fault, FAULT_AT_S + 3 * 3600.0)
    figures = check_fault_caught(reference, faulty, sensor, FAULT_AT_S)
    print("\nFIGURES bias", figures)
    records = faulty.trace.records
    flagged = int(figures["flagged_index"])
    # Flagged at 5 × 0.1 °C (the σ floor) of bias, 30 min into the ramp; allow noise to 0.75 °C.
    assert figures["flagged_after_s"] <= 0.75 / 2.0 * 7200.0, figures
    assert all(r.quality[sensor] == "bad" for r in records[flagged:])
    assert all(r.model_id == f"mlr-error_um-all-without-{sensor}" for r in records[flagged:])
    assert figures["max_applied_difference_um"] <= MARGIN_UM, figures
    assert figures["false_flags_reference"] == 0


def test_a_long_fault_free_programme_raises_no_flag(store: Path) -> None:
    program = production_program(seed=47, duration_s=10 * 3600.0)
    closed = asyncio.run(run_machine(store, program, program.duration_s, seed=11))
    records = closed.trace.records
    largest = closed.loop.plausibility.largest_sound_z
    print("\nFIGURES no fault", len(records), "cycles", false_flags(records), "flags", largest)
    assert len(records) >= 1200
    assert false_flags(records) == 0
    assert closed.loop.plausibility.flags == 0
    assert closed.loop.plausibility.available
