"""The shared cycle scheduler: loops spread over the cycle, woken in due order, never early,
at once on stop; on a manual clock (no wall-clock sleeps)."""

from __future__ import annotations

import asyncio

import pytest

from drivers.clock import ManualClock, WallClock
from gateway.live.scheduler import (
    DEFAULT_TICK_S,
    LOOPS_PER_SLOT,
    SLOTS,
    CycleScheduler,
    spread_fraction,
)


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


def test_the_grid_is_shared_so_a_loop_that_starts_late_polls_with_its_slot() -> None:
    clock = ManualClock(origin_s=10.0)
    scheduler = CycleScheduler(clock)
    assert scheduler.next_due_s(0.25, 1.0) == 10.25  # the first call sets the origin (10.0)
    clock.advance(3.4)  # a loop built 3.4 s later, same phase: the grid's next time
    assert scheduler.next_due_s(0.25, 1.0) == 14.25
    assert scheduler.next_due_s(0.5, 1.0) == 13.5
    assert scheduler.next_due_s(0.25, 1.0, after_s=14.25) == 14.25  # on the grid: itself
    assert scheduler.next_due_s(0.25, 2.0, after_s=14.26) == 16.25
    with pytest.raises(ValueError, match="period_s"):
        scheduler.next_due_s(0.0, 0.0)


def test_loops_started_apart_run_their_cycles_on_one_wake_up() -> None:
    """Two machine loops whose tasks start 0.3 s apart still poll in the same burst: the
    late one waits for the grid time, and an overrun comes back onto the grid."""
    from types import SimpleNamespace

    from gateway.live.loop import MachineLoop

    clock = ManualClock(origin_s=0.0)
    stop = asyncio.Event()

    class Cycles:
        """MachineLoop.run's scheduling around a cycle that only notes when it ran;
        the late loop's third cycle overruns by 1.5 cycles."""

        run = MachineLoop.run

        def __init__(self, name: str) -> None:
            self.config = SimpleNamespace(id=name, cycle_s=1.0)
            self.clock = clock
            self.starts: list[float] = []
            self.lates: list[float] = []

        async def run_cycle(self) -> None:
            self.starts.append(clock.now())
            self.lates.append(self.start_late_s)
            if len(self.starts) == 3 and self.config.id == "late":
                clock.advance(1.5)
            if len(self.starts) >= 6 and self.config.id == "late":
                stop.set()

    early, late = Cycles("early"), Cycles("late")

    async def scenario() -> None:
        scheduler = CycleScheduler(clock)
        phase = scheduler.phase_s(1.0)
        first = asyncio.create_task(early.run(stop, scheduler=scheduler, phase_s=phase))
        await asyncio.sleep(0)
        clock.advance(0.3)
        second = asyncio.create_task(late.run(stop, scheduler=scheduler, phase_s=phase))
        await asyncio.wait_for(asyncio.gather(first, second), 5.0)

    asyncio.run(scenario())
    tick = DEFAULT_TICK_S
    # The late loop's first cycle is the grid's next time, on the other loop's wake-up.
    assert late.starts[0] == early.starts[1] == pytest.approx(1.0 + tick)
    assert late.starts[3] == pytest.approx(late.starts[2] + 1.5)  # after the overrun: at once
    assert late.starts[4:] == pytest.approx([5.0 + tick, 6.0 + tick])  # then on the grid again
    # Each cycle's start lateness (what benchmarks/console_gateway_cost.py collects): the
    # scheduler's tick on the grid, none for the cycle started at once after the overrun.
    assert late.lates[3] == pytest.approx(0.0)
    assert late.lates[4:] == early.lates[1:3] == pytest.approx([tick, tick])
