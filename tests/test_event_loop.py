"""The live loop on either event loop the config's ``event_loop`` names, over real protocols.

The suite runs on uvloop (tests/conftest.py), as the commands do by default; here one
simulated machine (transmitters over Modbus TCP, the CNC over OPC UA) is compensated
for a few cycles on each loop, and the loop that ran is checked to be the one asked.
"""

from __future__ import annotations

import asyncio
from pathlib import Path

import pytest
import uvloop

from drivers.clock import WallClock
from gateway.config import GatewayConfig
from gateway.live.record import CycleRecord
from gateway.process import event_loop
from gateway.wiring import Gateway
from tests import gateway_rig as rig

CYCLES = 6


@pytest.fixture(scope="module")
def store(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return rig.fit_store(tmp_path_factory.mktemp("event-loop"))


@pytest.mark.parametrize("name", ["uvloop", "asyncio"])
def test_the_live_loop_runs_on_the_configured_event_loop(
    tmp_path: Path, store: Path, name: str
) -> None:
    records: list[CycleRecord] = []

    async def scenario() -> type:
        clock = WallClock()
        served = rig.plant(clock)
        await served.start()
        config = GatewayConfig.model_validate(
            {
                "event_loop": name,
                "state_dir": str(tmp_path / "state"),
                "logging": {"local_store": str(tmp_path / "points.sqlite")},
                "machines": [rig.machine_entry("m1", served, store, cnc="opcua", cycle_s=0.2)],
            }
        )
        assert config.event_loop == name
        gateway = Gateway(config, clock=clock, sinks=[records.append])
        stop = asyncio.Event()
        running = asyncio.create_task(gateway.run(stop))
        try:
            async with asyncio.timeout(30):
                while len([r for r in records if r.speed_rpm is not None]) < CYCLES:
                    await asyncio.sleep(0.05)
        finally:
            stop.set()
            await asyncio.wait_for(running, 10)
            await served.stop()
        return type(asyncio.get_running_loop())

    ran_on = event_loop.run(scenario(), name)
    expected = uvloop.Loop if name == "uvloop" else asyncio.BaseEventLoop
    assert issubclass(ran_on, expected)
    assert name == "uvloop" or not issubclass(ran_on, uvloop.Loop)
    read = [r for r in records if r.speed_rpm is not None]
    assert len(read) >= CYCLES
    assert all(all(v is not None for v in r.temperatures_C.values()) for r in read)
