"""``CncClient.read_macros`` and ``write_macros_if``: several macros in one request,
each refusal its own.

Against real servers: the simulator's OPC UA and Modbus TCP CNCs and a plain asyncua
server holding macros in several types, with a counting proxy (:mod:`tests.counting_proxy`)
between client and server to count the requests on the wire.
"""

from __future__ import annotations

import dataclasses
import math
from collections import Counter
from collections.abc import AsyncIterator, Sequence
from contextlib import asynccontextmanager

import pytest
from asyncua import Server, ua

from drivers.cnc import CncClient, CncError, CncRefusedError, GuardedWrite, MacroWrite
from drivers.cnc_modbus import MACRO_SPAN_REGISTERS, ModbusCnc
from drivers.cnc_opcua import OpcUaCnc
from simulator.link import FixedLink
from simulator.servers.modbus_cnc import CncModbusServer
from simulator.servers.opcua_cnc import CncOpcUaServer
from tests.counting_proxy import CountingProxy
from tests.ports import free_tcp_port
from tests.test_drivers_cnc import HOST, NAMESPACE, TIMEOUT_S, run, snapshot, typed_macro_server

MACROS = {500: 0.0125, 502: -0.0375, 503: 2.0, 510: 1.5, 530: -4.25, 600: 7.0, 999: 3.0}


@asynccontextmanager
async def counted(port: int, protocol: str) -> AsyncIterator[CountingProxy]:
    proxy = CountingProxy((HOST, port), protocol)
    await proxy.start()
    try:
        yield proxy
    finally:
        await proxy.stop()


async def one_by_one(cnc: CncClient, numbers: Sequence[int]) -> dict[int, float | str]:
    """Each macro's own read_macro: its value, or the refusal's text."""
    results: dict[int, float | str] = {}
    for number in numbers:
        try:
            results[number] = await cnc.read_macro(number)
        except CncRefusedError as exc:
            results[number] = str(exc)
    return results


def same(many: float | CncError, one: float | str) -> bool:
    if isinstance(many, CncError):
        return isinstance(one, str)
    return (math.isnan(many) and math.isnan(one)) if isinstance(one, float) else False


def test_opcua_reads_several_macros_in_one_read_and_a_refused_node_fails_alone() -> None:
    async def body() -> None:
        link = FixedLink(dataclasses.replace(snapshot(), macros=MACROS))
        port = free_tcp_port()
        async with (
            CncOpcUaServer(link, port=port, macro_range=(500, 600)),
            counted(port, "opcua") as proxy,
        ):
            cnc = OpcUaCnc(f"opc.tcp://{HOST}:{proxy.port}/cnc", timeout_s=TIMEOUT_S)
            try:
                await cnc.read_speed()  # connect first: only the multi-read counted
                reads = proxy.counts["read"]
                numbers = [500, 501, 502, 503, 530, 600, 999]  # #999 is not served
                many = await cnc.read_macros(numbers)
                assert proxy.counts["read"] == reads + 1  # one Read for seven macros
                assert list(many) == numbers
                single = await one_by_one(cnc, numbers)
                assert proxy.counts["read"] == reads + 1 + len(numbers)
                for number in numbers:
                    assert many[number] == single[number] or same(many[number], single[number])
                assert many[502] == -0.0375 and many[600] == 7.0
                refused = many[999]
                assert isinstance(refused, CncRefusedError)
                assert "#999" in str(refused) and "BadNodeIdUnknown" in str(refused)
                assert cnc.health.connected and cnc.health.total_failures == 0
                assert cnc.health.reconnects == 0  # a refused node keeps the session
            finally:
                await cnc.close()

    run(body)


def test_opcua_multi_read_learns_each_macros_type_for_its_write() -> None:
    async def body() -> None:
        port = free_tcp_port()
        server = await typed_macro_server(port)
        try:
            cnc = OpcUaCnc(f"opc.tcp://{HOST}:{port}/cnc", timeout_s=TIMEOUT_S)
            try:
                many = await cnc.read_macros([500, 501, 502])
                assert many == await one_by_one(cnc, [500, 501, 502])
                await cnc.close()
                cnc = OpcUaCnc(f"opc.tcp://{HOST}:{port}/cnc", timeout_s=TIMEOUT_S)
                await cnc.read_macros([500, 501, 502])
                # #500 is a Float at this CNC: the multi-read's type is what it is written as
                guarded = await cnc.write_macro_if(500, 0.25, lambda held: held == 0.0)
                assert guarded.written
                assert await cnc.read_macro(500) == 0.25
                with pytest.raises(CncRefusedError, match="Int32"):
                    await cnc.write_macro(501, 1.0)  # an integer macro is never rounded into
            finally:
                await cnc.close()
        finally:
            await server.stop()

    run(body)


def test_modbus_reads_close_macros_in_one_request_and_far_ones_in_their_own() -> None:
    async def body() -> None:
        link = FixedLink(dataclasses.replace(snapshot(), macros=MACROS))
        async with CncModbusServer(link, host=HOST, port=0) as server:
            await server.publish()
            host, port = server.address
            async with counted(port, "modbus") as proxy:
                cnc = ModbusCnc(host, proxy.port, timeout_s=TIMEOUT_S)
                try:
                    # #500–#510 lie within MACRO_SPAN_REGISTERS: one read; #530 and #600 not
                    assert 2 * (510 - 500) + 2 <= MACRO_SPAN_REGISTERS < 2 * (530 - 500) + 2
                    numbers = [510, 500, 502, 501, 530, 600]
                    many = await cnc.read_macros(numbers)
                    assert proxy.counts["read"] == 3
                    single = await one_by_one(cnc, numbers)
                    for number in numbers:
                        assert many[number] == single[number] or same(many[number], single[number])
                    assert (many[500], many[502], many[510], many[600]) == (
                        0.0125,
                        -0.0375,
                        1.5,
                        7.0,
                    )
                    assert math.isnan(many[501])  # vacant

                    # #1000 (register 2000) is not mapped at this CNC: the span #998–#1000
                    # is refused, read again macro by macro, and only #1000 fails.
                    reads = proxy.counts["read"]
                    many = await cnc.read_macros([998, 999, 1000])
                    assert proxy.counts["read"] == reads + 1 + 3
                    assert math.isnan(many[998]) and many[999] == 3.0
                    refused = many[1000]
                    assert isinstance(refused, CncRefusedError)
                    assert "#1000" in str(refused) and "register 2000" in str(refused)
                    assert cnc.health.connected and cnc.health.reconnects == 0
                    assert cnc.health.total_failures == 0
                finally:
                    await cnc.close()

    run(body)


# -- several guarded writes at once --------------------------------------------------


async def guarded_server(port: int) -> Server:
    """A plain asyncua CNC: #500 and #502 writable Doubles, #501 a read-only Double (its
    write is refused with its own status code in the Write's results)."""
    server = Server()
    await server.init()
    server.set_endpoint(f"opc.tcp://{HOST}:{port}/cnc")
    server.set_security_policy([ua.SecurityPolicyType.NoSecurity])
    ns = await server.register_namespace(NAMESPACE)
    for number, writable in ((500, True), (501, False), (502, True)):
        nodeid = f"Macro.{number}"
        node = await server.nodes.objects.add_variable(
            ua.NodeId(nodeid, ns),
            ua.QualifiedName(nodeid, ns),
            ua.Variant(0.5, ua.VariantType.Double),
        )
        if writable:
            await node.set_writable()
    await server.start()
    return server


def test_opcua_guarded_writes_go_as_one_read_and_one_write_each_macro_its_own_outcome() -> None:
    async def body() -> None:
        port = free_tcp_port()
        server = await guarded_server(port)
        try:
            async with counted(port, "opcua") as proxy:
                cnc = OpcUaCnc(f"opc.tcp://{HOST}:{proxy.port}/cnc", timeout_s=TIMEOUT_S)
                try:
                    await cnc.read_macro(500)  # connect first: only the guarded writes counted
                    before = Counter(proxy.counts)
                    outcome = await cnc.write_macros_if(
                        [
                            MacroWrite(500, 1.5, lambda held: held == 0.5),
                            MacroWrite(501, 2.0, lambda held: held == 0.5),
                            MacroWrite(502, 3.0, lambda held: held == 9.0),  # not what it holds
                        ]
                    )
                    assert dict(proxy.counts - before) == {"read": 1, "write": 1}
                    assert outcome[500] == GuardedWrite(0.5, written=True)
                    refused = outcome[501]
                    assert isinstance(refused, CncRefusedError) and "#501" in str(refused)
                    assert outcome[502] == GuardedWrite(0.5, written=False)
                    assert await cnc.read_macros([500, 501, 502]) == {500: 1.5, 501: 0.5, 502: 0.5}
                    assert cnc.health.reconnects == 0 and cnc.health.total_failures == 0
                    with pytest.raises(ValueError):  # nothing sent when one value is not finite
                        await cnc.write_macros_if(
                            [MacroWrite(500, 1.0, bool), MacroWrite(502, math.nan, bool)]
                        )
                    assert await cnc.read_macro(500) == 1.5
                finally:
                    await cnc.close()
        finally:
            await server.stop()

    run(body)


class ProtectedLink(FixedLink):
    """The simulator's machine with one write-protected macro: its OPC UA server answers a
    Write holding that node with a fault of the whole request."""

    def __init__(self, protected: int) -> None:
        super().__init__(dataclasses.replace(snapshot(), macros={500: 0.0, 502: 0.0, 503: 0.0}))
        self.protected = protected

    def write_macro(self, number: int, value: float) -> None:
        if number == self.protected:
            raise ValueError(f"macro #{number} is write-protected")
        super().write_macro(number, value)


@pytest.mark.parametrize("cnc_kind", ["opcua", "modbus"])
def test_a_refused_macro_fails_alone_among_guarded_writes(cnc_kind: str) -> None:
    async def body() -> None:
        link = ProtectedLink(502)
        port = free_tcp_port()
        server = (
            CncOpcUaServer(link, port=port)
            if cnc_kind == "opcua"
            else CncModbusServer(link, host=HOST, port=port)
        )
        async with server:
            await server.publish()
            cnc: CncClient = (
                OpcUaCnc(f"opc.tcp://{HOST}:{port}/cnc", timeout_s=TIMEOUT_S)
                if cnc_kind == "opcua"
                else ModbusCnc(HOST, port, timeout_s=TIMEOUT_S)
            )
            try:
                outcome = await cnc.write_macros_if(
                    [
                        MacroWrite(n, v, lambda held: held == 0.0)
                        for n, v in ((500, 0.25), (502, 0.5), (503, 0.75))
                    ]
                )
                assert outcome[500] == GuardedWrite(0.0, written=True)
                assert isinstance(outcome[502], CncRefusedError)
                assert outcome[503] == GuardedWrite(0.0, written=True)
                assert sorted(link.writes) == [(500, 0.25), (503, 0.75)]  # each once
                assert await cnc.read_macros([500, 502, 503]) == {500: 0.25, 502: 0.0, 503: 0.75}
                assert cnc.health.reconnects == 0
            finally:
                await cnc.close()

    run(body)
