"""The InfluxDB forwarder of a running gateway survives influxd dying and its own failure.

Two simulated machines (Modbus TCP transmitters and CNC on loopback) compensated
by one gateway on an accelerated clock, logging to a real InfluxDB 2.7.12 (with a
token of its bucket) through the disk buffer. influxd is killed and started again;
meanwhile the forwarder task itself fails once (the buffer's disk reporting an I/O
error) and is restarted by its supervisor. Every point the loops produced reaches
InfluxDB exactly once.
"""

from __future__ import annotations

import asyncio
import sqlite3
import time
from collections.abc import Callable
from pathlib import Path

import pytest

from drivers.clock import AcceleratedClock
from gateway.config import GatewayConfig
from gateway.live.record import CycleRecord
from gateway.outputs.disk_buffer import PointBuffer
from gateway.outputs.influx import Forwarder, InfluxWriter
from gateway.outputs.points import Point, points_from_record
from gateway.wiring import Gateway
from tests import gateway_rig as rig
from tests.influx_server import InfluxServer
from tests.test_influx import canonical, read_all

SPEEDUP = 20.0


@pytest.fixture(scope="module")
def store(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return rig.fit_store(tmp_path_factory.mktemp("forwarder"))


async def wait_until(condition: Callable[[], bool], timeout_s: float, what: str) -> None:
    deadline = time.monotonic() + timeout_s
    while not condition():
        if time.monotonic() > deadline:
            raise AssertionError(f"not within {timeout_s:g} s: {what}")
        await asyncio.sleep(0.05)


def test_forwarder_is_supervised_and_loses_nothing_through_an_influxd_kill(
    tmp_path: Path, store: Path
) -> None:
    produced: list[Point] = []
    buffer_path = tmp_path / "data" / "buffer.sqlite"

    def expect(record: CycleRecord) -> None:
        produced.extend(points_from_record(record))

    with InfluxServer(tmp_path / "influxdb") as server:
        bucket = server.create_database("gateway")
        token_file = tmp_path / "influx.token"
        token_file.write_text(server.create_token("gateway", bucket), encoding="utf-8")

        async def scenario() -> dict[str, int]:
            clock = AcceleratedClock(SPEEDUP, origin_s=time.time())
            plants = [rig.plant(clock, seed=i, cnc=("modbus",)) for i in range(2)]
            for served in plants:
                await served.start()
            config = GatewayConfig.model_validate(
                {
                    "state_dir": str(tmp_path / "state"),
                    "logging": {
                        "influxdb": {
                            "url": server.url,
                            "org": server.org,
                            "bucket": bucket,
                            "token_file": str(token_file),
                            "timeout_s": 2.0,
                        },
                        "buffer_path": str(buffer_path),
                    },
                    "machines": [
                        rig.machine_entry(f"m{i}", p, store, cycle_s=2.0)
                        for i, p in enumerate(plants)
                    ],
                }
            )
            gateway = Gateway(config, clock=clock, sinks=[expect])
            forwarder = gateway.outputs.forwarder
            buffer = gateway.outputs.buffer
            assert forwarder is not None and buffer is not None
            stop = asyncio.Event()
            running = asyncio.create_task(gateway.run(stop))
            figures: dict[str, int] = {}
            try:
                await wait_until(lambda: forwarder.sent > 200, 30, "points sent")
                server.kill()  # influxd dies: points pile up in the buffer
                await wait_until(lambda: forwarder.failures >= 2, 30, "failed writes")
                real_peek = buffer.peek
                failed = []

                def failing_peek(n: int) -> list[tuple[int, Point]]:
                    if not failed:
                        failed.append(True)
                        raise sqlite3.OperationalError("disk I/O error")
                    return real_peek(n)

                buffer.peek = failing_peek  # type: ignore[method-assign]
                await wait_until(lambda: forwarder.supervisor.restarts == 1, 30, "a restart")
                figures["backlog_during_outage"] = len(buffer)
                await asyncio.sleep(2.0)
                server.start()
                restarted = time.monotonic()
                await wait_until(lambda: len(buffer) < 50, 60, "the backlog sent")
                figures["catch_up_ms"] = int(1000 * (time.monotonic() - restarted))
                figures["health_restarts"] = int(gateway.health("m0")["forwarder_restarts"] or 0)
                figures["running"] = int(forwarder.health()["running"])
            finally:
                stop.set()
                await asyncio.wait_for(running, 10)
                for served in plants:
                    await served.stop()
            # Whatever the stop left buffered goes out at the next start, as after a restart.
            with PointBuffer(buffer_path) as left:
                figures["left_at_stop"] = len(left)
                writer = InfluxWriter(server.url, server.token, server.org, bucket, 5.0)
                again = Forwarder(left, writer, retry_s=0.1, max_retry_s=0.5)
                again.start()
                assert await again.flush(timeout=30)
                await again.stop()
                writer.close()
            return figures

        figures = asyncio.run(scenario())
        stored = read_all(server, bucket)
    print(f"forwarder: {figures}; {len(produced)} points produced, {len(stored)} stored")
    assert figures["backlog_during_outage"] > 0
    assert figures["health_restarts"] == 1 and figures["running"] == 1
    assert len(produced) > 400
    assert len(stored) == len(produced)  # none lost, none twice
    assert canonical(stored) == canonical(produced)
