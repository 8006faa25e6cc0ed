"""The interval and the training-span state over Sparkplug B, as a host sees them.

A real Mosquitto 2 (TLS, password file) on loopback, Eclipse Tahu's payload library
decoding every message (tests/node/sparkplug_host.mjs), three simulated machines over
Modbus TCP, the gateway on wall time. The DBIRTH declares the three metrics; the DDATA
(report by exception) carry every change, so the host's view rebuilt from the birth
and the data equals the cycle records, cycle by cycle. An open circuit on T1 widens
the interval while the sensor is held; the host sees the width return after it.
"""

from __future__ import annotations

import asyncio
from pathlib import Path
from typing import Any

import pytest

from simulator.faults import SensorFault
from tests import gateway_rig as rig
from tests.mqtt_broker import PASSWORD
from tests.test_sparkplug_host import Run, cycles_of

NAMES = ("Prediction/Interval", "Prediction/Training Span", "Prediction/Outside Inputs")
FAULT_S = 3.0


@pytest.fixture(scope="module")
def store(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return rig.fit_store(tmp_path_factory.mktemp("sparkplug-interval"))


def host_view(birth: dict[str, Any], data: list[dict[str, Any]]) -> dict[int, dict[str, Any]]:
    """By cycle: the three metrics as the host knows them after each DDATA (the birth's
    values, then every change the data carried)."""
    known = {m["name"]: m.get("value") for m in birth["metrics"] if m["name"] in NAMES}
    view: dict[int, dict[str, Any]] = {}
    for message in data:
        values = {m["name"]: m.get("value") for m in message["metrics"]}
        known.update({k: v for k, v in values.items() if k in NAMES})
        if "Health/cycles" in values:
            view[int(values["Health/cycles"])] = dict(known)
    return view


def test_births_declare_and_data_carry_the_interval(
    tmp_path: Path, store: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.setenv("SPB_TEST_PASSWORD", PASSWORD)

    async def scenario() -> tuple[Run, list[Any]]:
        async with Run(tmp_path, store, {}) as run:
            host = run.host
            await host.wait(lambda: len(cycles_of(host, "m1")) >= 10, 60, "10 DDATA of m1")
            plant = run.plants[0]
            now = plant.clock.now()
            plant.machine.add_fault(SensorFault("T1", "open_circuit", now, now + FAULT_S))
            m1 = [r for r in run.records if r.machine == "m1"]
            start = len(m1)

            def recovered() -> bool:
                after = [r for r in run.records if r.machine == "m1"][start:]
                flagged = [k for k, r in enumerate(after) if r.quality["T1"] == "bad"]
                return bool(flagged) and len(after) > flagged[-1] + 10

            await host.wait(recovered, 120, "T1 flagged bad, then 10 good cycles")
            await run.stop_gateway()
            records = [r for r in run.records if r.machine == "m1"]
        return run, records

    run, records = asyncio.run(scenario())
    births = run.host.messages("DBIRTH", "m1")
    assert len(births) == 1
    declared = {m["name"]: m for m in births[0]["metrics"]}
    assert declared["Prediction/Interval"]["type"] == "Double"
    assert declared["Prediction/Interval"].get("unit") == "µm"
    assert declared["Prediction/Training Span"]["type"] == "String"
    assert declared["Prediction/Outside Inputs"]["type"] == "String"

    view = host_view(births[0], run.host.messages("DDATA", "m1"))
    assert len(view) >= 20
    for cycle, seen in view.items():
        record = records[cycle - 1]
        assert seen["Prediction/Interval"] == record.interval_um, (cycle, seen, record)
        assert seen["Prediction/Training Span"] == record.training_span, (cycle, seen)
        assert seen["Prediction/Outside Inputs"] == ",".join(record.outside_inputs)

    trace = [(c, r.model_id, r.interval_um, r.quality["T1"]) for c, r in enumerate(records, 1)]
    trace = [(c, None if w is None else round(w, 3), q) for c, _, w, q in trace if c > 8]
    # from the fault on (the first cycles wait for their first readings)
    held = [c for c in view if c > 10 and records[c - 1].quality["T1"] == "bad"]
    assert held, trace
    before = [view[c]["Prediction/Interval"] for c in sorted(view) if c < min(held)]
    assert before and before[-1] is not None and before[-1] > 0, trace
    during = [view[c]["Prediction/Interval"] for c in held]
    assert max(w for w in during if w is not None) > 1.4 * before[-1], trace
    after = [c for c in view if c > max(held)]
    assert after and view[max(after)]["Prediction/Interval"] == before[-1], trace
