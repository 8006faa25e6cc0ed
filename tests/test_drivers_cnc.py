"""The gateway's CNC clients (OPC UA, Modbus TCP) against the simulator's servers.

Real servers from ``simulator.servers`` with a FixedLink behind them, so a macro write
is checked where it lands (``FixedLink.writes``) and read back through the client.
Server restarts happen for real on the same port; nothing in asyncua or pymodbus is
mocked.
"""

from __future__ import annotations

import asyncio
import math
import struct
import time
from collections.abc import Awaitable, Callable
from pathlib import Path
from typing import TypeVar

import pytest
from asyncua import Client, Server, ua

from drivers.cnc import CncClient, CncError, CncRefusedError, SpeedReading
from drivers.cnc_modbus import ModbusCnc
from drivers.cnc_opcua import OpcUaCnc
from drivers.link_health import Backoff
from drivers.register_codec import registers_to_float32_shortest
from simulator.link import FixedLink, MachineSnapshot, RunMode
from simulator.servers.modbus_cnc import CncModbusServer
from simulator.servers.opcua_cnc import CncOpcUaServer
from tests.ports import free_tcp_port

T = TypeVar("T")
HOST = "127.0.0.1"
NAMESPACE = "urn:spindle-gateway:simulated-cnc"
FAST_BACKOFF = {"initial_s": 0.1, "max_s": 0.4}
#: Request timeout of the CNC clients of tests not about a timeout: generous for a loaded
#: test machine (an OPC UA connect is several round trips under one bound of three timeouts).
TIMEOUT_S = 5.0


def snapshot(speed: float = 4000.0, commanded: float = 4500.0) -> MachineSnapshot:
    return MachineSnapshot(
        time_s=3600.0,
        channels={},
        actual_speed_rpm=speed,
        commanded_speed_rpm=commanded,
        run_mode=RunMode.AUTO,
        macros={500: 0.0125},
        probe_error_um=3.25,  # Modbus registers 5–6
    )


def run(body: Callable[[], Awaitable[T]], timeout_s: float = 25.0) -> T:
    """Run one async test body (pytest-asyncio is not used in this project)."""

    async def bounded() -> T:
        return await asyncio.wait_for(body(), timeout_s)

    return asyncio.run(bounded())


async def recover(cnc: CncClient, deadline_s: float) -> SpeedReading:
    """Call read_speed until it works again (the backoff decides when it reconnects)."""
    started = time.monotonic()
    while True:
        try:
            return await cnc.read_speed()
        except CncError:
            if time.monotonic() - started > deadline_s:
                raise
            await asyncio.sleep(0.02)


async def check_macro_round_trip(cnc: CncClient, link: FixedLink, value: float) -> None:
    await cnc.write_macro(500, value)
    assert link.writes[-1] == (500, value)  # the machine has it when the call returns
    assert await cnc.read_macro(500) == value  # and the controller shows it


def test_float32_read_back_is_the_value_written() -> None:
    """Modbus macros are float32: the read-back must equal the double that was written."""
    for value in (0.0125, -0.0375, 1e-3, 4000.0, 0.1):
        high, low = struct.unpack(">HH", struct.pack(">f", value))
        assert registers_to_float32_shortest(high, low) == value
    assert math.isnan(registers_to_float32_shortest(0x7FC0, 0))


# -- OPC UA -------------------------------------------------------------------------


def test_opcua_reads_speed_and_round_trips_a_macro() -> None:
    async def body() -> None:
        link = FixedLink(snapshot())
        async with CncOpcUaServer(link, port=free_tcp_port()) as server:
            cnc = OpcUaCnc(server.endpoint, timeout_s=TIMEOUT_S)
            assert cnc.namespace_index is None  # lazy: the constructor did no I/O
            try:
                assert await cnc.read_speed() == SpeedReading(4000.0, 4500.0, int(RunMode.AUTO))
                assert cnc.namespace_index == server.namespace_index
                assert await cnc.read_macro(500) == 0.0125
                await check_macro_round_trip(cnc, link, -0.0375)
                await check_macro_round_trip(cnc, link, 2.0)  # an integral value, still Double

                with pytest.raises(ValueError):
                    await cnc.write_macro(500, math.nan)  # never reaches the machine
                assert link.writes[-1] == (500, 2.0)
                with pytest.raises(CncRefusedError, match=r"Macro\.1000.*BadNodeIdUnknown"):
                    await cnc.read_macro(1000)  # not served: refused, session kept
                assert await cnc.read_macro(500) == 2.0
                assert cnc.health.connected and cnc.health.reconnects == 0
                assert cnc.health.total_failures == 0
            finally:
                await cnc.close()
            with pytest.raises(CncError, match="closed"):
                await cnc.read_speed()

            # Misconfigured clients fail with messages that say what is wrong.
            other = OpcUaCnc(server.endpoint, namespace="urn:nobody", timeout_s=TIMEOUT_S)
            with pytest.raises(CncError, match="urn:nobody") as info:
                await other.read_speed()
            assert server.endpoint in str(info.value)
            assert not other.health.connected and other.health.total_failures == 1
            await other.close()

            named = OpcUaCnc(server.endpoint, username="operator", password="x", timeout_s=0.5)
            with pytest.raises(CncError, match="cannot connect"):
                await named.read_speed()  # the simulator takes anonymous sessions only
            await named.close()

            no_run_mode = OpcUaCnc(server.endpoint, run_mode_node=None, timeout_s=TIMEOUT_S)
            assert (await no_run_mode.read_speed()).run_mode is None
            await no_run_mode.close()

    run(body)


async def shifted_namespace_server(port: int) -> Server:
    """A plain asyncua server where the CNC namespace has index 3, not the simulator's 2.

    A client that kept the old index would read ``ns=2`` ids, which do not exist here.
    """
    server = Server()
    await server.init()
    server.set_endpoint(f"opc.tcp://{HOST}:{port}/cnc")
    server.set_security_policy([ua.SecurityPolicyType.NoSecurity])
    await server.register_namespace("urn:another-vendor:extensions")
    ns = await server.register_namespace(NAMESPACE)
    assert ns == 3
    for nodeid, variant in [
        ("Spindle.ActualSpeed", ua.Variant(777.0, ua.VariantType.Double)),
        ("Spindle.CommandedSpeed", ua.Variant(800.0, ua.VariantType.Double)),
        ("Cnc.RunMode", ua.Variant(2, ua.VariantType.Int32)),
    ]:
        await server.nodes.objects.add_variable(
            ua.NodeId(nodeid, ns), ua.QualifiedName(nodeid, ns), variant
        )
    await server.start()
    return server


def test_opcua_recovers_after_server_restarts_with_a_new_session() -> None:
    async def body() -> None:
        port = free_tcp_port()
        first_link = FixedLink(snapshot())
        server = CncOpcUaServer(first_link, port=port)
        await server.start()
        cnc = OpcUaCnc(server.endpoint, timeout_s=0.5, backoff=Backoff(**FAST_BACKOFF))
        try:
            assert (await cnc.read_speed()).actual_rpm == 4000.0
            await server.stop()

            with pytest.raises(CncError) as info:
                await cnc.read_speed()
            assert server.endpoint in str(info.value)
            assert not cnc.health.connected and cnc.health.consecutive_failures == 1
            assert cnc.namespace_index is None  # the old Client is gone
            started = time.monotonic()
            with pytest.raises(CncError, match="next attempt"):
                await cnc.write_macro(500, 0.5)  # inside the backoff: fails without I/O
            assert time.monotonic() - started < 0.25  # no connect attempt (its timeout is 0.5 s)
            assert first_link.writes == []

            # A new server process on the same port: new session, namespace resolved again.
            second_link = FixedLink(snapshot(speed=1234.0, commanded=1250.0))
            server = CncOpcUaServer(second_link, port=port)
            await server.start()
            reading = await recover(cnc, deadline_s=2.0)
            assert reading == SpeedReading(1234.0, 1250.0, int(RunMode.AUTO))
            assert cnc.health.connected and cnc.health.reconnects == 1
            await check_macro_round_trip(cnc, second_link, 0.0075)
            await server.stop()

            # Restarted with another namespace layout: the index must be looked up again.
            shifted = await shifted_namespace_server(port)
            try:
                reading = await recover(cnc, deadline_s=3.0)
                assert reading == SpeedReading(777.0, 800.0, 2)
                assert cnc.namespace_index == 3
                assert cnc.health.reconnects == 2
            finally:
                await shifted.stop()
        finally:
            await cnc.close()
            await server.stop()

    run(body, timeout_s=90.0)  # three OPC UA server start-ups; the recoveries have their own


def test_opcua_wrong_endpoint_names_it_and_backs_off() -> None:
    async def body() -> None:
        now = [100.0]
        endpoint = f"opc.tcp://{HOST}:{free_tcp_port()}/cnc"
        cnc = OpcUaCnc(endpoint, timeout_s=0.3, clock=lambda: now[0], backoff=Backoff(jitter=0.0))
        with pytest.raises(CncError, match="cannot connect") as info:
            await cnc.read_speed()
        assert endpoint in str(info.value)
        with pytest.raises(CncError, match=r"next attempt in 0\.50 s"):
            await cnc.read_macro(500)
        now[0] += 0.5  # the backoff has passed: a real attempt again, then 1 s
        with pytest.raises(CncError, match="cannot connect"):
            await cnc.read_speed()
        with pytest.raises(CncError, match=r"next attempt in 1\.00 s"):
            await cnc.read_speed()
        assert cnc.health.total_failures == 4 and cnc.health.reconnects == 0
        assert endpoint in str(cnc.health.last_error)
        await cnc.close()

    run(body)


# -- Modbus TCP ----------------------------------------------------------------------


def test_modbus_reads_speed_and_round_trips_a_macro() -> None:
    async def body() -> None:
        link = FixedLink(snapshot())
        async with CncModbusServer(link, host=HOST, port=0) as server:
            host, port = server.address
            cnc = ModbusCnc(host, port, timeout_s=1.0)
            try:
                assert await cnc.read_speed() == SpeedReading(4000.0, 4500.0, int(RunMode.AUTO))
                assert await cnc.read_macro(500) == 0.0125
                assert math.isnan(await cnc.read_macro(501))  # vacant variable
                await check_macro_round_trip(cnc, link, -0.0375)
                await check_macro_round_trip(cnc, link, 0.0125)

                with pytest.raises(ValueError):
                    await cnc.write_macro(500, math.inf)
                with pytest.raises(ValueError):
                    await cnc.write_macro(499, 1.0)  # below the mapped macro range
                assert link.writes[-1] == (500, 0.0125)
                with pytest.raises(CncRefusedError, match="exception 2"):
                    await cnc.read_macro(1000)  # register 2000: not mapped
                assert await cnc.read_macro(500) == 0.0125  # same connection still good
                assert cnc.health.connected and cnc.health.reconnects == 0
                assert cnc.health.total_failures == 0
            finally:
                await cnc.close()

            # Registers need not be adjacent or in order.
            swapped = ModbusCnc(
                host, port, speed_register=2, commanded_register=0, run_mode_register=None
            )
            assert await swapped.read_speed() == SpeedReading(4500.0, 4000.0, None)
            await swapped.close()
            # A map with gaps is read item by item (registers 2–3 are skipped; the
            # probe error at 5–6 stands in for the commanded speed).
            gaps = ModbusCnc(host, port, speed_register=0, commanded_register=5)
            assert await gaps.read_speed() == SpeedReading(4000.0, 3.25, int(RunMode.AUTO))
            await gaps.close()

            # A device id the server does not serve: silence, one timeout, a link failure.
            silent = ModbusCnc(host, port, device_id=9, timeout_s=0.2)
            started = time.monotonic()
            with pytest.raises(CncError, match="no response from device 9"):
                await silent.read_speed()
            assert time.monotonic() - started < 0.2 + 0.3
            assert not silent.health.connected
            await silent.close()

    run(body)


def test_modbus_recovers_after_server_drop() -> None:
    async def body() -> None:
        port = free_tcp_port()
        first_link = FixedLink(snapshot())
        server = CncModbusServer(first_link, host=HOST, port=port)
        await server.start()
        cnc = ModbusCnc(HOST, port, timeout_s=0.3, backoff=Backoff(**FAST_BACKOFF))
        try:
            assert (await cnc.read_speed()).actual_rpm == 4000.0
            await server.stop()

            with pytest.raises(CncError) as info:
                await cnc.write_macro(500, 0.5)
            assert f"{HOST}:{port}" in str(info.value)
            assert not cnc.health.connected and cnc.health.last_error is not None
            assert first_link.writes == []

            second_link = FixedLink(snapshot(speed=1234.0, commanded=1250.0))
            server = CncModbusServer(second_link, host=HOST, port=port)
            await server.start()
            reading = await recover(cnc, deadline_s=2.0)
            assert reading == SpeedReading(1234.0, 1250.0, int(RunMode.AUTO))
            assert cnc.health.connected and cnc.health.reconnects >= 1
            await check_macro_round_trip(cnc, second_link, 0.0075)
        finally:
            await cnc.close()
            await server.stop()

    run(body)


def test_modbus_wrong_endpoint_names_it() -> None:
    async def body() -> None:
        port = free_tcp_port()
        cnc = ModbusCnc(HOST, port, timeout_s=0.3)
        with pytest.raises(CncError, match="cannot connect") as info:
            await cnc.read_speed()
        assert f"Modbus TCP {HOST}:{port}" in str(info.value)
        assert cnc.health.total_failures == 1 and not cnc.health.connected
        await cnc.close()

    run(body)


async def typed_macro_server(port: int) -> Server:
    """Another vendor's CNC: #500 held as a Float, #501 as an Int32, #502 as a Double, each
    writable by anyone (asyncua refuses a write whose type differs: BadTypeMismatch)."""
    server = Server()
    await server.init()
    server.set_endpoint(f"opc.tcp://{HOST}:{port}/cnc")
    server.set_security_policy([ua.SecurityPolicyType.NoSecurity])
    ns = await server.register_namespace(NAMESPACE)
    for nodeid, variant in [
        ("Macro.500", ua.Variant(0.0, ua.VariantType.Float)),
        ("Macro.501", ua.Variant(0, ua.VariantType.Int32)),
        ("Macro.502", ua.Variant(0.0, ua.VariantType.Double)),
    ]:
        node = await server.nodes.objects.add_variable(
            ua.NodeId(nodeid, ns), ua.QualifiedName(nodeid, ns), variant
        )
        await node.set_writable()
    await server.start()
    return server


def test_opcua_writes_a_macro_as_the_type_the_cnc_holds_it_in() -> None:
    async def body() -> None:
        port = free_tcp_port()
        server = await typed_macro_server(port)
        try:
            # A first write with no read before it: the type is read first.
            cnc = OpcUaCnc(f"opc.tcp://{HOST}:{port}/cnc", timeout_s=TIMEOUT_S)
            await cnc.write_macro(500, 0.0125)
            assert await cnc.read_macro(500) == pytest.approx(0.0125, abs=1e-9)  # float32
            await cnc.write_macro(502, -0.0375)
            assert await cnc.read_macro(502) == -0.0375
            with pytest.raises(CncRefusedError, match=r"Macro\.501 holds a Int32; the comp"):
                await cnc.write_macro(501, 0.01)
            assert await cnc.read_macro(501) == 0.0  # untouched
            # An independent client sees what landed, as the type the server holds.
            async with Client(f"opc.tcp://{HOST}:{port}/cnc", timeout=5) as client:
                ns = await client.get_namespace_index(NAMESPACE)
                held = await client.get_node(ua.NodeId("Macro.500", ns)).read_data_value()
                assert held.Value.VariantType == ua.VariantType.Float
                assert held.Value.Value == pytest.approx(0.0125, abs=1e-9)
            await cnc.close()
        finally:
            await server.stop()

    asyncio.run(body())


def test_opcua_over_a_signed_and_encrypted_channel_with_its_own_certificate(
    tmp_path: Path,
) -> None:
    """A control that takes Basic256Sha256 SignAndEncrypt only: a plain client is refused,
    the secured one makes its certificate on first use, reads and writes; pinned to the
    CNC's certificate it works, pinned to another it does not."""
    from drivers.cnc_opcua import OpcUaSecurity

    async def body() -> None:
        link = FixedLink(snapshot())
        served = (tmp_path / "cnc" / "cert.der", tmp_path / "cnc" / "key.pem")
        async with CncOpcUaServer(link, port=free_tcp_port(), secure=served) as server:
            plain = OpcUaCnc(server.endpoint, timeout_s=TIMEOUT_S)
            with pytest.raises(CncError, match=r"No matching endpoints: 1, .*SecurityPolicy#None"):
                await plain.read_speed()
            await plain.close()

            mine = OpcUaSecurity(tmp_path / "pki" / "cert.der", tmp_path / "pki" / "key.pem")
            secured = OpcUaCnc(server.endpoint, timeout_s=TIMEOUT_S, security=mine)
            assert await secured.read_speed() == SpeedReading(4000.0, 4500.0, int(RunMode.AUTO))
            assert mine.certificate.exists() and mine.private_key.stat().st_mode & 0o077 == 0
            await check_macro_round_trip(secured, link, -0.0375)
            await secured.close()

            pinned = OpcUaSecurity(mine.certificate, mine.private_key, server_certificate=served[0])
            right = OpcUaCnc(server.endpoint, timeout_s=TIMEOUT_S, security=pinned)
            assert (await right.read_speed()).actual_rpm == 4000.0
            await right.close()

            stranger = (tmp_path / "other" / "cert.der", tmp_path / "other" / "key.pem")
            async with CncOpcUaServer(FixedLink(snapshot()), port=free_tcp_port(), secure=stranger):
                pass  # only to make another server's certificate
            key, cert = mine.private_key, mine.certificate
            wrong = OpcUaSecurity(cert, key, server_certificate=stranger[0])
            impostor = OpcUaCnc(server.endpoint, timeout_s=1.0, security=wrong)
            with pytest.raises(CncError, match="cannot connect"):  # the CNC cannot decrypt it
                await impostor.read_speed()
            await impostor.close()

    run(body)


def test_the_configured_security_reaches_the_cnc_client(tmp_path: Path) -> None:
    from gateway.config import MachineSection
    from gateway.wiring import build_cnc

    async def body() -> None:
        link = FixedLink(snapshot())
        served = (tmp_path / "cnc" / "cert.der", tmp_path / "cnc" / "key.pem")
        async with CncOpcUaServer(link, port=free_tcp_port(), secure=served) as server:
            machine = MachineSection.model_validate(
                {
                    "id": "m1",
                    "transmitters": [
                        {
                            "name": "bus1",
                            "tcp": {"host": HOST, "port": free_tcp_port()},
                            "devices": [{"device_id": 1, "channels": ["T1"]}],
                        }
                    ],
                    "cnc": {
                        "opcua": {
                            "endpoint": server.endpoint,
                            "security": {
                                "certificate": str(tmp_path / "pki" / "gateway_cert.der"),
                                "private_key": str(tmp_path / "pki" / "gateway_key.pem"),
                                "server_certificate": str(served[0]),
                            },
                        }
                    },
                    "models": {"store": str(tmp_path / "models")},
                }
            )
            cnc = build_cnc(machine)
            assert (await cnc.read_speed()).actual_rpm == 4000.0
            await check_macro_round_trip(cnc, link, 0.0125)
            await cnc.close()

    run(body)
