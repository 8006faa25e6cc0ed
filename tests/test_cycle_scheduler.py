"""The shared cycle scheduler: loops spread over the cycle, woken in due order, never early,
at once on stop; on a manual clock (no wall-clock sleeps)."""

from __future__ import annotations

import asyncio

import pytest

from drivers.clock import ManualClock, WallClock
from gateway.cycle_scheduler import LOOPS_PER_SLOT, SLOTS, CycleScheduler, spread_fraction


def test_phases_stay_evenly_spread_whatever_the_number_of_loops() -> None:
    assert [spread_fraction(i) for i in range(8)] == [
        0.0,
        0.5,
        0.25,
        0.75,
        0.125,
        0.625,
        0.375,
        0.875,
    ]
    for count in (3, 10, 100, 1000):
        points = sorted(spread_fraction(i) for i in range(count))
        gaps = [b - a for a, b in zip(points, [*points[1:], 1.0], strict=True)]
        # Never a gap wider than twice the even spacing: no bunch of loops firing together.
        assert max(gaps) <= 2.0 / count
    scheduler = CycleScheduler(ManualClock(), loops_per_slot=1)
    assert [scheduler.phase_s(2.0) for _ in range(4)] == [0.0, 1.0, 0.5, 1.5]
    # Beyond SLOTS loops, slots are shared evenly: 100 loops, 5 per slot.
    phases = [scheduler.phase_s(2.0) for _ in range(96)]
    counts = {p: phases.count(p) for p in set(phases)}
    assert len(counts) == SLOTS and set(counts.values()) <= {4, 5, 6}


def test_a_slot_fills_before_the_next_opens_and_many_loops_use_every_slot() -> None:
    scheduler = CycleScheduler(ManualClock())
    assert scheduler.loops_per_slot == LOOPS_PER_SLOT
    # A small gateway polls in full bursts: the first slot's loops, then half a cycle on.
    first = [scheduler.phase_s(1.0) for _ in range(LOOPS_PER_SLOT)]
    second = [scheduler.phase_s(1.0) for _ in range(LOOPS_PER_SLOT)]
    assert set(first) == {0.0} and set(second) == {0.5}
    # SLOTS × LOOPS_PER_SLOT loops: every slot in use, each with LOOPS_PER_SLOT loops.
    phases = first + second
    phases += [scheduler.phase_s(1.0) for _ in range((SLOTS - 2) * LOOPS_PER_SLOT)]
    counts = {p: phases.count(p) for p in set(phases)}
    assert len(counts) == SLOTS and set(counts.values()) == {LOOPS_PER_SLOT}
    with pytest.raises(ValueError):
        CycleScheduler(ManualClock(), loops_per_slot=0)


def test_loops_wake_in_due_order_never_early_and_at_most_a_tick_late() -> None:
    async def scenario() -> list[tuple[str, float, float]]:
        clock = ManualClock(origin_s=100.0)
        scheduler = CycleScheduler(clock, tick_s=0.005)
        stop = asyncio.Event()
        woke: list[tuple[str, float, float]] = []

        async def waiter(name: str, due_s: float) -> None:
            await scheduler.wait_until(due_s, stop)
            woke.append((name, due_s, clock.now()))

        await asyncio.gather(
            waiter("b", 100.102),  # within one tick of a: woken by the same wake-up
            waiter("a", 100.1),
            waiter("past", 99.0),  # already due: returns at once
        )
        # A manual clock moves whenever the timer sleeps, so the next waiter comes after.
        await waiter("c", 100.9)
        assert scheduler.waiting == 0
        return woke

    woke = asyncio.run(scenario())
    assert [name for name, _, _ in woke] == ["past", "a", "b", "c"]
    for name, due_s, at_s in woke[1:]:
        assert due_s <= at_s <= due_s + 0.005 + 1e-9, name
    assert woke[1][2] == woke[2][2]  # one wake-up for a and b


def test_a_stop_wakes_every_waiting_loop_at_once_and_later_waits_return() -> None:
    async def scenario() -> None:
        # A wall clock and loops due in ~12 days: only the stop can wake them in time.
        clock = WallClock()
        scheduler = CycleScheduler(clock)
        stop = asyncio.Event()
        waiters = [asyncio.create_task(scheduler.wait_until(1e6 + i, stop)) for i in range(50)]
        await asyncio.sleep(0)
        assert scheduler.waiting == 50
        stop.set()
        await asyncio.wait_for(asyncio.gather(*waiters), 1.0)
        await asyncio.wait_for(scheduler.wait_until(2e6, stop), 1.0)
        await asyncio.sleep(0.01)
        assert scheduler.idle  # nothing left to time: the timer task has ended

    asyncio.run(scenario())


def test_a_cancelled_waiter_is_not_woken_and_the_others_are() -> None:
    async def scenario() -> None:
        clock = ManualClock()
        scheduler = CycleScheduler(clock)
        stop = asyncio.Event()
        gone = asyncio.create_task(scheduler.wait_until(5.0, stop))
        kept = asyncio.create_task(scheduler.wait_until(6.0, stop))
        await asyncio.sleep(0)
        gone.cancel()
        with pytest.raises(asyncio.CancelledError):
            await gone
        await asyncio.wait_for(kept, 1.0)
        assert clock.now() >= 6.0

    asyncio.run(scenario())


def test_tick_must_not_be_negative() -> None:
    with pytest.raises(ValueError, match="tick_s"):
        CycleScheduler(ManualClock(), tick_s=-0.001)
