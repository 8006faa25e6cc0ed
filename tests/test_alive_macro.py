"""The alive count (``compensation.alive_macro``): the CNC's sign that the gateway runs.

The gateway's loop runs against the simulated CNC over OPC UA and over Modbus TCP, as in
``tests/test_write_path.py`` (manual clock, one cycle at a time). The machine behind the
server records the alive macro's writes as they land, and (``tests/test_operator_write.py``)
the gateway's reads and writes of #500 in the order the server handles them.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import math
from collections.abc import AsyncIterator
from pathlib import Path
from typing import Any

import pytest

from drivers.clock import ManualClock
from gateway.live.loop import ALIVE_WRAP, next_alive_count
from simulator.servers.modbus_cnc import CncModbusServer
from simulator.servers.opcua_cnc import CncOpcUaServer
from tests.test_operator_write import WatchedBench, WatchedCnc, mid_ramp
from tests.test_write_path import CNCS, MACRO, Bench, model_store, ramp_up, run

ALIVE = 510


@pytest.fixture(scope="module")
def store(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """One MLR model on all seven sensors (error ≈ 4·ΔT1 − 2·ΔT6)."""
    return model_store(tmp_path_factory.mktemp("alive-macro"))


class AliveCnc(WatchedCnc):
    """The machine behind the server; ``events`` also holds ("alive", count) in order."""

    def write_macro(self, number: int, value: float) -> None:
        super().write_macro(number, value)
        if number == ALIVE:
            self.events.append(("alive", float(value)))


class AliveBench(WatchedBench):
    def __init__(self, cnc_kind: str, clock: ManualClock, macros: tuple[int, int]) -> None:
        super().__init__(cnc_kind, clock)
        self.cnc = AliveCnc(clock)
        self.macros = macros  # the OPC UA server's macro nodes, first and last

    async def start_cnc(self, held_mm: float) -> None:
        """A fresh CNC on the same port (a restart): #500 holds ``held_mm``, no alive count."""
        self.cnc = AliveCnc(self.clock)
        self.cnc.macros[MACRO] = held_mm
        self.server = self._new_server()
        await self.server.start()

    def _new_server(self) -> CncOpcUaServer | CncModbusServer:
        if self.cnc_kind == "opcua":
            return CncOpcUaServer(self.cnc, port=self.cnc_port, macro_range=self.macros)
        return super()._new_server()


def alive(bench: Bench) -> float | None:
    """The alive macro's value at the CNC (None: never written since the CNC started)."""
    value = bench.cnc.macros.get(ALIVE)
    return None if value is None or math.isnan(value) else value


@contextlib.asynccontextmanager
async def alive_bench(
    cnc_kind: str,
    store: Path,
    compensation: dict[str, Any] | None = None,
    macros: tuple[int, int] = (500, 999),
) -> AsyncIterator[AliveBench]:
    bench = AliveBench(cnc_kind, ManualClock(), macros)
    try:
        await bench.start(store, {"alive_macro": ALIVE, **(compensation or {})}, False)
        yield bench
    finally:
        await bench.stop()


def test_the_count_runs_1_to_9999_then_1_again_and_is_never_0() -> None:
    counts = [0]
    for _ in range(2 * ALIVE_WRAP + 5):
        counts.append(next_alive_count(counts[-1]))
    assert counts[1:4] == [1, 2, 3]
    assert counts[ALIVE_WRAP - 1 : ALIVE_WRAP + 3] == [ALIVE_WRAP - 1, ALIVE_WRAP, 1, 2]
    assert 0 not in counts[1:] and max(counts) == ALIVE_WRAP


@pytest.mark.parametrize("cnc_kind", CNCS)
def test_the_count_moves_every_cycle_inside_the_deadband(cnc_kind: str, store: Path) -> None:
    async def body() -> None:
        async with alive_bench(cnc_kind, store) as b:
            await b.cycle()
            assert alive(b) == 1.0  # the first cycle that reached the CNC
            await ramp_up(b)  # 11 cycles so far
            assert b.cnc.received and alive(b) == 11.0
            writes = len(b.cnc.received)
            counts = []
            for _ in range(6):
                record = await b.cycle()
                assert record.write_status.startswith("no write"), record.write_status
                counts.append(alive(b))
            assert len(b.cnc.received) == writes  # #500 not written: inside the deadband
            assert counts == [12.0, 13.0, 14.0, 15.0, 16.0, 17.0]
            assert b.loop is not None and b.loop.failed_writes == 0

    run(body)


@pytest.mark.parametrize("cnc_kind", CNCS)
def test_the_count_moves_while_compensation_is_off_and_held(cnc_kind: str, store: Path) -> None:
    async def body() -> None:
        async with alive_bench(cnc_kind, store, {"on_disable": "hold"}) as b:
            await ramp_up(b)
            assert b.loop is not None
            writes, held = len(b.cnc.received), b.cnc.held_um
            b.loop.compensation_enabled = False  # what the SCADA switch does
            b.temperatures.set_snapshot(b._snapshot({"T1": 25.0}))  # would move #500 if on
            before = alive(b)
            assert before is not None
            for n in range(1, 6):
                record = await b.cycle()
                assert record.write_status.startswith("disabled"), record.write_status
                assert alive(b) == before + n
            assert len(b.cnc.received) == writes and b.cnc.held_um == held

    run(body)


@pytest.mark.parametrize("cnc_kind", CNCS)
def test_the_count_is_written_after_the_write_of_500_and_its_read_back(
    cnc_kind: str, store: Path
) -> None:
    async def body() -> list[tuple[str, float]]:
        async with alive_bench(cnc_kind, store) as b:
            await mid_ramp(b)
            b.cnc.events.clear()
            record = await b.cycle()
            assert record.write_status.startswith("ok"), record.write_status
            return list(b.cnc.events)

    events = run(body)
    print(f"{cnc_kind}: {events}")
    kinds = [kind for kind, _ in events]
    # The cycle's read, the compare read, the write, the read-back; then the alive count.
    assert kinds == ["read", "read", "write", "read", "alive"], events
    assert events[3][1] == events[2][1]  # the read-back answered the value written


@pytest.mark.parametrize("cnc_kind", CNCS)
def test_a_cnc_link_drop_invents_no_count_and_the_count_resumes(cnc_kind: str, store: Path) -> None:
    async def body() -> None:
        async with alive_bench(cnc_kind, store) as b:
            await b.cycles(3)
            assert alive(b) == 3.0
            assert b.loop is not None
            await b.stop_cnc()
            down = await b.cycles(3)
            assert all(r.link_errors for r in down)
            assert b.loop.alive == 3  # nothing counted that no CNC received
            # Not tried on a link the cycle found down: no alive failure on top of the link's.
            assert not any("alive" in r.write_status for r in down), down
            await b.start_cnc(held_mm=0.0)  # the same CNC back, its macros as it restarted
            assert alive(b) is None
            counts = []
            for _ in range(3):
                await b.cycle()
                counts.append(alive(b))
            assert counts == [4.0, 5.0, 6.0]

    run(body)


@pytest.mark.parametrize("cnc_kind", CNCS)
def test_the_count_stops_when_the_loop_stops(cnc_kind: str, store: Path) -> None:
    async def body() -> None:
        async with alive_bench(cnc_kind, store) as b:
            assert b.loop is not None
            stop = asyncio.Event()
            running = asyncio.create_task(b.loop.run(stop))  # back to back on the manual clock
            async with asyncio.timeout(60):
                while (alive(b) or 0.0) < 5.0:
                    await asyncio.sleep(0.01)
            stop.set()
            await running
            last = alive(b)
            assert last is not None and last == b.loop.alive == b.loop.cycles
            counts = [value for kind, value in b.cnc.events if kind == "alive"]
            assert counts == [float(n) for n in range(1, int(last) + 1)]  # one a cycle
            for _ in range(3):  # machine time goes on, the CNC serves: nothing more comes
                b.clock.advance(60.0)
                await b.transmitters.publish()
                assert b.server is not None
                await b.server.publish()
                await asyncio.sleep(0.2)
            assert alive(b) == last

    run(body)


def test_a_refused_alive_write_is_counted_logged_once_and_keeps_the_compensation(
    store: Path, caplog: pytest.LogCaptureFixture
) -> None:
    """A CNC without the alive macro (no such node) refuses every alive write."""

    async def body() -> None:
        async with alive_bench("opcua", store, macros=(500, 505)) as b:
            await ramp_up(b)  # #500 ramps up and is confirmed as without the alive macro
            assert b.loop is not None
            assert b.loop.failed_writes == 10 and alive(b) is None and b.loop.alive == 0
            assert all("alive count not written to #510" in r.write_status for r in b.records)
            assert any(r.write_status.startswith("ok") for r in b.records)

    with caplog.at_level(logging.INFO, logger="gateway.live.loop"):
        run(body)
    logged = [r.getMessage() for r in caplog.records if "alive count" in r.getMessage()]
    assert len(logged) == 1, logged
    assert "BadNodeIdUnknown" in logged[0] and "failed writes: 1" in logged[0], logged
