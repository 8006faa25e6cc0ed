"""Export logged time series to the measured-run CSV (contract §1).

Reads the ``spindle_cycle``, ``spindle_temperature`` and ``spindle_probe`` points
of one machine from a :class:`PointSource` — the embedded
:class:`~gateway.outputs.local_store.LocalStore` or InfluxDB through
:class:`~gateway.outputs.influx.InfluxReader` (Flux) — and writes::

    run,time_s,speed_rpm,T1,…,Tn,[ambient_C],error_um

* one row per cycle (a time stamp of the machine's cycle or temperature points);
* ``time_s`` is machine time: the point's Unix time minus ``epoch_s``;
* ``run``: the cycles are cut into runs where the time between two cycles is
  more than ``gap_factor`` (10) × the cycle time (the median spacing unless
  given); a run is named ``<machine>-<UTC start, YYYYmmddTHHMMSSZ>``;
* ``T<n>`` from the sensors named ``T`` + digits, ``ambient_C`` from a sensor
  named ``ambient`` or ``ambient_C``; other sensors are not exported (listed in
  the result). With ``good_only`` (default) a reading whose quality tag is not
  ``good`` is left empty, so a faulty sensor never reaches a model fit;
* ``error_um`` is the measured error: the probe point that falls in the cycle
  (from the cycle's time stamp up to the next cycle, less than one cycle time
  later; the last one when several do). Rows without a probe value are left out
  and counted (:attr:`ExportResult.rows_without_probe`);
* a row with a missing temperature or speed keeps an empty cell; ``load_runs``
  skips such rows and says how many, and the result counts them too;
* a logged value that is not plausible for its unit (NaN, infinite, or outside
  the ranges of :mod:`models.data.unit_ranges`, e.g. 1e308 °C) is left empty too,
  and counted (:attr:`ExportResult.implausible_values`), so the file always
  passes ``load_runs`` and no absurd number reaches a fit.

A machine with several axes logs one ``spindle_cycle`` point per axis and cycle (tag
``axis``); only their time and ``speed_rpm`` are read here, the cycle's and the same on
every axis's point, so each cycle is still one row whatever the axes, and no axis's
values are mixed into another's (``error_um`` is the probe's, of the first axis).

The file passes :func:`models.data.dataset.load_runs`.
"""

from __future__ import annotations

import bisect
import csv
import itertools
import re
import statistics
from collections.abc import Sequence
from dataclasses import dataclass
from datetime import UTC, datetime
from pathlib import Path

from tqdm import tqdm

from gateway.outputs.influx import InfluxReader
from gateway.outputs.local_store import LocalStore
from gateway.outputs.points import (
    CYCLE_MEASUREMENT,
    NS_PER_S,
    PROBE_MEASUREMENT,
    TEMPERATURE_MEASUREMENT,
    Point,
    to_time_ns,
)
from models.data.dataset import ambient_sensor_of
from models.data.unit_ranges import DISPLACEMENT_UM, SPEED_RPM, TEMPERATURE_C
from models.json_files import atomic_text

SENSOR_PATTERN = re.compile(r"^T(\d+)$")


#: Where points are read from: the embedded store or InfluxDB (one ``query`` signature).
PointSource = LocalStore | InfluxReader


class ExportError(ValueError):
    """Nothing to export (no cycles, or no cycle with a probe value, in the window)."""


@dataclass(frozen=True)
class ExportResult:
    path: Path
    columns: tuple[str, ...]
    runs: tuple[str, ...]
    rows: int  # rows written
    rows_without_probe: int  # cycles left out: no probe value in their cycle
    rows_incomplete: int  # rows written with an empty temperature or speed cell
    cycle_s: float
    ignored_sensors: tuple[str, ...] = ()
    implausible_values: int = 0  # logged values left empty: not plausible for their unit


def export_runs(
    points_source: PointSource,
    machine: str,
    start_s: float | None,
    stop_s: float | None,
    out_csv: str | Path,
    epoch_s: float = 0.0,
    cycle_s: float | None = None,
    gap_factor: float = 10.0,
    good_only: bool = True,
    progress: bool = False,
) -> ExportResult:
    """Write the measured-run CSV of ``machine`` for machine time ``start_s ≤ t < stop_s``.

    ``start_s``/``stop_s`` are machine seconds (``None``: unbounded); ``epoch_s``
    must be the one the points were made with (:func:`gateway.outputs.points.to_time_ns`).
    ``progress``: a bar over the export's steps (each measurement read, the rows, the
    file) on stderr.
    """
    out_csv = Path(out_csv)
    start_ns = None if start_s is None else to_time_ns(start_s, epoch_s)
    stop_ns = None if stop_s is None else to_time_ns(stop_s, epoch_s)

    bar = tqdm(total=len(EXPORT_STEPS), desc="export", unit="step", disable=not progress,
               leave=False, mininterval=0)  # fmt: skip
    with bar:
        return _export(points_source, machine, (start_ns, stop_ns), out_csv, epoch_s,
                       cycle_s, gap_factor, good_only, bar)  # fmt: skip


#: The steps of an export its progress bar counts.
EXPORT_STEPS = ("read cycles", "read temperatures", "read probes", "assemble rows", "write")


def _export(
    points_source: PointSource,
    machine: str,
    window_ns: tuple[int | None, int | None],
    out_csv: Path,
    epoch_s: float,
    cycle_s: float | None,
    gap_factor: float,
    good_only: bool,
    bar: tqdm,
) -> ExportResult:
    """:func:`export_runs`, one step of ``bar`` at a time."""

    def step() -> None:
        bar.set_postfix_str(f"{EXPORT_STEPS[bar.n]} done", refresh=False)
        bar.update(1)

    def read(measurement: str) -> list[Point]:
        start_ns, stop_ns = window_ns
        points = points_source.query(
            measurement, machine=machine, start_ns=start_ns, stop_ns=stop_ns
        )
        step()
        return points

    cycles = read(CYCLE_MEASUREMENT)
    temperatures = read(TEMPERATURE_MEASUREMENT)
    probes = read(PROBE_MEASUREMENT)
    check = _Plausible()
    speed = _speeds(cycles, check)
    readings, sensors = _readings(temperatures, check, good_only)
    times = sorted({p.time_ns for p in cycles} | set(readings))
    if not times:
        raise ExportError(f"no cycles of machine '{machine}' in the time window")
    cycle_ns = _cycle_ns(times, cycle_s)
    run_of = _runs(times, cycle_ns, gap_factor, machine)
    error = _probe_rows(probes, times, cycle_ns, check)
    layout = _Layout.of(sensors, readings, times, error)
    if not error:
        raise ExportError(
            f"none of the {len(times)} cycle(s) of machine '{machine}' in the time window "
            "has a probe (spindle_probe error_um) value"
        )
    rows = []
    for row in sorted(error):
        time_ns = times[row]
        values = readings.get(time_ns, {})
        cells = [speed.get(time_ns), *(values.get(s) for s in layout.exported)]
        rows.append((run_of[row], round(time_ns / NS_PER_S - epoch_s, 6), cells, error[row]))
    step()
    incomplete = _write_csv(out_csv, layout.columns, rows)
    step()
    return ExportResult(
        path=out_csv,
        columns=layout.columns,
        runs=tuple(dict.fromkeys(run_of[r] for r in sorted(error))),
        rows=len(error),
        rows_without_probe=len(times) - len(error),
        rows_incomplete=incomplete,
        cycle_s=cycle_ns / NS_PER_S,
        ignored_sensors=layout.ignored,
        implausible_values=check.implausible,
    )


class _Plausible:
    """Judges logged values against their unit's range and counts those that fail."""

    def __init__(self) -> None:
        self.implausible = 0

    def __call__(self, value: float, low: float, high: float) -> bool:
        if low <= value <= high:  # False for NaN
            return True
        self.implausible += 1
        return False


def _number_field(point: Point, name: str) -> float | None:
    """The point's numeric field ``name`` (a bool or a string is no number), or None."""
    value = point.fields.get(name)
    if not isinstance(value, int | float) or isinstance(value, bool):
        return None
    return float(value)


def _speeds(cycles: list[Point], check: _Plausible) -> dict[int, float]:
    """time_ns → plausible spindle speed (r/min) of the cycle points."""
    speed: dict[int, float] = {}
    for point in cycles:
        value = _number_field(point, "speed_rpm")
        if value is not None and check(value, SPEED_RPM.low, SPEED_RPM.high):
            speed[point.time_ns] = value
    return speed


def _readings(
    temperatures: list[Point], check: _Plausible, good_only: bool
) -> tuple[dict[int, dict[str, float | None]], set[str]]:
    """time_ns → sensor → °C (None where implausible or, with ``good_only``, not good),
    and every sensor seen."""
    readings: dict[int, dict[str, float | None]] = {}
    sensors: set[str] = set()
    for point in temperatures:
        sensor = point.tags.get("sensor")
        value = _number_field(point, "value_C")
        if sensor is None or value is None:
            continue
        sensors.add(sensor)
        good = point.tags.get("quality", "good") == "good"
        keep = check(value, TEMPERATURE_C.low, TEMPERATURE_C.high)
        readings.setdefault(point.time_ns, {})[sensor] = (
            value if keep and (good or not good_only) else None
        )
    return readings, sensors


def _probe_rows(
    probes: list[Point], times: list[int], cycle_ns: int, check: _Plausible
) -> dict[int, float]:
    """Row index → the probe value measured within that row's cycle (the last one wins)."""
    error: dict[int, float] = {}
    for point in sorted(probes, key=lambda p: p.time_ns):
        value = _number_field(point, "error_um")
        if value is None or not check(value, DISPLACEMENT_UM.low, DISPLACEMENT_UM.high):
            continue
        row = bisect.bisect_right(times, point.time_ns) - 1
        if row >= 0 and point.time_ns - times[row] < cycle_ns:
            error[row] = value
    return error


@dataclass(frozen=True)
class _Layout:
    """Which sensors become columns, in which order, and which are left out."""

    exported: list[str]
    columns: tuple[str, ...]
    ignored: tuple[str, ...]

    @classmethod
    def of(
        cls,
        sensors: set[str],
        readings: dict[int, dict[str, float | None]],
        times: list[int],
        error: dict[int, float],
    ) -> _Layout:
        t_sensors = sorted((s for s in sensors if SENSOR_PATTERN.match(s)), key=_sensor_number)
        ambient = ambient_sensor_of(sensors)
        exported = [*t_sensors, *([ambient] if ambient else [])]
        ignored = tuple(sorted(sensors - set(exported)))
        # A column with no value in any exported row would make every row unusable.
        exported = [
            s for s in exported if any(readings.get(times[r], {}).get(s) is not None for r in error)
        ]
        t_columns = [s for s in exported if s != ambient]
        columns = (
            "run",
            "time_s",
            "speed_rpm",
            *t_columns,
            *(["ambient_C"] if ambient in exported else []),
            "error_um",
        )
        return cls(exported, columns, ignored)


def _write_csv(
    out_csv: Path,
    columns: tuple[str, ...],
    rows: list[tuple[str, float, list[float | None], float]],
) -> int:
    """Write the rows (run, time_s, cells, error_um); the number with an empty cell."""
    incomplete = 0
    with atomic_text(out_csv) as handle:  # a full disk leaves no half file behind
        writer = csv.writer(handle)
        writer.writerow(columns)
        for run, time_s, cells, error_um in rows:
            if any(cell is None for cell in cells):
                incomplete += 1
            writer.writerow(
                [run, _number(time_s), *(_number(cell) for cell in cells), _number(error_um)]
            )
    return incomplete


def _number(value: float | None) -> str:
    return "" if value is None else repr(float(value))


def _sensor_number(name: str) -> int:
    match = SENSOR_PATTERN.match(name)
    assert match is not None
    return int(match.group(1))


def _cycle_ns(times: Sequence[int], cycle_s: float | None) -> int:
    if cycle_s is not None:
        if cycle_s <= 0:
            raise ValueError(f"cycle_s must be positive, got {cycle_s}")
        return round(cycle_s * NS_PER_S)
    if len(times) < 2:
        return NS_PER_S  # a single cycle: assume the usual 1 s
    return max(1, round(statistics.median(b - a for a, b in itertools.pairwise(times))))


def _runs(times: Sequence[int], cycle_ns: int, gap_factor: float, machine: str) -> list[str]:
    """The run name of every cycle: a new run after a gap of more than gap_factor cycles."""
    names: list[str] = []
    used: set[str] = set()
    current = ""
    for i, time_ns in enumerate(times):
        if i == 0 or time_ns - times[i - 1] > gap_factor * cycle_ns:
            start = datetime.fromtimestamp(time_ns / NS_PER_S, UTC)
            current = base = f"{machine}-{start:%Y%m%dT%H%M%SZ}"
            suffix = 2
            while current in used:
                current = f"{base}-{suffix}"
                suffix += 1
            used.add(current)
        names.append(current)
    return names
