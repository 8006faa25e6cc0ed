"""The gateway's transmitter bus against the simulator's Modbus slaves (TCP and RTU).

Real servers from ``simulator.servers`` with a FixedLink behind them, real sockets and
a socat pty pair: no protocol library is mocked. Field faults are produced the way
they happen: a device id nobody answers for (a dead RS-485 slave) and a server that
goes away and comes back on the same port.
"""

from __future__ import annotations

import asyncio
import time
from collections.abc import Awaitable, Callable
from pathlib import Path
from typing import TypeVar

import pytest

from drivers.link_health import Backoff, LinkHealth
from drivers.transmitters import ChannelResult, DeviceMap, TransmitterBus, decode_channels
from simulator.link import FixedLink, RunMode
from simulator.servers.modbus_transmitters import TransmitterDevice, TransmitterServer
from tests.ports import free_tcp_port
from tests.serial_pty import socat_pty_pair
from tests.test_modbus_servers import machine as reference_machine

T = TypeVar("T")
HOST = "127.0.0.1"
TIMEOUT_S = 0.3
SILENT_ID = 3

#: The reference machine of the server tests, at rest: its channels are what is read here
#: (T5 beyond int16 counts: clamped, status 3; T9 312.5 counts: ties away from zero → 31.3).
SNAPSHOT = reference_machine(
    actual_speed_rpm=0.0, commanded_speed_rpm=0.0, run_mode=RunMode.STOP, macros={}
)
SERVED = [
    TransmitterDevice(1, ["T1", "T2", "T3", "T4", "T5"]),
    TransmitterDevice(2, ["T9", "ambient"]),
]
DEVICE_1 = DeviceMap(1, ("T1", "T2", "T3", "T4", "T5"))
DEVICE_2 = DeviceMap(2, ("T9", "ambient", None))
SILENT = DeviceMap(SILENT_ID, ("S1", None, "S3"))
#: (value_C, status) per sensor, as the gateway must report them.
EXPECTED = {
    "T1": (23.5, 0),
    "T2": (-5.2, 0),
    "T3": (None, 1),
    "T4": (None, 2),
    "T5": (None, 3),
    "T9": (31.3, 0),
    "ambient": (20.0, 0),
}


def run(body: Callable[[], Awaitable[T]], timeout_s: float = 20.0) -> T:
    """Run one async test body (pytest-asyncio is not used in this project)."""

    async def bounded() -> T:
        return await asyncio.wait_for(body(), timeout_s)

    return asyncio.run(bounded())


def assert_expected(results: dict[str, ChannelResult], sensors: list[str]) -> None:
    for sensor in sensors:
        value, status = EXPECTED[sensor]
        result = results[sensor]
        assert (result.value_C, result.status) == (value, status), result
        assert (result.error is None) == (status == 0), result


def assert_silent(results: dict[str, ChannelResult]) -> None:
    for sensor in ("S1", "S3"):
        result = results[sensor]
        assert result.value_C is None and result.status is None, result
        assert result.error is not None and f"no response from device {SILENT_ID}" in result.error


# -- link health (no I/O; the back-off is tested in test_backoff.py) ----------------------


def test_link_health_counts_failures_and_reconnects() -> None:
    health = LinkHealth()
    health.record_connect()
    health.record_ok(1.0)
    assert (health.connected, health.reconnects, health.last_ok_s) == (True, 0, 1.0)
    health.record_failure("boom")
    health.record_failure("bang")
    assert (health.connected, health.consecutive_failures, health.total_failures) == (False, 2, 2)
    health.record_connect()
    health.record_ok(5.0)
    assert (health.consecutive_failures, health.total_failures, health.reconnects) == (0, 2, 1)
    assert (health.last_error, health.last_ok_s) == ("bang", 5.0)


def test_decode_never_takes_a_fault_code_for_a_temperature() -> None:
    device = DeviceMap(7, ("a", "b", None, "c", "d"))
    values = [0xFFCC, 0x7FFF, 0, 0x8000, 100, 0, 0, 0]
    statuses = [0, 0, 1, 0, 9, 1, 1, 1]
    results = decode_channels(device, values + statuses)
    assert set(results) == {"a", "b", "c", "d"}
    assert results["a"] == ChannelResult("a", -5.2, 0, None)
    assert results["b"].value_C is None and "fault code 32767" in str(results["b"].error)
    assert results["c"].value_C is None and "fault code -32768" in str(results["c"].error)
    assert results["d"] == ChannelResult("d", None, 9, "unknown status 9")


def test_bus_configuration_is_checked_without_io() -> None:
    with pytest.raises(ValueError, match="exactly one"):
        TransmitterBus([DEVICE_1])
    with pytest.raises(ValueError, match="unique"):
        TransmitterBus([DEVICE_1, DeviceMap(1, ("x",))], tcp=(HOST, 1))
    with pytest.raises(ValueError, match="sensor names"):
        TransmitterBus([DEVICE_1, DeviceMap(2, ("T1",))], tcp=(HOST, 1))
    with pytest.raises(ValueError):
        DeviceMap(1, ("a",) * 9)
    with pytest.raises(ValueError):
        DeviceMap(248, ("a",))


# -- real servers ---------------------------------------------------------------------------


def test_tcp_bus_reads_two_devices_exactly() -> None:
    async def body() -> None:
        link = FixedLink(SNAPSHOT)
        async with TransmitterServer(link, SERVED, tcp=(HOST, 0)) as server:
            bus = TransmitterBus([DEVICE_1, DEVICE_2], tcp=server.address, timeout_s=TIMEOUT_S)
            try:
                results = await bus.read_all(10.0)
                assert set(results) == set(EXPECTED)
                assert_expected(results, list(EXPECTED))
                assert results["T3"].error == "open circuit"
                assert bus.health.connected and bus.health.last_ok_s == 10.0
                assert bus.health.total_failures == 0
                assert all(h.connected for h in bus.device_health.values())
            finally:
                await bus.close()

    run(body)


def test_rtu_bus_over_a_pty_pair_reads_two_devices(tmp_path: Path) -> None:
    async def body() -> None:
        with socat_pty_pair(tmp_path) as pair:
            link = FixedLink(SNAPSHOT)
            async with TransmitterServer(link, SERVED, serial_port=pair.server_port):
                bus = TransmitterBus(
                    [DEVICE_1, DEVICE_2], serial_port=pair.client_port, timeout_s=TIMEOUT_S
                )
                try:
                    for now in (1.0, 2.0):
                        results = await bus.read_all(now)
                        assert_expected(results, list(EXPECTED))
                    assert bus.health.connected and bus.health.reconnects == 0
                finally:
                    await bus.close()

    run(body)


@pytest.mark.parametrize("transport", ["rtu", "tcp"])
def test_silent_slave_costs_one_timeout_and_spares_the_others(
    transport: str, tmp_path: Path
) -> None:
    """A dead slave between two live ones (pymodbus #1654: it must not close the port)."""

    async def cycle(bus: TransmitterBus, now: float) -> float:
        started = time.monotonic()
        results = await bus.read_all(now)
        elapsed = time.monotonic() - started
        assert_expected(results, list(EXPECTED))  # the live devices, in the same call
        assert_silent(results)
        return elapsed

    async def check(bus: TransmitterBus) -> None:
        try:
            elapsed = [await cycle(bus, float(now)) for now in (1, 2, 3)]
            # One timeout for the silent device (not two: no retry), a few ms for the live ones.
            assert all(TIMEOUT_S * 0.9 <= e < 2 * TIMEOUT_S for e in elapsed), elapsed
            assert bus.health.connected and bus.health.reconnects == 0
            assert bus.health.total_failures == 0
            assert bus.device_health[SILENT_ID].consecutive_failures == 3
            assert bus.device_health[1].connected and bus.device_health[2].connected
        finally:
            await bus.close()

    async def body() -> None:
        link = FixedLink(SNAPSHOT)
        devices = [DEVICE_1, SILENT, DEVICE_2]
        if transport == "tcp":
            async with TransmitterServer(link, SERVED, tcp=(HOST, 0)) as server:
                await check(TransmitterBus(devices, tcp=server.address, timeout_s=TIMEOUT_S))
            return
        with socat_pty_pair(tmp_path) as pair:
            async with TransmitterServer(link, SERVED, serial_port=pair.server_port):
                await check(
                    TransmitterBus(devices, serial_port=pair.client_port, timeout_s=TIMEOUT_S)
                )

    run(body)


def test_a_run_of_silent_slaves_does_not_drop_the_connection() -> None:
    """pymodbus closes a TCP connection after retries + 3 silent requests in a row; the
    bus must not let it, or live devices behind a gateway go dark with the dead ones."""

    async def body() -> None:
        timeout_s = 0.1
        silent = [DeviceMap(i, (f"S{i}",)) for i in range(3, 9)]
        link = FixedLink(SNAPSHOT)
        async with TransmitterServer(link, SERVED, tcp=(HOST, 0)) as server:
            bus = TransmitterBus(
                [DEVICE_1, *silent, DEVICE_2], tcp=server.address, timeout_s=timeout_s
            )
            try:
                for now in (1.0, 2.0):
                    results = await bus.read_all(now)
                    assert_expected(results, list(EXPECTED))
                    assert all("no response" in str(results[f"S{i}"].error) for i in range(3, 9))
                assert bus.health.connected and bus.health.reconnects == 0
            finally:
                await bus.close()

    run(body)


def test_nothing_listening_gives_errors_and_waits_for_the_backoff() -> None:
    async def body() -> None:
        port = free_tcp_port()
        bus = TransmitterBus(
            [DEVICE_1],
            tcp=(HOST, port),
            timeout_s=TIMEOUT_S,
            backoff=Backoff(initial_s=1.0, jitter=0.0),
        )
        first = await bus.read_all(0.0)  # must not raise
        assert set(first) == {"T1", "T2", "T3", "T4", "T5"}
        assert all(r.value_C is None and r.status is None for r in first.values())
        assert f"{HOST}:{port}" in str(first["T1"].error)
        assert "cannot connect" in str(first["T1"].error)
        second = await bus.read_all(0.5)  # inside the backoff: no attempt, same diagnosis
        assert "next connection attempt in 0.50 s" in str(second["T1"].error)
        assert bus.health.consecutive_failures == 2 and not bus.health.connected
        assert bus.device_health[1].last_error is not None
        await bus.close()

        absent = TransmitterBus([DEVICE_2], serial_port="/nonexistent/ttyUSB9")
        results = await absent.read_all(0.0)
        assert "serial /nonexistent/ttyUSB9: cannot connect" in str(results["ambient"].error)
        assert absent.health.total_failures == 1

    run(body)


def test_tcp_connection_drop_and_recovery_on_the_same_port() -> None:
    async def body() -> None:
        port = free_tcp_port()
        link = FixedLink(SNAPSHOT)
        bus = TransmitterBus(
            [DEVICE_1, DEVICE_2],
            tcp=(HOST, port),
            timeout_s=TIMEOUT_S,
            backoff=Backoff(initial_s=0.1, max_s=0.4),
        )
        try:
            server = TransmitterServer(link, SERVED, tcp=(HOST, port))
            await server.start()
            assert_expected(await bus.read_all(time.monotonic()), list(EXPECTED))
            await server.stop()

            results = await bus.read_all(time.monotonic())  # no exception
            assert all(r.value_C is None and r.error for r in results.values())
            assert not bus.health.connected and bus.health.consecutive_failures >= 1
            assert bus.health.last_error is not None
            # Still down: more failures, no exception, no busy loop (backoff).
            await asyncio.sleep(0.15)
            await bus.read_all(time.monotonic())
            assert bus.health.consecutive_failures >= 2

            server = TransmitterServer(link, SERVED, tcp=(HOST, port))
            await server.start()
            try:
                restarted = time.monotonic()
                while True:
                    results = await bus.read_all(time.monotonic())
                    if results["T1"].value_C is not None:
                        break
                    assert time.monotonic() - restarted < 2.0, results["T1"]
                    await asyncio.sleep(0.02)
                assert time.monotonic() - restarted <= 0.4 + 0.3  # within the backoff cap
                assert_expected(results, list(EXPECTED))
                assert bus.health.connected and bus.health.reconnects >= 1
                assert bus.health.consecutive_failures == 0
                assert bus.health.total_failures >= 2
            finally:
                await server.stop()
        finally:
            await bus.close()

    run(body)
