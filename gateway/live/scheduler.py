"""One timer for every machine loop of a gateway process, with the loops spread over the cycle.

A loop that sleeps on its own between cycles costs a timer, a task watching the stop
event and a wake-up per cycle; a thousand such loops that all started together also
fire together, every cycle, so the last machine of the burst is read up to a whole
burst late and a burst as long as a transmitter timeout collapses into reconnects.

:class:`CycleScheduler` keeps the waiting loops in one heap ordered by due time and
wakes once per ``tick_s`` for everything due by then (one timer for the process);
each loop gets a phase within its cycle (:meth:`CycleScheduler.phase_s`: one of
``SLOTS`` slots) so the polls are spread over the cycle in batches. A slot takes
``LOOPS_PER_SLOT`` loops before the next one opens, so a small gateway polls its
machines in a few full bursts rather than in twenty bursts of two or three: the
poll's CPU per request at 200 simulated machines was 2× what it is at 1000
(``benchmarks/poll_vs_telegraf.py``), much of it the loop sleeping and being woken
between replies, and full bursts let more replies share a wake-up (measured: about
15 % less CPU per request at 200 machines, no change seen at 50). From
``SLOTS × LOOPS_PER_SLOT`` loops on, every slot is used and they fill evenly. One
watcher per stop event wakes every loop waiting on it at once.

The slots sit on one grid for the process (:meth:`CycleScheduler.next_due_s`):
times ``origin + phase + k × period``, the origin taken when the first loop asks.
A loop that starts later than the others (built after a slow connect, restarted,
back from an overrun) still polls with its slot's burst; a phase counted from each
loop's own start would scatter the loops over the cycle, one wake-up each: the
poll benchmark's loops, built one after the other, cost 3.4× the CPU per request
that way (95 µs against 28 µs at 50 machines).
"""

from __future__ import annotations

import asyncio
import heapq
import itertools
import math

from drivers.clock import Clock

#: Loops due within this much of each other are released by one wake-up (machine s).
DEFAULT_TICK_S = 0.005
#: Phases are whole multiples of ``period / SLOTS``: the loops of one slot poll
#: together, so their replies share the event loop's wake-ups (one wake-up per
#: reply costs more CPU than the reply), while each burst is 1/SLOTS of the machines.
SLOTS = 20
#: Loops a slot takes before the next slot opens (the burst a small gateway polls in);
#: 1000 loops fill the 20 slots with 50 each, as they always did.
LOOPS_PER_SLOT = 50


def spread_fraction(index: int) -> float:
    """The ``index``-th point of the base-2 van der Corput sequence, in [0, 1).

    The first n points of it are spread evenly over [0, 1) for every n (0, ½, ¼, ¾,
    ⅛, …), so loops added one by one stay evenly spaced without knowing how many
    will come.
    """
    fraction, scale = 0.0, 0.5
    while index:
        if index & 1:
            fraction += scale
        index >>= 1
        scale /= 2
    return fraction


def after_cycle(grid_due_s: float, period_s: float, now_s: float) -> tuple[float, float]:
    """(due time of the next cycle, its grid time) after the cycle due at ``grid_due_s``
    ended at ``now_s``: the next grid time, or, after an overrun, at once (no catching
    up in a burst) with the grid time the cycle after it counts on from (the last one
    not after now)."""
    grid_due_s += period_s
    if grid_due_s > now_s:
        return grid_due_s, grid_due_s
    grid_due_s += math.floor((now_s - grid_due_s) / period_s) * period_s
    return now_s, grid_due_s


def _slot_order() -> tuple[int, ...]:
    """Every slot once, in the order the van der Corput points first reach it (0, the
    half cycle, the quarters, …): the slots in use are spread evenly at any count."""
    order: list[int] = []
    index = 0
    while len(order) < SLOTS:
        slot = int(spread_fraction(index) * SLOTS)
        if slot not in order:
            order.append(slot)
        index += 1
    return tuple(order)


#: The order in which slots open.
SLOT_ORDER = _slot_order()


class CycleScheduler:
    """Wakes loops at their due times (machine time of ``clock``) from one shared timer.

    A due loop is released at most ``tick_s`` late and never early. Construction does
    no I/O and needs no running event loop; the timer task starts with the first wait.
    """

    def __init__(
        self, clock: Clock, tick_s: float = DEFAULT_TICK_S, loops_per_slot: int = LOOPS_PER_SLOT
    ) -> None:
        if tick_s < 0:
            raise ValueError(f"tick_s must be >= 0, got {tick_s}")
        if loops_per_slot < 1:
            raise ValueError(f"loops_per_slot must be >= 1, got {loops_per_slot}")
        self.clock = clock
        self.tick_s = tick_s
        self.loops_per_slot = loops_per_slot
        self._heap: list[tuple[float, int, asyncio.Future[None]]] = []
        self._order = itertools.count()
        self._phases = itertools.count()
        self._origin_s: float | None = None
        self._timer: asyncio.Task[None] | None = None
        self._timer_due: float | None = None
        self._rearm = asyncio.Event()
        self._watchers: dict[asyncio.Event, asyncio.Task[None]] = {}
        self._waiting: dict[asyncio.Event, set[asyncio.Future[None]]] = {}

    def phase_s(self, period_s: float) -> float:
        """The next loop's offset within its cycle: one of ``SLOTS`` slots, each filled with
        ``loops_per_slot`` loops before the next opens (the slots in use spread evenly)."""
        index = next(self._phases)
        if index < SLOTS * self.loops_per_slot:
            slot = SLOT_ORDER[index // self.loops_per_slot]
        else:  # every slot is full: one more each, in turn
            slot = SLOT_ORDER[index % SLOTS]
        return slot * period_s / SLOTS

    def next_due_s(self, phase_s: float, period_s: float, after_s: float | None = None) -> float:
        """The first time on the grid of ``phase_s`` (``origin + phase_s + k·period_s``)
        that is not before ``after_s`` (default: now); the grid's origin is the machine
        time of the first call, shared by every loop of the scheduler."""
        if not period_s > 0:
            raise ValueError(f"period_s must be > 0, got {period_s}")
        now = self.clock.now()
        if self._origin_s is None:
            self._origin_s = now
        after = now if after_s is None else after_s
        first = self._origin_s + phase_s
        if after <= first:
            return first
        return first + math.ceil((after - first) / period_s - 1e-9) * period_s

    @property
    def waiting(self) -> int:
        """Loops waiting for their due time now."""
        return sum(1 for _, _, future in self._heap if not future.done())

    async def wait_until(self, due_s: float, stop: asyncio.Event) -> None:
        """Return at ``due_s`` (machine time), or at once when ``stop`` is or gets set."""
        if stop.is_set():
            return
        if due_s <= self.clock.now():
            await asyncio.sleep(0)  # let the others run, as a sleep would
            return
        # The timer task's loop is the running one while it runs: asking asyncio for the
        # running loop costs a getpid() system call, once per loop and cycle.
        timer = self._timer
        loop = timer.get_loop() if timer is not None and not timer.done() else None
        future: asyncio.Future[None] = (loop or asyncio.get_running_loop()).create_future()
        heapq.heappush(self._heap, (due_s, next(self._order), future))
        waiting = self._waiting.setdefault(stop, set())
        waiting.add(future)
        if stop not in self._watchers:
            self._watchers[stop] = asyncio.create_task(self._watch(stop))
        self._arm(due_s)
        try:
            await future
        finally:
            waiting.discard(future)
            if not future.done():  # the waiter was cancelled: never wake it
                future.cancel()

    def _arm(self, due_s: float) -> None:
        """Make sure the timer runs and wakes by ``due_s``."""
        if self._timer is None or self._timer.done():
            self._timer_due = None
            self._timer = asyncio.create_task(self._run_timer())
        elif self._timer_due is not None and due_s < self._timer_due:
            self._rearm.set()  # it sleeps past this one: let it look again

    @property
    def idle(self) -> bool:
        """No timer task runs (nothing is waiting)."""
        return self._timer is None or self._timer.done()

    async def _run_timer(self) -> None:
        heap = self._heap
        while heap:
            if heap[0][2].done():  # woken by a stop, or cancelled: nothing to time
                heapq.heappop(heap)
                continue
            due_s = heap[0][0]
            wait_s = due_s + self.tick_s - self.clock.now()
            if wait_s > 0:
                self._timer_due = due_s + self.tick_s
                self._rearm.clear()
                await self.clock.sleep(wait_s, self._rearm)
                self._timer_due = None
            now = self.clock.now()
            while heap and heap[0][0] <= now:
                _, _, future = heapq.heappop(heap)
                if not future.done():
                    future.set_result(None)

    async def _watch(self, stop: asyncio.Event) -> None:
        """Wake everyone waiting on ``stop`` once it is set."""
        try:
            await stop.wait()
            for future in self._waiting.pop(stop, set()):
                if not future.done():
                    future.set_result(None)
            self._rearm.set()  # the timer drops what was woken, and ends if that was all
        finally:
            self._watchers.pop(stop, None)
