"""The CNC requests of a three-axis cycle, counted on the wire (OPC UA and Modbus TCP).

The three-axis bench of :mod:`tests.test_axes_live` with a counting proxy
(:mod:`tests.counting_proxy`) between the gateway and the simulated CNC. Every axis's
macro is read in one request at the cycle start and every written macro read back in
one request after the writes; each write keeps its own read right before it. So a
cycle in which ``n`` axes write sends 5 + n reads (speed, the axes' macros, the
handshake check, n guards, the read-back, the handshake's guard) and n + 2 writes
(n axes, the handshake, the alive count), where one read per axis held, one guard
and one read-back per axis made 6 + 2n reads.
"""

from __future__ import annotations

from collections import Counter
from pathlib import Path

import pytest

from drivers.clock import ManualClock
from gateway.live.record import CycleRecord
from tests.axes_rig import axes_store
from tests.counting_proxy import CountingProxy
from tests.test_axes_live import CNCS, HOST, MODEL_SENSORS, Bench, run


class CountedBench(Bench):
    """The bench, its gateway reaching the CNC through a :class:`CountingProxy`."""

    async def start(self, store: Path) -> None:
        self.proxy = CountingProxy((HOST, self.cnc_port), self.cnc_kind)
        await self.proxy.start()
        server_port, self.cnc_port = self.cnc_port, self.proxy.port
        try:
            await super().start(store)  # the gateway's link goes to the proxy
        finally:
            self.cnc_port = server_port

    async def stop(self) -> None:
        try:
            await super().stop()
        finally:
            await self.proxy.stop()


@pytest.fixture(scope="module")
def store(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return axes_store(tmp_path_factory.mktemp("axes-requests"), sensors=MODEL_SENSORS)


@pytest.mark.parametrize("cnc_kind", CNCS)
def test_a_cycle_reads_every_axis_in_one_request_and_reads_back_in_one(
    cnc_kind: str, store: Path
) -> None:
    async def body() -> list[tuple[CycleRecord, Counter[str]]]:
        b = CountedBench(cnc_kind, ManualClock())
        cycles = []
        try:
            await b.start(store)
            for _ in range(8):
                before = Counter(b.proxy.counts)
                record = await b.cycle()
                cycles.append((record, b.proxy.counts - before))
        finally:
            await b.stop()
        return cycles

    cycles = run(body)
    writing = []
    for record, sent in cycles[1:]:  # the first cycle also connects and starts the token
        statuses = [a.write_status for a in record.axes.values()]
        assert not any(s.startswith(("not written", "write failed")) for s in statuses)
        n = sum(s.startswith("ok") for s in statuses)
        writing.append(n)
        expected = {"read": 5 + n, "write": n + 2} if n else {"read": 2, "write": 1}
        assert dict(sent) == expected, (n, statuses)
    print(f"{cnc_kind}: axes written per cycle {writing}")
    assert 3 in writing  # cycles with every axis writing were counted
