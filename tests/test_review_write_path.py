"""The handshake macro's count is not written over a change at the CNC (OPC UA and Modbus TCP).

The handshake macro is the gateway's ownership token: a CNC programme or an operator
that resets it takes the machine over for a cycle, and the gateway counts that as an
external change. The gateway bumps the count after each confirmed write of #500; that
bump wrote blindly, so a reset landing between the gateway's check of the token and
its bump (here: the CNC's programme reacts to the gateway's write of #500) was
overwritten with the next count and never seen.
"""

from __future__ import annotations

import asyncio
import contextlib
from collections.abc import AsyncIterator
from pathlib import Path

import pytest

from drivers.clock import ManualClock
from tests.test_operator_write import HANDSHAKE, WatchedBench, WatchedCnc, mid_ramp
from tests.test_write_path import CNCS, MACRO, model_store, run


@pytest.fixture(scope="module")
def store(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return model_store(tmp_path_factory.mktemp("review-write-path"))


class ResettingCnc(WatchedCnc):
    """Its programme resets the handshake right after the gateway's next write of #500."""

    def __init__(self, clock: ManualClock) -> None:
        super().__init__(clock)
        self.reset_on_write = False
        self.on_reset = None  # set by the bench: publishes the reset to the server

    def write_macro(self, number: int, value: float) -> None:
        super().write_macro(number, value)
        if number == MACRO and self.reset_on_write:
            self.reset_on_write = False
            asyncio.get_running_loop().create_task(self._reset())

    async def _reset(self) -> None:
        super().write_macro(HANDSHAKE, 0.0)
        assert self.on_reset is not None
        await self.on_reset()


@pytest.mark.parametrize("cnc_kind", CNCS)
def test_a_handshake_reset_after_the_gateways_write_is_not_overwritten(
    cnc_kind: str, store: Path
) -> None:
    async def body() -> None:
        async with resetting(cnc_kind, store) as b:
            cnc = b.cnc
            await mid_ramp(b)
            assert b.loop is not None
            count = b.loop.handshake
            assert cnc.macros[HANDSHAKE] == float(count) > 0
            writes = len(cnc.received)
            cnc.reset_on_write = True
            record = await b.cycle()  # writes #500; the programme then resets the handshake
            assert len(cnc.received) == writes + 1, record.write_status
            assert not cnc.reset_on_write
            await asyncio.sleep(0.05)  # nothing the gateway does later brings its count back
            assert cnc.macros[HANDSHAKE] == 0.0, record.write_status
            assert "handshake" in record.write_status, record.write_status

            held = cnc.held_um
            skipped = await b.cycle()  # the reset is seen: an external change, not written
            assert "not written" in skipped.write_status, skipped.write_status
            assert b.loop.external_changes == 1
            assert len(cnc.received) == writes + 1 and cnc.held_um == held
            await b.cycles(2)  # then the gateway writes again, with a new count
            assert cnc.macros[HANDSHAKE] == float(b.loop.handshake) > 0
            assert b.loop.external_changes == 1

    run(body)


class ResettingBench(WatchedBench):
    def __init__(self, cnc_kind: str, clock: ManualClock) -> None:
        super().__init__(cnc_kind, clock)
        self.cnc: ResettingCnc = ResettingCnc(clock)


@contextlib.asynccontextmanager
async def resetting(cnc_kind: str, store: Path) -> AsyncIterator[ResettingBench]:
    bench = ResettingBench(cnc_kind, ManualClock())
    try:
        await bench.start(store, {"handshake_macro": HANDSHAKE}, False)
        assert bench.server is not None
        bench.cnc.on_reset = bench.server.publish
        yield bench
    finally:
        await bench.stop()
