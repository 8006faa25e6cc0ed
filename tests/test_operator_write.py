"""The operator's write to #500 is never overwritten unseen (OPC UA and Modbus TCP CNC).

The gateway's loop runs against the simulated CNC as in ``tests/test_write_path.py``.
The CNC side records, in the order it handles them, every read of #500 the gateway
makes and every write to #500. Two operators:

- the CNC's own programme, which sets ``#500 := 0`` right after the CNC answered the
  gateway's first read of #500 in a cycle (a server-side hook: deterministic), i.e.
  between the read the cycle decides on and the gateway's write;
- a second client (asyncua or pymodbus) writing ``#500 := 0`` at random moments
  while the loop cycles back to back.

A write of 0 the gateway saw (a read of #500 came after it, before the gateway's next
write) must be counted as an external change and the gateway must move on from 0 at
the slew limit (its next write ≤ 10 µm), never from its old value.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import random
from collections.abc import AsyncIterator
from pathlib import Path
from typing import Any

import pytest
from asyncua import Client, ua
from asyncua.common.callback import CallbackType, ServerItemCallback
from pymodbus.client import AsyncModbusTcpClient

from drivers.clock import ManualClock
from drivers.register_codec import float32_to_registers
from simulator.servers.modbus_cnc import CncModbusServer, macro_register
from simulator.servers.opcua_cnc import CncOpcUaServer
from tests.test_write_path import (
    CNCS,
    HOST,
    MACRO,
    Bench,
    ReceivingCnc,
    model_store,
    ramp_up,
    run,
)

HANDSHAKE = 501
STEP_UM = 10.0  # one cycle at the slew limit (20 µm/min, 30 s)
#: The largest step the policy takes from a value it holds: one cycle's slew plus the
#: deadband (0.5 µm) and one CNC step (0.1 µm) it may have banked (gateway/live/writeback.py).
MOVE_ON_UM = STEP_UM + 0.5 + 0.1


@pytest.fixture(scope="module")
def store(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """One MLR model on all seven sensors (error ≈ 4·ΔT1 − 2·ΔT6)."""
    return model_store(tmp_path_factory.mktemp("operator-write"))


async def mid_ramp(bench: Bench) -> None:
    """Cycles until the gateway is ramping up (15–30 µm held): the next cycle writes."""
    for _ in range(20):
        await bench.cycle()
        if 15.0 <= bench.cnc.held_um <= 30.0:
            return
    raise AssertionError(f"no ramp: the CNC holds {bench.cnc.held_um} µm")


class WatchedCnc(ReceivingCnc):
    """The machine behind the server; ``events`` holds ("read"|"write", value µm) in order."""

    def __init__(self, clock: ManualClock) -> None:
        super().__init__(clock)
        self.events: list[tuple[str, float]] = []

    def write_macro(self, number: int, value: float) -> None:
        super().write_macro(number, value)
        if number == MACRO:
            self.events.append(("write", float(value) * 1000.0))


class HookedModbus(CncModbusServer):
    """Calls ``on_read`` when a client reads #500 (pymodbus's action runs right before
    it takes the registers for the reply)."""

    on_read: Any = None

    async def _action(self, function_code: int, start: int, address: int, count: int, *rest):
        if function_code == 3 and address == macro_register(MACRO) and count == 2:
            self.on_read()
        return await super()._action(function_code, start, address, count, *rest)


class WatchedBench(Bench):
    """A bench whose CNC reports the gateway's reads of #500 and can run the programme."""

    def __init__(self, cnc_kind: str, clock: ManualClock) -> None:
        super().__init__(cnc_kind, clock)
        self.cnc = WatchedCnc(clock)
        self.clear_on_reads = 0  # the programme clears #500 after this many more reads

    def _new_server(self) -> CncOpcUaServer | CncModbusServer:
        if self.cnc_kind == "opcua":
            return CncOpcUaServer(self.cnc, port=self.cnc_port)
        server = HookedModbus(self.cnc, port=self.cnc_port)
        server.on_read = self._read_seen
        return server

    async def start(self, store: Path, compensation: dict[str, Any], slow: bool) -> None:
        await super().start(store, compensation, slow)
        if isinstance(self.server, CncOpcUaServer):
            inner = self.server._server
            assert inner is not None
            inner.subscribe_server_callback(CallbackType.PostRead, self._post_read)

    async def _post_read(self, event: ServerItemCallback, _dispatcher: object) -> None:
        """asyncua calls this after it took the values of a Read, before it replies."""
        assert isinstance(self.server, CncOpcUaServer)
        nodeid = ua.NodeId(f"Macro.{MACRO}", self.server.namespace_index)
        if event.is_external and any(r.NodeId == nodeid for r in event.request_params.NodesToRead):
            self._read_seen()

    def _read_seen(self) -> None:
        self.cnc.events.append(("read", self.cnc.held_um))
        if self.clear_on_reads:
            self.clear_on_reads -= 1
            if not self.clear_on_reads:  # the reply keeps the value read: clear after it
                asyncio.get_running_loop().create_task(self._programme_clears())

    async def _programme_clears(self) -> None:
        self.cnc.write_macro(MACRO, 0.0)
        assert self.server is not None
        await self.server.publish()

    async def client_writes(self, number: int, value_mm: float, client: Any = None) -> None:
        """A second client writes macro #number (a fresh connection unless one is given)."""
        if self.cnc_kind == "opcua":
            assert isinstance(self.server, CncOpcUaServer)
            async with contextlib.AsyncExitStack() as stack:
                if client is None:
                    client = await stack.enter_async_context(
                        Client(self.server.endpoint, timeout=5)
                    )
                node = client.get_node(ua.NodeId(f"Macro.{number}", self.server.namespace_index))
                await node.write_value(ua.Variant(value_mm, ua.VariantType.Double))
            return
        own = client is None
        if own:
            client = AsyncModbusTcpClient(HOST, port=self.cnc_port, timeout=2)
            assert await client.connect()
        try:
            words = list(float32_to_registers(value_mm))
            reply = await client.write_registers(macro_register(number), words, device_id=1)
            assert not reply.isError(), reply
        finally:
            if own:
                client.close()


@contextlib.asynccontextmanager
async def watched(
    cnc_kind: str, store: Path, compensation: dict[str, Any] | None = None
) -> AsyncIterator[WatchedBench]:
    bench = WatchedBench(cnc_kind, ManualClock())
    try:
        await bench.start(store, compensation or {}, False)
        yield bench
    finally:
        await bench.stop()


@pytest.mark.parametrize("cnc_kind", CNCS)
def test_a_write_between_the_cycles_read_and_the_gateways_write_is_not_overwritten(
    cnc_kind: str, store: Path
) -> None:
    """The programme clears #500 right after the CNC answered the cycle's read of it."""

    async def body() -> None:
        async with watched(cnc_kind, store) as b:
            await mid_ramp(b)
            assert b.loop is not None
            believed = b.cnc.held_um
            b.clear_on_reads = 1  # the cycle's first read of #500
            record = await b.cycle()
            assert b.clear_on_reads == 0
            assert b.cnc.held_um == 0.0, (b.cnc.held_um, record.write_status)
            assert "not written" in record.write_status, record.write_status
            assert b.loop.external_changes == 1
            assert record.applied_um == 0.0
            assert believed >= 15.0
            after = await b.cycle()  # moves on from the CNC's 0 at the slew limit
            assert 0.0 < b.cnc.held_um <= STEP_UM + 1e-6, (b.cnc.held_um, after.write_status)
            assert b.loop.external_changes == 1

    run(body)


def episodes(events: list[tuple[str, float]]) -> tuple[list[float], int]:
    """Operator writes (0) grouped up to the gateway's next write (non-zero).

    Returns the gateway's write after each group the gateway read after (it saw 0),
    and how many groups it did not read after (landed between its last read and its
    write: the remaining window).
    """
    seen_next: list[float] = []
    unseen = 0
    pending = False  # an operator write since the gateway's last write
    read_since = False  # and a gateway read after it
    for kind, value_um in events:
        if kind == "write" and value_um == 0.0:
            pending, read_since = True, False
        elif kind == "read" and pending:
            read_since = True
        elif kind == "write" and pending:
            if read_since:
                seen_next.append(value_um)
            else:
                unseen += 1
            pending = False
    return seen_next, unseen


@pytest.mark.parametrize("cnc_kind", CNCS)
def test_an_operator_writing_at_random_moments_is_never_overwritten_unseen(
    cnc_kind: str, store: Path
) -> None:
    async def body() -> tuple[list[float], int, int, int]:
        async with watched(cnc_kind, store) as b:
            await ramp_up(b)
            assert b.loop is not None
            b.cnc.events.clear()
            stop = asyncio.Event()
            rng = random.Random(500)
            writes = 0

            async def operator(client: Any) -> None:
                nonlocal writes
                while not stop.is_set():
                    await asyncio.sleep(rng.uniform(0.0, 0.02))
                    await b.client_writes(MACRO, 0.0, client)
                    writes += 1

            async with contextlib.AsyncExitStack() as stack:
                if cnc_kind == "opcua":
                    assert isinstance(b.server, CncOpcUaServer)
                    client = await stack.enter_async_context(Client(b.server.endpoint, timeout=5))
                else:
                    client = AsyncModbusTcpClient(HOST, port=b.cnc_port, timeout=2)
                    assert await client.connect()
                    stack.callback(client.close)
                task = asyncio.create_task(operator(client))
                # 60 cycles, and on until the operator hit the loop 5 times (a busy
                # machine can starve the operator's task for most of 60 fast cycles)
                await b.cycles(60)
                for _ in range(20):
                    if len(episodes(b.cnc.events)[0]) >= 5:
                        break
                    await b.cycles(20)
                stop.set()
                await task
            seen_next, unseen = episodes(b.cnc.events)
            noticed = b.loop.external_changes + b.loop.failed_writes  # a read-back mismatch
            return seen_next, unseen, noticed, writes

    seen_next, unseen, noticed, writes = run(body)
    print(f"{cnc_kind}: {writes} operator writes, {len(seen_next)} episodes seen, {unseen} unseen")
    assert len(seen_next) >= 5  # the operator did hit the loop, many times
    assert noticed >= len(seen_next)  # each one seen was counted, none passed silently
    # seen: the gateway moved on from 0 at the slew limit, never from its old value (≥ 20 µm)
    assert all(0.0 < v <= MOVE_ON_UM + 1e-6 for v in seen_next), seen_next


@pytest.mark.parametrize("cnc_kind", CNCS)
def test_a_handshake_reset_at_the_cnc_is_an_external_change(cnc_kind: str, store: Path) -> None:
    async def body() -> None:
        async with watched(cnc_kind, store, {"handshake_macro": HANDSHAKE}) as b:
            await mid_ramp(b)
            assert b.loop is not None
            assert b.cnc.macros[HANDSHAKE] == float(b.loop.handshake) > 0
            held = b.cnc.held_um
            writes = len(b.cnc.received)
            await b.client_writes(HANDSHAKE, 0.0)  # a programme takes the handshake
            record = await b.cycle()
            assert "handshake" in record.write_status and "not written" in record.write_status
            assert b.loop.external_changes == 1
            assert len(b.cnc.received) == writes and b.cnc.held_um == held
            assert b.cnc.macros[HANDSHAKE] == 0.0
            await b.cycles(2)  # the gateway writes again, and a new count
            assert b.cnc.macros[HANDSHAKE] == float(b.loop.handshake) > 0
            assert b.loop.external_changes == 1

    run(body)


@pytest.mark.parametrize("cnc_kind", CNCS)
@pytest.mark.parametrize("typed_mm", [1e30, 1.0])
def test_a_value_beyond_the_clamp_is_warned_and_left_within_it(
    cnc_kind: str, typed_mm: float, store: Path, caplog: pytest.LogCaptureFixture
) -> None:
    """1e30, and 1.0 typed into the mm macro where 1 µm was meant (1000 µm)."""

    async def body() -> tuple[list[float], int]:
        async with watched(cnc_kind, store) as b:
            await ramp_up(b)
            assert b.loop is not None
            before = len(b.cnc.received)
            await b.client_writes(MACRO, typed_mm)
            await b.cycles(3)
            return [v for _, v in b.cnc.received[before + 1 :]], b.loop.external_changes

    with caplog.at_level(logging.WARNING, logger="gateway.live.loop"):
        written, counted = run(body)
    warned = [r.getMessage() for r in caplog.records if "would never write" in r.getMessage()]
    assert len(warned) == 1, warned
    assert "beyond the ±50 µm clamp" in warned[0]
    assert counted == 1
    assert written and all(abs(v) <= 50.0 + 1e-6 for v in written), written
