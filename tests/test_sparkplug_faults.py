"""Faults on the Sparkplug path, seen by the independent Tahu host, in one run: the broker
killed (SIGKILL) and restarted, then the primary host offline (its STATE) for ten minutes
of machine time at the production cycle (1 s): 600 cycles held back per machine.

The gateway runs on the simulator's accelerated clock (machine time ``SPEEDUP`` × the
wall, as the demo runs), so ten machine minutes take 40 s. The node's buffer, births and
delivery run on wall time and count points, not minutes; the points carry machine-time
stamps. Every cycle's point must arrive once, in order (by its cycle counter and its
timestamp), those held back marked historical, and every cycle must have run on its due
time (the scheduler's own ``due_s`` of each cycle).
"""

from __future__ import annotations

import asyncio
import itertools
import statistics
from pathlib import Path

import pytest

from tests.mqtt_broker import PASSWORD
from tests.test_sparkplug_host import (
    MACHINES,
    Run,
    assert_every_cycle_once_in_order,
    cycles_of,
    store,  # noqa: F401 - the module's fixture
)

CYCLE_S = 1.0  # machine time, the production cycle
SPEEDUP = 15.0
OUTAGE_CYCLES = 600  # ten minutes of machine time
BROKER_DOWN_S = 3.0  # wall: 45 cycles per machine


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


def assert_on_the_grid(run: Run) -> dict[str, float]:
    """Every cycle ran on its due time: the due times step by exactly one cycle (none was
    skipped by an overrun) and none started a cycle late. Returns the lateness figures."""
    late = [s for m in MACHINES for s in run.late_s[m]]
    for machine in MACHINES:
        steps = {round(b - a, 6) for a, b in itertools.pairwise(run.due_s[machine])}
        assert steps == {CYCLE_S}, (machine, sorted(steps)[:3], sorted(steps)[-3:])
        assert max(run.late_s[machine]) < CYCLE_S, (machine, max(run.late_s[machine]))
    return {
        "p50_s": statistics.median(late),
        "p99_s": statistics.quantiles(late, n=100)[98],
        "max_s": max(late),
    }


async def broker_restart(run: Run) -> None:
    host = run.host
    await asyncio.to_thread(run.broker.kill)  # off the loop the gateway runs on
    await asyncio.sleep(BROKER_DOWN_S)
    await asyncio.to_thread(run.broker.start)
    await host.wait(lambda: len(host.messages("NBIRTH")) == 2, 30, "births after restart")
    ran = cycles_ran(run)
    await host.wait(
        lambda: all(cycles_of(host, m)[-1] >= ran[m] + 3 for m in MACHINES),
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
    await host.wait(lambda: len(host.messages("NBIRTH")) == 3, 30, "births after outage")
    await host.wait(
        lambda: all(cycles_of(host, m)[-1] >= online[m] for m in MACHINES), 60, "the backlog"
    )
    return offline, online


def test_broker_restart_and_ten_minute_host_outage_lose_and_repeat_nothing(
    tmp_path: Path,
    store: Path,  # noqa: F811
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    monkeypatch.setenv("SPB_TEST_PASSWORD", PASSWORD)

    async def scenario() -> tuple[Run, dict[str, int], dict[str, int]]:
        async with Run(tmp_path, store, {}, cycle_s=CYCLE_S, speedup=SPEEDUP) as run:
            host = run.host
            await host.wait(
                lambda: all(len(cycles_of(host, m)) >= 5 for m in MACHINES), 60, "5 DDATA each"
            )
            await broker_restart(run)
            offline, online = await host_outage(run)
            await run.stop_gateway()
        return run, offline, online

    run, offline, online = asyncio.run(scenario())
    events = run.host.snapshot()
    assert not [e for e in events if e["event"] == "undecodable"]
    assert not [e for e in events if e["event"] == "message" and e["gap"]]
    assert_every_cycle_once_in_order(run.host, run.records)
    for machine in MACHINES:
        held = set(range(offline[machine] + 1, online[machine] + 1))
        assert len(held) >= OUTAGE_CYCLES
        missing = held - historical_cycles(run, machine)
        assert not missing, (machine, len(missing), min(missing))
        stamps = timestamps_of(run, machine)  # each cycle's machine time, in order
        assert all(b > a for a, b in itertools.pairwise(stamps)), machine
    lateness = assert_on_the_grid(run)
    print(f"cycles ran {cycles_ran(run)}; lateness (machine s) {lateness}")
