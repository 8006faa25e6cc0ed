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

The window is read in time slices of about :data:`SLICE_POINTS` points, twice: the
cycle times first (their count, the sensors, the median cycle from a bounded count of
intervals), then the rows, spooled beside the output until the columns are known. The
memory an export takes does not grow with its window (a year of history on the edge box).

The file passes :func:`models.data.dataset.load_runs`.
"""

from __future__ import annotations

import csv
import re
import tempfile
from collections import Counter
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from datetime import UTC, datetime
from pathlib import Path
from typing import IO

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


#: Points read at once, about: the export holds one time slice of points (and a bounded
#: count of cycle intervals), whatever the window's length. A slice starts 10 minutes long
#: and is halved after one of more points, doubled (to 4 h at most) after one of under a
#: quarter; a slice without points jumps to the next logged point.
SLICE_POINTS = 50_000
FIRST_SLICE_S = 600
MAX_SLICE_S = 4 * 3600
DAY_S = 86_400


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
    slice_points: int = SLICE_POINTS,
) -> ExportResult:
    """Write the measured-run CSV of ``machine`` for machine time ``start_s ≤ t < stop_s``.

    ``start_s``/``stop_s`` are machine seconds (``None``: unbounded); ``epoch_s``
    must be the one the points were made with (:func:`gateway.outputs.points.to_time_ns`).
    ``progress``: a bar over the export's steps (the scan of the cycle times, the rows,
    the file) on stderr. The window is read in time slices of about ``slice_points``
    points, twice (the cycle times first, for the median cycle), so the memory it takes
    does not grow with the window.
    """
    out_csv = Path(out_csv)
    start_ns = None if start_s is None else to_time_ns(start_s, epoch_s)
    stop_ns = None if stop_s is None else to_time_ns(stop_s, epoch_s)
    if slice_points < 1:
        raise ValueError(f"slice_points must be positive, got {slice_points}")
    if cycle_s is not None and cycle_s <= 0:
        raise ValueError(f"cycle_s must be positive, got {cycle_s}")
    reader = _SliceReader(points_source, machine, (start_ns, stop_ns), slice_points)
    bar = tqdm(total=len(EXPORT_STEPS), desc="export", unit="step", disable=not progress,
               leave=False, mininterval=0)  # fmt: skip
    out_csv.parent.mkdir(parents=True, exist_ok=True)
    # The rows wait beside the output (as large as it), not in a /tmp that may be in RAM.
    with (
        bar,
        tempfile.TemporaryFile("w+", encoding="utf-8", newline="", dir=out_csv.parent) as spool,
    ):
        return _export(reader, out_csv, epoch_s, cycle_s, gap_factor, good_only, bar, spool)


#: The steps of an export its progress bar counts.
EXPORT_STEPS = ("scan cycle times", "assemble rows", "write")


class _SliceReader:
    """The points of one machine's window, one measurement and time slice at a time: the
    slices sized by the points the first pass found in them, the same for the second."""

    def __init__(
        self,
        source: PointSource,
        machine: str,
        window_ns: tuple[int | None, int | None],
        slice_points: int,
    ) -> None:
        self.source = source
        self.machine = machine
        self.window_ns = window_ns
        self.slice_points = slice_points
        self.read_points = 0  # in the current slice
        self.bounds: list[tuple[int | None, int | None]] | None = None

    def slices(self) -> Iterator[tuple[int | None, int | None]]:
        """``[start, stop)`` time slices covering every point of the machine in the window
        (the whole window at once from a source that cannot tell its time span)."""
        if self.bounds is not None:
            yield from self.bounds
            return
        bounds = []
        for bound in self._sized_slices():
            bounds.append(bound)
            yield bound
        self.bounds = bounds

    def _sized_slices(self) -> Iterator[tuple[int | None, int | None]]:
        time_span = getattr(self.source, "time_span", None)
        if time_span is None:
            yield self.window_ns
            return
        span = time_span(self.machine, *self.window_ns)
        length_ns = FIRST_SLICE_S * NS_PER_S
        while span is not None:
            start_ns, last_ns = span
            stop_ns = min(start_ns + length_ns, last_ns + 1)
            self.read_points = 0
            yield start_ns, stop_ns
            if self.read_points > self.slice_points:
                length_ns = max(NS_PER_S, length_ns // 2)
            elif self.read_points < self.slice_points // 4:
                length_ns = min(MAX_SLICE_S * NS_PER_S, length_ns * 2)
            if stop_ns > last_ns:
                return
            span = (stop_ns, last_ns)
            if not self.read_points:  # skip a pause: on from the next logged point
                span = self._next_span(time_span, stop_ns, last_ns)

    def _next_span(
        self, time_span: Callable[..., tuple[int, int] | None], start_ns: int, last_ns: int
    ) -> tuple[int, int] | None:
        """From the first point at or after ``start_ns`` to ``last_ns``: looked for in the
        next day first, so a nightly pause does not scan the rest of the window."""
        day_ns = DAY_S * NS_PER_S
        found = time_span(self.machine, start_ns, min(last_ns + 1, start_ns + day_ns))
        if found is None and start_ns + day_ns <= last_ns:
            found = time_span(self.machine, start_ns + day_ns, last_ns + 1)
        return None if found is None else (found[0], last_ns)

    def read(self, measurement: str, slice_ns: tuple[int | None, int | None]) -> list[Point]:
        start_ns, stop_ns = slice_ns
        points = self.source.query(
            measurement, machine=self.machine, start_ns=start_ns, stop_ns=stop_ns
        )
        self.read_points += len(points)
        return points


def _export(
    reader: _SliceReader,
    out_csv: Path,
    epoch_s: float,
    cycle_s: float | None,
    gap_factor: float,
    good_only: bool,
    bar: tqdm,
    spool: IO[str],
) -> ExportResult:
    """:func:`export_runs`, one step of ``bar`` at a time: scan the cycle times (their
    count, the sensors, the median interval), assemble the rows into ``spool``, write."""

    def step() -> None:
        bar.set_postfix_str(f"{EXPORT_STEPS[bar.n]} done", refresh=False)
        bar.update(1)

    machine = reader.machine
    scan = _scan_times(reader)
    step()
    if not scan.n_times:
        raise ExportError(f"no cycles of machine '{machine}' in the time window")
    cycle_ns = _cycle_ns(scan.intervals, scan.n_times, cycle_s)
    candidates = _Layout.candidates(scan.sensors)
    rows = _RowWriter(spool, candidates, machine, epoch_s)
    check = _Plausible()
    _assemble(reader, rows, check, good_only, cycle_ns, gap_factor)
    step()
    layout = _Layout.of(scan.sensors, candidates, rows.filled)
    if not rows.count:
        raise ExportError(
            f"none of the {rows.n_times} cycle(s) of machine '{machine}' in the time window "
            "has a probe (spindle_probe error_um) value"
        )
    spool.seek(0)
    incomplete = _write_csv(out_csv, layout, candidates, spool)
    step()
    return ExportResult(
        path=out_csv,
        columns=layout.columns,
        runs=tuple(rows.runs),
        rows=rows.count,
        rows_without_probe=rows.n_times - rows.count,
        rows_incomplete=incomplete,
        cycle_s=cycle_ns / NS_PER_S,
        ignored_sensors=layout.ignored,
        implausible_values=check.implausible,
    )


@dataclass
class _TimeScan:
    """What the first pass learns: how many distinct cycle times, their intervals, and
    every sensor with a numeric reading."""

    n_times: int = 0
    intervals: _IntervalCounts = field(default_factory=lambda: _IntervalCounts())
    sensors: set[str] = field(default_factory=set)


def _scan_times(reader: _SliceReader) -> _TimeScan:
    """Stream the cycle and temperature times of the window, slice by slice: only the
    previous time is kept, the intervals go to a bounded counter."""
    scan = _TimeScan()
    previous: int | None = None
    for slice_ns in reader.slices():
        times = {p.time_ns for p in reader.read(CYCLE_MEASUREMENT, slice_ns)}
        for point in reader.read(TEMPERATURE_MEASUREMENT, slice_ns):
            sensor = point.tags.get("sensor")
            if sensor is not None and _number_field(point, "value_C") is not None:
                times.add(point.time_ns)
                scan.sensors.add(sensor)
        for time_ns in sorted(times):
            if previous is not None:
                scan.intervals.add(time_ns - previous)
            previous = time_ns
        scan.n_times += len(times)
    return scan


class _IntervalCounts:
    """A count of the intervals between cycles, for their median: exact while there are
    at most :attr:`LIMIT` distinct intervals (a steady cycle has a few); beyond, the
    intervals are counted in bins 10 × wider each time (1 µs, 10 µs, …), so the memory
    stays bounded and the median is within a bin's width."""

    LIMIT = 1 << 16

    def __init__(self) -> None:
        self.counts: Counter[int] = Counter()
        self.bin_ns = 1
        self.total = 0

    def add(self, interval_ns: int) -> None:
        self.counts[interval_ns // self.bin_ns] += 1
        self.total += 1
        if len(self.counts) > self.LIMIT:
            self.bin_ns *= 1000 if self.bin_ns == 1 else 10
            coarse: Counter[int] = Counter()
            factor = self.bin_ns if self.bin_ns == 1000 else 10
            for key, count in self.counts.items():
                coarse[key // factor] += count
            self.counts = coarse

    def median(self) -> float:
        """The median interval (ns), as :func:`statistics.median` gives it on the list."""
        middle = self.total // 2
        wanted = [middle - 1, middle] if self.total % 2 == 0 else [middle]
        found: list[float] = []
        seen = 0
        for key in sorted(self.counts):
            seen += self.counts[key]
            while wanted and wanted[0] < seen:
                wanted.pop(0)
                found.append(key * self.bin_ns + (self.bin_ns - 1) / 2)
            if not wanted:
                break
        return found[0] if len(found) == 1 else (found[0] + found[1]) / 2


def _assemble(
    reader: _SliceReader,
    rows: _RowWriter,
    check: _Plausible,
    good_only: bool,
    cycle_ns: int,
    gap_factor: float,
) -> None:
    """The second pass: each slice's cycles in time order, the probe values matched to
    them (from a cycle's time up to less than one cycle later; the last one wins), the
    finished rows handed to ``rows``. Only the cycle being filled crosses a slice."""
    runs = _RunNames(reader.machine, cycle_ns, gap_factor)
    current: _Row | None = None
    for slice_ns in reader.slices():
        cycles = reader.read(CYCLE_MEASUREMENT, slice_ns)
        speed = _speeds(cycles, check)
        cycle_times = {p.time_ns for p in cycles}
        del cycles
        readings = _readings(reader.read(TEMPERATURE_MEASUREMENT, slice_ns), check, good_only)
        probes = sorted(reader.read(PROBE_MEASUREMENT, slice_ns), key=lambda p: p.time_ns)
        events = sorted(
            [(t, 0, None) for t in cycle_times | set(readings)]
            + [(p.time_ns, 1, i) for i, p in enumerate(probes)],
            key=lambda e: (e[0], e[1], -1 if e[2] is None else e[2]),
        )
        for time_ns, kind, index in events:
            if kind == 0:
                rows.add(current)
                current = _Row(runs.name(time_ns), time_ns, speed.get(time_ns),
                               readings.get(time_ns, {}))  # fmt: skip
                continue
            assert index is not None
            value = _number_field(probes[index], "error_um")
            if value is None or not check(value, DISPLACEMENT_UM.low, DISPLACEMENT_UM.high):
                continue
            if current is not None and time_ns - current.time_ns < cycle_ns:
                current.error_um = value
    rows.add(current)


@dataclass
class _Row:
    """One cycle being assembled: its run, time, speed, readings and probe value."""

    run: str
    time_ns: int
    speed_rpm: float | None
    readings: dict[str, float | None]
    error_um: float | None = None


class _RowWriter:
    """Writes the finished rows with a probe value to the spool file, every candidate
    sensor's cell, and notes which sensors have a value in some row (the final columns)."""

    def __init__(self, spool: IO[str], candidates: list[str], machine: str, epoch_s: float):
        self.writer = csv.writer(spool)
        self.candidates = candidates
        self.epoch_s = epoch_s
        self.filled: set[str] = set()
        self.runs: dict[str, None] = {}
        self.count = 0
        self.n_times = 0

    def add(self, row: _Row | None) -> None:
        if row is None:
            return
        self.n_times += 1
        if row.error_um is None:
            return
        cells = [row.readings.get(s) for s in self.candidates]
        self.filled.update(s for s, c in zip(self.candidates, cells, strict=True) if c is not None)
        self.runs[row.run] = None
        self.count += 1
        time_s = round(row.time_ns / NS_PER_S - self.epoch_s, 6)
        self.writer.writerow([row.run, _number(time_s), _number(row.speed_rpm),
                              *(_number(c) for c in cells), _number(row.error_um)])  # fmt: skip


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
) -> dict[int, dict[str, float | None]]:
    """time_ns → sensor → °C (None where implausible or, with ``good_only``, not good)."""
    readings: dict[int, dict[str, float | None]] = {}
    for point in temperatures:
        sensor = point.tags.get("sensor")
        value = _number_field(point, "value_C")
        if sensor is None or value is None:
            continue
        good = point.tags.get("quality", "good") == "good"
        keep = check(value, TEMPERATURE_C.low, TEMPERATURE_C.high)
        readings.setdefault(point.time_ns, {})[sensor] = (
            value if keep and (good or not good_only) else None
        )
    return readings


@dataclass(frozen=True)
class _Layout:
    """Which sensors become columns, in which order, and which are left out."""

    exported: list[str]
    columns: tuple[str, ...]
    ignored: tuple[str, ...]

    @staticmethod
    def candidates(sensors: set[str]) -> list[str]:
        """The sensors that can be columns: ``T<n>`` by number, then the ambient one."""
        t_sensors = sorted((s for s in sensors if SENSOR_PATTERN.match(s)), key=_sensor_number)
        ambient = ambient_sensor_of(sensors)
        return [*t_sensors, *([ambient] if ambient else [])]

    @classmethod
    def of(cls, sensors: set[str], candidates: list[str], filled: set[str]) -> _Layout:
        ignored = tuple(sorted(sensors - set(candidates)))
        ambient = ambient_sensor_of(sensors)
        # A column with no value in any exported row would make every row unusable.
        exported = [s for s in candidates if s in filled]
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


def _write_csv(out_csv: Path, layout: _Layout, candidates: list[str], spool: IO[str]) -> int:
    """Copy the spooled rows (run, time_s, speed, every candidate's cell, error_um) to
    ``out_csv`` with the exported columns only; the number of rows with an empty cell."""
    keep = [0, 1, 2, *(3 + candidates.index(s) for s in layout.exported), 3 + len(candidates)]
    incomplete = 0
    with atomic_text(out_csv) as handle:  # a full disk leaves no half file behind
        writer = csv.writer(handle)
        writer.writerow(layout.columns)
        for spooled in csv.reader(spool):
            row = [spooled[i] for i in keep]
            if any(cell == "" for cell in row[2:-1]):
                incomplete += 1
            writer.writerow(row)
    return incomplete


def _number(value: float | None) -> str:
    return "" if value is None else repr(float(value))


def _sensor_number(name: str) -> int:
    match = SENSOR_PATTERN.match(name)
    assert match is not None
    return int(match.group(1))


def _cycle_ns(intervals: _IntervalCounts, n_times: int, cycle_s: float | None) -> int:
    """The cycle time: ``cycle_s`` when given, else the median interval between cycles."""
    if cycle_s is not None:
        return round(cycle_s * NS_PER_S)
    if n_times < 2:
        return NS_PER_S  # a single cycle: assume the usual 1 s
    return max(1, round(intervals.median()))


class _RunNames:
    """The run name of each cycle in time order: a new run after a gap of more than
    ``gap_factor`` cycles, named by its UTC start (``-2``, ``-3`` … when one repeats)."""

    def __init__(self, machine: str, cycle_ns: int, gap_factor: float) -> None:
        self.machine = machine
        self.gap_ns = gap_factor * cycle_ns
        self.previous: int | None = None
        self.used: set[str] = set()
        self.current = ""

    def name(self, time_ns: int) -> str:
        if self.previous is None or time_ns - self.previous > self.gap_ns:
            start = datetime.fromtimestamp(time_ns / NS_PER_S, UTC)
            self.current = base = f"{self.machine}-{start:%Y%m%dT%H%M%SZ}"
            suffix = 2
            while self.current in self.used:
                self.current = f"{base}-{suffix}"
                suffix += 1
            self.used.add(self.current)
        self.previous = time_ns
        return self.current
