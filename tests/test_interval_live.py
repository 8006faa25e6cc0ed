"""The interval and the training-span state, live: a simulated machine over Modbus TCP
(transmitters) and OPC UA (CNC), the gateway's own loop on a manual clock.

The machine runs on a model fitted on constant speeds up to 6000 r/min; taken to
8000 r/min, the span state turns "outside" (naming the speed) within two cycles and
the interval widens. A transmitter open circuit widens the interval while the sensor
is held bad, and the width returns once it recovers.
"""

from __future__ import annotations

import asyncio
import itertools
import json
import logging
import math
from pathlib import Path

import pytest

from drivers.clock import ManualClock
from gateway.config import MachineSection
from gateway.demo.compensate import open_loop
from gateway.live.record import CycleRecord
from simulator.faults import SensorFault
from simulator.programs import SpeedProgram
from simulator.serve import SimulatedPlant, SimulatorConfig
from tests import gateway_rig as rig
from tests.ports import free_tcp_port

CYCLE_S = 30.0
TRAINED_MODEL = "mlr-error_um-constant"  # fitted on the constant-speed runs, 0…6000 r/min


@pytest.fixture(scope="module")
def store(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return rig.fit_store(tmp_path_factory.mktemp("interval-live"))


#: Wall seconds a transmitter or the CNC may take to answer (machine time is stepped).
LINK_TIMEOUT_S = 5.0


def served_plant(clock: ManualClock, program: SpeedProgram) -> SimulatedPlant:
    plant = SimulatedPlant(
        SimulatorConfig.model_validate(
            {
                "seed": 3,
                "publish_period_s": 1e6,  # publish only when a cycle steps the machine
                "transmitters": {"tcp": {"port": free_tcp_port(), "devices": rig.DEVICES}},
                "cnc": {"opcua": {"port": free_tcp_port()}},
            }
        ),
        clock=clock,
    )
    plant.machine.program = program
    plant.machine.schedule_program(0.0)
    return plant


def machine(plant: SimulatedPlant, store: Path, compensation: dict | None) -> MachineSection:
    # The runs are compared cycle by cycle: a read timed out on a loaded machine would
    # change one run's path, so the links wait as long as a loaded CI machine needs.
    tcp = plant.config.transmitters.tcp
    assert tcp is not None
    bus = rig.tcp_bus("127.0.0.1", tcp.port, timeout_s=LINK_TIMEOUT_S)
    entry = rig.machine_entry(
        "m1", plant, store, cnc="opcua", cycle_s=CYCLE_S, stale_s=1e6, transmitters=[bus]
    )
    entry["cnc"]["opcua"]["timeout_s"] = LINK_TIMEOUT_S
    entry["models"]["regimes"] = {"models": {}, "fallback_model": TRAINED_MODEL}
    entry["compensation"].update(compensation or {})
    return MachineSection.model_validate(entry)


async def run(
    plant: SimulatedPlant,
    store: Path,
    clock: ManualClock,
    cycles: int,
    fault=None,
    compensation: dict | None = None,
):
    closed = await open_loop(plant, machine(plant, store, compensation), clock)
    records: list[CycleRecord] = []
    async with rig.closing(closed, plant):
        for k in range(cycles):
            if fault is not None and k == fault[0]:
                plant.machine.add_fault(fault[1](clock.now()))
            records.append(await closed.step(clock))
    return records


def test_above_training_speed_turns_outside_within_two_cycles_and_widens(store: Path) -> None:
    change_s = 40 * CYCLE_S
    program = SpeedProgram("up", ((change_s, 4000.0), (3600.0, 8000.0)))
    clock = ManualClock()
    records = asyncio.run(run(served_plant(clock, program), store, clock, 50))

    before = [r for r in records if 20 * CYCLE_S <= r.time_s < change_s]
    assert before and all(r.training_span == "inside" for r in before), [
        (r.time_s, r.speed_rpm, r.training_span, r.outside_inputs) for r in before
    ]
    assert all(r.interval_um is not None and r.interval_um > 0 for r in before)
    fast = [r for r in records if r.speed_rpm is not None and r.speed_rpm > 7000]
    assert fast, "the machine never reached 8000 r/min"
    first_fast = records.index(fast[0])
    outside = records[first_fast : first_fast + 2]
    assert any(r.training_span == "outside" for r in outside), [
        (r.time_s, r.speed_rpm, r.training_span) for r in outside
    ]
    flagged = next(r for r in outside if r.training_span == "outside")
    assert "speed" in flagged.outside_inputs
    assert flagged.model_id == TRAINED_MODEL
    assert flagged.interval_um is not None
    assert flagged.interval_um > 1.3 * before[-1].interval_um  # type: ignore[operator]


def test_sensor_fault_widens_while_held_and_width_returns(store: Path) -> None:
    program = SpeedProgram("steady", ((6 * 3600.0, 4000.0),))
    clock = ManualClock()
    fault_at, fault_cycles = 60, 30
    plant = served_plant(clock, program)

    def fault(now: float) -> SensorFault:
        return SensorFault("T1", "open_circuit", start_s=now, end_s=now + fault_cycles * CYCLE_S)

    records = asyncio.run(run(plant, store, clock, 120, fault=(fault_at, fault)))
    before = records[fault_at - 5 : fault_at]
    during = [r for r in records[fault_at : fault_at + fault_cycles] if r.quality["T1"] == "bad"]
    after = records[-5:]
    assert during, "the open circuit was never flagged"
    assert all(r.quality["T1"] == "good" for r in before + after)
    widths_before = [r.interval_um for r in before]
    widths_during = [r.interval_um for r in during if r.interval_um is not None]
    widths_after = [r.interval_um for r in after]
    assert all(w is not None for w in widths_before + widths_after)
    assert widths_during and min(widths_during) > 1.2 * max(widths_before)  # type: ignore[type-var]
    assert all(math.isclose(a, widths_before[-1], rel_tol=0.02) for a in widths_after), (
        widths_before,
        widths_after,
    )


SLEW_UM_PER_MIN = 3.0
CHANGE_S = 40 * CYCLE_S
UP = SpeedProgram("up", ((CHANGE_S, 4000.0), (3600.0, 8000.0)))


def gated_run(store: Path, gate: dict | None) -> list[CycleRecord]:
    clock = ManualClock()
    compensation = {"slew_um_per_min": SLEW_UM_PER_MIN, "deadband_um": 0.1}
    if gate is not None:
        compensation["when_uncertain"] = gate
    return asyncio.run(run(served_plant(clock, UP), store, clock, 70, compensation=compensation))


def stored_half_width(store: Path) -> float:
    document = json.loads((store / f"{TRAINED_MODEL}.json").read_text(encoding="utf-8"))
    return float(document["interval"]["half_width_um"])


def assert_slew_limited(records: list[CycleRecord]) -> None:
    applied = [(r.time_s, r.applied_um) for r in records if r.applied_um is not None]
    for (t0, a0), (t1, a1) in itertools.pairwise(applied):
        assert abs(a1 - a0) <= SLEW_UM_PER_MIN * (t1 - t0) / 60.0 + 0.1 + 1e-6, (t1, a0, a1)


def test_gate_hold_and_scale_ramp_and_gate_off_changes_only_the_flag(
    store: Path, caplog: pytest.LogCaptureFixture
) -> None:
    above_um = 1.2 * stored_half_width(store)  # inside the span the width is the stored one
    off = gated_run(store, None)
    never = gated_run(store, {"above_um": 1e6})
    assert [r.applied_um for r in off] == [r.applied_um for r in never]
    assert not any(r.uncertain for r in off + never)
    assert any(r.training_span == "outside" for r in off)  # the flag, without the gate

    with caplog.at_level(logging.INFO, logger="gateway.live.uncertainty_gate"):
        held = gated_run(store, {"above_um": above_um, "action": "hold"})
    gated = [i for i, r in enumerate(held) if r.uncertain]
    assert gated, [(r.time_s, r.interval_um) for r in held[35:45]]
    first = gated[0]
    assert held[first].training_span == "outside"
    assert all(r.uncertain for r in held[first:])
    values = {r.applied_um for r in held[first + 1 :]}
    assert len(values) == 1, values  # held where it was
    assert off[-1].applied_um != held[-1].applied_um
    episodes = [m for m in caplog.messages if "prediction unsure" in m]
    assert len(episodes) == 1, caplog.messages

    scaled = gated_run(store, {"above_um": above_um, "action": "scale", "scale": 0.5})
    assert_slew_limited(scaled)
    last = scaled[-1]
    assert last.uncertain and last.predicted_um is not None and last.applied_um is not None
    assert abs(last.applied_um - 0.5 * last.predicted_um) < abs(
        off[-1].applied_um - 0.5 * last.predicted_um  # type: ignore[operator]
    )


def test_scada_shows_outside_and_the_wider_interval_over_opc_ua(
    tmp_path: Path, store: Path
) -> None:
    """The whole gateway as ``run`` builds it (transmitters over an RTU pty pair, the CNC
    over OPC UA, SCADA on): a SCADA client reads the span state and the width."""
    from asyncua import ua

    from tests.test_closed_loop import CYCLE_S as RIG_CYCLE_S
    from tests.test_closed_loop import closed_loop
    from tests.test_monitor_loop import SCADA_WAIT_S, GatewayOpener, eventually
    from tests.test_promotion import VIEWER, scada_client, scada_gateway

    change_s = 40 * RIG_CYCLE_S
    program = SpeedProgram("up", ((change_s, 4000.0), (3600.0, 8000.0)))
    opener = GatewayOpener(scada_gateway(tmp_path))
    regimes = {"models": {}, "fallback_model": TRAINED_MODEL}

    async def scenario() -> tuple[list[CycleRecord], list[object]]:
        (tmp_path / "rig").mkdir()
        async with closed_loop(
            tmp_path / "rig", store, program, regimes=regimes, opener=opener
        ) as (closed, clock):
            app = opener.app
            assert app is not None and app.scada is not None
            pki = app.config.scada.pki_dir  # type: ignore[union-attr]
            viewer = await scada_client(app.scada.endpoint, pki, tmp_path / "v", VIEWER)
            ns, machine_id = app.scada.namespace_index, closed.loop.config.id
            try:

                def node(name: str):
                    return viewer.get_node(ua.NodeId(f"{machine_id}.{name}", ns))

                records = [await closed.step(clock) for _ in range(36)]
                span = await eventually(node("TrainingSpan").read_value, "inside")
                before = await node("IntervalUm").read_value()
                while len(records) < 60 and not (records[-1].speed_rpm or 0) > 7000:
                    records.append(await closed.step(clock))
                records.append(await closed.step(clock))
                after = await eventually(node("TrainingSpan").read_value, "outside")
                seen = [span, before, after, await node("IntervalUm").read_value()]
                seen.append(await node("OutsideInputs").read_value())
                return records, seen
            finally:
                await viewer.disconnect()

    assert SCADA_WAIT_S > 0
    records, (span, before, after, wider, names) = asyncio.run(scenario())
    fast = next(i for i, r in enumerate(records) if r.speed_rpm and r.speed_rpm > 7000)
    assert any(r.training_span == "outside" for r in records[fast : fast + 2])
    assert (span, after) == ("inside", "outside")
    assert "speed" in str(names).split(",")
    assert wider > 1.3 * before  # type: ignore[operator]
