"""Health counters are assembled once (gateway.outputs.health) and every reader takes
its view from there: SCADA's Health nodes, the heartbeat, the console, Sparkplug.

The protocol-level checks (the same numbers over OPC UA and in the heartbeat file)
are in tests/test_supervision.py; here the assembly itself, on a supervised task
that really failed and restarted.
"""

from __future__ import annotations

import asyncio
from types import SimpleNamespace

from drivers.backoff import Backoff
from gateway.outputs.health import (
    forwarder_counters,
    integer_counters,
    machine_health,
    scalar_counters,
)
from gateway.process.supervision import Supervised
from gateway.scada.server import HEALTH_COUNTERS
from gateway.sparkplug.metrics import health_counters


def loop_with_counters() -> SimpleNamespace:
    return SimpleNamespace(
        failed_writes=2,
        external_changes=1,
        link_errors=7,
        sink_failures={"log": 3, "scada": 1},
        cycles=40,
        compensation_enabled=True,
        promotions=SimpleNamespace(swaps=1, refused=0),
    )


def restarted_once() -> Supervised:
    """A supervisor whose task raised once, then returned."""
    calls = []

    async def task(stop: asyncio.Event) -> None:
        calls.append(1)
        if len(calls) == 1:
            raise RuntimeError("a fault injected into the task")

    supervisor = Supervised("m1 loop", task, backoff=Backoff(initial_s=0.01, max_s=0.01))
    asyncio.run(supervisor.supervise(asyncio.Event()))
    return supervisor


def test_every_scada_health_node_has_its_counter_from_the_one_assembly() -> None:
    health = machine_health(loop_with_counters(), restarted_once(), None)
    assert set(HEALTH_COUNTERS) <= set(health), set(HEALTH_COUNTERS) - set(health)
    assert health["loop_restarts"] == 1
    assert "a fault injected" in str(health["last_loop_error"])
    assert health["sink_failures"] == 4
    assert health["sink_failures_by_sink"] == {"log": 3, "scada": 1}
    assert health["link_errors_total"] == 7
    assert {k: health[k] for k in forwarder_counters(None)} == forwarder_counters(None)


def test_each_reader_takes_its_view_of_the_same_counters() -> None:
    health = machine_health(loop_with_counters(), restarted_once(), None)
    scada = scalar_counters(health)
    assert scada["compensation_enabled"] is True and "sink_failures_by_sink" not in scada
    counters = integer_counters(health)
    assert "compensation_enabled" not in counters and "last_loop_error" not in counters
    assert counters["cycles"] == 40 and counters["loop_restarts"] == 1
    # Sparkplug's Health/… metrics are exactly the console's counters, by name.
    assert health_counters(health) == dict(sorted(counters.items()))
    assert all(scada[k] == v for k, v in counters.items())
