"""Reading a machine's logged window back for plots and the event table.

The local store is read through DuckDB from its typed columns
(:mod:`gateway.web.store_window`: a day of 1 Hz data is about a million
temperature rows, handed over as numpy arrays); InfluxDB is read through
:class:`gateway.outputs.influx.InfluxReader`, as ``export`` does.

The machine page draws :func:`machine_view`: every line cut to a min/max envelope
per pixel column of the window (:func:`window_envelope`), the temperatures of the
local store grouped per column in DuckDB (:mod:`gateway.web.store_window`), the events
from the full rows. :func:`read_machine` gives the whole window, row by row.

A machine with several axes logs one ``spindle_cycle`` point per axis and cycle, tagged
``axis`` (:mod:`gateway.outputs.points`). The readers here never mix them: "the" cycle
series of a machine (its speed, predicted, applied, events, the probes' residuals) is
the rows of its first configured axis together with any rows without an ``axis`` tag
(a single-axis machine's, or the same machine's before it had several axes), and each
axis's own lines are read apart (:attr:`MachineView.axis_lines`). Without configured
axes the untagged rows alone are the series.
"""

from __future__ import annotations

import json
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from gateway.outputs.points import (
    CYCLE_MEASUREMENT,
    NS_PER_S,
    PROBE_MEASUREMENT,
    TEMPERATURE_MEASUREMENT,
)
from gateway.web.store_history import (
    CYCLE_NUMBERS,
    HistoryWindow,
    column_width_ns,
    history_window,
    minute_floor,
)
from gateway.web.store_window import temperature_envelopes, window_columns, window_rows

#: ("local", path) or ("influx", url, token, org, bucket, timeout_s): picklable for the worker.
SourceSpec = tuple

#: A cycle's numbers the page reads (the history keeps each one's extremes per minute).
CYCLE_FIELDS = CYCLE_NUMBERS
MAX_EVENTS = 200
#: Pixel columns of a plot: the envelope keeps two points per column.
COLUMNS = 900
PARTS = ("cycles", "temps", "probes")
#: A local-store window whose plot columns are at least this long (7.5 h and more at
#: 900 columns: the 8 h, 24 h and 30-day pages) is read from the per-minute history: a
#: minute is then at most two pixel columns. Measured on a day of 1 Hz data: 8 h
#: 0.34 s from the 1-s rows, 0.12 s from the history; 24 h 0.39 s, 0.09 s; a shorter
#: window reads the 1-s rows (1 h: 0.16 s), its columns finer than a minute.
HISTORY_COLUMN_S = 30.0
HISTORY_FROM_S = HISTORY_COLUMN_S * COLUMNS

Event = tuple[float, str, str]
Series = tuple[np.ndarray, np.ndarray]


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


@dataclass
class MachineView:
    """What the machine page draws: each line ``(Unix s, value)`` cut to the window's
    column envelope, the probes, and the events (newest first), from all the rows."""

    cycles: int
    #: speed_rpm, predicted_um, applied_um, cnc_um, correction_um, and the 90 % interval's
    #: edges interval_low_um, interval_high_um (NaN where it was unknown)
    lines: dict[str, Series]
    temperatures_C: dict[str, Series]
    probe_t_s: np.ndarray
    probe_error_um: np.ndarray
    probe_residual_um: np.ndarray
    events: list[Event]
    quality_changes: list[tuple[float, str, str]]  # (Unix s, sensor, "before → after"), all
    #: a multi-axis machine's axes in configured order → that axis's predicted_um,
    #: applied_um and cnc_um lines (empty for a single-axis machine)
    axis_lines: dict[str, dict[str, Series]] = field(default_factory=dict)
    #: the window read, (start, stop) in Unix s; None: the lines' own extent
    window_s: tuple[float, float] | None = None


@dataclass
class _Cycles:
    t_ns: np.ndarray
    t_s: np.ndarray
    values: dict[str, np.ndarray]
    write_status: list[str]
    link_errors: np.ndarray


def _array(values: Iterable[object]) -> np.ndarray:
    """Floats with ``None`` as NaN."""
    return np.array(list(values), dtype=float)


_LOCAL_SQL = {
    "cycles": (
        CYCLE_MEASUREMENT,
        f"time_ns, {', '.join((*CYCLE_FIELDS, 'write_status', 'link_errors', 'tags_extra'))}",
    ),
    "temps": (TEMPERATURE_MEASUREMENT, "time_ns, sensor, quality, value_C"),
    "probes": (PROBE_MEASUREMENT, "time_ns, error_um"),
}


def _local_part(path: Path, part: str, machine: str, window: tuple[int, int]) -> list:
    measurement, select = _LOCAL_SQL[part]
    return window_rows(path, measurement, machine, window, select, "time_ns, sensor, quality")


def _local_rows(
    path: Path, machine: str, start_ns: int, stop_ns: int, parts: tuple[str, ...] = PARTS
) -> dict[str, list]:
    return {p: _local_part(path, p, machine, (start_ns, stop_ns)) for p in parts}


_MEASUREMENTS = (CYCLE_MEASUREMENT, TEMPERATURE_MEASUREMENT, PROBE_MEASUREMENT)
_INFLUX_ROW = {
    "cycles": lambda p: (
        p.time_ns,
        *(p.fields.get(f) for f in CYCLE_FIELDS),
        p.fields.get("write_status"),
        p.fields.get("link_errors"),
        p.tags.get("axis"),
    ),
    "temps": lambda p: (
        p.time_ns,
        p.tags.get("sensor"),
        p.tags.get("quality"),
        p.fields.get("value_C"),
    ),
    "probes": lambda p: (p.time_ns, p.fields.get("error_um")),
}


def _influx_rows(
    spec: SourceSpec, machine: str, start_ns: int, stop_ns: int, parts: tuple[str, ...] = PARTS
) -> dict[str, list]:
    from gateway.outputs.influx import InfluxReader

    _, url, token, org, bucket, timeout_s = spec
    reader = InfluxReader(url, token, org, bucket, timeout_s)
    measurements = dict(zip(PARTS, _MEASUREMENTS, strict=True))
    try:
        return {
            part: [
                _INFLUX_ROW[part](p)
                for p in reader.query(
                    measurements[part], machine=machine, start_ns=start_ns, stop_ns=stop_ns
                )
            ]
            for part in parts
        }
    finally:
        reader.close()


def _rows(
    spec: SourceSpec, machine: str, start_ns: int, stop_ns: int, parts: tuple[str, ...] = PARTS
) -> dict[str, list]:
    if spec[0] == "local":
        return _local_rows(Path(spec[1]), machine, start_ns, stop_ns, parts)
    return _influx_rows(spec, machine, start_ns, stop_ns, parts)


def _split_temperatures(rows: list) -> tuple[dict[str, tuple[list, list]], list]:
    """Per sensor ``(times ns, values)``, and the quality changes ``(Unix s, sensor,
    "before → after")`` ordered by time, then sensor."""
    by_sensor: dict[str, tuple[list, list]] = {}
    last_quality: dict[str, str] = {}
    changes = []
    for time_ns, sensor, quality, value in rows:
        name = str(sensor)
        times, values = by_sensor.setdefault(name, ([], []))
        times.append(time_ns)
        values.append(value)
        before = last_quality.get(name)
        if before is not None and before != quality:
            changes.append((time_ns / NS_PER_S, name, f"{before} → {quality}"))
        last_quality[name] = quality
    changes.sort(key=lambda c: (c[0], c[1]))
    return by_sensor, changes


#: The cycle columns: the time, the fields, write status, link errors, then the axis
#: (the local store's ``tags_extra`` JSON or InfluxDB's ``axis`` tag).
_CYCLE_COLUMNS = len(CYCLE_FIELDS) + 4


def _axis_of(tag: object, known: dict[object, str | None]) -> str | None:
    """The axis a cycle row's tag column names (None: untagged), parsed once per text."""
    if tag not in known:
        axis = json.loads(str(tag)).get("axis") if isinstance(tag, str) and tag[:1] == "{" else tag
        known[tag] = None if axis in (None, "") else str(axis)
    return known[tag]


def _split_axes(columns: list, axes: Sequence[str]) -> dict[str | None, _Cycles]:
    """The cycles of "the" series (key None: the first of ``axes`` and every untagged
    row; without ``axes`` the untagged rows) and of each of ``axes``, from the cycle
    columns (the axis tag last): made into arrays once, then cut by axis."""
    every = _cycles_of(columns if columns else [[]] * _CYCLE_COLUMNS)
    known: dict[object, str | None] = {}
    tags = [_axis_of(tag, known) for tag in (columns[-1] if columns else [])]
    if not axes and all(t is None for t in tags):
        return {None: every}
    codes = {key: i for i, key in enumerate(dict.fromkeys([None, *axes, *known.values()]))}
    code = np.array([codes[t] for t in tags], dtype=np.int64)
    split = {}
    for key in (None, *axes):
        wanted = [codes[None], codes[axes[0]]] if key is None and axes else [codes[key]]
        split[key] = _cycles_where(every, np.isin(code, wanted))
    return split


def _cycles_where(cycles: _Cycles, keep: np.ndarray) -> _Cycles:
    return _Cycles(
        t_ns=cycles.t_ns[keep],
        t_s=cycles.t_s[keep],
        values={f: v[keep] for f, v in cycles.values.items()},
        write_status=[cycles.write_status[i] for i in np.flatnonzero(keep)],
        link_errors=cycles.link_errors[keep],
    )


def _cycles(rows: list, axes: Sequence[str] = ()) -> _Cycles:
    columns = [list(c) for c in zip(*rows, strict=True)] if rows else []
    return _split_axes(columns, axes)[None]


def _cycles_of(columns: list) -> _Cycles:
    """The cycles from their columns: time, the fields, write status, link errors."""
    n = len(CYCLE_FIELDS) + 1  # the time, then the fields
    return _Cycles(
        t_ns=np.array(columns[0], dtype=np.int64),
        t_s=np.array(columns[0], dtype=float) / NS_PER_S,
        values={f: _array(c) for f, c in zip(CYCLE_FIELDS, columns[1:n], strict=True)},
        write_status=[str(s or "") for s in columns[n]],
        link_errors=_array(columns[n + 1]),
    )


def _probes(rows: list, cycles: _Cycles) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Probe times (Unix s), measured errors, and residuals against the prediction of
    the cycle at or before each probe."""
    probe_t = np.array([r[0] for r in rows], dtype=float) / NS_PER_S
    probe_err = _array(r[1] for r in rows)
    t_s, predicted = cycles.t_s, cycles.values["predicted_um"]
    if len(t_s) and len(probe_t):
        at = np.clip(np.searchsorted(t_s, probe_t, side="right") - 1, 0, len(t_s) - 1)
        return probe_t, probe_err, probe_err - predicted[at]
    return probe_t, probe_err, np.zeros(len(probe_t))


def read_machine(
    spec: SourceSpec,
    machine: str,
    start_s: float,
    stop_s: float,
    cnc_um_per_unit: float,
    axes: Sequence[str] = (),
) -> MachineSeries:
    """The logged window ``start_s ≤ t < stop_s`` (Unix seconds) of ``machine``, every row
    (its cycles: "the" series of the module docstring, ``axes`` its configured axes)."""
    rows = _rows(spec, machine, int(start_s * NS_PER_S), int(stop_s * NS_PER_S))
    cycles = _cycles(rows["cycles"], axes)
    by_sensor, changes = _split_temperatures(rows["temps"])
    temperatures = {
        s: (np.array([t / NS_PER_S for t in times]), _array(values))
        for s, (times, values) in by_sensor.items()
    }
    probe_t, probe_err, residual = _probes(rows["probes"], cycles)
    values = cycles.values
    return MachineSeries(
        t_s=cycles.t_s,
        speed_rpm=values["speed_rpm"],
        predicted_um=values["predicted_um"],
        applied_um=values["applied_um"],
        cnc_um=values["written_cnc"] * cnc_um_per_unit,
        correction_um=values["correction_um"],
        write_status=cycles.write_status,
        link_errors=cycles.link_errors,
        temperatures_C=temperatures,
        quality_changes=changes,
        probe_t_s=probe_t,
        probe_error_um=probe_err,
        probe_residual_um=residual,
    )


def read_probes(
    spec: SourceSpec, machine: str, start_s: float, stop_s: float, axes: Sequence[str] = ()
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Probe times (Unix s), measured errors and residuals (µm) of the window: its cycles
    and probes only (the residuals against "the" series: the first of ``axes``)."""
    window = (int(start_s * NS_PER_S), int(stop_s * NS_PER_S))
    rows = _rows(spec, machine, *window, parts=("cycles", "probes"))
    return _probes(rows["probes"], _cycles(rows["cycles"], axes))


def window_envelope(
    t_ns: np.ndarray, y: np.ndarray, start_ns: int, stop_ns: int, columns: int = COLUMNS
) -> Series:
    """``(t_ns, y)`` (sorted by time) cut to each column's first time with its lowest
    value and last time with its highest; column ``k`` holds the times with
    ``(t - start) * columns // (stop - start) == k``. NaNs are dropped; a series of at
    most ``2 × columns`` points comes back whole."""
    keep = np.isfinite(y)
    t, y = t_ns[keep], y[keep]
    if len(t) <= 2 * columns:
        return t, y
    column = (t - start_ns) * columns // (stop_ns - start_ns)
    starts = np.flatnonzero(np.r_[True, column[1:] != column[:-1]])
    ends = np.r_[starts[1:], len(t)] - 1
    lows = np.minimum.reduceat(y, starts)
    highs = np.maximum.reduceat(y, starts)
    return np.column_stack([t[starts], t[ends]]).ravel(), np.column_stack([lows, highs]).ravel()


def _full_temperatures(
    rows: list, start_ns: int, stop_ns: int, columns: int
) -> tuple[dict[str, Series], list]:
    by_sensor, changes = _split_temperatures(rows)
    series = {
        s: window_envelope(np.array(t, dtype=np.int64), _array(v), start_ns, stop_ns, columns)
        for s, (t, v) in by_sensor.items()
    }
    return series, changes


def machine_view(
    spec: SourceSpec,
    machine: str,
    start_s: float,
    stop_s: float,
    cnc_um_per_unit: float,
    columns: int = COLUMNS,
    aggregate: bool = True,
    axes: Mapping[str, float] | None = None,
) -> MachineView:
    """The window ``start_s ≤ t < stop_s`` as the machine page draws it. ``aggregate``:
    the local store's temperatures are cut per column in DuckDB (the same result as
    reading every row, which ``aggregate=False`` does). ``axes``: a multi-axis machine's
    axes in configured order, each with its CNC value's µm per unit; its main lines are
    "the" series (the first axis, see the module docstring), each axis's are apart."""
    axes = dict(axes or {})
    if spec[0] == "local" and aggregate and stop_s - start_s >= HISTORY_FROM_S:
        return history_view(
            Path(spec[1]), machine, (start_s, stop_s), cnc_um_per_unit, columns, axes
        )
    start_ns, stop_ns = int(start_s * NS_PER_S), int(stop_s * NS_PER_S)
    if spec[0] == "local" and aggregate:
        path = Path(spec[1])
        rows = _local_rows(path, machine, start_ns, stop_ns, ("probes",))
        cycle_columns = window_columns(
            path, CYCLE_MEASUREMENT, machine, (start_ns, stop_ns), _LOCAL_SQL["cycles"][1]
        )
        temps, changes = temperature_envelopes(path, machine, start_ns, stop_ns, columns)
    else:
        rows = _rows(spec, machine, start_ns, stop_ns)
        temps, changes = _full_temperatures(rows["temps"], start_ns, stop_ns, columns)
        logged = rows["cycles"]
        cycle_columns = [list(c) for c in zip(*logged, strict=True)] if logged else []
    by_axis = _split_axes(cycle_columns, list(axes))
    cycles = by_axis[None]
    axis_lines = {
        axis: _axis_lines(by_axis[axis], factor, (start_ns, stop_ns), columns)
        for axis, factor in axes.items()
    }
    probe_t, probe_err, residual = _probes(rows["probes"], cycles)
    values = dict(cycles.values, cnc_um=cycles.values["written_cnc"] * cnc_um_per_unit)
    values["interval_low_um"] = values["predicted_um"] - values["interval_um"]
    values["interval_high_um"] = values["predicted_um"] + values["interval_um"]
    names: tuple[str, ...] = ("speed_rpm", "predicted_um", "applied_um", "cnc_um", "correction_um")
    names += ("interval_low_um", "interval_high_um")
    lines = {n: window_envelope(cycles.t_ns, values[n], start_ns, stop_ns, columns) for n in names}
    found = _cycle_events(cycles.t_s, cycles.write_status, cycles.link_errors)
    found += [(t, "sensor flag", f"{sensor}: {change}") for t, sensor, change in changes]
    for axis in list(axes)[1:]:  # the first axis's writes are the machine's, above
        found += _axis_write_events(axis, by_axis[axis])
    return MachineView(
        cycles=len(cycles.t_ns),
        lines={n: _seconds(s) for n, s in lines.items()},
        temperatures_C={s: _seconds(series) for s, series in temps.items()},
        probe_t_s=probe_t,
        probe_error_um=probe_err,
        probe_residual_um=residual,
        events=_newest_first(found),
        quality_changes=changes,
        axis_lines=axis_lines,
        window_s=(start_s, stop_s),
    )


def _axis_lines(
    cycles: _Cycles, cnc_um_per_unit: float, window: tuple[int, int], columns: int
) -> dict[str, Series]:
    """One axis's predicted, applied and CNC-held lines (µm), cut to the window's columns."""
    values = dict(cycles.values, cnc_um=cycles.values["written_cnc"] * cnc_um_per_unit)
    return {
        name: _seconds(window_envelope(cycles.t_ns, values[name], *window, columns))
        for name in ("predicted_um", "applied_um", "cnc_um")
    }


def _seconds(series: Series) -> Series:
    t_ns, y = series
    return np.asarray(t_ns, dtype=np.int64) / NS_PER_S, np.asarray(y, dtype=float)


def _refused(status: str) -> bool:
    """A write the loop did not make for a fault (not a hold or a deadband)."""
    return bool(status) and not status.startswith(("ok", "no write"))


def _cycle_events(t_s: np.ndarray, statuses: list[str], link_errors: np.ndarray) -> list[Event]:
    """Macro changes, write refusals, source faults (a bus, a sensor channel or the CNC
    failing: the cycle logs only their count) and reconnects, each at the cycle where it
    began (the first cycle follows an "ok" one with every link up). Only cycles whose
    status or link state differs from the one before can begin one, so only those are
    looked at."""
    if not statuses:
        return []
    links = np.where(np.isnan(link_errors), 0.0, link_errors)
    status = np.array(statuses, dtype=object)
    up = links > 0
    changed = np.flatnonzero((status[1:] != status[:-1]) | (up[1:] != up[:-1])) + 1
    found: list[Event] = []
    for i in [0, *changed.tolist()]:
        previous, previous_links = ("ok", 0.0) if i == 0 else (statuses[i - 1], links[i - 1])
        t, now, count = float(t_s[i]), statuses[i], float(links[i])
        if "external" in now and "external" not in previous:
            found.append((t, "external macro change", now))
        elif _refused(now) and now[:24] != previous[:24]:
            found.append((t, "write", now))
        if count > 0 and previous_links == 0:
            text = f"{count:.0f} source(s) failing: a bus, a sensor channel or the CNC"
            found.append((t, "source fault", text))
        elif count == 0 and previous_links > 0:
            found.append((t, "reconnected", "every source answering again"))
    return found


def _axis_write_events(axis: str, cycles: _Cycles) -> list[Event]:
    """One further axis's macro changes and write refusals, its name in their kind (its
    link faults are the machine's, listed once)."""
    quiet = np.zeros(len(cycles.write_status))
    return [
        (t, f"{kind} ({axis})", text)
        for t, kind, text in _cycle_events(cycles.t_s, cycles.write_status, quiet)
    ]


def _newest_first(found: list[Event]) -> list[Event]:
    found.sort(key=lambda e: e[0], reverse=True)
    return found[:MAX_EVENTS]


def events(data: MachineSeries) -> list[Event]:
    """(Unix s, kind, text), newest first: macro changes, write refusals, sensor flags,
    link losses and reconnects, each at the cycle where it began."""
    found = _cycle_events(data.t_s, data.write_status, data.link_errors)
    found += [
        (t, "sensor flag", f"{sensor}: {change}") for t, sensor, change in data.quality_changes
    ]
    return _newest_first(found)


def history_window_of(
    path: Path, machine: str, window_s: tuple[float, float], columns: int = COLUMNS
) -> tuple[HistoryWindow, int, int]:
    """The local store's window ``(start_s, stop_s)`` from its per-minute history, its
    start on a minute and its columns whole minutes (so the history's envelope is exact):
    the window, its start and its column width (ns)."""
    start_s, stop_s = window_s
    start_ns = minute_floor(int(start_s * NS_PER_S))
    width_ns = column_width_ns(stop_s - start_s, columns)
    found = history_window(path, machine, start_ns, int(stop_s * NS_PER_S), width_ns)
    return found, start_ns, width_ns


def _merged(series: list[Series]) -> Series:
    """Several envelopes (the first axis's and the untagged rows') as one, by time."""
    t = np.concatenate([s[0] for s in series]) if series else np.zeros(0, dtype=np.int64)
    y = np.concatenate([s[1] for s in series]) if series else np.zeros(0)
    order = np.argsort(t, kind="stable")
    return t[order], y[order]


def _keys_of(found: Mapping[object, object], axes: Sequence[str]) -> dict[str | None, list]:
    """The tag sets of "the" series (key None) and of each axis (the module docstring)."""
    known: dict[object, str | None] = {}
    keys: dict[str | None, list] = {None: [], **{a: [] for a in axes}}
    for tag in found:
        axis = _axis_of(tag, known)
        if axis is None or (axes and axis == axes[0]):
            keys[None].append(tag)
        if axis is not None and axis in keys:
            keys[axis].append(tag)
    return keys


def history_view(
    path: Path,
    machine: str,
    window_s: tuple[float, float],
    cnc_um_per_unit: float,
    columns: int = COLUMNS,
    axes: Mapping[str, float] | None = None,
) -> MachineView:
    """:func:`machine_view` of a long local-store window from the per-minute history.
    The 90 % interval's edges are each column's outer bound (lowest prediction less
    the widest interval, highest plus it)."""
    axes = dict(axes or {})
    found, start_ns, width_ns = history_window_of(path, machine, window_s, columns)
    keys = _keys_of({**found.cycle_lines, **found.predicted_minutes}, list(axes))
    lines = _history_lines(found, keys[None], cnc_um_per_unit)
    by_axis = _split_axes(found.changes, list(axes))
    probe_t = found.probes[0] / NS_PER_S
    minutes = _merged(
        [found.predicted_minutes[k] for k in keys[None] if k in found.predicted_minutes]
    )
    residual = np.zeros(len(probe_t))
    if len(minutes[0]) and len(probe_t):
        at = np.searchsorted(minutes[0], found.probes[0] // 60_000_000_000 * 60_000_000_000)
        at = np.clip(at, 0, len(minutes[0]) - 1)
        residual = found.probes[1] - minutes[1][at]
    keep = _probe_extremes(found.probes[0], (found.probes[1], residual), start_ns, width_ns)
    probe_t, residual = probe_t[keep], residual[keep]
    changes = [(t / NS_PER_S, str(s), f"{b} → {a}") for t, s, b, a in found.flips]
    events = _cycle_events(by_axis[None].t_s, by_axis[None].write_status, by_axis[None].link_errors)
    events += [(t, "sensor flag", f"{sensor}: {change}") for t, sensor, change in changes]
    for axis in list(axes)[1:]:
        events += _axis_write_events(axis, by_axis[axis])
    return MachineView(
        cycles=sum(found.cycles.get(k, 0) for k in keys[None]),
        lines={n: _seconds(s) for n, s in lines.items()},
        temperatures_C={s: _seconds(v) for s, v in found.temperatures_C.items()},
        probe_t_s=probe_t,
        probe_error_um=found.probes[1][keep],
        probe_residual_um=residual,
        events=_newest_first(events),
        quality_changes=changes,
        axis_lines={
            axis: {
                n: _seconds(s)
                for n, s in _history_lines(found, keys[axis], factor).items()
                if n in ("predicted_um", "applied_um", "cnc_um")
            }
            for axis, factor in axes.items()
        },
        window_s=window_s,
    )


def _probe_extremes(
    t_ns: np.ndarray, values: tuple[np.ndarray, ...], start_ns: int, width_ns: int
) -> np.ndarray:
    """The probes (indices, by time) holding a column's lowest or highest of any of
    ``values``: a month of probes every 2 min is 21 600 markers, at most 4 a column."""
    column = (t_ns - start_ns) // width_ns
    kept = []
    for y in values:
        order = np.lexsort((y, column))
        ordered = column[order]
        starts = np.flatnonzero(np.r_[True, ordered[1:] != ordered[:-1]]) if len(order) else order
        ends = np.r_[starts[1:], len(order)] - 1 if len(order) else order
        kept += [order[starts], order[ends]]
    return np.unique(np.concatenate(kept)) if kept else np.zeros(0, dtype=np.int64)


def _history_lines(found: HistoryWindow, keys: list, cnc_um_per_unit: float) -> dict[str, Series]:
    """The page's cycle lines of the tag sets ``keys`` from the history's envelopes."""

    def line(name: str) -> Series:
        return _merged([found.cycle_lines[k][name] for k in keys if k in found.cycle_lines])

    lines = {n: line(n) for n in ("speed_rpm", "predicted_um", "applied_um", "correction_um")}
    t, cnc = line("written_cnc")
    lines["cnc_um"] = (t, cnc * cnc_um_per_unit)
    # the interval's outer bound per column: the column's pairs are (low, high)
    pt, predicted = lines["predicted_um"]
    it, width = line("interval_um")
    if len(it) and len(it) == len(pt):
        widest = np.repeat(np.maximum(width[0::2], width[1::2]), 2)
        lines["interval_low_um"] = (pt[0::2], predicted[0::2] - widest[0::2])
        lines["interval_high_um"] = (pt[1::2], predicted[1::2] + widest[1::2])
    else:
        empty = (np.zeros(0, dtype=np.int64), np.zeros(0))
        lines["interval_low_um"] = lines["interval_high_um"] = empty
    return lines
