"""One faulty sensor must not cost the compensation; the relations work from a warm start.

Over the real protocols (Modbus TCP transmitters and CNC, the simulator's faults
injected behind them), with the gateway's own loop on a manual clock and the
store the demo fits; see tests/test_plausibility_loop.py for the rig.
"""

from __future__ import annotations

import asyncio
import logging
import math
from pathlib import Path

import pytest

from drivers.clock import ManualClock
from gateway.demo.compensate import open_loop
from gateway.live.plausibility import WarmStarts
from simulator.closed_loop import ClosedLoop
from simulator.faults import SensorFault
from tests import gateway_rig as rig
from tests.test_plausibility_loop import (
    BUSY_PROGRAM,
    CYCLE_S,
    FAULT_AT_S,
    run_machine,
    step_for,
    stepped_machine,
    stepped_plant,
)

CYCLES = 150  # after the fault starts
AVAILABILITY = 0.95  # share of those cycles with a prediction, at least


@pytest.fixture(scope="module")
def store(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return rig.fit_store(tmp_path_factory.mktemp("availability"))


def after_fault(closed: ClosedLoop, fault_at_s: float) -> list:
    start = closed.start_s  # type: ignore[attr-defined]
    return [r for r in closed.trace.records if r.time_s > start + fault_at_s]


def implausible(records: list) -> set[str]:
    return {s for r in records for s, why in r.quality_reasons.items() if "implausible" in why}


@pytest.mark.parametrize(("kind", "sensor"), [("drift", "T2"), ("drift", "T9"), ("offset", "T5")])
def test_one_faulty_sensor_keeps_the_compensation_predicting(
    store: Path, kind: str, sensor: str
) -> None:
    """A 20 °C/h drift on T2 dragged T1 past the threshold first: T1 was held, then T2,
    and with two sensors held no stored model was left (30 of 149 cycles)."""
    magnitude_C = 20.0 if kind == "drift" else 3.0
    fault = SensorFault(sensor, kind, start_s=FAULT_AT_S, magnitude_C=magnitude_C)
    closed = asyncio.run(run_machine(store, BUSY_PROGRAM, FAULT_AT_S + CYCLES * CYCLE_S, fault))
    records = after_fault(closed, FAULT_AT_S)
    predicting = sum(r.predicted_um is not None for r in records) / len(records)
    assert predicting >= AVAILABILITY, predicting
    assert records[-1].model_id == f"mlr-error_um-all-without-{sensor}"
    # At most one sensor held at any cycle; the faulty one at the end.
    assert all(sum(q == "bad" for q in r.quality.values()) <= 1 for r in records)
    assert [s for s, q in records[-1].quality.items() if q == "bad"] == [sensor]


async def run_warm_start(
    store: Path, warm_s: float, seconds: float, fault: SensorFault | None
) -> ClosedLoop:
    """The machine turns for ``warm_s`` before the gateway's first cycle (a new state
    folder: the reference is taken warm); ``fault`` times count from that first cycle."""
    clock = ManualClock()
    plant = stepped_plant(clock)
    plant.machine.program = BUSY_PROGRAM
    plant.machine.schedule_program(0.0)
    machine = stepped_machine(store, plant)
    clock.advance(warm_s)
    closed = await open_loop(plant, machine, clock)
    async with rig.closing(closed, plant):
        await plant.update()
        await closed.loop.run_cycle()
        closed.start_s = plant.machine.time_s  # type: ignore[attr-defined]
        if fault is not None:
            fault.start_s += plant.machine.time_s
            plant.machine.add_fault(fault)
        await step_for(closed, clock, seconds)
    return closed


def test_a_warm_start_judges_the_sensors_and_flags_an_offset(store: Path) -> None:
    """Started 40 min into a 6000 r/min warm-up, the check was switched off: an offset
    of +3 °C on T1 an hour later went unseen into the model."""
    fault_at_s = 3600.0 + 10.0
    fault = SensorFault("T1", "offset", start_s=fault_at_s, magnitude_C=3.0)
    closed = asyncio.run(run_warm_start(store, 2400.0, fault_at_s + 20 * CYCLE_S, fault))
    plausibility = closed.loop.plausibility
    assert plausibility.available and plausibility.warm
    assert closed.loop.reference.taken_turning is True
    start = closed.start_s  # type: ignore[attr-defined]
    before = [r for r in closed.trace.records if r.time_s <= start + fault_at_s]
    assert len(before) >= 100 and implausible(before) == set()  # no false flag while warm
    records = after_fault(closed, fault_at_s)
    assert "implausible" in records[0].quality_reasons.get("T1", ""), records[0].quality_reasons
    assert all(r.model_id == "mlr-error_um-all-without-T1" for r in records)


def test_warm_starts_of_many_machines_are_one_line(caplog: pytest.LogCaptureFixture) -> None:
    notes = WarmStarts(delay_s=0.2)

    async def start_all() -> None:
        for k in range(1000):
            notes.note(f"vmc-{k}")
        await asyncio.sleep(0.4)

    with caplog.at_level(logging.WARNING, logger="gateway.live.plausibility"):
        asyncio.run(start_all())
    lines = [r.getMessage() for r in caplog.records if "spindle turned" in r.getMessage()]
    assert len(lines) == 1, lines
    assert lines[0].startswith("1000 machine(s)") and "and 995 more" in lines[0]
    assert math.isfinite(notes.delay_s) and notes.machines == []


def test_warm_starts_spread_wider_than_the_delay_are_still_one_line(
    caplog: pytest.LogCaptureFixture,
) -> None:
    """A thousand first cycles under load come over seconds, not at once: the machines
    are named together once none has been noted for the delay (a fixed delay after the
    first said them as several lines of a few hundred)."""
    notes = WarmStarts(delay_s=0.2, max_wait_s=5.0)

    async def start_spread() -> None:
        for k in range(1000):
            notes.note(f"vmc-{k}")
            if k % 100 == 99:
                await asyncio.sleep(0.1)  # 1 s of first cycles in all: 5 delays long
        await asyncio.sleep(0.4)

    with caplog.at_level(logging.WARNING, logger="gateway.live.plausibility"):
        asyncio.run(start_spread())
    lines = [r.getMessage() for r in caplog.records if "spindle turned" in r.getMessage()]
    assert len(lines) == 1, lines
    assert lines[0].startswith("1000 machine(s)")


def test_warm_starts_that_never_pause_are_said_by_the_longest_wait(
    caplog: pytest.LogCaptureFixture,
) -> None:
    notes = WarmStarts(delay_s=0.2, max_wait_s=0.5)

    async def start_steadily() -> None:
        for k in range(20):
            notes.note(f"vmc-{k}")
            await asyncio.sleep(0.05)  # never quiet for the delay: the longest wait says it
        await asyncio.sleep(0.4)

    with caplog.at_level(logging.WARNING, logger="gateway.live.plausibility"):
        asyncio.run(start_steadily())
    lines = [r.getMessage() for r in caplog.records if "spindle turned" in r.getMessage()]
    assert 2 <= len(lines) <= 3, lines
    assert sum(int(line.split(" ", 1)[0]) for line in lines) == 20
