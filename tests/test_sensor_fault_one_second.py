"""One faulty sensor, or a restart of the transmitters, at a 1 s cycle: the compensation
goes on predicting.

Over the real protocols (Modbus TCP transmitters and CNC, the simulator's faults
injected behind them, the simulator restarted as a new process would be: new
servers on the same ports, a machine starting cold), with the gateway's own loop
on a manual clock and the store the demo fits (tests/one_second_rig.py).

At a 1 s cycle the prediction rate bound allows 1.1 µm from one cycle to the next.
The model without T5 leans on T3 by 5.9 µm/°C: one register step on five sensors
moved it 1.15 µm, and the bound held a sound T3 beside the faulty T5, leaving no
model (90 % of 150 cycles predicting with a spike on T5; 20 % and 93 % of 900
cycles with an offset on T5). A restart whose temperatures came back lower moved
the prediction by −7.5 µm and held the sensors one after the other.
"""

from __future__ import annotations

import asyncio
import logging
import math
from pathlib import Path

import pytest

from drivers.clock import ManualClock
from gateway.demo.compensate import open_loop
from simulator.closed_loop import ClosedLoop
from simulator.faults import SensorFault
from simulator.serve import SimulatedPlant
from tests import gateway_rig as rig
from tests import one_second_rig as one
from tests.test_plausibility_loop import BUSY_PROGRAM, stepped_plant

CYCLES = 150
AVAILABILITY = 0.95


@pytest.fixture(scope="module")
def store(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return rig.fit_store(tmp_path_factory.mktemp("one-second"))


@pytest.mark.parametrize("sensor", one.SENSORS)
@pytest.mark.parametrize("name", list(one.FAULTS))
def test_one_faulty_sensor_keeps_the_compensation_predicting(
    store: Path, name: str, sensor: str
) -> None:
    """A spike (+3 °C for 60 s) or a 20 °C/h drift on each sensor in turn, 150 cycles."""
    run = asyncio.run(one.run(store, one.fault_of(name, sensor), 600.0, CYCLES))
    print(
        f"\nFIGURES {name} on {sensor}: {100 * run.predicting:.1f} % predicting, held {run.held()}"
    )
    assert len(run.after) == CYCLES
    assert run.predicting >= AVAILABILITY, (run.predicting, run.held())
    assert len(run.held()) <= 1, run.held()  # never a second sensor beside the one at fault


@pytest.mark.parametrize(("seed", "warm"), [(1, False), (2, False), (2, True)])
def test_the_noisy_model_without_t5_holds_no_sound_sensor(
    store: Path, seed: int, warm: bool
) -> None:
    """A +3 °C offset on T5 for 900 cycles: the model without it serves throughout; also
    with the gateway started 10 min into the programme (a reference taken warm)."""
    fault = SensorFault("T5", "offset", start_s=0.0, magnitude_C=3.0)
    run = asyncio.run(one.run(store, fault, 600.0, 900, seed=seed, warm=warm))
    assert run.closed.loop.plausibility.warm is warm
    assert run.held() == ["T5"]
    # Every cycle the transmitters answered predicts (a bus timeout under a loaded test
    # machine, seen once in 900 cycles, is no fault of the rules: rig.answered).
    assert run.predicting_answered == 1.0, run.predicting_answered
    assert run.after[-1].model_id == "mlr-error_um-all-without-T5"


async def restart_at_another_level(store: Path, down_s: float, cycles: int) -> ClosedLoop:
    """20 min of the busy day, the simulator gone for ``down_s``, then a new one on the
    same ports whose machine starts cold: the temperatures come back lower."""
    clock = ManualClock()
    plant = stepped_plant(clock)
    plant.machine.program = BUSY_PROGRAM
    plant.machine.schedule_program(math.inf)
    closed = await open_loop(plant, one.machine(store, plant), clock)
    try:
        await closed.loop.run_cycle()  # the cold reference
        plant.machine.schedule_program(plant.machine.time_s + one.CYCLE_S)
        for _ in range(1200):
            await closed.step(clock)
        await plant.stop()
        for _ in range(int(down_s / one.CYCLE_S)):  # the gateway polls a silent plant
            clock.advance(one.CYCLE_S)
            await closed.loop.run_cycle()
        plant = SimulatedPlant(plant.config, clock=clock)  # cold, at the clock's time
        plant.machine.program = BUSY_PROGRAM
        plant.machine.schedule_program(clock.now())
        await plant.start()
        closed.plant = plant
        closed.restarted_s = clock.now()  # type: ignore[attr-defined]
        for _ in range(cycles):
            await closed.step(clock)
    finally:
        await closed.loop.close()
        await plant.stop()
    return closed


def test_a_restart_at_another_level_re_references_instead_of_holding(
    store: Path, caplog: pytest.LogCaptureFixture
) -> None:
    with caplog.at_level(logging.INFO, logger="gateway.live.plausibility"):
        closed = asyncio.run(restart_at_another_level(store, 16.0, CYCLES))
    restarted = closed.restarted_s  # type: ignore[attr-defined]
    before = [r for r in closed.trace.records if r.time_s <= restarted - 16.0]
    after = [r for r in closed.trace.records if r.time_s > restarted]
    assert len(after) == CYCLES
    held = {s for r in after for s, why in r.quality_reasons.items() if "implaus" in why}
    assert held == set(), held
    predicting = sum(r.predicted_um is not None for r in after) / len(after)
    assert predicting >= AVAILABILITY, predicting  # the stale sensors' 3 recovering cycles
    assert all(r.predicted_um is not None for r in rig.answered(after[5:]))
    was, now = before[-1].predicted_um, after[-1].predicted_um
    print(f"\nFIGURES restart: prediction {was:.1f} µm before, {now:.1f} µm 150 s after")
    assert was - now > 3.0, (was, now)  # the level did change, well past the 1.1 µm bound
    assert closed.loop.plausibility.re_references >= 1
    lines = [
        r.getMessage() for r in caplog.records if "no sensor stepped on its own" in r.getMessage()
    ]
    assert lines and "moved together" in lines[0], lines
