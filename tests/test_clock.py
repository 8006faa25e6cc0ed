"""Machine time: wall, accelerated and manual clocks."""

from __future__ import annotations

import asyncio
import time

import pytest

from drivers.clock import AcceleratedClock, ManualClock, WallClock


def test_accelerated_clock_runs_speedup_times_faster() -> None:
    clock = AcceleratedClock(speedup=1000.0, origin_s=50.0)
    wall_start, machine_start = time.monotonic(), clock.now()
    asyncio.run(clock.sleep(100.0))  # 100 machine seconds = 0.1 wall seconds
    wall, machine = time.monotonic() - wall_start, clock.now() - machine_start
    assert machine_start >= 50.0
    assert machine >= 100.0
    assert machine == pytest.approx(1000.0 * wall, rel=0.05)
    with pytest.raises(ValueError, match="speedup must be > 0"):
        AcceleratedClock(0)


def test_manual_clock_moves_only_when_told() -> None:
    clock = ManualClock(origin_s=10.0)
    assert clock.now() == 10.0
    assert clock.advance(5.0) == 15.0
    asyncio.run(clock.sleep(30.0))
    assert clock.now() == 45.0
    with pytest.raises(ValueError, match="backwards"):
        clock.advance(-1.0)


def test_wall_clock_follows_the_wall() -> None:
    clock = WallClock(origin_s=0.0)
    first = clock.now()
    asyncio.run(clock.sleep(0.05))
    assert 0.04 <= clock.now() - first <= 1.0


@pytest.mark.parametrize("clock", [WallClock(), AcceleratedClock(speedup=2.0)])
def test_sleep_returns_as_soon_as_stop_is_set(clock: WallClock | AcceleratedClock) -> None:
    async def scenario() -> float:
        stop = asyncio.Event()
        asyncio.get_running_loop().call_later(0.05, stop.set)
        start = time.monotonic()
        await clock.sleep(300.0, stop)  # a five-minute cycle
        return time.monotonic() - start

    assert asyncio.run(scenario()) < 0.5
    already = asyncio.Event()
    already.set()
    start = time.monotonic()
    asyncio.run(clock.sleep(300.0, already))
    assert time.monotonic() - start < 0.5


def test_manual_clock_does_not_move_for_a_stopped_sleeper() -> None:
    clock = ManualClock()
    stop = asyncio.Event()
    asyncio.run(clock.sleep(30.0, stop))
    assert clock.now() == 30.0
    stop.set()
    asyncio.run(clock.sleep(30.0, stop))
    assert clock.now() == 30.0


def test_outputs_stamp_wall_time_on_the_wall_clock_and_machine_time_in_a_simulation() -> None:
    wall = WallClock(origin_s=0.0)  # machine time from 0: far from the wall's Unix time
    before, stamp, after = time.time(), wall.stamp(), time.time()
    assert before <= stamp <= after and wall.now() < 1e6
    accelerated, manual = AcceleratedClock(speedup=100.0, origin_s=50.0), ManualClock(7.0)
    assert accelerated.stamp() == pytest.approx(accelerated.now(), abs=0.5)
    assert manual.stamp() == manual.now() == 7.0
