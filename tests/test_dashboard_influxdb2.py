"""The shipped Grafana dashboard, checked without Grafana against the tested InfluxDB 2.

A gateway compensates a simulated machine (Modbus TCP transmitters and CNC on
loopback, its probe cycle writing macro #600) and logs through the disk buffer to
InfluxDB 2.7.12 with a write token of one bucket, as deploy/docker-compose.yml runs
it. Then every query of deploy/grafana/dashboards/*.json — the panels' and the
template variables' — is sent the way Grafana's Flux datasource sends it (dashboard
variables replaced by the frontend, then ``v.timeRangeStart``/``v.timeRangeStop``
as RFC 3339 times and ``v.windowPeriod`` as a Go duration, replaced as text by the
backend) with a read-only token. Each must return data, and each measurement,
field and tag a query names must be one the gateway wrote: a renamed field turns
a panel blank in Grafana without any error, so the names are checked as well.
"""

from __future__ import annotations

import asyncio
import json
import re
import time
from collections.abc import Iterator
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

import pytest
from influxdb_client import InfluxDBClient

from drivers.clock import AcceleratedClock
from gateway.config import GatewayConfig
from gateway.wiring import Gateway
from tests import gateway_rig as rig
from tests.influx_server import InfluxServer

REPO = Path(__file__).resolve().parents[1]
DASHBOARDS = sorted((REPO / "deploy" / "grafana" / "dashboards").glob("*.json"))
SPEEDUP = 60.0  # machine seconds per real second
CYCLE_S = 5.0  # machine time
PROBE_MACRO = 600  # the simulator's probe cycle (simulator/machine.yaml), every 300 s
MACHINE = "vmc-1"
WINDOW_PERIOD_S = 60  # what Grafana would pick for ~1000 px over the run
RUN_S = 16.0  # real seconds the gateway runs: ~16 machine minutes, three probe cycles


def go_duration(seconds: int) -> str:
    """Go's time.Duration.String(), which Grafana puts in for v.windowPeriod: 1m0s, 10s."""
    hours, rest = divmod(seconds, 3600)
    minutes, secs = divmod(rest, 60)
    if hours:
        return f"{hours}h{minutes}m{secs}s"
    return f"{minutes}m{secs}s" if minutes else f"{secs}s"


def rfc3339(unix_s: float) -> str:
    return datetime.fromtimestamp(unix_s, UTC).strftime("%Y-%m-%dT%H:%M:%SZ")


def grafana_query(text: str, variables: dict[str, str], start_s: float, stop_s: float) -> str:
    """The Flux Grafana sends: ${var}/$var by the frontend, then its v.* macros."""
    for name, value in variables.items():
        text = text.replace("${" + name + "}", value).replace("$" + name, value)
    text = text.replace("v.timeRangeStart", rfc3339(start_s))
    text = text.replace("v.timeRangeStop", rfc3339(stop_s))
    return text.replace("v.windowPeriod", go_duration(WINDOW_PERIOD_S))


def dashboard_queries() -> Iterator[tuple[str, str]]:
    """(where, query) for every panel target and query variable of every dashboard."""
    for path in DASHBOARDS:
        doc = json.loads(path.read_text(encoding="utf-8"))
        for panel in doc.get("panels", []):
            for target in panel.get("targets", []):
                yield f"{path.name}: panel '{panel['title']}'", target["query"]
        for variable in doc.get("templating", {}).get("list", []):
            if variable.get("type") == "query":
                query = variable["query"]
                query = query["query"] if isinstance(query, dict) else query
                yield f"{path.name}: variable '{variable['name']}'", query


def names_in(query: str) -> dict[str, set[str]]:
    """The measurements, fields and columns (tags) a Flux query names."""
    columns = set(re.findall(r"\br\.(\w+)", query))
    columns |= set(re.findall(r'r\["(\w+)"\]', query))
    for listed in re.findall(r"columns:\s*\[([^\]]*)\]", query):
        columns |= set(re.findall(r'"(\w+)"', listed))
    columns |= set(re.findall(r'column:\s*"(\w+)"', query))
    return {
        "measurements": set(re.findall(r'r\._measurement\s*==\s*"([^"]+)"', query)),
        "fields": set(re.findall(r'r\._field\s*==\s*"([^"]+)"', query)),
        "tags": {c for c in columns if not c.startswith("_") and c not in ("result", "table")},
    }


def written_schema(client: InfluxDBClient, bucket: str) -> dict[str, dict[str, set[str]]]:
    """measurement → {"fields": …, "tags": …} as InfluxDB holds them after the run."""
    query = client.query_api()

    def values(flux: str) -> set[str]:
        return {str(r.get_value()) for t in query.query(flux) for r in t.records}

    schema = {}
    head = 'import "influxdata/influxdb/schema"\n'
    for measurement in values(head + f'schema.measurements(bucket: "{bucket}", start: 0)'):
        where = f'bucket: "{bucket}", measurement: "{measurement}", start: 0'
        schema[measurement] = {
            "fields": values(head + f"schema.measurementFieldKeys({where})"),
            "tags": values(head + f"schema.measurementTagKeys({where})") - {"_field", "_start"},
        }
    return schema


@pytest.fixture(scope="module")
def store(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return rig.fit_store(tmp_path_factory.mktemp("dashboard"))


def run_gateway(tmp_path: Path, server: InfluxServer, bucket: str, token: str, store: Path):
    """A gateway compensating one simulated machine for ~16 s (~16 machine minutes)."""
    token_file = tmp_path / "influx.token"
    token_file.write_text(token, encoding="utf-8")

    async def scenario() -> tuple[float, float, int]:
        # The run ends ~9 machine minutes before the real now: the points are in the past,
        # where a real gateway's are (the machine variable looks back from now()).
        clock = AcceleratedClock(SPEEDUP, origin_s=time.time() - RUN_S * SPEEDUP - 540)
        served = rig.plant(clock, program="iso230-spectrum", seed=3, cnc=("modbus",))
        await served.start()
        entry = rig.machine_entry(MACHINE, served, store, cycle_s=CYCLE_S)
        entry["compensation"]["probe_macro"] = PROBE_MACRO
        entry["models"]["regimes"]["window_s"] = 120
        entry["models"]["regimes"]["min_dwell_s"] = 60
        config = GatewayConfig.model_validate(
            {
                "state_dir": str(tmp_path / "state"),
                "logging": {
                    "influxdb": {
                        "url": server.url,
                        "org": server.org,
                        "bucket": bucket,
                        "token_file": str(token_file),
                        "timeout_s": 5.0,
                    },
                    "buffer_path": str(tmp_path / "buffer.sqlite"),
                },
                "machines": [entry],
            }
        )
        gateway = Gateway(config, clock=clock)
        forwarder = gateway.outputs.forwarder
        assert forwarder is not None
        stop = asyncio.Event()
        started_s = clock.now()
        running = asyncio.create_task(gateway.run(stop))
        try:
            await asyncio.sleep(RUN_S)
            assert await forwarder.flush(timeout=30)
        finally:
            stop.set()
            await asyncio.wait_for(running, 20)
            await served.stop()
        return started_s, clock.now(), forwarder.sent

    return asyncio.run(scenario())


def test_every_dashboard_query_returns_data_the_gateway_wrote(tmp_path: Path, store: Path) -> None:
    assert DASHBOARDS, "no dashboard in deploy/grafana/dashboards"
    with InfluxServer(tmp_path / "influxdb") as server:
        bucket = server.create_bucket("spindle")
        write_token = server.create_token("gateway", bucket, write=True)
        read_token = server.create_token("grafana", bucket, write=False)
        start_s, stop_s, sent = run_gateway(tmp_path, server, bucket, write_token, store)
        print(f"gateway run: {stop_s - start_s:.0f} s machine time, {sent} points sent")
        assert sent > 500

        client = InfluxDBClient(url=server.url, token=read_token, org=server.org)
        try:
            schema = written_schema(client, bucket)
            variables = {"bucket": bucket, "machine": MACHINE}
            answers: dict[str, list[Any]] = {}
            for where, query in dashboard_queries():
                flux = grafana_query(query, variables, start_s - 60, stop_s + 60)
                tables = client.query_api().query(flux)
                answers[where] = [r.get_value() for t in tables for r in t.records]
                check_names(where, query, schema)
        finally:
            client.close()

    print({where: len(values) for where, values in answers.items()})
    assert set(schema) == {"spindle_cycle", "spindle_temperature", "spindle_probe"}
    empty = [where for where, values in answers.items() if not values]
    assert not empty, f"queries that return no data after a gateway run: {empty}"
    machines = next(v for w, v in answers.items() if w.endswith("variable 'machine'"))
    assert machines == [MACHINE]
    buckets = next(v for w, v in answers.items() if w.endswith("variable 'bucket'"))
    assert buckets == [bucket]  # the read token sees its bucket only


def check_names(where: str, query: str, schema: dict[str, dict[str, set[str]]]) -> None:
    """Fail when the query names a measurement, field or tag the gateway does not write."""
    named = names_in(query)
    unknown = named["measurements"] - set(schema)
    assert not unknown, f"{where}: measurement(s) the gateway does not write: {unknown}"
    measurements = named["measurements"] or set(schema)
    fields = set().union(*(schema[m]["fields"] for m in measurements))
    tags = set().union(*(schema[m]["tags"] for m in measurements))
    assert not named["fields"] - fields, (
        f"{where}: field(s) {named['fields'] - fields} not written to {sorted(measurements)}"
    )
    assert not named["tags"] - tags - {"name"}, (
        f"{where}: tag(s) {named['tags'] - tags} not written to {sorted(measurements)}"
    )


def test_the_name_check_catches_a_renamed_field_and_tag() -> None:
    """check_names itself: a dashboard naming what the gateway does not write fails."""
    schema = {"spindle_cycle": {"fields": {"speed_rpm"}, "tags": {"machine", "regime"}}}
    good = 'from(bucket: "b") |> filter(fn: (r) => r._measurement == "spindle_cycle" and '
    good += 'r.machine == "m" and r._field == "speed_rpm")'
    check_names("good", good, schema)
    for bad in (
        good.replace("speed_rpm", "speed"),
        good.replace("r.machine", "r.host"),
        good.replace('"spindle_cycle"', '"spindle_cycles"'),
        good + ' |> keep(columns: ["_time", "sensor"])',
    ):
        with pytest.raises(AssertionError):
            check_names("bad", bad, schema)
