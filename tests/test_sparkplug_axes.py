"""A multi-axis machine as a Sparkplug device: ``Axes/<A>/…`` metrics, read by a host
nobody here wrote.

A real Mosquitto 2 (TLS, password file) on loopback and Eclipse Tahu's JavaScript
payload library in tests/node/sparkplug_host.mjs decoding every message; the edge node
is the gateway's own, fed cycle records of a 3-axis machine and a single-axis one. The
3-axis machine's DBIRTH declares each axis's metrics with their types and units, and its
DDATA carry each axis's values; the single-axis machine's metrics are those of before.
"""

from __future__ import annotations

import asyncio
from pathlib import Path
from typing import Any

from gateway.outputs.disk_buffer import PointBuffer
from gateway.sparkplug.commands import Actions, Allowed, CommandHandler
from gateway.sparkplug.metrics import AXIS_LEAVES, device_specs
from gateway.sparkplug.mqtt import MqttSettings
from gateway.sparkplug.node import EdgeNode, NodeSettings
from tests.mqtt_broker import PASSWORD, USER, mosquitto
from tests.records import axes_record, written_record
from tests.sparkplug_host import TahuHost

GROUP, NODE, HOST = "plant1", "edge1", "scada"
MULTI, SINGLE = "vmc-3", "vmc-1"
AXES = ("Z", "X", "Y")
HEALTH_KEYS = ("cycles", "failed_writes")


def cycle(n: int) -> Any:
    """Cycle ``n`` of the 3-axis machine: Z applies n µm, X −n/2, Y n + 0.25."""
    record = axes_record(
        MULTI, float(n), {"T1": 30.0 + n}, {"Z": float(n), "X": -n / 2, "Y": n + 0.25}
    )
    record.axes["Y"].write_status = "held: slew"
    record.axes["X"].outside_inputs = ["T1", "speed_rpm"]
    return record


def metrics_of(message: dict[str, Any]) -> dict[str, dict[str, Any]]:
    return {m["name"]: m for m in message["metrics"]}


def test_three_axis_device_births_and_data_carry_every_axis(tmp_path: Path) -> None:
    health = {"cycles": 0, "failed_writes": 0}

    async def scenario() -> TahuHost:
        with mosquitto(tmp_path / "broker") as broker:
            host = TahuHost(broker, GROUP, HOST)
            await host.wait(
                lambda: any(e["event"] == "online" for e in host.snapshot()), 20, "host STATE"
            )
            settings = NodeSettings(
                GROUP,
                NODE,
                HOST,
                {MULTI: ("T1",), SINGLE: ("T1",)},
                HEALTH_KEYS,
                tmp_path / "state",
                startup_delay_max_s=0.0,
                axes={MULTI: AXES},
            )
            settings.state_dir.mkdir()
            mqtt = MqttSettings((broker.url,), "edge1-test", USER, PASSWORD, broker.ca_file)
            actions = Actions(lambda m, on: None, lambda m, p: "", lambda m: "", lambda: None)
            buffer = PointBuffer(tmp_path / "spb.sqlite", 1000)
            node = EdgeNode(
                settings, mqtt, buffer, CommandHandler(Allowed(), actions), lambda m: health
            )
            node.sink(cycle(1))
            node.sink(written_record(SINGLE, 1.0, {"T1": 25.0}, 2.0))
            stop = asyncio.Event()
            task = asyncio.create_task(node.run(stop))
            try:
                await host.wait(lambda: host.count("DBIRTH") == 2, 30, "two DBIRTHs")
                for n in (2, 3):
                    health["cycles"] = n
                    node.sink(cycle(n))
                await host.wait(lambda: host.count("DDATA", MULTI) >= 3, 30, "DDATA of 3 cycles")
            finally:
                stop.set()
                await asyncio.wait_for(task, 20)
                buffer.close()
            host.close()
            return host

    host = asyncio.run(scenario())
    assert not [e for e in host.snapshot() if e["event"] == "undecodable"]
    birth = metrics_of(host.messages("DBIRTH", MULTI)[0])
    for axis in AXES:
        for leaf, _, unit, _ in AXIS_LEAVES:
            name = f"Axes/{axis}/{leaf}"
            assert name in birth, name
            assert birth[name].get("unit") == (unit or None), name
    assert birth["Axes/Z/Prediction"]["type"] == "Double"
    assert birth["Axes/X/Model"]["type"] == "String"
    assert birth["Axes/Y/Compensation/Write Status"]["type"] == "String"
    assert birth["Axes/X/Compensation/Applied"]["value"] == -0.5  # cycle 1
    # today's metrics keep the first axis's values, and the aliases a single axis has
    assert birth["Compensation/Applied"]["value"] == 1.0 and birth["Model"]["value"] == (
        "lag-ridge-Z"
    )
    single = metrics_of(host.messages("DBIRTH", SINGLE)[0])
    assert not [n for n in single if n.startswith("Axes/")]
    one_axis = {s.name: s.alias for s in device_specs(0, ("T1",), HEALTH_KEYS)}
    assert {n: birth[n]["alias"] for n in one_axis} == one_axis
    # DDATA: each axis's changed values, by alias, named from the birth by the host
    last: dict[str, Any] = {}
    for message in host.messages("DDATA", MULTI):
        last.update({m["name"]: m for m in message["metrics"]})
    assert last["Axes/Z/Compensation/Applied"]["value"] == 3.0
    assert last["Axes/X/Compensation/Applied"]["value"] == -1.5
    assert last["Axes/Y/Compensation/Applied"]["value"] == 3.25
    assert last["Axes/Y/Prediction"]["value"] == 3.25
    assert last["Axes/Z/Compensation/Applied"]["type"] == "Double"
    assert birth["Axes/Y/Compensation/Write Status"]["value"] == "held: slew"
    assert birth["Axes/X/Prediction/Outside Inputs"]["value"] == "T1,speed_rpm"
    assert birth["Axes/Y/Prediction/Interval"]["value"] == 2.0
    assert last["Compensation/Applied"]["value"] == 3.0
