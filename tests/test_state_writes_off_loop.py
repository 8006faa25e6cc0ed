"""The heartbeat, the lag states and the cold reference are written off the event loop,
whole or not at all.

Every machine writes its heartbeat each cycle, and its lag states and, at a first start,
its cold reference (two ``fsync`` each) on its first cycle. Written on the event loop, a
thousand machines' first cycles held it for seconds, and every other machine's cycle
waited. Here 300 machines run their first cycle as tasks, on this machine's real disk
kept busy by another process (8 MB blocks, each synced), while a probe task measures
how long the event loop was held at a stretch: with the writer threads, and (as a
control in the same run, showing the probe sees what it must) with the same files
written on the loop.

A gateway process killed (SIGKILL) right after a cycle leaves every heartbeat and
lag-state file readable: the old state or the new one, never a torn one. And on a full
disk the writer thread keeps the one-warning-per-episode rule.
"""

from __future__ import annotations

import asyncio
import json
import logging
import os
import signal
import subprocess
import sys
import textwrap
import time
from collections.abc import Callable
from pathlib import Path

import pytest

from gateway.live.bank.lag_state import EffectStates, WarmLags
from gateway.live.reference import TemperatureReference
from gateway.outputs.heartbeat import heartbeat_path, submit_heartbeat, write_heartbeat
from gateway.process.file_writer import HEARTBEATS, STATE, FileWriter
from tests.cli import ROOT
from tests.test_retention import fill, small_disk

MACHINES = 300
SENSORS = ("T1", "T2", "T3", "T4", "T5", "T6", "ambient")
RISES_C = {name: 0.5 + 0.1 * i for i, name in enumerate(SENSORS)}


def machines(state_dir: Path, writer: FileWriter | None) -> list[EffectStates]:
    return [
        EffectStates(
            [],
            state_dir / f"m{i:03d}-effect-state.json",
            warm=WarmLags(SENSORS, "ambient"),
            writer=writer,
        )
        for i in range(MACHINES)
    ]


async def longest_hold_s(cycle: Callable[[int], None]) -> float:
    """Run every machine's ``cycle(i)`` as a task (as the machine loops do) and return the
    longest time the event loop was held at a stretch meanwhile, as a probe task saw it."""
    holds: list[float] = []
    done = asyncio.Event()

    async def probe() -> None:
        while not done.is_set():
            before = time.perf_counter()
            await asyncio.sleep(0)
            holds.append(time.perf_counter() - before)

    async def machine(i: int) -> None:
        await asyncio.sleep(0)  # every machine is due at once, as at a start
        cycle(i)

    prober = asyncio.create_task(probe())
    await asyncio.sleep(0)
    await asyncio.gather(*(machine(i) for i in range(MACHINES)))
    done.set()
    await prober
    return max(holds)


def first_cycles(state_dir: Path, background: bool) -> float:
    """Two cycles of every machine (lag states saved at each, heartbeat at each, the cold
    reference taken and saved at the first); the event loop's longest hold in the first."""
    effects = machines(state_dir, STATE if background else None)
    references = [
        TemperatureReference(
            "first-reading",
            {},
            state_dir / f"m{i:03d}-reference.json",
            writer=STATE if background else None,
        )
        for i in range(MACHINES)
    ]

    def cycle(time_s: float) -> Callable[[int], None]:
        def one(i: int) -> None:
            references[i].observe({name: 20.0 + rise for name, rise in RISES_C.items()}, 0.0)
            effects[i].advance(time_s, RISES_C, 4000.0)
            if background:
                submit_heartbeat(state_dir, f"m{i:03d}", time_s, cycles=int(time_s))
            else:
                write_heartbeat(state_dir, f"m{i:03d}", time_s, cycles=int(time_s))

        return one

    async def body() -> float:
        held_s = await longest_hold_s(cycle(1.0))
        for states in effects:
            states.save_every_s = 0.0  # the second cycle saves again
        await longest_hold_s(cycle(2.0))
        await asyncio.wait_for(STATE.drain(), 60)
        await asyncio.wait_for(HEARTBEATS.drain(), 60)
        return held_s

    return asyncio.run(body())


#: Another process writing to the same disk, each block synced: every ``fsync`` of a
#: small file then waits behind it, as on a gateway whose disk is busy.
DISK_LOAD = textwrap.dedent(
    """
    import os, sys
    block = b"\\0" * (8 << 20)
    while True:
        with open(sys.argv[1], "wb") as out:
            out.write(block)
            out.flush()
            os.fsync(out.fileno())
    """
)


def test_first_cycles_do_not_hold_the_event_loop_for_the_disk(tmp_path: Path) -> None:
    load = subprocess.Popen([sys.executable, "-c", DISK_LOAD, str(tmp_path / "load.bin")])
    try:
        time.sleep(0.5)  # the first blocks are on their way
        on_loop_s = first_cycles(tmp_path / "on-loop", background=False)
        off_loop_s = first_cycles(tmp_path / "off-loop", background=True)
    finally:
        load.kill()
        load.wait()
    print(
        f"{MACHINES} first cycles: loop held {on_loop_s * 1e3:.0f} ms at a stretch with "
        f"the writes on it, {off_loop_s * 1e3:.0f} ms with the writer threads"
    )
    assert off_loop_s < on_loop_s / 3
    # Every file was written, with the newest state (the second cycle's).
    for i in range(MACHINES):
        saved = json.loads((tmp_path / "off-loop" / f"m{i:03d}-effect-state.json").read_text())
        assert saved["warm_lags"]["time_s"] == 2.0
        beat = json.loads(heartbeat_path(tmp_path / "off-loop", f"m{i:03d}").read_text())
        assert beat["time_s"] == 2.0 and beat["cycles"] == 2
        reference = json.loads((tmp_path / "off-loop" / f"m{i:03d}-reference.json").read_text())
        assert reference == {"reference_C": {n: 20.0 + r for n, r in RISES_C.items()},
                             "taken_turning": False}  # fmt: skip


#: A gateway's saving pattern at full speed: 40 machines, a lag-state save and a heartbeat
#: every cycle, cycles back to back; after each, a line: the cycle, the lag-state files
#: and the heartbeats written so far.
KILLED = textwrap.dedent(
    """
    import asyncio, sys
    from pathlib import Path
    from gateway.live.bank.lag_state import EffectStates, WarmLags
    from gateway.outputs.heartbeat import submit_heartbeat
    from gateway.process.file_writer import HEARTBEATS, STATE

    SENSORS = ("T1", "T2", "T3", "T4", "T5", "T6", "ambient")
    state_dir = Path(sys.argv[1])
    effects = [
        EffectStates([], state_dir / f"m{i:02d}-effect-state.json",
                     save_every_s=0.0, warm=WarmLags(SENSORS, "ambient"), writer=STATE)
        for i in range(40)
    ]

    async def main():
        cycle = 0
        while True:
            cycle += 1
            rises = {name: 0.01 * cycle for name in SENSORS}
            for i, states in enumerate(effects):
                states.advance(float(cycle), rises, 4000.0)
                submit_heartbeat(state_dir, f"m{i:02d}", float(cycle), cycles=cycle)
                await asyncio.sleep(0)
            print(cycle, STATE.written, HEARTBEATS.written, flush=True)

    asyncio.run(main())
    """
)


@pytest.mark.parametrize("cycles_before_kill", [1, 5, 40])
def test_a_kill_right_after_a_cycle_leaves_whole_state_files(
    tmp_path: Path, cycles_before_kill: int
) -> None:
    state_dir = tmp_path / "state"
    process = subprocess.Popen(
        [sys.executable, "-c", KILLED, str(state_dir)],
        cwd=ROOT,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        env={**os.environ, "PYTHONPATH": str(ROOT)},
    )
    try:
        assert process.stdout is not None
        deadline = time.monotonic() + 60
        for line in process.stdout:
            cycle, states_written, beats_written = map(int, line.split())
            written = states_written > 0 and beats_written > 0  # some file to look at
            if (cycle >= cycles_before_kill and written) or time.monotonic() > deadline:
                break
        process.send_signal(signal.SIGKILL)
        process.wait(timeout=10)
    finally:
        if process.poll() is None:
            process.kill()
            process.wait()
    assert process.returncode == -signal.SIGKILL, process.stderr.read() if process.stderr else ""
    states = sorted(state_dir.glob("*-effect-state.json"))
    beats = sorted(state_dir.glob("*-heartbeat.json"))
    assert states and beats
    for path in states:
        saved = json.loads(path.read_text(encoding="utf-8"))  # never torn
        assert saved["models"] == {} and saved["warm_lags"]["time_s"] >= 1.0
    for path in beats:
        assert json.loads(path.read_text(encoding="utf-8"))["cycles"] >= 1


def test_a_full_disk_gives_one_warning_per_episode_from_the_writer_thread(
    tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    writer = FileWriter("test-state-writer", durable=True)
    with small_disk(tmp_path / "disk", "1m") as disk:
        effects = [
            EffectStates(
                [],
                disk / f"m{i:02d}-effect-state.json",
                warm=WarmLags(SENSORS, None),
                writer=writer,
            )
            for i in range(20)
        ]

        def minutes(start_s: float, count: int) -> None:
            for minute in range(count):
                for states in effects:
                    states.advance(start_s + 60.0 * minute, RISES_C, 4000.0)
                assert writer.flush(30)

        filler = fill(disk)
        with caplog.at_level(logging.INFO, logger="gateway.live.bank.lag_state"):
            minutes(0.0, 5)
            filler.unlink()
            minutes(300.0, 2)
            assert all(states.state_file.exists() for states in effects)
        failed = [r for r in caplog.records if "cannot save the lag states" in r.message]
        assert len(failed) == 1, [r.message for r in failed][:5]
        assert "No space left on device" in failed[0].message
        assert len([r for r in caplog.records if "saved again" in r.message]) == 1
