"""The overview's live board: what a tick costs the event loop it shares with the cycles.

Real asyncio, no server: the board's ticker runs beside a task that measures how
long the loop was held between two of its wake-ups, as a machine's cycle would see.
"""

from __future__ import annotations

import asyncio
import gc
import json
import time

from gateway.live.record import CycleRecord
from gateway.web.live import SLICE, LiveBoard

SENSORS = [f"T{i}" for i in range(1, 10)]


def _record(machine: str, t: float) -> CycleRecord:
    return CycleRecord(
        machine=machine,
        time_s=t,
        temperatures_C={s: 25.0 + i for i, s in enumerate(SENSORS)},
        quality=dict.fromkeys(SENSORS, "good"),
        quality_reasons={},
        speed_rpm=8000.0,
        regime="variable",
        model_id="lag-ridge-error_um",
        predicted_um=12.3,
        target_um=12.3,
        applied_um=12.1,
        written_cnc=0.0121,
        write_status="ok: tracking",
    )


def _board(machines: int, tick_s: float = 0.05) -> LiveBoard:
    names = [f"m{i:04d}" for i in range(machines)]
    return LiveBoard(names, lambda m: {"cycles": 1}, tick_s)


async def _held_ms(board: LiveBoard, watch: bool) -> tuple[float, list[bytes]]:
    """Longest time the loop was held away from a 1 ms sleeper over a few ticks,
    with one watcher (``watch``) or none; and the events the watcher got.

    Counted in this thread's CPU time: on a busy machine the kernel may take the core
    away for tens of ms at any moment, which says nothing about how long the board
    holds the loop. The collector is paused for the same reason: a full collection of a
    test process's heap (this loop makes 2000 records a turn) can take as long as a
    whole build, in whichever turn it falls, and says nothing about the board."""
    gc.collect()
    gc.disable()
    try:
        return await _watch_ticks(board, watch)
    finally:
        gc.enable()


async def _watch_ticks(board: LiveBoard, watch: bool) -> tuple[float, list[bytes]]:
    stop = asyncio.Event()
    ticker = asyncio.create_task(board.run(stop))
    await asyncio.sleep(0)
    got: list[bytes] = []

    async def watcher() -> None:
        serial = board.serial
        while True:
            serial, event = await board.next_event(serial)
            got.append(event)

    watching = asyncio.create_task(watcher()) if watch else None
    worst = 0.0
    # at least 0.6 s; with a watcher, on until it got an event (a tick of 2000
    # machines is 125 slices, each after a turn of this loop, and on a busy machine
    # 0.6 s can end before the first tick does)
    started = time.monotonic()
    while time.monotonic() < started + 0.6 or (
        watch and not got and time.monotonic() < started + 20.0
    ):
        for m in board.machines:
            board.record(_record(m, time.time()))
        before = time.thread_time()
        await asyncio.sleep(0.001)
        worst = max(worst, time.thread_time() - before)
    stop.set()
    for task in (ticker, watching):
        if task is not None:
            task.cancel()
    await asyncio.gather(ticker, *([watching] if watching else []), return_exceptions=True)
    return worst * 1000, got


def test_a_tick_hands_the_loop_back_between_slices_of_machines() -> None:
    """2000 machines' rows take tens of ms to build; the loop is never held for a
    whole tick, only for a slice of it."""
    board = _board(2000)
    for m in board.machines:
        board.record(_record(m, time.time()))
    gc.collect()
    gc.disable()
    try:
        started = time.thread_time()
        json.dumps(board.rows())
        whole_ms = (time.thread_time() - started) * 1000
    finally:
        gc.enable()
    held_ms, got = asyncio.run(_held_ms(board, watch=True))
    assert got, "the watcher received no event"
    rows = json.loads(got[-1].decode().split("data: ", 1)[1])
    assert len(rows) == 2000 and rows[0]["machine"] == "m0000"
    assert rows[0]["sensors"][0]["value_C"] == 25.0
    assert whole_ms > 4 * held_ms, (whole_ms, held_ms, SLICE)


def test_nothing_is_encoded_while_nobody_watches_and_a_new_stream_gets_only_news() -> None:
    board = _board(50)
    asyncio.run(_held_ms(board, watch=False))
    assert board.serial == 0, "the board encoded rows with no overview open"

    async def late_watcher() -> tuple[int, int]:
        stop = asyncio.Event()
        ticker = asyncio.create_task(board.run(stop))
        await asyncio.sleep(0)
        start = board.serial
        board.record(_record("m0007", time.time()))
        serial, event = await asyncio.wait_for(board.next_event(start), 2.0)
        stop.set()
        await ticker
        return serial - start, len(json.loads(event.decode().split("data: ", 1)[1]))

    newer, rows = asyncio.run(late_watcher())
    assert newer == 1
    # every machine recorded while nobody watched is sent with the first event
    assert rows == 50
