"""Loading measured runs (the measured-run CSV of the public contract).

One row per sample, header first, comma-separated, UTF-8:

    run, time_s, speed_rpm, T1, T2, …, [ambient_C], error_um, [other columns]

Every problem is refused with a :class:`DataError` that names the file, the
1-based line of the file and the column, and says what was expected and what was
found. Nothing is dropped silently: a row with an empty cell in a column the
command needs is skipped, and the loader reports how many rows and why
(:attr:`MeasuredRuns.skipped`), so the command can print it.

The file is read with pandas (C parser, fast on million-row files) as text, then
every numeric column is converted and checked in bulk; a failing cell is located
exactly for the message.
"""

from __future__ import annotations

import codecs
import csv
import re
from collections.abc import Iterable, Sequence
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd

from models.data import csv_text
from models.data.unit_ranges import (
    SENSOR_PATTERN,
    TIME_COLUMN,
    bounds_of,
    first_implausible,
    has_unit,
    why_implausible,
)

RUN_COLUMN = "run"
SPEED_COLUMN = "speed_rpm"
REVERSE_NOTE = "speed_rpm reversed"  # key of the note on negative speeds
AMBIENT_COLUMN = "ambient_C"
AMBIENT_SENSORS = ("ambient_C", "ambient")  # machine sensor names that feed AMBIENT_COLUMN
DEFAULT_TARGET = "error_um"
HEADER_LINE = 1
CHUNK_ROWS = 1 << 18  # rows parsed per block: about 30 MB of a 14-column file
# A number as pandas' C parser reads it (leading/trailing blanks are stripped first).
NUMBER_PATTERN = r"[+-]?(\d+\.?\d*|\.\d+)([eE][+-]?\d+)?|[+-]?inf(inity)?"


class DataError(ValueError):
    """Bad measured-run input: says where (file, line, column) and what was expected."""

    def __init__(self, path: str | Path, line: int | None, column: str | None, message: str):
        self.path = str(path)
        self.line = line
        self.column = column
        self.reason = message
        where = self.path if line is None else f"{self.path}:{line}"
        what = f"column '{column}': " if column else ""
        super().__init__(f"{where}: {what}{message}")


@dataclass(frozen=True)
class SkippedRows:
    """Rows left out because a needed cell was empty: how many, why, and where."""

    count: int
    reason: str
    first_lines: tuple[int, ...]

    def describe(self) -> str:
        lines = ", ".join(str(line) for line in self.first_lines)
        more = " …" if self.count > len(self.first_lines) else ""
        return f"skipped {self.count} row(s): {self.reason} (lines {lines}{more})"


@dataclass(frozen=True)
class MeasuredRuns:
    """The samples of one file, in file order; each run's rows are contiguous.

    Attributes:
        source: the file read.
        run: (n,) run identifier of each row.
        time_s: (n,) seconds, increasing within each run.
        speed_rpm: (n,) spindle speed, r/min.
        sensors: names of the machine temperature columns (``T`` + digits), °C.
        target: name of the measured thermal-error column, µm.
        numeric: every numeric column by name (sensors, target, ambient, others).
        labels: text columns other than ``run`` (e.g. a regime label), by name.
        lines: (n,) 1-based file line of each row, for messages.
        skipped: rows left out and why (empty when none were).
        notes: optional columns not used as signals and why (a bad cell in a
            column the command does not need does not refuse the file).
        released: columns whose readings were let go after their rises were
            taken (:meth:`without_readings`), each with whether its readings
            varied at all; ``column_order`` then keeps every numeric column's
            place in the file.
    """

    source: str
    run: np.ndarray
    time_s: np.ndarray
    speed_rpm: np.ndarray
    sensors: tuple[str, ...]
    target: str
    numeric: dict[str, np.ndarray]
    labels: dict[str, np.ndarray] = field(default_factory=dict)
    lines: np.ndarray = field(default_factory=lambda: np.zeros(0, dtype=int))
    skipped: tuple[SkippedRows, ...] = ()
    notes: tuple[str, ...] = ()
    released: dict[str, bool] = field(default_factory=dict)
    column_order: tuple[str, ...] = ()  # every numeric column in file order, once released

    @property
    def n_samples(self) -> int:
        return int(self.time_s.shape[0])

    @property
    def run_ids(self) -> tuple[str, ...]:
        """Run identifiers in order of first appearance."""
        starts, _ = group_bounds(self.run)
        return tuple(dict.fromkeys(str(self.run[s]) for s in starts))

    @property
    def run_index(self) -> np.ndarray:
        """(n,) run number 0, 1, … of each row, in order of first appearance."""
        starts, ends = group_bounds(self.run)
        order = {run_id: i for i, run_id in enumerate(self.run_ids)}
        numbers = [order[str(self.run[s])] for s in starts]
        return np.repeat(np.array(numbers, dtype=np.int32), ends - starts)

    def run_slices(self) -> list[tuple[str, slice]]:
        """(run id, row slice) per run, in file order (runs are contiguous)."""
        starts, ends = group_bounds(self.run)
        return [
            (str(self.run[s]), slice(int(s), int(e))) for s, e in zip(starts, ends, strict=True)
        ]

    def temperatures(self, names: Sequence[str] | None = None) -> np.ndarray:
        """(n, k) temperatures in °C of the named sensors (default: all)."""
        names = self.sensors if names is None else tuple(names)
        return np.column_stack([self.column(name) for name in names])

    @property
    def error_um(self) -> np.ndarray:
        return self.numeric[self.target]

    @property
    def ambient_C(self) -> np.ndarray | None:
        return self.numeric.get(AMBIENT_COLUMN)

    def column(self, name: str) -> np.ndarray:
        if name in self.numeric:
            return self.numeric[name]
        raise DataError(
            self.source,
            HEADER_LINE,
            name,
            f"no such numeric column (numeric columns: {', '.join(self.numeric)})",
        )

    def take(self, rows: np.ndarray) -> MeasuredRuns:
        """The same data restricted to ``rows`` (boolean mask or index array)."""
        return replace(
            self,
            run=self.run[rows],
            time_s=self.time_s[rows],
            speed_rpm=self.speed_rpm[rows],
            numeric={k: v[rows] for k, v in self.numeric.items()},
            labels={k: v[rows] for k, v in self.labels.items()},
            lines=self.lines[rows],
        )

    def without_readings(self, names: Sequence[str]) -> MeasuredRuns:
        """The same runs without the readings of ``names``.

        For a command that has taken the rises of these columns and reads
        nothing else of them: on a million-row file each column is megabytes.
        Whether each one varied is kept, for the residual analysis.
        """
        released = dict(self.released)
        released |= {n: bool(np.ptp(self.numeric[n]) > 0) for n in names if n in self.numeric}
        return replace(
            self,
            numeric={k: v for k, v in self.numeric.items() if k not in released},
            released=released,
            column_order=self.column_order or tuple(self.numeric),
        )

    def label_per_run(self, column: str) -> dict[str, str]:
        """The value of a label column for each run; refuses a run with two values."""
        if column in self.labels:
            values = self.labels[column]
        elif column in self.numeric:
            values = np.array([f"{v:g}" for v in self.numeric[column]], dtype=object)
        else:
            raise DataError(
                self.source,
                HEADER_LINE,
                column,
                f"no such column (columns: {', '.join([*self.numeric, *self.labels])})",
            )
        result: dict[str, str] = {}
        for run_id, rows in self.run_slices():
            distinct = list(dict.fromkeys(values[rows]))
            if len(distinct) != 1:
                line = int(self.lines[rows][list(values[rows]).index(distinct[1])])
                raise DataError(
                    self.source,
                    line,
                    column,
                    f"run '{run_id}' changes its {column} from '{distinct[0]}' to "
                    f"'{distinct[1]}'; one value per run was expected",
                )
            result[run_id] = str(distinct[0])
        return result


def read_header(path: Path) -> list[str]:
    """The header row's column names; refuses an unreadable or empty file, or duplicate names.

    A UTF-8 byte order mark (as spreadsheet programs write) is accepted.
    """
    raw = _first_line(path)
    if raw.startswith(codecs.BOM_UTF8):
        raw = raw[len(codecs.BOM_UTF8) :]
    if b"\0" in raw:
        raise DataError(path, HEADER_LINE, None, "a NUL byte: binary data where text was expected")
    try:
        text = raw.decode("utf-8")
    except UnicodeDecodeError as exc:
        raise DataError(
            path,
            HEADER_LINE,
            None,
            csv_text.undecodable(raw[exc.start]),
        ) from None
    header = next(csv.reader([text.rstrip("\r\n")]), None)
    if header is None or not any(cell.strip() for cell in header):
        raise DataError(path, HEADER_LINE, None, "the file is empty; a header row was expected")
    names = [cell.strip() for cell in header]
    seen: set[str] = set()
    for name in names:
        if not name:
            raise DataError(path, HEADER_LINE, None, "a column has an empty name")
        if name in seen:
            raise DataError(path, HEADER_LINE, name, "column name appears twice")
        seen.add(name)
    return names


def _first_line(path: Path) -> bytes:
    """The file's first line as bytes, after checking it is a readable regular file."""
    if not path.exists():
        raise DataError(path, None, None, "file not found")
    if path.is_dir():
        raise DataError(path, None, None, "is a directory; a measured-run CSV file was expected")
    if not path.is_file():
        raise DataError(
            path, None, None, "not a regular file; a measured-run CSV file was expected"
        )
    try:
        with path.open("rb") as handle:
            return handle.readline()
    except PermissionError:
        raise DataError(path, None, None, "cannot be read: permission denied") from None
    except OSError as exc:
        raise DataError(path, None, None, f"cannot be read: {exc.strerror}") from None


def load_runs(
    path: str | Path,
    target: str = DEFAULT_TARGET,
    sensors: Sequence[str] | None = None,
    sparse_target: bool = False,
    also_targets: Sequence[str] = (),
) -> MeasuredRuns:
    """Read and check a measured-run CSV.

    Args:
        path: the file.
        target: the measured thermal-error column, µm (``--target``).
        sensors: the temperature columns the command needs (default: every
            ``T<n>`` column); an unknown name is refused.
        sparse_target: the target is known only at some rows (probe rows of a
            logged history): a row with an empty target is kept (NaN there);
            the values present are checked as always.
        also_targets: more error columns read in the same pass, for a command on
            several targets (:mod:`models.data.targets`); then a row with an empty
            sensor, ambient or target cell is kept (NaN there) and each target's view
            leaves out the rows its own single-target read would have skipped.
    """
    path = Path(path)
    names = read_header(path)
    sensor_names = [n for n in names if SENSOR_PATTERN.match(n)]
    for name in (target, *also_targets):
        _require_columns(path, names, name, sensor_names, sensors)
    chosen_sensors = tuple(sensors) if sensors is not None else tuple(sensor_names)

    scanned = csv_text.scan(path, len(names))
    if isinstance(scanned, csv_text.TextProblem):
        column = names[scanned.field] if scanned.field is not None else None
        raise DataError(path, scanned.line, column, scanned.reason)
    if scanned == 0:
        raise DataError(path, HEADER_LINE + 1, None, "no data rows after the header")

    extra = [name for name in dict.fromkeys(also_targets) if name != target]
    needed = [TIME_COLUMN, SPEED_COLUMN, *chosen_sensors, target, *extra]
    if AMBIENT_COLUMN in names:
        needed.append(AMBIENT_COLUMN)
    reader = _ColumnReader(path, names, needed, capacity=scanned)
    if sparse_target:
        reader.sparse = {target}
    if also_targets:  # each target's view drops the rows its own read would skip
        reader.sparse = set(needed) - {TIME_COLUMN, SPEED_COLUMN}
    table = reader.read()
    _check_runs(path, table.run, table.run_code, table.numeric[TIME_COLUMN], table.lines)
    return MeasuredRuns(
        source=str(path),
        run=table.run,
        time_s=table.numeric[TIME_COLUMN],
        speed_rpm=table.numeric[SPEED_COLUMN],
        sensors=chosen_sensors,
        target=target,
        numeric={k: v for k, v in table.numeric.items() if k not in (TIME_COLUMN, SPEED_COLUMN)},
        labels=table.labels,
        lines=table.lines,
        skipped=table.skipped,
        notes=table.notes,
    )


@dataclass
class _Table:
    run: np.ndarray
    run_code: np.ndarray
    numeric: dict[str, np.ndarray]
    labels: dict[str, np.ndarray]
    lines: np.ndarray
    skipped: tuple[SkippedRows, ...]
    notes: tuple[str, ...]


@dataclass
class _Filling:
    """The arrays a read fills chunk by chunk (allocated once for every row of the file)."""

    numbers: dict[str, np.ndarray]
    run_code: np.ndarray
    lines: np.ndarray
    text_parts: dict[str, list[np.ndarray]]
    run_ids: dict[str, int] = field(default_factory=dict)
    filled: int = 0
    skipped_count: int = 0
    skipped_first: list[int] = field(default_factory=list)

    @classmethod
    def empty(cls, n: int, typed: Iterable[str], text: Iterable[str]) -> _Filling:
        return cls(
            numbers={name: np.empty(n) for name in typed},
            run_code=np.empty(n, dtype=np.int32),
            lines=np.empty(n, dtype=np.int32),
            text_parts={name: [] for name in text},
        )


@dataclass(frozen=True)
class _Part:
    """One chunk of the file on its way into the arrays: the kept rows and where they go."""

    chunk: pd.DataFrame
    keep: slice | np.ndarray  # the chunk's rows kept
    lines: np.ndarray  # their line numbers in the file
    rows: slice  # where they go in the arrays


class _UnparsedCellError(Exception):
    """The typed read met a cell its float parser refused (located by a second pass)."""


class _ColumnReader:
    """Reads the file column-wise into preallocated float64 arrays, one block of rows at a time.

    Columns whose name carries a unit (and every column the command needs) are
    parsed straight to float64 by pandas' C parser; ``run`` is read as a
    category (a few distinct strings, shared by every row); any other column is
    read as text and kept as a number only if every cell is one. Each block is
    checked as it arrives, so a bad value is refused before the rest is read, and
    memory stays at the final arrays plus one block.
    """

    def __init__(self, path: Path, names: list[str], needed: list[str], capacity: int) -> None:
        self.path = path
        self.names = names
        self.needed = needed
        self.capacity = capacity
        self.typed = [n for n in names if n != RUN_COLUMN and (n in needed or has_unit(n))]
        self.text: list[str] = [n for n in names if n != RUN_COLUMN and n not in self.typed]
        self.notes: dict[str, str] = {}
        self.sparse: set[str] = set()  # needed columns that may be empty (NaN kept)

    def read(self) -> _Table:
        try:
            return self._read()
        except _UnparsedCellError:
            pass
        # A cell the float parser refused: find it; a needed column is refused there,
        # any other column with text is read as text and the file read again.
        demoted = self._locate_text()
        if not demoted:
            raise DataError(self.path, None, None, "not a readable CSV file") from None
        self.typed = [n for n in self.typed if n not in demoted]
        self.text = [n for n in self.names if n != RUN_COLUMN and n not in self.typed]
        try:
            return self._read()
        except _UnparsedCellError:
            raise DataError(self.path, None, None, "not a readable CSV file") from None

    def _chunks(self, dtypes: dict[str, Any], usecols: list[str] | None = None):
        try:
            yield from pd.read_csv(
                self.path,
                header=0,
                names=self.names,
                usecols=usecols,
                dtype=dtypes,
                encoding="utf-8-sig",
                keep_default_na=False,
                na_values=[""],
                skip_blank_lines=False,
                skipinitialspace=True,
                chunksize=CHUNK_ROWS,
                engine="c",
            )
        except pd.errors.ParserError as exc:
            found = re.search(r"line (\d+)", str(exc))
            line = int(found.group(1)) if found else None
            raise DataError(self.path, line, None, f"not a readable CSV file ({exc})") from None
        except ValueError as exc:
            raise _UnparsedCellError(str(exc)) from None

    def _read(self) -> _Table:
        fill = _Filling.empty(self.capacity, self.typed, self.text)
        dtypes: dict[str, Any] = {RUN_COLUMN: "category"}
        dtypes |= {name: np.float64 for name in self.typed}
        dtypes |= {name: str for name in self.text}
        next_line = HEADER_LINE + 1
        for chunk in self._chunks(dtypes):
            m = len(chunk)
            if fill.filled + m > self.capacity:
                raise DataError(self.path, None, None, "not a readable CSV file (rows miscounted)")
            chunk_lines = np.arange(next_line, next_line + m, dtype=np.int32)
            next_line += m
            keep = self._rows_to_keep(chunk, chunk_lines, fill)
            kept_lines = chunk_lines[keep]
            rows = slice(fill.filled, fill.filled + kept_lines.size)
            part = _Part(chunk, keep, kept_lines, rows)
            self._store_needed(part, fill.numbers)
            self._store_optional(part, fill.numbers)
            self._store_runs_and_text(part, fill)
            del part
            fill.lines[rows] = kept_lines
            fill.filled += kept_lines.size
            del chunk
        if fill.filled == 0:
            raise DataError(
                self.path,
                fill.skipped_first[0] if fill.skipped_first else HEADER_LINE + 1,
                None,
                "every data row has an empty needed cell" if fill.skipped_count else "no data rows",
            )
        for array in (fill.run_code, fill.lines, *fill.numbers.values()):
            array.resize(fill.filled, refcheck=False)
        numeric, labels = self._typed_columns(fill)
        return _Table(
            run=np.array(list(fill.run_ids), dtype=object)[fill.run_code],
            run_code=fill.run_code,
            numeric=numeric,
            labels=labels,
            lines=fill.lines,
            skipped=self._skipped(fill),
            notes=tuple(self.notes.values()),
        )

    def _rows_to_keep(
        self, chunk: pd.DataFrame, chunk_lines: np.ndarray, fill: _Filling
    ) -> slice | np.ndarray:
        """The chunk's rows with every needed cell filled; the others are counted."""
        dense = [name for name in self.needed if name not in self.sparse]
        empty = chunk[[RUN_COLUMN, *dense]].isna().to_numpy().any(axis=1)
        if not empty.any():
            return slice(None)
        fill.skipped_count += int(empty.sum())
        fill.skipped_first += [int(x) for x in chunk_lines[empty][: 5 - len(fill.skipped_first)]]
        return ~empty

    def _store_needed(self, part: _Part, numbers: dict[str, np.ndarray]) -> None:
        """Copy the needed columns; the first implausible value (by line) is an error."""
        worst: tuple[int, str, float] | None = None
        for name in self.needed:
            values = part.chunk[name].to_numpy(dtype=np.float64)[part.keep]
            if name == SPEED_COLUMN:
                values = self._speed_magnitude(values, part.lines)
            bad = first_implausible(values, bounds_of(name))
            if bad is not None and name in self.sparse:
                present = np.flatnonzero(~np.isnan(values))
                found = first_implausible(values[present], bounds_of(name))
                bad = None if found is None else int(present[found])
            if bad is not None and (worst is None or bad < worst[0]):
                worst = (bad, name, float(values[bad]))
            numbers[name][part.rows] = values
        if worst is not None:
            bad, name, value = worst
            raise DataError(
                self.path, int(part.lines[bad]), name, why_implausible(value, bounds_of(name))
            )

    def _store_optional(self, part: _Part, numbers: dict[str, np.ndarray]) -> None:
        """Copy the optional columns; one with an implausible value is set aside (a note)."""
        for name in self.typed:
            if name in self.needed or name in self.notes:
                continue
            values = part.chunk[name].to_numpy(dtype=np.float64)[part.keep]
            bad = first_implausible(values, bounds_of(name))
            if bad is not None:
                self.notes[name] = _set_aside(name, int(part.lines[bad]), float(values[bad]))
            numbers[name][part.rows] = values

    def _store_runs_and_text(self, part: _Part, fill: _Filling) -> None:
        """Each kept row's run as a code (runs numbered in order of appearance), and the
        text columns' cells."""
        runs = part.chunk[RUN_COLUMN].array
        code_of = np.array(
            [fill.run_ids.setdefault(str(c).strip(), len(fill.run_ids)) for c in runs.categories],
            dtype=np.int32,
        )
        fill.run_code[part.rows] = code_of[np.asarray(runs.codes)[part.keep]]
        for name in self.text:
            fill.text_parts[name].append(
                part.chunk[name].fillna("").to_numpy(dtype=object)[part.keep]
            )

    def _skipped(self, fill: _Filling) -> tuple[SkippedRows, ...]:
        if not fill.skipped_count:
            return ()
        columns = ", ".join([RUN_COLUMN, *self.needed])
        return (
            SkippedRows(
                count=fill.skipped_count,
                reason=f"an empty cell in a needed column ({columns})",
                first_lines=tuple(fill.skipped_first),
            ),
        )

    def _typed_columns(self, fill: _Filling) -> tuple[dict[str, np.ndarray], dict[str, np.ndarray]]:
        """Numeric columns (a text column whose every cell is a plausible number counts),
        and label columns."""
        numeric: dict[str, np.ndarray] = {}
        labels: dict[str, np.ndarray] = {}
        for name in self.names:
            if name in fill.numbers and name not in self.notes:
                numeric[name] = fill.numbers[name]
            elif name in fill.text_parts:
                cells = np.concatenate(fill.text_parts.pop(name))
                converted = pd.to_numeric(pd.Series(cells), errors="coerce").to_numpy(float)
                if first_implausible(converted, bounds_of(name)) is None:
                    numeric[name] = converted
                else:
                    labels[name] = cells
        return numeric, labels

    def _speed_magnitude(self, values: np.ndarray, lines: np.ndarray) -> np.ndarray:
        """A control that signs the speed by direction (M04, reverse) heats the bearings as
        much as forward: the magnitude counts, as in the live loop; noted once per file."""
        negative = np.flatnonzero(values < 0)
        if negative.size == 0:
            return values
        if REVERSE_NOTE not in self.notes:
            first = int(negative[0])
            self.notes[REVERSE_NOTE] = (
                f"column '{SPEED_COLUMN}': line {int(lines[first])}: a negative speed "
                f"({values[first]:g} r/min, turning in reverse); its magnitude is used"
            )
        return np.abs(values)

    def _locate_text(self) -> set[str]:
        """Typed columns holding a cell that is not a number; refuses one the command needs."""
        found: dict[str, tuple[int, str]] = {}
        next_line = HEADER_LINE + 1
        dtypes = {name: str for name in self.typed}
        for chunk in self._chunks(dtypes, usecols=self.typed):
            for name in self.typed:
                if name in found:
                    continue
                cells = chunk[name]
                text = cells.notna().to_numpy() & ~cells.str.strip().str.fullmatch(
                    NUMBER_PATTERN, flags=re.IGNORECASE
                ).fillna(True).to_numpy(dtype=bool)
                if text.any():
                    row = int(np.argmax(text))
                    found[name] = (next_line + row, str(cells.iloc[row]))
            needed = [(line, name) for name, (line, _) in found.items() if name in self.needed]
            if needed:
                line, name = min(needed)
                raise DataError(
                    self.path,
                    line,
                    name,
                    f"expected a finite number, found {found[name][1]!r} "
                    f"(the column holds {bounds_of(name).what})",
                )
            next_line += len(chunk)
        for name, (line, cell) in found.items():
            self.notes[name] = (
                f"column '{name}' is read as text, not as {bounds_of(name).what}: "
                f"line {line} holds {cell!r}"
            )
        return set(found)


def _set_aside(name: str, line: int, value: float) -> str:
    """The note for an optional numeric column that is not used because of one value."""
    what = "an empty cell" if np.isnan(value) else why_implausible(value, bounds_of(name))
    return f"column '{name}' is not used as a signal: line {line}: {what}"


def _require_columns(
    path: Path,
    names: list[str],
    target: str,
    sensor_names: list[str],
    sensors: Sequence[str] | None,
) -> None:
    header = ", ".join(names)
    for required in (RUN_COLUMN, TIME_COLUMN, SPEED_COLUMN):
        if required not in names:
            raise DataError(
                path,
                HEADER_LINE,
                required,
                f"missing required column (header has: {header}){_separator_hint(names)}",
            )
    if target not in names:
        if target == DEFAULT_TARGET:
            message = f"missing required column (header has: {header}); pass --target COLUMN"
        else:
            message = f"unknown --target: no such column (header has: {header})"
        raise DataError(path, HEADER_LINE, target, message)
    if not sensor_names:
        raise DataError(
            path, HEADER_LINE, "T1", f"no temperature columns named T<n> (header has: {header})"
        )
    for name in sensors or ():
        if name not in names:
            raise DataError(
                path,
                HEADER_LINE,
                name,
                f"unknown sensor in --sensors (temperature columns: {', '.join(sensor_names)})",
            )


def _separator_hint(names: list[str]) -> str:
    """Why a header read as one column, when another separator split it: a spreadsheet
    saved with regional settings writes ';' (and decimal commas), a logger often tabs."""
    if len(names) != 1:
        return ""
    for separator, called in ((";", "';'"), ("\t", "tabs"), ("|", "'|'")):
        if separator in names[0]:
            return (
                f"; the header is one column separated by {called}: the format is "
                "comma-separated with a decimal point"
            )
    return ""


def group_bounds(labels: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """First row and end row (exclusive) of each contiguous block of equal labels."""
    starts = np.flatnonzero(np.r_[True, labels[1:] != labels[:-1]])
    return starts, np.r_[starts[1:], labels.size]


def _check_runs(
    path: Path, run: np.ndarray, run_code: np.ndarray, time_s: np.ndarray, lines: np.ndarray
) -> None:
    """Runs must be contiguous blocks with strictly increasing time (``run_code``: the
    same runs as small integers, compared faster than strings)."""
    starts, _ = group_bounds(run_code)
    seen: dict[str, int] = {}
    for start in starts:
        run_id = str(run[start])
        if run_id in seen:
            raise DataError(
                path,
                int(lines[start]),
                RUN_COLUMN,
                f"run '{run_id}' starts again after other runs (first seen at line "
                f"{seen[run_id]}); the rows of one run must be contiguous",
            )
        seen[run_id] = int(lines[start])
    same_run = run_code[1:] == run_code[:-1]
    backwards = same_run & (np.diff(time_s) <= 0)
    if backwards.any():
        row = int(np.flatnonzero(backwards)[0]) + 1
        raise DataError(
            path,
            int(lines[row]),
            TIME_COLUMN,
            f"time does not increase within run '{run[row]}': {time_s[row]:g} s after "
            f"{time_s[row - 1]:g} s at line {int(lines[row - 1])}",
        )


def ambient_sensor_of(sensor_names: Iterable[str]) -> str | None:
    """The machine sensor that measures the hall, if any (``AMBIENT_SENSORS``, in order)."""
    names = set(sensor_names)
    return next((name for name in AMBIENT_SENSORS if name in names), None)
