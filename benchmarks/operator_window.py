"""The window left to an operator's write: from the CNC answering the gateway's last
read of #500 to the gateway's write of #500 landing (OPC UA and Modbus TCP, loopback).

An operator's write that lands inside this window is overwritten without the gateway
having seen it; one that lands before it is seen by the compare-before-write
(``CncClient.write_macro_if``) and not overwritten. Both ends are timed at the
simulated CNC (``time.perf_counter``): the read when the server takes the value for
its reply (asyncua's PostRead callback, pymodbus's request action), the write when
it reaches the machine. Writes alternate between two values, so every one lands.

``--busy N`` runs N more clients polling the spindle speed on the same server and
event loop meanwhile, as other machines' loops of one gateway would.

Prints one JSON document (ms: median, p99, max over ``--writes`` writes per protocol).

    .venv/bin/python benchmarks/operator_window.py [--writes 1000] [--busy 0]
"""

from __future__ import annotations

import argparse
import asyncio
import json
import socket
import statistics
import time
from typing import Any

from asyncua import ua
from asyncua.common.callback import CallbackType, ServerItemCallback

from drivers.cnc_modbus import ModbusCnc
from drivers.cnc_opcua import OpcUaCnc
from simulator.link import FixedLink, MachineSnapshot, RunMode
from simulator.servers.modbus_cnc import CncModbusServer, macro_register
from simulator.servers.opcua_cnc import CncOpcUaServer

HOST = "127.0.0.1"
MACRO = 500


class TimedLink(FixedLink):
    """The machine: the time each write of #500 reaches it."""

    def __init__(self) -> None:
        snapshot = MachineSnapshot(0.0, {}, 4000.0, 4000.0, RunMode.AUTO, macros={MACRO: 0.0})
        super().__init__(snapshot)
        self.written_at: list[float] = []
        self.read_at: list[float] = []

    def write_macro(self, number: int, value: float) -> None:
        super().write_macro(number, value)
        if number == MACRO:
            self.written_at.append(time.perf_counter())


class TimedModbus(CncModbusServer):
    """pymodbus calls the action right before it takes the registers of a read."""

    async def _action(self, function_code: int, start: int, address: int, count: int, *rest):
        if function_code == 3 and address == macro_register(MACRO) and count == 2:
            assert isinstance(self._link, TimedLink)
            self._link.read_at.append(time.perf_counter())
        return await super()._action(function_code, start, address, count, *rest)


async def serve(kind: str, link: TimedLink) -> tuple[Any, Any]:
    """The simulated CNC and a gateway driver connected to it."""
    if kind == "modbus":
        server: Any = TimedModbus(link, host=HOST, port=free_port())
        await server.start()
        return server, ModbusCnc(HOST, server.address[1], timeout_s=2.0)
    server = CncOpcUaServer(link, host=HOST, port=free_port())
    await server.start()
    nodeid = ua.NodeId(f"Macro.{MACRO}", server.namespace_index)

    async def post_read(event: ServerItemCallback, _dispatcher: object) -> None:
        if event.is_external and any(r.NodeId == nodeid for r in event.request_params.NodesToRead):
            link.read_at.append(time.perf_counter())

    server._server.subscribe_server_callback(CallbackType.PostRead, post_read)
    return server, OpcUaCnc(server.endpoint, timeout_s=2.0)


def free_port() -> int:
    with socket.socket() as probe:
        probe.bind((HOST, 0))
        return int(probe.getsockname()[1])


async def poll(cnc: Any, stop: asyncio.Event) -> None:
    while not stop.is_set():
        await cnc.read_speed()


async def measure(kind: str, writes: int, busy: int) -> dict[str, float]:
    link = TimedLink()
    server, cnc = await serve(kind, link)
    others = [(await serve_client(kind, server)) for _ in range(busy)]
    stop = asyncio.Event()
    pollers = [asyncio.create_task(poll(other, stop)) for other in others]
    try:
        await cnc.read_macro(MACRO)  # connect
        windows_ms = []
        for i in range(writes):
            link.read_at.clear()
            link.written_at.clear()
            result = await cnc.write_macro_if(MACRO, 0.01 * (i % 2 + 1), lambda _held: True)
            assert result.written and link.read_at and link.written_at
            windows_ms.append((link.written_at[-1] - link.read_at[-1]) * 1000.0)
    finally:
        stop.set()
        await asyncio.gather(*pollers, return_exceptions=True)
        for client in [cnc, *others]:
            await client.close()
        await server.stop()
    windows_ms.sort()
    return {
        "median_ms": round(statistics.median(windows_ms), 3),
        "p99_ms": round(windows_ms[int(0.99 * (len(windows_ms) - 1))], 3),
        "max_ms": round(windows_ms[-1], 3),
        "writes": len(windows_ms),
    }


async def serve_client(kind: str, server: Any) -> Any:
    if kind == "modbus":
        return ModbusCnc(HOST, server.address[1], timeout_s=2.0)
    return OpcUaCnc(server.endpoint, timeout_s=2.0)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--writes", type=int, default=1000)
    parser.add_argument("--busy", type=int, default=0)
    args = parser.parse_args()
    report = {
        kind: asyncio.run(measure(kind, args.writes, args.busy)) for kind in ("opcua", "modbus")
    }
    print(json.dumps({"busy_clients": args.busy, **report}, indent=2))


if __name__ == "__main__":
    main()
