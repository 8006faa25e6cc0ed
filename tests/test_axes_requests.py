"""The CNC requests of a three-axis cycle, counted on the wire (OPC UA and Modbus TCP).

The three-axis bench of :mod:`tests.test_axes_live` with a counting proxy
(:mod:`tests.counting_proxy`) between the gateway and the simulated CNC. Every axis's
macro is read in one request at the cycle start and every written macro read back in
one request after the writes; each write keeps its own read right before it. Over
Modbus TCP a cycle in which ``n`` axes write sends 5 + n reads (speed, the axes' macros,
the handshake check, n guards, the read-back, the handshake's guard) and n + 2 writes
(n axes, the handshake, the alive count), where one read per axis held, one guard and
one read-back per axis made 6 + 2n reads. Over OPC UA the guards are one Read and the
writes one Write right after it: 6 reads and 3 writes for any n.
"""

from __future__ import annotations

from collections import Counter
from pathlib import Path

import pytest

from drivers.clock import ManualClock
from gateway.config import MachineSection
from gateway.live.record import CycleRecord
from simulator.servers.opcua_cnc import CncOpcUaServer
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
        expected = {"read": 2, "write": 1}  # the speed, the axes' macros; the alive count
        if n and cnc_kind == "opcua":  # the guards in one Read, the writes in one Write
            expected = {"read": 6, "write": 3}
        elif n:  # Modbus: each guarded write its own read and write
            expected = {"read": 5 + n, "write": n + 2}
        assert dict(sent) == expected, (n, statuses)
    print(f"{cnc_kind}: axes written per cycle {writing}")
    assert 3 in writing  # cycles with every axis writing were counted


class UnservedY(CountedBench):
    """Y's macro configured as #520, a node this OPC UA CNC does not serve (it serves
    #500–#515): every read of it is refused with BadNodeIdUnknown."""

    def __init__(self, clock: ManualClock) -> None:
        super().__init__("opcua", clock)
        self.server = CncOpcUaServer(self.cnc, port=self.cnc_port, macro_range=(500, 515))

    def machine(self, store: Path) -> MachineSection:
        machine = super().machine(store)
        axes = machine.compensation.axes
        assert axes is not None
        axes = {**axes, "Y": axes["Y"].model_copy(update={"macro": 520})}
        compensation = machine.compensation.model_copy(update={"axes": axes})
        return machine.model_copy(update={"compensation": compensation})


def test_an_axis_whose_macro_read_is_refused_waits_alone_in_the_shared_read(store: Path) -> None:
    async def body() -> tuple[list[CycleRecord], list[Counter[str]], UnservedY]:
        b = UnservedY(ManualClock())
        records, sent = [], []
        try:
            await b.start(store)
            for _ in range(6):
                before = Counter(b.proxy.counts)
                records.append(await b.cycle())
                sent.append(b.proxy.counts - before)
        finally:
            await b.stop()
        return records, sent, b

    records, sent, b = run(body)
    for record in records:
        status = record.axes["Y"].write_status
        assert status.startswith("waiting for the CNC: CNC macro #520 not read"), status
        assert "BadNodeIdUnknown" in status
    assert b.loop is not None and b.loop.axes[2].policy is None  # never started blind
    assert 520 not in b.cnc.received
    # Z and X read in the same request as Y, and compensate all the same.
    assert any(r.axes["Z"].write_status.startswith("ok") for r in records)
    assert any(r.axes["X"].write_status.startswith("ok") for r in records)
    assert b.cnc.held_um("Z") == pytest.approx(records[-1].axes["Z"].predicted_um, abs=0.5)
    assert b.cnc.macros[502] == pytest.approx(-12.0)  # X at its clamp
    assert b.loop.cnc.health.reconnects == 0 and b.loop.cnc.health.total_failures == 0
    for record, counts in zip(records[1:], sent[1:], strict=True):
        n = sum(a.write_status.startswith("ok") for a in record.axes.values())
        assert counts["read"] == (6 if n else 2), (n, counts)
