"""Two machines on one RS-485 line: one port, one lock, no collision (drivers.bus_hub).

The line is a socat pty pair whose traffic socat logs byte by byte (the wire tap
of ``tests/rtu_wire.py``); the simulator's RTU transmitter server answers for the
modules of both machines and counts the requests it receives. The gateway is the
real one (``Gateway`` built from a configuration file by ``load_config``), each
machine compensating its own simulated CNC over Modbus TCP, on an accelerated
clock. Each machine's channels carry values of their own, so a reply that went
to the wrong machine would show as a wrong temperature.
"""

from __future__ import annotations

import asyncio
import statistics
import time
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import pytest
import yaml

from drivers.bus_hub import BusHub, rtu_silence_s
from drivers.clock import AcceleratedClock
from drivers.transmitters import DeviceMap, ModbusConnection, TransmitterBus
from gateway.config import load_config
from gateway.live.record import CycleRecord
from gateway.wiring import Gateway
from simulator.link import ChannelReading, FixedLink, MachineSnapshot, RunMode
from simulator.serve import SimulatedPlant, SimulatorConfig
from simulator.servers.modbus_transmitters import TransmitterDevice, TransmitterServer
from tests import gateway_rig as rig
from tests.ports import free_tcp_port
from tests.rtu_wire import collisions, read_wire
from tests.serial_pty import PtyPair, socat_pty_pair

BAUDRATE = 115200
SENSORS = [f"T{i}" for i in range(1, 10)]
#: Device ids per machine on the shared line: (8-channel module, module with T9).
MODULES = {"left": (1, 2), "right": (3, 4)}
DEAD_ID = 9  # a module of "left" that lost power


def value_C(machine: str, sensor: str) -> float:
    """What each channel shows: distinct per machine and per sensor."""
    base = 20.0 if machine == "left" else 40.0
    return base + int(sensor[1:]) / 2


SNAPSHOT = MachineSnapshot(
    time_s=0.0,
    channels={
        f"{machine}-{sensor}": ChannelReading(value_C(machine, sensor))
        for machine in MODULES
        for sensor in SENSORS
    },
    actual_speed_rpm=0.0,
    commanded_speed_rpm=0.0,
    run_mode=RunMode.STOP,
)
SERVED = [
    device
    for machine, (module, small) in MODULES.items()
    for device in (
        TransmitterDevice(module, [f"{machine}-T{i}" for i in range(1, 9)]),
        TransmitterDevice(small, [f"{machine}-T9"]),
    )
]


@pytest.fixture(scope="module")
def store(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return rig.fit_store(tmp_path_factory.mktemp("bus-hub"))


@pytest.fixture(name="line")
def line_fixture(tmp_path: Path) -> Iterator[PtyPair]:
    with socat_pty_pair(tmp_path, hexdump=True) as pair:
        yield pair


def wire_log(line: PtyPair) -> Path:
    assert line.log_path is not None, "the line is opened with hexdump=True"
    return line.log_path


def cnc_plant(clock: AcceleratedClock, seed: int) -> SimulatedPlant:
    """A simulated machine serving only its CNC (Modbus TCP); its transmitters are the line's."""
    config = {"program": "const8000", "seed": seed, "publish_period_s": 0.05}
    config["cnc"] = {"modbus": {"port": free_tcp_port()}}
    return SimulatedPlant(SimulatorConfig.model_validate(config), clock=clock)


def machine_entry(
    machine: str, plant: SimulatedPlant, store: Path, port: str, timeout_s: float, extra: list[int]
) -> dict[str, Any]:
    """The config entry of one machine on the shared line, its CNC on ``plant``."""
    module, small = MODULES[machine]
    devices = [
        {"device_id": module, "channels": [f"T{i}" for i in range(1, 9)]},
        {"device_id": small, "channels": ["T9"]},
        *({"device_id": d, "channels": [f"D{d}"]} for d in extra),
    ]
    line = {
        "name": f"{machine}-bus",
        "rtu": {"port": port, "baudrate": BAUDRATE},
        "timeout_s": timeout_s,
        "devices": devices,
    }
    return rig.machine_entry(machine, plant, store, transmitters=[line])


def write_config(tmp_path: Path, machines: list[dict[str, Any]]) -> Path:
    path = tmp_path / "config.yaml"
    document = {
        "state_dir": str(tmp_path / "state"),
        "logging": {"local_store": str(tmp_path / "data" / "points.sqlite")},
        "machines": machines,
    }
    path.write_text(yaml.safe_dump(document, sort_keys=False), encoding="utf-8")
    return path


async def run_gateway(
    config_path: Path,
    clock: AcceleratedClock,
    done: Callable[[dict[str, list[CycleRecord]]], bool],
    timeout_s: float,
) -> tuple[Gateway, dict[str, list[CycleRecord]], float]:
    """Run the gateway until ``done(records)``; the records per machine and the wall time."""
    records: dict[str, list[CycleRecord]] = {machine: [] for machine in MODULES}
    stop = asyncio.Event()

    def collect(record: CycleRecord) -> None:
        records[record.machine].append(record)
        if done(records):
            stop.set()

    gateway = Gateway(load_config(config_path, check_host=True), clock=clock, sinks=[collect])
    started = time.monotonic()
    await asyncio.wait_for(gateway.run(stop), timeout_s)
    return gateway, records, time.monotonic() - started


def assert_read_every_cycle(machine: str, records: list[CycleRecord]) -> None:
    for record in records:
        expected = {sensor: value_C(machine, sensor) for sensor in SENSORS}
        assert {s: record.temperatures_C[s] for s in SENSORS} == expected, record
        transmitter_errors = [e for e in record.link_errors if not e.startswith("CNC")]
        assert not [e for e in transmitter_errors if "D9" not in e], record


# -- no I/O ---------------------------------------------------------------------------------


async def serve_and_run(server, plants, config_path: Path, clock, cycles: int):
    """The shared line's modules and both CNCs served while the gateway runs ``cycles``
    cycles on every machine; (gateway, records, wall seconds)."""
    async with server:
        for plant in plants:
            await plant.start()
        try:
            return await run_gateway(
                config_path,
                clock,
                lambda r: min(len(v) for v in r.values()) >= cycles,
                timeout_s=60,
            )
        finally:
            for plant in plants:
                await plant.stop()


def test_rtu_silence_is_three_and_a_half_characters_or_fixed_above_19200_baud() -> None:
    assert rtu_silence_s(9600) == pytest.approx(3.5 * 11 / 9600)  # 4.01 ms
    assert rtu_silence_s(19200) == pytest.approx(3.5 * 11 / 19200)  # 2.01 ms
    assert rtu_silence_s(38400) == rtu_silence_s(BAUDRATE) == 0.00175
    with pytest.raises(ValueError, match="baudrate"):
        rtu_silence_s(0)


def test_buses_on_one_port_get_one_hub_with_the_most_patient_settings(tmp_path: Path) -> None:
    from gateway.wiring import build_buses, shared_hubs

    clock = AcceleratedClock(1.0)
    plants = [cnc_plant(clock, 0), cnc_plant(clock, 1)]
    left = machine_entry("left", plants[0], tmp_path, "/dev/ttyRS485", 0.2, [])
    right = machine_entry("right", plants[1], tmp_path, "/dev/ttyRS485", 0.3, [])
    right["transmitters"][0]["rtu"]["min_silence_s"] = 0.004
    config = load_config(write_config(tmp_path, [left, right]))
    hubs = shared_hubs(config.machines)
    assert list(hubs) == ["/dev/ttyRS485"]
    hub = hubs["/dev/ttyRS485"]
    (bus_left,) = build_buses(config.machines[0], hubs)
    (bus_right,) = build_buses(config.machines[1], hubs)
    assert bus_left.hub is bus_right.hub is hub
    assert hub.silence_s == 0.004  # the configured minimum beats t3.5 (1.75 ms here)
    assert isinstance(hub.link, ModbusConnection) and hub.link.timeout_s == 0.3
    assert hub.where == "left-bus, right-bus (serial /dev/ttyRS485)"
    # One machine alone builds its own hub, as before.
    (alone,) = build_buses(config.machines[0])
    assert alone.hub is not hub and alone.hub.silence_s == 0.00175


# -- the line -------------------------------------------------------------------------------


def test_two_machines_on_one_line_read_every_cycle_without_collision(
    tmp_path: Path, store: Path, line: PtyPair
) -> None:
    cycles = 300

    async def scenario() -> tuple[Gateway, dict[str, list[CycleRecord]], float, TransmitterServer]:
        clock = AcceleratedClock(40.0)  # a 1 s cycle every 25 ms of wall time
        plants = [cnc_plant(clock, 0), cnc_plant(clock, 1)]
        machines = [
            machine_entry(name, plant, store, line.client_port, 1.0, [])
            for name, plant in zip(MODULES, plants, strict=True)
        ]
        server = TransmitterServer(
            FixedLink(SNAPSHOT), SERVED, serial_port=line.server_port, baudrate=BAUDRATE
        )
        gateway, records, wall_s = await serve_and_run(
            server, plants, write_config(tmp_path, machines), clock, cycles
        )
        return gateway, records, wall_s, server

    gateway, records, wall_s, server = asyncio.run(scenario())
    for machine, machine_records in records.items():
        assert len(machine_records) >= cycles
        assert_read_every_cycle(machine, machine_records)
    (bus_left,), (bus_right,) = (loop.buses for loop in gateway.loops)
    hub = bus_left.hub
    assert bus_right.hub is hub and hub.opens == 1  # one port, opened once, never dropped
    assert not hub.link.connected  # closed when the gateway stopped
    read = {m: len(v) for m, v in records.items()}
    served = {m: [server.requests[d] for d in ids] for m, ids in MODULES.items()}
    # Every cycle asked each module once (a cycle may be cut short at the stop).
    for machine in MODULES:
        assert all(read[machine] <= n <= read[machine] + 1 for n in served[machine]), served
    wire = read_wire(wire_log(line))
    requests = [f for f in wire.frames if f.to_server]
    replies = [f for f in wire.frames if not f.to_server]
    assert wire.framing_errors == 0
    assert collisions(wire.frames, silent=set()) == 0
    assert len(requests) == sum(server.requests.values()) == hub.requests
    assert len(replies) == len(requests)
    gaps_s = [b.time_s - a.time_s for a, b in zip(replies, requests[1:], strict=False)]
    print(
        f"\nbus hub: {read} cycles in {wall_s:.1f} s wall "
        f"({1000 * wall_s / min(read.values()):.1f} ms per cycle); {len(requests)} requests, "
        f"{len(replies)} replies, {wire.framing_errors} framing errors, 0 collisions; "
        f"reply→next request gap min {1000 * min(gaps_s):.2f} ms, "
        f"median {1000 * statistics.median(gaps_s):.2f} ms"
    )
    # The hub waited t3.5 after each reply before the next request (socat's stamps).
    assert min(gaps_s) >= 0.9 * rtu_silence_s(BAUDRATE)


def test_a_dead_module_of_one_machine_does_not_stop_the_other_machine(
    tmp_path: Path, store: Path, line: PtyPair
) -> None:
    cycles = 30
    timeout_s = 0.6  # wall time: shorter ones miss live replies on a loaded machine

    async def scenario() -> tuple[Gateway, dict[str, list[CycleRecord]], TransmitterServer]:
        clock = AcceleratedClock(2.5)  # a 1 s cycle every 400 ms of wall time
        plants = [cnc_plant(clock, 0), cnc_plant(clock, 1)]
        machines = [
            machine_entry("left", plants[0], store, line.client_port, timeout_s, [DEAD_ID]),
            machine_entry("right", plants[1], store, line.client_port, timeout_s, []),
        ]
        server = TransmitterServer(
            FixedLink(SNAPSHOT), SERVED, serial_port=line.server_port, baudrate=BAUDRATE
        )
        gateway, records, _ = await serve_and_run(
            server, plants, write_config(tmp_path, machines), clock, cycles
        )
        return gateway, records, server

    gateway, records, server = asyncio.run(scenario())
    for machine, machine_records in records.items():
        assert len(machine_records) >= cycles
        assert_read_every_cycle(machine, machine_records)  # the other machine too, every cycle
    for record in records["left"]:
        assert record.temperatures_C["D9"] is None
        assert any(f"no response from device {DEAD_ID}" in e for e in record.link_errors)
    # One bounded request per cycle to the dead module (no retry), and the port stayed open.
    cycles_left = len(records["left"])
    assert cycles_left <= server.requests[DEAD_ID] <= cycles_left + 1
    (bus_left,), (bus_right,) = (loop.buses for loop in gateway.loops)
    assert bus_left.hub is bus_right.hub and bus_left.hub.opens == 1
    assert bus_right.health.total_failures == 0
    assert bus_left.device_health[DEAD_ID].consecutive_failures >= cycles
    wire = read_wire(wire_log(line))
    assert wire.framing_errors == 0
    assert collisions(wire.frames, silent={DEAD_ID}) == 0
    print(
        f"\ndead module: {len(records['left'])} + {len(records['right'])} cycles, "
        f"{server.requests[DEAD_ID]} requests to the dead module, "
        f"{sum(server.requests.values())} in all, {wire.framing_errors} framing errors"
    )


def test_the_port_closes_with_its_last_user_and_reopens_only_when_the_whole_line_is_silent(
    line: PtyPair,
) -> None:
    async def body() -> None:
        link = ModbusConnection(serial_port=line.client_port, baudrate=BAUDRATE, timeout_s=0.5)
        hub = BusHub(link, silence_s=rtu_silence_s(BAUDRATE))
        left = TransmitterBus([DeviceMap(1, ("T1",)), DeviceMap(2, ("T9",))], hub=hub)
        right = TransmitterBus([DeviceMap(3, ("T1",))], hub=hub)
        server = TransmitterServer(
            FixedLink(SNAPSHOT), SERVED, serial_port=line.server_port, baudrate=BAUDRATE
        )
        async with server:
            await asyncio.gather(left.read_all(1.0), right.read_all(1.0))
            assert hub.opens == 1 and hub.users == 2
            # All of one machine's modules silent: its bus fails, the port stays open.
            server.silenced.update({1, 2})
            for now in (2.0, 3.0):
                results = await left.read_all(now)
                assert all(r.value_C is None for r in results.values())
                assert (await right.read_all(now))["T1"].value_C == value_C("right", "T1")
            assert hub.opens == 1 and link.connected
            assert left.health.consecutive_failures == 2 and right.health.connected
            # The whole line silent for a round: the port is reopened, once, for both.
            server.silenced.add(3)
            await left.read_all(4.0)
            assert link.connected  # one silent user of two: not yet
            await right.read_all(4.0)
            assert not link.connected
            server.silenced.clear()
            await asyncio.gather(left.read_all(5.0), right.read_all(5.0))
            assert hub.opens == 2 and left.health.reconnects == right.health.reconnects == 1
            # Closing one user keeps the port for the other; the last one closes it.
            await left.close()
            assert link.connected and hub.users == 1
            assert (await right.read_all(6.0))["T1"].value_C == value_C("right", "T1")
            await right.close()
            assert not link.connected and hub.users == 0

    asyncio.run(asyncio.wait_for(body(), 30))
