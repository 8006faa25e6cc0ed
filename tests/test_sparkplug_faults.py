"""Faults on the Sparkplug path, seen by the independent Tahu host: the broker killed
(SIGKILL) and restarted mid-run, then the primary host offline (its STATE) for
``OUTAGE_S``. Every cycle's point must arrive once, in order, those held during the
outage marked historical, and every cycle must have run on time.

``OUTAGE_S`` is 20 s at a 0.2 s cycle (100 cycles per machine held back); the
buffer and the delivery do not depend on the outage's length, only its point count.
"""

from __future__ import annotations

import asyncio
from pathlib import Path

import pytest

from tests.mqtt_broker import PASSWORD
from tests.test_sparkplug_host import (
    CYCLE_S,
    MACHINES,
    Run,
    assert_every_cycle_once_in_order,
    assert_on_time,
    cycles_of,
    store,  # noqa: F401 - the module's fixture
)

OUTAGE_S = 20.0
BROKER_DOWN_S = 3.0


def historical_cycles(run: Run, device: str) -> list[int]:
    return [
        m["value"]
        for e in run.host.messages("DDATA", device)
        for m in e["metrics"]
        if m["name"] == "Health/cycles" and m["historical"]
    ]


def test_broker_restart_and_host_outage_lose_and_repeat_nothing(
    tmp_path: Path,
    store: Path,  # noqa: F811
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    monkeypatch.setenv("SPB_TEST_PASSWORD", PASSWORD)

    async def scenario() -> Run:
        async with Run(tmp_path, store, {}) as run:
            host = run.host
            await host.wait(
                lambda: all(len(cycles_of(host, m)) >= 5 for m in MACHINES), 60, "5 DDATA each"
            )
            await asyncio.to_thread(run.broker.kill)  # off the loop the gateway runs on
            await asyncio.sleep(BROKER_DOWN_S)
            await asyncio.to_thread(run.broker.start)
            await host.wait(lambda: len(host.messages("NBIRTH")) == 2, 30, "births after restart")
            ran = len(run.records)
            await host.wait(
                lambda: all(cycles_of(host, m)[-1] >= ran // 3 + 3 for m in MACHINES),
                30,
                "data after the restart",
            )
            host.send(op="state", online=False)
            await asyncio.sleep(OUTAGE_S)
            held = len([r for r in run.records if r.machine == "m1"])
            host.send(op="state", online=True)
            await host.wait(lambda: len(host.messages("NBIRTH")) == 3, 30, "births after outage")
            await host.wait(
                lambda: all(cycles_of(host, m)[-1] >= held for m in MACHINES), 60, "the backlog"
            )
            await run.stop_gateway()
        return run

    run = asyncio.run(scenario())
    events = run.host.snapshot()
    assert not [e for e in events if e["event"] == "undecodable"]
    assert not [e for e in events if e["event"] == "message" and e["gap"]]
    assert_every_cycle_once_in_order(run.host, run.records)
    assert_on_time(run.records)
    for machine in MACHINES:
        historical = historical_cycles(run, machine)
        assert len(historical) >= 0.8 * OUTAGE_S / CYCLE_S, (machine, len(historical))
