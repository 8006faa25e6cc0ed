"""Reading a machine's logged window back for plots and the event table.

The local store is read with SQLite's own JSON functions on a read-only
connection (a day of 1 Hz data is about a million temperature rows: parsing each
row's JSON in Python would take seconds); InfluxDB is read through
:class:`gateway.outputs.influx.InfluxReader`, as ``export`` does.
"""

from __future__ import annotations

import sqlite3
from collections.abc import Iterable
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from gateway.outputs.points import (
    CYCLE_MEASUREMENT,
    NS_PER_S,
    PROBE_MEASUREMENT,
    TEMPERATURE_MEASUREMENT,
)

#: ("local", path) or ("influx", url, token, org, bucket, timeout_s): picklable for the worker.
SourceSpec = tuple

CYCLE_FIELDS = ("speed_rpm", "predicted_um", "applied_um", "written_cnc", "correction_um")
MAX_EVENTS = 200


@dataclass
class MachineSeries:
    """One machine's logged window as arrays (Unix seconds, units in the names)."""

    t_s: np.ndarray
    speed_rpm: np.ndarray
    predicted_um: np.ndarray
    applied_um: np.ndarray
    cnc_um: np.ndarray
    correction_um: np.ndarray
    write_status: list[str]
    link_errors: np.ndarray
    temperatures_C: dict[str, tuple[np.ndarray, np.ndarray]]
    quality_changes: list[tuple[float, str, str]] = field(default_factory=list)
    probe_t_s: np.ndarray = field(default_factory=lambda: np.zeros(0))
    probe_error_um: np.ndarray = field(default_factory=lambda: np.zeros(0))
    probe_residual_um: np.ndarray = field(default_factory=lambda: np.zeros(0))

    @property
    def cycles(self) -> int:
        return len(self.t_s)


def _array(values: Iterable[object]) -> np.ndarray:
    return np.array([np.nan if v is None else v for v in values], dtype=float)


def _local_rows(path: Path, machine: str, start_ns: int, stop_ns: int) -> dict[str, list]:
    db = sqlite3.connect(f"file:{path}?mode=ro", uri=True, timeout=5.0)
    try:
        where = "measurement = ? AND machine = ? AND time_ns >= ? AND time_ns < ?"
        cycle_cols = ", ".join(f"json_extract(fields, '$.{f}')" for f in CYCLE_FIELDS)
        cycles = db.execute(
            f"SELECT time_ns, {cycle_cols}, json_extract(fields, '$.write_status'), "
            f"json_extract(fields, '$.link_errors') FROM points WHERE {where} ORDER BY time_ns",
            (CYCLE_MEASUREMENT, machine, start_ns, stop_ns),
        ).fetchall()
        temps = db.execute(
            "SELECT time_ns, json_extract(tags, '$.sensor'), json_extract(tags, '$.quality'), "
            f"json_extract(fields, '$.value_C') FROM points WHERE {where} ORDER BY time_ns",
            (TEMPERATURE_MEASUREMENT, machine, start_ns, stop_ns),
        ).fetchall()
        probes = db.execute(
            "SELECT time_ns, json_extract(fields, '$.error_um') FROM points "
            f"WHERE {where} ORDER BY time_ns",
            (PROBE_MEASUREMENT, machine, start_ns, stop_ns),
        ).fetchall()
    finally:
        db.close()
    return {"cycles": cycles, "temps": temps, "probes": probes}


def _influx_rows(spec: SourceSpec, machine: str, start_ns: int, stop_ns: int) -> dict[str, list]:
    from gateway.outputs.influx import InfluxReader

    _, url, token, org, bucket, timeout_s = spec
    reader = InfluxReader(url, token, org, bucket, timeout_s)
    try:

        def read(measurement: str) -> list:
            return reader.query(measurement, machine=machine, start_ns=start_ns, stop_ns=stop_ns)

        cycles = [
            (
                p.time_ns,
                *(p.fields.get(f) for f in CYCLE_FIELDS),
                p.fields.get("write_status"),
                p.fields.get("link_errors"),
            )
            for p in read(CYCLE_MEASUREMENT)
        ]
        temps = [
            (p.time_ns, p.tags.get("sensor"), p.tags.get("quality"), p.fields.get("value_C"))
            for p in read(TEMPERATURE_MEASUREMENT)
        ]
        probes = [(p.time_ns, p.fields.get("error_um")) for p in read(PROBE_MEASUREMENT)]
    finally:
        reader.close()
    return {"cycles": cycles, "temps": temps, "probes": probes}


def _temperatures(rows: list) -> tuple[dict, list[tuple[float, str, str]]]:
    by_sensor: dict[str, tuple[list, list]] = {}
    last_quality: dict[str, str] = {}
    changes = []
    for time_ns, sensor, quality, value in rows:
        times, values = by_sensor.setdefault(str(sensor), ([], []))
        times.append(time_ns / NS_PER_S)
        values.append(value)
        before = last_quality.get(sensor)
        if before is not None and before != quality:
            changes.append((time_ns / NS_PER_S, str(sensor), f"{before} → {quality}"))
        last_quality[sensor] = quality
    arrays = {s: (np.array(t), _array(v)) for s, (t, v) in by_sensor.items()}
    return arrays, changes


def read_machine(
    spec: SourceSpec, machine: str, start_s: float, stop_s: float, cnc_um_per_unit: float
) -> MachineSeries:
    """The logged window ``start_s ≤ t < stop_s`` (Unix seconds) of ``machine``."""
    start_ns, stop_ns = int(start_s * NS_PER_S), int(stop_s * NS_PER_S)
    if spec[0] == "local":
        rows = _local_rows(Path(spec[1]), machine, start_ns, stop_ns)
    else:
        rows = _influx_rows(spec, machine, start_ns, stop_ns)
    cycles = rows["cycles"]
    columns = list(zip(*cycles, strict=True)) if cycles else [()] * (len(CYCLE_FIELDS) + 3)
    t_s = np.array(columns[0], dtype=float) / NS_PER_S
    speed, predicted, applied, written, correction = (_array(c) for c in columns[1:6])
    temperatures, changes = _temperatures(rows["temps"])
    probe_t = np.array([r[0] for r in rows["probes"]], dtype=float) / NS_PER_S
    probe_err = _array(r[1] for r in rows["probes"])
    if len(t_s) and len(probe_t):
        at = np.clip(np.searchsorted(t_s, probe_t, side="right") - 1, 0, len(t_s) - 1)
        residual = probe_err - predicted[at]
    else:
        residual = np.zeros(len(probe_t))
    return MachineSeries(
        t_s=t_s,
        speed_rpm=speed,
        predicted_um=predicted,
        applied_um=applied,
        cnc_um=written * cnc_um_per_unit,
        correction_um=correction,
        write_status=[str(s or "") for s in columns[6]],
        link_errors=_array(columns[7]),
        temperatures_C=temperatures,
        quality_changes=changes,
        probe_t_s=probe_t,
        probe_error_um=probe_err,
        probe_residual_um=residual,
    )


def _refused(status: str) -> bool:
    """A write the loop did not make for a fault (not a hold or a deadband)."""
    return bool(status) and not status.startswith(("ok", "no write"))


def events(data: MachineSeries) -> list[tuple[float, str, str]]:
    """(Unix s, kind, text), newest first: macro changes, write refusals, sensor flags,
    link losses and reconnects, each at the cycle where it began."""
    found: list[tuple[float, str, str]] = []
    previous_status, previous_links = "ok", 0.0
    for t, status, links in zip(data.t_s, data.write_status, data.link_errors, strict=True):
        if "external" in status and "external" not in previous_status:
            found.append((float(t), "external macro change", status))
        elif _refused(status) and status[:24] != previous_status[:24]:
            found.append((float(t), "write", status))
        links = 0.0 if np.isnan(links) else float(links)
        if links > 0 and previous_links == 0:
            found.append((float(t), "link lost", f"{links:.0f} source(s) not answering"))
        elif links == 0 and previous_links > 0:
            found.append((float(t), "reconnected", "every source answering again"))
        previous_status, previous_links = status, links
    found += [
        (t, "sensor flag", f"{sensor}: {change}") for t, sensor, change in data.quality_changes
    ]
    found.sort(key=lambda e: e[0], reverse=True)
    return found[:MAX_EVENTS]
