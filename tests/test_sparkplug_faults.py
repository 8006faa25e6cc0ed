"""Faults on the Sparkplug path, seen by the independent Tahu host, in one run: the broker
killed (SIGKILL) and restarted, then the primary host offline (its STATE) for ten minutes
of machine time at the production cycle (1 s): 600 cycles held back per machine.

The gateway runs on the simulator's accelerated clock (machine time ``SPEEDUP`` × the
wall, as the demo runs), so ten machine minutes take 60 s. The node's buffer, births and
delivery run on wall time and count points, not minutes; the points carry machine-time
stamps. Every cycle's point must arrive once, in order (by its cycle counter and its
timestamp), those held back marked historical, and every cycle must have run on its due
time (the scheduler's own ``due_s`` of each cycle, judged at production speed).
The node runs at QoS 1 (``sparkplug.qos: 1``, the broker acknowledges every point):
at Sparkplug's QoS 0 a broker killed mid-run loses the points in flight.

bdSeq counts the MQTT CONNECTs that went out (Sparkplug 3.0): the attempts refused at
TCP while the broker is down send none, so the NBIRTH after the restart carries the
previous bdSeq + 1; the host's offline STATE ends the session (NDEATH, disconnect), so
the NBIRTH after the outage carries one more.
"""

from __future__ import annotations

import asyncio
import itertools
import shutil
import statistics
import tempfile
from collections.abc import Iterator
from pathlib import Path

import pytest

from tests.mqtt_broker import PASSWORD
from tests.test_sparkplug_host import (
    MACHINES,
    Run,
    assert_every_cycle_once_in_order,
    bd_seq_of,
    logged,
    store,  # noqa: F401 - the module's fixture
)

CYCLE_S = 1.0  # machine time, the production cycle
SPEEDUP = 10.0
OUTAGE_CYCLES = 600  # ten minutes of machine time
BROKER_DOWN_S = 3.0  # wall: 30 cycles per machine


def historical_cycles(run: Run, device: str) -> set[int]:
    return {
        m["value"]
        for e in run.host.messages("DDATA", device)
        for m in e["metrics"]
        if m["name"] == "Health/cycles" and m["historical"]
    }


def timestamps_of(run: Run, device: str) -> list[int]:
    return [e["timestamp"] for e in run.host.messages("DDATA", device)]


def cycles_ran(run: Run) -> dict[str, int]:
    return {m: run.gateway._loop_of(m).cycles for m in MACHINES}


def assert_on_time(run: Run) -> dict[str, float]:
    """Every cycle ran on time, judged at production speed from the scheduler's own due
    times: on the accelerated clock a wall stall of the event loop (a loaded box) costs
    ``SPEEDUP`` × its length in machine time, so lateness and the gaps between due times
    are brought back to wall seconds, what they cost a 1 s production cycle. No cycle
    started a whole cycle late, and no gap between due times exceeded the cycle by a
    whole cycle (so at 1 s none was skipped). Returns the figures."""
    late_s = [s / SPEEDUP for m in MACHINES for s in run.late_s[m]]
    stalls_s = [
        (b - a - CYCLE_S) / SPEEDUP for m in MACHINES for a, b in itertools.pairwise(run.due_s[m])
    ]
    assert max(late_s) < CYCLE_S, max(late_s)
    assert max(stalls_s) < CYCLE_S, max(stalls_s)
    slots = {m: (run.due_s[m][-1] - run.due_s[m][0]) / CYCLE_S + 1 for m in MACHINES}
    return {
        "late_p50_wall_s": statistics.median(late_s),
        "late_p99_wall_s": statistics.quantiles(late_s, n=100)[98],
        "longest_stall_wall_s": max(stalls_s),
        "machine_time_slots_run": min(len(run.due_s[m]) / slots[m] for m in MACHINES),
    }


async def broker_restart(run: Run, caplog: pytest.LogCaptureFixture) -> None:
    host = run.host
    await asyncio.to_thread(run.broker.kill)  # off the loop the gateway runs on
    await asyncio.sleep(BROKER_DOWN_S)
    refused = logged(caplog, "Sparkplug: cannot connect to")
    assert len(refused) >= 2, refused  # attempts without a CONNECT: no bdSeq used
    await asyncio.to_thread(run.broker.start)
    await host.wait(lambda: host.count("NBIRTH") == 2, 30, "births after restart")
    ran = cycles_ran(run)
    await host.wait(
        lambda: all(host.last_cycle(m) >= ran[m] + 3 for m in MACHINES),
        30,
        "data after the restart",
    )


async def host_outage(run: Run) -> tuple[dict[str, int], dict[str, int]]:
    """The primary host offline for ``OUTAGE_CYCLES`` cycles of every machine, from the
    moment the node saw it go; the cycles ran before and at its return."""
    host, node = run.host, run.gateway.sparkplug
    assert node is not None
    host.send(op="state", online=False)
    await host.wait(lambda: not node.host_online, 10, "the node seeing the host offline")
    offline = cycles_ran(run)
    await host.wait(
        lambda: all(n >= offline[m] + OUTAGE_CYCLES for m, n in cycles_ran(run).items()),
        2 * OUTAGE_CYCLES * CYCLE_S / SPEEDUP + 30,
        "ten minutes of machine time",
    )
    online = cycles_ran(run)
    host.send(op="state", online=True)
    await host.wait(lambda: host.count("NBIRTH") == 3, 30, "births after outage")
    await host.wait(
        lambda: all(host.last_cycle(m) >= online[m] for m in MACHINES), 60, "the backlog"
    )
    return offline, online


@pytest.fixture
def memory_dir() -> Iterator[Path]:
    """State (heartbeats, references) and the logged points in memory: the accelerated
    clock writes them ``SPEEDUP`` × as often as production, and a shared disk's fsync
    stalls (0.1-2.5 s seen on the loaded test box) would be charged to the loops
    ``SPEEDUP`` × over. The Sparkplug buffer, what this test is about, stays on disk."""
    folder = Path(tempfile.mkdtemp(dir="/dev/shm" if Path("/dev/shm").is_dir() else None))
    yield folder
    shutil.rmtree(folder, ignore_errors=True)


def test_broker_restart_and_ten_minute_host_outage_lose_and_repeat_nothing(
    tmp_path: Path,
    memory_dir: Path,
    store: Path,  # noqa: F811
    monkeypatch: pytest.MonkeyPatch,
    caplog: pytest.LogCaptureFixture,
) -> None:
    monkeypatch.setenv("SPB_TEST_PASSWORD", PASSWORD)

    async def scenario() -> tuple[Run, dict[str, int], dict[str, int]]:
        accelerated = {"cycle_s": CYCLE_S, "speedup": SPEEDUP, "state_dir": memory_dir, "qos": 1}
        async with Run(tmp_path, store, {}, **accelerated) as run:  # type: ignore[arg-type]
            host = run.host
            await host.wait(
                lambda: all(host.count("DDATA", m) >= 5 for m in MACHINES), 60, "5 DDATA each"
            )
            await broker_restart(run, caplog)
            offline, online = await host_outage(run)
            await run.stop_gateway()
        return run, offline, online

    run, offline, online = asyncio.run(scenario())
    events = run.host.snapshot()
    assert not [e for e in events if e["event"] == "undecodable"]
    assert not [e for e in events if e["event"] == "message" and e["gap"]]
    assert_every_cycle_once_in_order(run.host, run.records)
    births = [bd_seq_of(e) for e in run.host.messages("NBIRTH")]
    first = births[0]
    assert births == [first, (first + 1) % 256, (first + 2) % 256], births
    for machine in MACHINES:
        held = set(range(offline[machine] + 1, online[machine] + 1))
        assert len(held) >= OUTAGE_CYCLES
        missing = held - historical_cycles(run, machine)
        assert not missing, (machine, len(missing), min(missing))
        stamps = timestamps_of(run, machine)  # each cycle's machine time, in order
        assert all(b > a for a, b in itertools.pairwise(stamps)), machine
    lateness = assert_on_time(run)
    print(f"cycles ran {cycles_ran(run)}; lateness {lateness}")
