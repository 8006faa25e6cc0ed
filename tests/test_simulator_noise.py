"""The simulator's noise is a function of (seed, machine time, channel), not of when it is read.

A served machine is read by every endpoint on a wall-clock period; the same
test must see the same readings whatever that period and its jitter. Checked
on the noise function itself, on the machine, on the offline recorder and on
two served plants read over Modbus TCP with pymodbus.
"""

from __future__ import annotations

import asyncio

import numpy as np
import pytest
from pymodbus.client import AsyncModbusTcpClient

from drivers.clock import ManualClock
from simulator.machine import AMBIENT_CHANNEL, SimulatedMachine
from simulator.noise import PROBE, SENSORS, MachineNoise
from simulator.params import load_params
from simulator.programs import SpeedProgram, load_programs
from simulator.record import REST_BEFORE_S, record
from simulator.serve import SimulatedPlant, SimulatorConfig
from simulator.servers.modbus_common import encode_temperature
from tests.ports import free_tcp_port

PARAMS = load_params()
PROGRAMS = load_programs()
CHANNELS = [*PARAMS.sensors, AMBIENT_CHANNEL]


def test_noise_is_fixed_by_seed_stream_and_index_and_looks_like_white_noise() -> None:
    noise = MachineNoise(11)
    first = noise.normal(SENSORS, 1234, 10)
    noise.normal(PROBE, 1234, 3)  # other draws in between change nothing
    noise.normal(SENSORS, 99, 10)
    np.testing.assert_array_equal(noise.normal(SENSORS, 1234, 10), first)
    np.testing.assert_array_equal(MachineNoise(11).normal(SENSORS, 1234, 10), first)
    assert not np.array_equal(MachineNoise(12).normal(SENSORS, 1234, 10), first)
    assert not np.array_equal(noise.normal(PROBE, 1234, 10), first)
    assert not np.array_equal(noise.normal(SENSORS, 1235, 10), first)
    # Fewer channels: the same first values (a channel's noise does not move).
    np.testing.assert_array_equal(noise.normal(SENSORS, 1234, 4), first[:4])
    draws = np.array([noise.normal(SENSORS, k, 10) for k in range(5000)])
    assert abs(draws.mean()) < 0.03 and draws.std() == pytest.approx(1.0, abs=0.03)
    lag1 = np.corrcoef(draws[:-1, 0], draws[1:, 0])[0, 1]  # neighbouring samples
    across = np.corrcoef(draws[:, 0], draws[:, 1])[0, 1]  # neighbouring channels
    assert abs(lag1) < 0.05 and abs(across) < 0.05


def test_readings_and_probe_do_not_depend_on_how_often_the_machine_is_read() -> None:
    program = PROGRAMS["const6000"]
    once, often = (SimulatedMachine(PARAMS, program, seed=3) for _ in range(2))
    for t in np.arange(0.0, 3 * 3600.0, 60.0):
        once.advance_to(t)
        often.advance_to(t)
        for _ in range(7):  # seven publishes in one sample
            often.readings()
            often.measured_error_um()
        assert once.readings() == often.readings()
        assert once.measured_error_um() == often.measured_error_um()
        assert once.probe_error_um == often.probe_error_um
    assert once.probe_error_um is not None
    readings = np.array([[r.value_C for r in once.readings().values()]])
    assert readings.shape == (1, len(CHANNELS))


def test_the_recorder_reads_the_same_noise_function_as_a_machine() -> None:
    program = PROGRAMS["const4000"]
    seed = 7
    recording = record(PARAMS, [program], seed=seed, sample_s=60.0)
    child = int(np.random.SeedSequence(seed).spawn(1)[0].generate_state(1)[0])
    with_rest = SpeedProgram(program.name, ((REST_BEFORE_S, 0.0), *program.segments))
    machine = SimulatedMachine(PARAMS, with_rest, seed=child)
    header = list(recording.header)
    for row in recording.rows[::17]:
        machine.advance_to(row[1])
        readings = machine.readings()
        for name in PARAMS.sensors:
            assert row[header.index(name)] == readings[name].value_C
        assert row[header.index("ambient_C")] == readings[AMBIENT_CHANNEL].value_C
        assert row[header.index("error_um")] == machine.measured_error_um()


async def served_readings(seed: int, publish_period_s: float, times_s: list[float]) -> list:
    """Temperatures and probe value read over Modbus TCP at each machine time."""
    clock = ManualClock()
    devices = [
        {"device_id": 1, "channels": CHANNELS[:8]},
        {"device_id": 2, "channels": CHANNELS[8:]},
    ]
    config = SimulatorConfig.model_validate(
        {
            "program": "const6000",
            "seed": seed,
            "publish_period_s": publish_period_s,
            "transmitters": {"tcp": {"port": free_tcp_port(), "devices": devices}},
            "cnc": {"modbus": {"port": free_tcp_port()}},
        }
    )
    plant = SimulatedPlant(config, clock=clock)
    assert plant.tcp_transmitters is not None and plant.cnc_modbus is not None
    seen = []
    async with plant:
        host, port = plant.tcp_transmitters.address
        cnc_host, cnc_port = plant.cnc_modbus.address
        transmitters = AsyncModbusTcpClient(host, port=port, timeout=2)
        cnc = AsyncModbusTcpClient(cnc_host, port=cnc_port, timeout=2)
        await transmitters.connect()
        await cnc.connect()
        try:
            for t in times_s:
                clock.advance(t - clock.now())
                await plant.update()
                await asyncio.sleep(3 * publish_period_s)  # a few more wall-clock publishes
                values = []
                for device, count in ((1, 8), (2, len(CHANNELS) - 8)):
                    rr = await transmitters.read_input_registers(0, count=count, device_id=device)
                    values += [(r - 65536 if r >= 32768 else r) / 10.0 for r in rr.registers]
                rr = await cnc.read_holding_registers(5, count=2, device_id=1)
                probe = cnc.convert_from_registers(
                    rr.registers, cnc.DATATYPE.FLOAT32, word_order="big"
                )
                seen.append((values, probe))
        finally:
            transmitters.close()
            cnc.close()
    return seen


def test_served_readings_are_the_same_whatever_the_publish_period() -> None:
    times = [600.0, 1800.0, 3605.0, 7200.0]
    fast = asyncio.run(served_readings(5, 0.005, times))
    slow = asyncio.run(served_readings(5, 0.25, times))
    assert fast == slow
    # ...and they are the offline machine's readings at those times (0.1 °C registers).
    machine = SimulatedMachine(PARAMS, PROGRAMS["const6000"], seed=5)
    for t, (values, probe) in zip(times, fast, strict=True):
        machine.advance_to(t)
        registers = [encode_temperature(r)[0] for r in machine.readings().values()]
        expected = [(r - 65536 if r >= 32768 else r) / 10.0 for r in registers]
        assert values == pytest.approx(expected, abs=1e-9)
        assert probe == pytest.approx(machine.probe_error_um, abs=1e-5)
    other_seed = asyncio.run(served_readings(6, 0.25, times))
    assert other_seed != fast
