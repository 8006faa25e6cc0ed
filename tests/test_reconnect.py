"""After a 20 s outage of the CNC or the transmitters, reads resume within 5 s of their return.

A simulated machine serves its transmitters (Modbus TCP) and its CNC (OPC UA and
Modbus TCP) on loopback, in real time; the gateway compensates it with a 0.5 s
cycle. One server is stopped for 20 s and a fresh one started on the same port,
as when a CNC or a transmitter gateway reboots. The back-off must neither hammer
the dead server nor, capped at 2 s, leave the link idle long after it is back.
"""

from __future__ import annotations

import asyncio
import time
from pathlib import Path

import pytest

from drivers.clock import WallClock
from gateway.config import GatewayConfig
from gateway.live.record import CycleRecord
from gateway.wiring import Gateway
from tests import gateway_rig as rig

CYCLE_S = 0.5
OUTAGE_S = 20.0
RESUME_LIMIT_S = 5.0


@pytest.fixture(scope="module")
def store(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return rig.fit_store(tmp_path_factory.mktemp("reconnect"))


def read_ok(record: CycleRecord, endpoint: str) -> bool:
    """Did this cycle read the link that ``endpoint`` serves?"""
    if endpoint.startswith("cnc_"):
        return record.speed_rpm is not None
    return all(record.temperatures_C[s] is not None for s in rig.SENSORS)


@pytest.mark.parametrize(
    ("endpoint", "cnc"),
    [("cnc_opcua", "opcua"), ("cnc_modbus", "modbus"), ("tcp_transmitters", "modbus")],
)
def test_reads_resume_within_5_s_of_the_server_coming_back(
    tmp_path: Path, store: Path, endpoint: str, cnc: str
) -> None:
    seen: list[tuple[float, CycleRecord]] = []

    async def scenario() -> tuple[float, float, int]:
        clock = WallClock()
        served = rig.plant(clock, cnc=(cnc,))
        await served.start()
        config = GatewayConfig.model_validate(
            {
                "state_dir": str(tmp_path / "state"),
                "logging": {"local_store": str(tmp_path / "points.sqlite")},
                "machines": [rig.machine_entry("m1", served, store, cnc=cnc, cycle_s=CYCLE_S)],
            }
        )
        gateway = Gateway(
            config, clock=clock, sinks=[lambda record: seen.append((time.monotonic(), record))]
        )
        stop = asyncio.Event()
        running = asyncio.create_task(gateway.run(stop))
        try:
            deadline = time.monotonic() + 30
            while not (seen and read_ok(seen[-1][1], endpoint)):
                assert time.monotonic() < deadline, "the link never worked"
                await asyncio.sleep(0.05)
            down = time.monotonic()
            await served.take_down(endpoint)
            await asyncio.sleep(OUTAGE_S)
            await served.bring_up(endpoint)
            up = time.monotonic()
            while not any(t > up and read_ok(r, endpoint) for t, r in seen):
                assert time.monotonic() < up + 30, "the link never came back"
                await asyncio.sleep(0.05)
            return down, up, gateway.loops[0].link_errors
        finally:
            stop.set()
            await asyncio.wait_for(running, 10)
            await served.stop()

    down, up, link_errors = asyncio.run(scenario())
    resumed = min(t for t, r in seen if t > up and read_ok(r, endpoint))
    resume_s = resumed - up
    print(f"{endpoint}: reads resumed {resume_s:.2f} s after the server came back")
    assert resume_s <= RESUME_LIMIT_S, f"{endpoint}: {resume_s:.2f} s"
    # The loop kept cycling through the outage (failed reads, not a stall), and said why.
    during = [r for t, r in seen if down + 1.0 < t < up]
    assert len(during) >= 0.5 * (OUTAGE_S - 1.0) / CYCLE_S
    assert all(not read_ok(r, endpoint) and r.link_errors for r in during)
    assert link_errors >= len(during)
