"""Modbus slaves of the simulator: real traffic over loopback TCP and a socat pty pair.

Two independent masters talk to the servers: pymodbus's async clients and mbpoll
(libmodbus), so a register map that only pymodbus understands would fail here.
"""

from __future__ import annotations

import asyncio
import math
import os
import re
import select
import shutil
import struct
from collections.abc import Awaitable, Callable
from dataclasses import replace
from pathlib import Path
from typing import TypeVar

import pytest
from pymodbus.client import AsyncModbusSerialClient, AsyncModbusTcpClient
from pymodbus.exceptions import ModbusIOException

from drivers.register_codec import (
    OPEN_CIRCUIT_CODE,
    SHORT_CIRCUIT_CODE,
    float32_to_registers,
    int16_to_register,
    register_to_int16,
    registers_to_float32,
    registers_to_float32_shortest,
)
from simulator.link import ChannelReading, ChannelStatus, FixedLink, MachineSnapshot, RunMode
from simulator.servers.modbus_cnc import MACRO_BASE, CncModbusServer, macro_register
from simulator.servers.modbus_common import encode_temperature
from simulator.servers.modbus_transmitters import TransmitterDevice, TransmitterServer
from tests.ports import free_tcp_port
from tests.serial_pty import PtyPair, serial_pty_fixture, socat_pty_pair  # noqa: F401

T = TypeVar("T")
HOST = "127.0.0.1"
OK, OPEN, SHORT, RANGE = (int(s) for s in ChannelStatus)


def machine(**changes: object) -> MachineSnapshot:
    """The reference machine state; keyword arguments replace fields."""
    snapshot = MachineSnapshot(
        time_s=0.0,
        channels={
            "T1": ChannelReading(23.5),
            "T2": ChannelReading(-5.2),
            "T3": ChannelReading(math.nan, ChannelStatus.OPEN_CIRCUIT),
            "T4": ChannelReading(30.0, ChannelStatus.SHORT_CIRCUIT),
            "T5": ChannelReading(4000.0),  # beyond int16 counts: clamped
            "T9": ChannelReading(31.25),
            "ambient": ChannelReading(20.0),
        },
        actual_speed_rpm=4000.0,
        commanded_speed_rpm=4500.0,
        run_mode=RunMode.AUTO,
        macros={500: 0.0125},
        probe_error_um=None,
    )
    return replace(snapshot, **changes)


MODULE_1 = TransmitterDevice(1, ["T1", "T2", "T3", "T4", "T5", "T6", "T7", "T8"])
MODULE_2 = TransmitterDevice(2, ["T9", "ambient", None])
# Input registers 0–15 as unsigned words, what a master receives. T6–T8 are not in
# the snapshot and channels 3–8 of module 2 have no sensor: both read as no probe.
VALUES_1 = [235, int16_to_register(-52), 0x7FFF, 0x8000, 0x7FFF, 0x7FFF, 0x7FFF, 0x7FFF]
EXPECTED_1 = [*VALUES_1, OK, OK, OPEN, SHORT, RANGE, OPEN, OPEN, OPEN]
EXPECTED_2 = [313, 200, *[0x7FFF] * 6, OK, OK, *[OPEN] * 6]  # 31.25 °C: ties away from 0


def run(coro_fn: Callable[[], Awaitable[T]], timeout_s: float = 20.0) -> T:
    """Run one async test body (pytest-asyncio is not used in this project)."""

    async def bounded() -> T:
        return await asyncio.wait_for(coro_fn(), timeout_s)

    return asyncio.run(bounded())


def decode_temperatures(registers: list[int]) -> tuple[list[float], list[int]]:
    return [register_to_int16(r) * 0.1 for r in registers[:8]], list(registers[8:16])


async def read_inputs(
    client: AsyncModbusTcpClient | AsyncModbusSerialClient, device_id: int
) -> list[int]:
    response = await client.read_input_registers(0, count=16, device_id=device_id)
    assert not response.isError(), response
    return list(response.registers)


async def mbpoll(*args: str) -> tuple[int, dict[int, str], str]:
    """Run mbpoll once; return its exit status, {reference: first value token}, output."""
    executable = shutil.which("mbpoll")
    assert executable, "mbpoll is not installed (scripts/setup-system.sh installs it)"
    process = await asyncio.create_subprocess_exec(
        executable,
        *args,
        stdout=asyncio.subprocess.PIPE,
        stderr=asyncio.subprocess.STDOUT,
    )
    out, _ = await asyncio.wait_for(process.communicate(), 10)
    text = out.decode(errors="replace")
    values = {int(m[1]): m[2] for m in re.finditer(r"^\[(\d+)\]:\s+(\S+)", text, re.MULTILINE)}
    assert process.returncode is not None
    return process.returncode, values, text


def mbpoll_rtu_args(device_id: int) -> list[str]:
    """mbpoll's RTU options matching the server (its default parity is even)."""
    serial = ["-b", "19200", "-d", "8", "-s", "1", "-P", "none"]
    return ["-m", "rtu", "-a", str(device_id), *serial, "-o", "1", "-1"]


# ---------------------------------------------------------------- pure encoders


def test_temperature_encoding_counts_faults_and_clamps() -> None:
    assert encode_temperature(ChannelReading(23.5)) == (235, OK)
    assert encode_temperature(ChannelReading(-5.2)) == (0x10000 - 52, OK)
    assert encode_temperature(ChannelReading(0.04)) == (0, OK)
    assert encode_temperature(ChannelReading(31.25)) == (313, OK)  # ties away from zero
    assert encode_temperature(ChannelReading(-31.25)) == (0x10000 - 313, OK)
    assert encode_temperature(ChannelReading(3276.7)) == (32767, OK)
    assert encode_temperature(ChannelReading(-3276.8)) == (0x8000, OK)
    assert encode_temperature(ChannelReading(math.nan, ChannelStatus.OPEN_CIRCUIT)) == (
        0x7FFF,
        OPEN,
    )
    assert encode_temperature(ChannelReading(25.0, ChannelStatus.SHORT_CIRCUIT)) == (0x8000, SHORT)
    assert encode_temperature(None) == (0x7FFF, OPEN)
    assert encode_temperature(ChannelReading(3276.8)) == (0x7FFF, RANGE)
    assert encode_temperature(ChannelReading(-5000.0)) == (0x8000, RANGE)
    assert encode_temperature(ChannelReading(math.inf)) == (0x7FFF, RANGE)
    assert encode_temperature(ChannelReading(math.nan)) == (0x7FFF, RANGE)
    assert encode_temperature(ChannelReading(80.0, ChannelStatus.OUT_OF_RANGE)) == (800, RANGE)
    assert register_to_int16(int16_to_register(OPEN_CIRCUIT_CODE)) == 32767
    assert register_to_int16(int16_to_register(SHORT_CIRCUIT_CODE)) == -32768
    with pytest.raises(ValueError):
        int16_to_register(40000)
    with pytest.raises(ValueError):
        register_to_int16(-1)


def test_float32_words_are_big_endian_ieee754() -> None:
    assert float32_to_registers(4000.0) == (0x457A, 0x0000)
    assert float32_to_registers(-1.5) == (0xBFC0, 0x0000)
    assert registers_to_float32(0x457A, 0x0000) == 4000.0
    high, low = float32_to_registers(0.0125)
    assert (high, low) == struct.unpack(">HH", struct.pack(">f", 0.0125))
    assert registers_to_float32(high, low) == pytest.approx(0.0125, rel=1e-7)
    assert registers_to_float32(high, low) != 0.0125  # float32 is not the double 0.0125 ...
    assert registers_to_float32_shortest(high, low) == 0.0125  # ... but means it
    assert math.isnan(registers_to_float32(*float32_to_registers(math.nan)))
    assert float32_to_registers(1e39) == float32_to_registers(math.inf)
    assert macro_register(500) == MACRO_BASE and macro_register(999) == 1998
    with pytest.raises(ValueError):
        macro_register(1000)


def test_device_configuration_is_checked_without_io() -> None:
    link = FixedLink(machine())
    assert MODULE_2.channels == ("T9", "ambient", None, None, None, None, None, None)
    with pytest.raises(ValueError):
        TransmitterDevice(0, ["T1"])
    with pytest.raises(ValueError):
        TransmitterDevice(1, ["T1"] * 9)
    with pytest.raises(ValueError):
        TransmitterServer(link, [MODULE_1])  # neither tcp nor serial
    with pytest.raises(ValueError):
        TransmitterServer(link, [MODULE_1], tcp=(HOST, 0), serial_port="/dev/null")
    with pytest.raises(ValueError):
        TransmitterServer(link, [MODULE_1, TransmitterDevice(1, [])], tcp=(HOST, 0))
    with pytest.raises(ValueError):
        CncModbusServer(link, port=0, device_id=0)
    server = TransmitterServer(link, [MODULE_1], tcp=(HOST, 0))
    assert not server.running and server.address == (HOST, 0)


# ---------------------------------------------------------------- transmitters over TCP


def test_transmitters_over_tcp_two_devices_pymodbus() -> None:
    async def body() -> None:
        link = FixedLink(machine())
        async with TransmitterServer(link, [MODULE_1, MODULE_2], tcp=(HOST, 0)) as server:
            host, port = server.address
            assert port != 0
            client = AsyncModbusTcpClient(host, port=port, timeout=0.3, retries=0)
            assert await client.connect()
            try:
                regs_1 = await read_inputs(client, 1)
                regs_2 = await read_inputs(client, 2)
                assert regs_1 == EXPECTED_1
                assert regs_2 == EXPECTED_2
                values, statuses = decode_temperatures(regs_1)
                assert values[0] == pytest.approx(23.5) and values[1] == pytest.approx(-5.2)
                assert values[2] == pytest.approx(3276.7)  # the fault code, not a temperature
                assert statuses == [OK, OK, OPEN, SHORT, RANGE, OPEN, OPEN, OPEN]
                values_2, _ = decode_temperatures(regs_2)
                assert values_2[:2] == pytest.approx([31.3, 20.0])

                info = await client.read_holding_registers(0, count=3, device_id=2)
                assert info.registers == [8, 100, 100]
                refused = await client.write_register(0, 16, device_id=1)
                assert refused.isError() and refused.exception_code == 2
                refused = await client.write_registers(1, [1, 2], device_id=2)
                assert refused.isError()
                beyond = await client.read_input_registers(10, count=7, device_id=1)
                assert beyond.isError() and beyond.exception_code == 2
                coils = await client.read_coils(0, count=1, device_id=1)
                assert coils.isError() and coils.exception_code == 1
                info = await client.read_holding_registers(0, count=3, device_id=1)
                assert info.registers == [8, 100, 100]  # the refused writes changed nothing

                # A device id nobody has is silent, as on a bus (client times out).
                with pytest.raises(ModbusIOException):
                    await client.read_input_registers(0, count=1, device_id=9)
            finally:
                client.close()
        assert not server.running

    run(body)


def test_publish_shows_new_snapshot_values() -> None:
    async def body() -> None:
        link = FixedLink(machine())
        async with TransmitterServer(link, [MODULE_1], tcp=(HOST, free_tcp_port())) as server:
            host, port = server.address
            client = AsyncModbusTcpClient(host, port=port, timeout=1, retries=0)
            assert await client.connect()
            try:
                assert (await read_inputs(client, 1))[0] == 235
                channels = dict(machine().channels)
                channels["T1"] = ChannelReading(24.1)
                channels["T3"] = ChannelReading(19.9)  # the probe is back
                channels["T2"] = ChannelReading(-5.2, ChannelStatus.SHORT_CIRCUIT)
                link.set_snapshot(machine(channels=channels))
                assert (await read_inputs(client, 1))[0] == 235  # not before publish()
                await server.publish()
                regs = await read_inputs(client, 1)
                assert regs[:3] == [241, 0x8000, 199]
                assert regs[8:11] == [OK, SHORT, OK]
            finally:
                client.close()

    run(body)


def test_transmitters_over_tcp_with_mbpoll() -> None:
    async def body() -> None:
        link = FixedLink(machine())
        async with TransmitterServer(link, [MODULE_1, MODULE_2], tcp=(HOST, 0)) as server:
            port = str(server.address[1])
            for device_id, expected in ((1, EXPECTED_1), (2, EXPECTED_2)):
                rc, values, text = await mbpoll(
                    "-m",
                    "tcp",
                    "-p",
                    port,
                    "-a",
                    str(device_id),
                    "-t",
                    "3",
                    "-0",
                    "-r",
                    "0",
                    "-c",
                    "16",
                    "-1",
                    HOST,
                )
                assert rc == 0, text
                assert [int(values[i]) for i in range(16)] == expected, text
            rc, _, text = await mbpoll(
                "-m", "tcp", "-p", port, "-a", "1", "-t", "4", "-0", "-r", "0", "-1", HOST, "5"
            )
            assert rc != 0 and "Illegal data address" in text

    run(body)


# ---------------------------------------------------------------- transmitters over RTU


def test_socat_pty_pair_carries_bytes_and_goes_away(tmp_path: Path) -> None:
    def read_within(fd: int, timeout_s: float = 2.0) -> bytes:
        ready, _, _ = select.select([fd], [], [], timeout_s)
        return os.read(fd, 64) if ready else b""

    with socat_pty_pair(tmp_path) as pair:
        server = os.open(pair.server_port, os.O_RDWR | os.O_NOCTTY)
        client = os.open(pair.client_port, os.O_RDWR | os.O_NOCTTY)
        try:
            os.write(client, b"\x01\x04request")
            assert read_within(server) == b"\x01\x04request"
            os.write(server, b"reply")
            assert read_within(client) == b"reply"
        finally:
            os.close(server)
            os.close(client)
    # socat is stopped at exit and removes its links: nothing is left to open.
    assert not os.path.lexists(pair.server_port)
    assert not os.path.lexists(pair.client_port)


def test_transmitters_over_rtu_pymodbus_and_mbpoll(serial_pty: PtyPair) -> None:
    async def body() -> None:
        link = FixedLink(machine())
        server = TransmitterServer(
            link, [MODULE_1, MODULE_2], serial_port=serial_pty.server_port, baudrate=19200
        )
        with pytest.raises(AttributeError):
            _ = server.address
        async with server:
            client = AsyncModbusSerialClient(
                serial_pty.client_port, baudrate=19200, parity="N", timeout=0.5, retries=0
            )
            assert await client.connect()
            try:
                assert await read_inputs(client, 1) == EXPECTED_1
                assert await read_inputs(client, 2) == EXPECTED_2
                values, statuses = decode_temperatures(await read_inputs(client, 1))
                assert values[:2] == pytest.approx([23.5, -5.2])
                assert statuses[2] == OPEN
                refused = await client.write_register(2, 1, device_id=2)
                assert refused.isError() and refused.exception_code == 2
                with pytest.raises(ModbusIOException):  # absent module: no answer on the bus
                    await client.read_input_registers(0, count=1, device_id=7)
                assert await read_inputs(client, 2) == EXPECTED_2  # the bus still works
            finally:
                client.close()

            for device_id, expected in ((1, EXPECTED_1), (2, EXPECTED_2)):
                rc, values, text = await mbpoll(
                    *mbpoll_rtu_args(device_id),
                    "-t",
                    "3",
                    "-r",
                    "1",
                    "-c",
                    "16",
                    serial_pty.client_port,
                )
                assert rc == 0, text
                assert [int(values[i]) for i in range(1, 17)] == expected, text

    run(body)


def test_serial_server_start_fails_without_port(tmp_path: Path) -> None:
    async def body() -> None:
        server = TransmitterServer(
            FixedLink(machine()), [MODULE_1], serial_port=str(tmp_path / "no-such-tty")
        )
        with pytest.raises(OSError):
            await server.start()
        assert not server.running

    run(body)


# ---------------------------------------------------------------- CNC over TCP


def test_cnc_read_and_macro_write_with_pymodbus() -> None:
    async def body() -> None:
        link = FixedLink(machine())
        async with CncModbusServer(link, port=0) as server:
            host, port = server.address
            client = AsyncModbusTcpClient(host, port=port, timeout=1, retries=0)
            assert await client.connect()
            f32 = client.DATATYPE.FLOAT32
            try:
                status = await client.read_holding_registers(0, count=7, device_id=1)
                assert not status.isError(), status
                regs = status.registers
                assert client.convert_from_registers(regs[0:2], f32, word_order="big") == 4000.0
                assert client.convert_from_registers(regs[2:4], f32, word_order="big") == 4500.0
                assert regs[4] == RunMode.AUTO
                assert math.isnan(client.convert_from_registers(regs[5:7], f32))
                macro = await client.read_holding_registers(macro_register(500), count=2)
                assert client.convert_from_registers(macro.registers, f32) == pytest.approx(0.0125)
                vacant = await client.read_holding_registers(macro_register(501), count=2)
                assert math.isnan(client.convert_from_registers(vacant.registers, f32))

                words = client.convert_to_registers(-0.0375, f32, word_order="big")
                written = await client.write_registers(macro_register(500), words, device_id=1)
                assert not written.isError(), written
                assert link.writes == [(500, -0.0375)]  # applied before the reply came back
                back = await client.read_holding_registers(macro_register(500), count=2)
                assert back.registers == words
                await server.publish()  # the link agrees: publish keeps the written value
                back = await client.read_holding_registers(macro_register(500), count=2)
                assert back.registers == words

                two = client.convert_to_registers([1.5, 2.5], f32, word_order="big")
                assert not (await client.write_registers(macro_register(998), two)).isError()
                assert link.writes[-2:] == [(998, 1.5), (999, 2.5)]
                half = client.convert_to_registers(0.5, f32, word_order="big")
                rw = await client.readwrite_registers(
                    read_address=macro_register(501),
                    read_count=2,
                    write_address=macro_register(501),
                    values=half,
                )  # FC23 is a write too: it reaches the machine the same way
                assert not rw.isError() and rw.registers == half
                assert link.writes[-1] == (501, 0.5)

                refusals = [
                    await client.write_registers(macro_register(500), words[:1]),  # half
                    await client.write_registers(macro_register(500) + 1, words),  # straddles
                    await client.write_register(macro_register(500), 0),  # FC6: half
                    await client.write_registers(0, words),  # spindle speed is read-only
                    await client.write_registers(4, [0]),  # run mode too
                    await client.write_registers(100, words),  # gap in the map
                    await client.write_registers(macro_register(999), words * 2),  # past #999
                    await client.read_holding_registers(7, count=1),  # gap in the map
                    await client.read_input_registers(0, count=1),  # no input registers
                ]
                assert all(r.isError() for r in refusals), refusals
                assert [r.exception_code for r in refusals[:7]] == [2] * 7
                nan_words = client.convert_to_registers(math.nan, f32, word_order="big")
                bad = await client.write_registers(macro_register(510), nan_words)
                assert bad.isError() and bad.exception_code == 3
                assert len(link.writes) == 4  # nothing refused reached the machine
                status = await client.read_holding_registers(0, count=7, device_id=1)
                assert status.registers == regs
            finally:
                client.close()

    run(body)


def test_cnc_publish_after_snapshot_change() -> None:
    async def body() -> None:
        link = FixedLink(machine())
        async with CncModbusServer(link, port=free_tcp_port()) as server:
            client = AsyncModbusTcpClient(HOST, port=server.address[1], timeout=1, retries=0)
            assert await client.connect()
            f32 = client.DATATYPE.FLOAT32
            try:
                link.set_snapshot(
                    machine(
                        actual_speed_rpm=0.0,
                        run_mode=RunMode.STOP,
                        probe_error_um=-3.5,
                        macros={500: 0.02, 777: 12.0},
                    )
                )
                await server.publish()
                regs = (await client.read_holding_registers(0, count=7)).registers
                assert client.convert_from_registers(regs[0:2], f32) == 0.0
                assert regs[4] == RunMode.STOP
                assert client.convert_from_registers(regs[5:7], f32) == -3.5
                m500 = (await client.read_holding_registers(macro_register(500), count=2)).registers
                m777 = (await client.read_holding_registers(macro_register(777), count=2)).registers
                assert client.convert_from_registers(m500, f32) == pytest.approx(0.02)
                assert client.convert_from_registers(m777, f32) == 12.0
                assert link.writes == []  # publishing is not a client write
            finally:
                client.close()

    run(body)


def test_cnc_with_mbpoll_float_read_and_macro_write() -> None:
    async def body() -> None:
        link = FixedLink(machine())
        async with CncModbusServer(link, port=0) as server:
            port = str(server.address[1])
            tcp = ["-m", "tcp", "-p", port, "-a", "1", "-0", "-o", "1", "-1"]
            rc, values, text = await mbpoll(*tcp, "-t", "4:float", "-B", "-r", "0", "-c", "2", HOST)
            assert rc == 0, text
            assert float(values[0]) == 4000.0 and float(values[2]) == 4500.0, text
            rc, values, text = await mbpoll(*tcp, "-t", "4", "-r", "4", HOST)
            assert rc == 0 and int(values[4]) == RunMode.AUTO, text

            address = str(macro_register(500))
            rc, _, text = await mbpoll(*tcp, "-t", "4:float", "-B", "-r", address, HOST, "0.0375")
            assert rc == 0, text
            assert link.writes == [(500, pytest.approx(0.0375, rel=1e-7))]
            assert link.macros[500] == 0.0375
            rc, values, text = await mbpoll(*tcp, "-t", "4:float", "-B", "-r", address, HOST)
            assert rc == 0 and float(values[int(address)]) == pytest.approx(0.0375), text

            # Half a float (a 16-bit write) is refused and does not reach the machine.
            rc, _, text = await mbpoll(*tcp, "-t", "4", "-r", address, HOST, "7")
            assert rc != 0 and "Illegal data address" in text
            assert len(link.writes) == 1

    run(body)


def test_cnc_life_cycle_and_real_port_for_port_zero() -> None:
    async def body() -> None:
        link = FixedLink(machine())
        first = CncModbusServer(link, port=0)
        second = CncModbusServer(link, port=0)
        async with first, second:
            assert first.address[1] != second.address[1]
            assert first.address[1] > 0
            with pytest.raises(RuntimeError):
                await first.start()
            taken = CncModbusServer(link, port=first.address[1])
            with pytest.raises(OSError):
                await taken.start()
            assert not taken.running
        assert not first.running
        with pytest.raises(RuntimeError):
            await first.publish()

    run(body)
