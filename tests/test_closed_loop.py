"""The gateway compensating the simulated machine over real protocols, through faults.

Transmitters on an RTU bus (socat pty pair), the CNC over OPC UA or Modbus TCP,
the gateway's own loop, all on one manual clock stepped cycle by cycle. The
models are fitted on recorded training runs; every programme here is one the
fit never saw. After every scenario, every value the simulated CNC received
is checked against the clamp and the slew limit.
"""

from __future__ import annotations

import asyncio
import contextlib
import itertools
import json
import logging
import math
import shutil
from collections.abc import AsyncIterator, Awaitable
from pathlib import Path
from typing import Any, Protocol

import numpy as np
import pytest

from drivers.clock import ManualClock
from gateway.config import MachineSection, RegimeSection
from gateway.demo.compensate import machine_config, open_loop
from models.analysis import augmented
from models.online.streaming import StreamingAugmented
from simulator.closed_loop import ClosedLoop
from simulator.faults import SensorFault
from simulator.params import load_params
from simulator.programs import SpeedProgram, production_program, program_by_name
from simulator.record import DEFAULT_PROGRAMS, record, write_recording
from simulator.serve import SimulatedPlant, SimulatorConfig
from tests import gateway_rig as rig
from tests.cli import gateway_in_process
from tests.ports import free_tcp_port
from tests.serial_pty import socat_pty_pair

CYCLE_S = 30.0
CLAMP_UM = 50.0
SLEW_UM_PER_MIN = 20.0
CNC_STEP_UM = 0.1  # 4 decimals of mm
RESUME_CYCLES = 6  # quality recovery (3 good checks) + reconnect back-off + one write
#: The gateway's RTU timeout (wall time): generous, a silent device is waited out each cycle.
RTU_TIMEOUT_S = 2.0
# Half an hour at 6000 r/min, then the speed changes every 20 minutes, so the
# machine keeps heating and cooling (a stuck sensor only shows while others move).
FAULT_PROGRAM = SpeedProgram(
    "busy-day",
    (
        (1800.0, 6000.0),
        *((1200.0, float(s)) for s in (2000, 7000, 1500, 6500, 3000, 7500, 2000, 6000)),
        (3600.0, 4000.0),
    ),
)


@pytest.fixture(scope="module")
def store(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return rig.fit_store(tmp_path_factory.mktemp("closed-loop"))


class Opener(Protocol):
    """Starts the plant and makes the loop that compensates it (:func:`open_loop`'s shape)."""

    def __call__(
        self,
        plant: SimulatedPlant,
        machine: MachineSection,
        clock: ManualClock,
        *,
        state_dir: Path | None = None,
    ) -> Awaitable[ClosedLoop]: ...


@contextlib.asynccontextmanager
async def closed_loop(
    tmp_path: Path,
    store: Path,
    program: SpeedProgram,
    cnc: str = "opcua",
    regimes: dict[str, Any] | None = None,
    state_dir: Path | None = None,
    effects: tuple[str, ...] = (),
    update: dict[str, Any] | None = None,
    opener: Opener = open_loop,
) -> AsyncIterator[tuple[ClosedLoop, ManualClock]]:
    """The plant and the gateway on a manual clock; ``regimes`` replaces the demo's rules,
    ``effects`` are hidden in the plant, ``update`` replaces machine config sections,
    ``opener`` starts the plant and makes the loop (default: the loop alone; a whole
    :class:`gateway.wiring.Gateway` for SCADA and the monitor as ``run`` has them)."""
    clock = ManualClock()
    with socat_pty_pair(tmp_path) as pty:
        devices = [
            {"device_id": 1, "channels": [f"T{i}" for i in range(1, 9)]},
            {"device_id": 2, "channels": ["T9", "ambient"]},
        ]
        plant = SimulatedPlant(
            SimulatorConfig.model_validate(
                {
                    "seed": 5,
                    "effects": list(effects),
                    "publish_period_s": 1e6,  # publish only when a cycle steps the machine
                    "transmitters": {"rtu": {"port": pty.server_port, "devices": devices}},
                    "cnc": {cnc: {"port": free_tcp_port()}},  # the protocol the gateway uses
                }
            ),
            clock=clock,
        )
        plant.machine.program = program
        plant.machine.schedule_program(math.inf)  # cycle start comes once the gateway runs
        if cnc == "opcua":
            assert plant.cnc_opcua is not None
            link: dict[str, Any] = {
                "opcua": {"endpoint": plant.cnc_opcua.endpoint, "timeout_s": 1.0}
            }
        else:
            assert plant.cnc_modbus is not None
            link = {
                "modbus": {
                    "host": "127.0.0.1",
                    "port": plant.cnc_modbus.address[1],
                    "timeout_s": 0.5,
                }
            }
        gateway_devices = [devices[0], {"device_id": 2, "channels": ["T9", None]}]
        machine = machine_config(
            store,
            transmitters=[
                {
                    "name": "rtu1",
                    "rtu": {"port": pty.client_port},
                    # Wall time. Plant and gateway share one process; on a loaded CI
                    # machine (four workers on two cores) a live reply came 0.5 s late,
                    # and once over 1 s.
                    "timeout_s": RTU_TIMEOUT_S,
                    "devices": gateway_devices,
                }
            ],
            cnc=link,
            cycle_s=CYCLE_S,
        )
        if regimes is not None:
            models = machine.models.model_copy(
                update={"regimes": RegimeSection.model_validate(regimes)}
            )
            machine = machine.model_copy(update={"models": models})
        if update is not None:
            machine = machine.model_copy(update=update)
        closed = await opener(plant, machine, clock, state_dir=state_dir)
        async with rig.closing(closed, plant):
            await closed.loop.run_cycle()
            plant.machine.schedule_program(plant.machine.time_s + CYCLE_S)
            yield closed, clock


async def run_for(closed: ClosedLoop, clock: ManualClock, seconds: float) -> None:
    for _ in range(int(seconds // CYCLE_S)):
        await closed.step(clock)


def assert_every_write_was_safe(closed: ClosedLoop) -> None:
    """Every value the CNC received: within the clamp, and no faster than the slew limit."""
    log = closed.plant.machine.compensation_log
    assert log, "the gateway never wrote"
    times = np.array([t for t, _ in log])
    values_um = np.array([v for _, v in log]) * 1000.0
    assert np.all(np.abs(values_um) <= CLAMP_UM + 1e-9)
    steps = np.abs(np.diff(np.r_[0.0, values_um]))
    allowed = SLEW_UM_PER_MIN * np.diff(np.r_[0.0, times]) / 60.0 + CNC_STEP_UM + 1e-9
    assert np.all(steps <= allowed), (steps - allowed).max()


def test_unseen_programme_compensated_peak_at_most_20_percent(tmp_path: Path, store: Path) -> None:
    program = production_program(seed=31, duration_s=5 * 3600.0)

    async def scenario() -> tuple[dict[str, float], list]:
        async with closed_loop(tmp_path, store, program) as (closed, clock):
            await run_for(closed, clock, program.duration_s)
            assert_every_write_was_safe(closed)
            worst = int(np.argmax(np.abs(closed.trace.compensated_um)))
            around = closed.trace.records[max(0, worst - 3) : worst + 2]
            return closed.trace.summary(), around

    summary, around_peak = asyncio.run(scenario())
    summary["cycles_around_peak"] = around_peak  # shown if an assertion below fails
    assert summary["uncompensated_peak_um"] > 15.0
    assert summary["compensated_peak_um"] <= 0.2 * summary["uncompensated_peak_um"], summary
    assert summary["compensated_rmse_um"] <= 0.2 * summary["uncompensated_rmse_um"], summary


def records_between(closed: ClosedLoop, start_s: float, end_s: float) -> list:
    return [r for r in closed.trace.records if start_s <= r.time_s < end_s]


def resumed_within(closed: ClosedLoop, cleared_s: float, cycles: int) -> bool:
    """Normal compensation: a regime model, a prediction and a confirmed write or deadband."""
    after = records_between(closed, cleared_s, math.inf)[:cycles]
    return any(
        r.model_id in ("mlr-error_um-variable", "mlr-error_um-constant")
        and r.predicted_um is not None
        and (r.write_status.startswith("ok") or "deadband" in r.write_status)
        for r in after
    )


SENSOR_FAULTS = [
    ("T1", "open_circuit", "mlr-error_um-all-without-T1", "transmitter fault code 1"),
    ("T5", "stuck", "mlr-error_um-all-without-T5", "stuck at"),
]


@pytest.mark.parametrize(("sensor", "kind", "fallback", "reason"), SENSOR_FAULTS)
def test_sensor_fault_switches_to_a_model_without_it(
    tmp_path: Path, store: Path, sensor: str, kind: str, fallback: str, reason: str
) -> None:
    program = FAULT_PROGRAM

    async def scenario() -> ClosedLoop:
        async with closed_loop(tmp_path, store, program) as (closed, clock):
            await run_for(closed, clock, 3600.0)
            start = clock.now()
            closed.plant.machine.add_fault(
                SensorFault(sensor, kind, start_s=start, end_s=start + 3600.0)
            )
            await run_for(closed, clock, 3600.0 + 300.0)
            closed.fault_window = (start, start + 3600.0)  # type: ignore[attr-defined]
            await run_for(closed, clock, 1800.0)
            assert_every_write_was_safe(closed)
            return closed

    closed = asyncio.run(scenario())
    start, cleared = closed.fault_window  # type: ignore[attr-defined]
    during = records_between(closed, start + 1200.0, cleared)  # stuck needs 900 s to show
    assert during and all(r.quality[sensor] == "bad" for r in during)
    assert all(r.model_id == fallback for r in during)
    assert any(reason in r.quality_reasons.get(sensor, "") for r in during)

    # Compensation carried on: every cycle whose transmitters answered predicted. A read
    # missed on a loaded machine (past the RTU timeout) is a link error of its own: rare,
    # and the applied value is held through it rather than moved.
    def missed(r) -> bool:
        return any("no response" in error for error in r.link_errors)

    answered = [r for r in during if not missed(r)]
    assert all(r.predicted_um is not None for r in answered)
    assert len(during) - len(answered) <= len(during) // 10
    records = closed.trace.records
    for r in during:
        if missed(r) and r.predicted_um is None:
            before = records[records.index(r) - 1]
            assert r.applied_um == before.applied_um
    assert resumed_within(closed, cleared, RESUME_CYCLES)


def test_silent_rtu_slave_does_not_stall_the_others(tmp_path: Path, store: Path) -> None:
    program = FAULT_PROGRAM

    async def scenario() -> tuple[ClosedLoop, float, float]:
        async with closed_loop(tmp_path, store, program) as (closed, clock):
            await run_for(closed, clock, 3600.0)
            start = clock.now()
            assert closed.plant.rtu_transmitters is not None
            closed.plant.rtu_transmitters.silenced.add(2)  # the module with T9 loses power
            await run_for(closed, clock, 900.0)  # 30 cycles, each waiting out one timeout
            closed.plant.rtu_transmitters.silenced.clear()
            cleared = clock.now()
            await run_for(closed, clock, 1800.0)
            assert_every_write_was_safe(closed)
            return closed, start, cleared

    closed, start, cleared = asyncio.run(scenario())
    during = records_between(closed, start + CYCLE_S, cleared)
    assert during and all(r.temperatures_C["T9"] is None for r in during)
    assert all(r.temperatures_C["T1"] is not None for r in during)  # device 1 still read
    assert all(any("no response from device 2" in e for e in r.link_errors) for r in during)
    assert all(r.model_id == "mlr-error_um-all-without-T9" for r in during[2:])
    assert resumed_within(closed, cleared, RESUME_CYCLES)


@pytest.mark.parametrize("cnc", ["opcua", "modbus"])
def test_cnc_server_restart_and_connection_drop(tmp_path: Path, store: Path, cnc: str) -> None:
    program = FAULT_PROGRAM

    async def scenario() -> tuple[ClosedLoop, float, float, int]:
        async with closed_loop(tmp_path, store, program, cnc=cnc) as (closed, clock):
            plant = closed.plant
            await run_for(closed, clock, 3600.0)
            start = clock.now()
            writes_before = len(plant.machine.compensation_log)
            name = f"cnc_{cnc}"
            await plant.take_down(name)  # OPC UA: server restart; Modbus: connection drop
            await run_for(closed, clock, 900.0)
            await plant.bring_up(name)
            cleared = clock.now()
            outage_writes = len(plant.machine.compensation_log) - writes_before
            await run_for(closed, clock, 1800.0)
            assert_every_write_was_safe(closed)
            return closed, start, cleared, outage_writes

    closed, start, cleared, outage_writes = asyncio.run(scenario())
    during = records_between(closed, start + CYCLE_S, cleared)
    assert outage_writes == 0
    assert during and all(r.speed_rpm is None for r in during)
    assert all(r.link_errors for r in during)
    assert closed.loop.failed_writes >= 1  # the loop tried, failed, counted it
    assert all(not r.write_status.startswith("ok") for r in during)
    assert resumed_within(closed, cleared, RESUME_CYCLES)


def test_variable_to_constant_switches_model_once(
    tmp_path: Path, store: Path, caplog: pytest.LogCaptureFixture
) -> None:
    spectrum = tuple(
        (600.0, float(s)) for s in (2000, 6000, 3000, 7000, 1000, 5000, 2500, 6500, 4000)
    )
    program = SpeedProgram("variable-then-constant", (*spectrum, (4 * 3600.0, 6000.0)))

    async def scenario() -> ClosedLoop:
        async with closed_loop(tmp_path, store, program) as (closed, clock):
            await run_for(closed, clock, program.duration_s)
            return closed

    with caplog.at_level(logging.INFO, logger="gateway.live.loop"):
        closed = asyncio.run(scenario())
    switches = closed.loop.selector.switches
    assert len(switches) == 1, switches
    _, before, after = switches[0]
    assert (before, after) == ("variable", "constant")
    logged = [
        r.getMessage() for r in caplog.records if "→ model mlr-error_um-constant" in r.getMessage()
    ]
    assert len(logged) == 1
    models = [r.model_id for r in closed.trace.records if r.model_id]
    changes = sum(1 for a, b in itertools.pairwise(models) if a != b)
    assert changes == 1


@pytest.fixture(scope="module")
def augmented_store(
    tmp_path_factory: pytest.TempPathFactory, store: Path
) -> tuple[Path, dict[str, Any]]:
    """The plain models plus the augmented model ``analyze --store`` makes of simulator
    data with a hidden thermal lag and a direct speed effect."""
    folder = tmp_path_factory.mktemp("augmented-loop")
    models = folder / "models"
    shutil.copytree(store, models)
    data = folder / "hidden.csv"
    programs = [program_by_name(name) for name in DEFAULT_PROGRAMS]
    write_recording(data, record(load_params(), programs, ["thermal_lag", "speed_direct"], seed=2))
    done = gateway_in_process("analyze", data, "--model", "mlr", "--store", models)
    assert done.returncode == 0, done.stderr
    (path,) = (models / augmented.FOLDER).glob("*.json")
    return models, augmented.load(path)


def test_augmented_model_switched_in_warm_compensates(
    tmp_path: Path, augmented_store: tuple[Path, dict[str, Any]]
) -> None:
    store, document = augmented_store
    model_id = document["model_id"]
    assert document["effects"], "analyze found no effect in the simulator data"
    assert not StreamingAugmented(document).uses_ambient  # the gateway reads no ambient here
    regimes = {
        "window_s": 1200,
        "constant_tolerance_rpm": 100,
        "min_dwell_s": 600,
        "models": {"variable": "mlr-error_um-variable", "constant": model_id},
        "fallback_model": "mlr-error_um-all",
    }
    spectrum = tuple((600.0, float(s)) for s in (2000, 6000, 3000, 7000, 1000, 5000, 2500))
    program = SpeedProgram("variable-then-constant", (*spectrum, (2 * 3600.0, 6000.0)))
    state_dir = tmp_path / "state"

    async def scenario() -> ClosedLoop:
        loop = closed_loop(tmp_path, store, program, regimes=regimes, state_dir=state_dir)
        async with loop as (closed, clock):
            await run_for(closed, clock, program.duration_s)
            assert_every_write_was_safe(closed)
            return closed

    closed = asyncio.run(scenario())
    records = closed.trace.records
    assert closed.loop.selector.switches[0][1:] == ("variable", "constant")
    switched = next(i for i, r in enumerate(records) if r.model_id == model_id)
    assert switched > 100  # the plain model compensated the first hour and more

    # The same cycles through the streaming model: every good rise above the gateway's
    # cold reference and the speed, from the first cycle on, selected or not.
    reference_C = closed.loop.reference.values_C
    warm = StreamingAugmented(document)
    cold = StreamingAugmented(document)  # started only when the model is switched in
    warm_um, cold_um = [], []
    for i, r in enumerate(records):
        good = {n: t for n, t in r.temperatures_C.items() if t is not None}
        good = {n: t for n, t in good.items() if r.quality[n] == "good"}
        rises_C = {n: t - reference_C[n] for n, t in good.items()}
        expected = warm.step(r.time_s, rises_C, r.speed_rpm)
        if i >= switched:
            assert r.model_id == model_id
            assert r.predicted_um == expected, (r.time_s, r.predicted_um, expected)
            warm_um.append(expected)
            cold_um.append(cold.step(r.time_s, rises_C, r.speed_rpm))
    # The state carried through the variable phase mattered.
    assert np.max(np.abs(np.array(warm_um) - np.array(cold_um))) > 0.1
    written = [r for r in records[switched:] if r.write_status.startswith("ok")]
    assert written and all(r.written_cnc is not None for r in written)

    # Closing the loop saved the states where a restarted gateway finds them.
    saved = json.loads((state_dir / "vmc-demo-effect-state.json").read_text(encoding="utf-8"))
    assert saved["models"][model_id]["sha256"] == document["sha256"]
    assert saved["models"][model_id]["state"] == warm.export_state()
