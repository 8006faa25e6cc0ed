"""The interval and the training-span state in every output that reads the cycle record:
SCADA (read by an independent node-opcua client over SignAndEncrypt), the time-series
points, the Sparkplug metrics, the console's overview row and its machine page."""

from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np
import pytest

from gateway.outputs.local_store import LocalStore
from gateway.outputs.points import points_from_record
from gateway.scada.server import ScadaServer
from gateway.sparkplug.metrics import device_specs, snapshot
from gateway.web.live import LiveBoard
from gateway.web.plots import machine_svg
from gateway.web.series import machine_view
from tests.test_scada import (
    HEALTH,
    MACHINE,
    VIEWER,
    known_record,
    node_client,
    node_pki,
    run_with_server,
    settings,
)
from tests.test_timeseries import EPOCH_S, make_records

__all__ = ["node_pki"]  # the fixture, shared with test_scada


def outside_record():
    return dataclasses.replace(
        known_record(), interval_um=0.7, training_span="outside", outside_inputs=["speed", "T5"]
    )


def test_scada_serves_the_interval_and_the_span_state(tmp_path: Path, node_pki: Path) -> None:
    replies: list[dict] = []
    names = ("IntervalUm", "TrainingSpan", "OutsideInputs")

    async def scenario(server: ScadaServer, calls: list) -> None:
        ops = [{"read": f"{MACHINE}.{n}"} for n in names]
        await server.publish(outside_record(), HEALTH)
        replies.append((await node_client(server, ops, node_pki, user=VIEWER))[1])
        await server.publish(known_record(), HEALTH)  # a model without a calibration
        replies.append((await node_client(server, ops, node_pki, user=VIEWER))[1])

    run_with_server(settings(tmp_path / "pki"), scenario)
    outside = {r["nodeId"].split(".", 1)[1]: r for r in replies[0]["results"]}
    assert (outside["IntervalUm"]["status"], outside["IntervalUm"]["value"]) == ("Good", 0.7)
    assert outside["TrainingSpan"]["value"] == "outside"
    assert outside["OutsideInputs"]["value"] == "speed,T5"
    unknown = {r["nodeId"].split(".", 1)[1]: r for r in replies[1]["results"]}
    assert unknown["IntervalUm"]["status"] != "Good"
    assert unknown["OutsideInputs"]["value"] == ""


def test_points_carry_the_interval_only_when_known() -> None:
    cycle = points_from_record(outside_record())[0]
    assert cycle.fields["interval_um"] == 0.7
    assert cycle.fields["training_span"] == "outside"
    assert cycle.fields["outside_inputs"] == "speed,T5"
    plain = points_from_record(known_record())[0]
    assert not {"interval_um", "training_span", "outside_inputs"} & set(plain.fields)


def test_sparkplug_metrics_carry_the_interval() -> None:
    sensors = list(known_record().temperatures_C)
    names = {spec.name for spec in device_specs(0, sensors, ["cycles"])}
    assert {"Prediction/Interval", "Prediction/Training Span"} <= names
    values = snapshot(outside_record(), HEALTH)
    assert values["Prediction/Interval"] == 0.7
    assert values["Prediction/Training Span"] == "outside"
    assert values["Prediction/Outside Inputs"] == "speed,T5"
    assert set(values) <= names | {f"Health/{k}" for k in HEALTH}


def test_console_row_carries_the_interval() -> None:
    rows = LiveBoard([MACHINE], lambda m: {"cycles": 1})
    rows.record(outside_record())
    row = rows.row(MACHINE)
    assert (row["interval_um"], row["training_span"]) == (0.7, "outside")
    assert row["outside_inputs"] == ["speed", "T5"]


def test_machine_page_draws_the_interval_around_predicted(tmp_path: Path) -> None:
    """Logged to the local store as the gateway logs, read back and drawn."""
    records = make_records("m1", 600, sensors=("T1",))
    for i, rec in enumerate(records):
        rec.interval_um = None if i < 100 else 0.5 + i / 1000
    path = tmp_path / "points.sqlite"
    with LocalStore(path) as local:
        local.write([p for rec in records for p in points_from_record(rec, EPOCH_S)])
    view = machine_view(("local", str(path)), "m1", EPOCH_S, EPOCH_S + 600, 1000.0, 60)
    t_hi, high = view.lines["interval_high_um"]
    _, low = view.lines["interval_low_um"]
    expected = [r.predicted_um + r.interval_um for r in records if r.interval_um is not None]
    assert np.nanmax(high) == pytest.approx(max(expected))
    assert np.isnan(high[t_hi < EPOCH_S + 100]).all()  # unknown before: no band
    assert np.nanmin(low) < np.nanmin(high)
    assert "90 % interval" in machine_svg(view, "m1")
    plain = make_records("m1", 100, sensors=("T1",))  # no interval logged: no band drawn
    other = tmp_path / "plain.sqlite"
    with LocalStore(other) as local:
        local.write([p for rec in plain for p in points_from_record(rec, EPOCH_S)])
    view = machine_view(("local", str(other)), "m1", EPOCH_S, EPOCH_S + 100, 1000.0, 60)
    assert "90 % interval" not in machine_svg(view, "m1")
