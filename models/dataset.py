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

import csv
import re
from collections.abc import Iterable, Sequence
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import pandas as pd

SENSOR_PATTERN = re.compile(r"^T\d+$")
RUN_COLUMN = "run"
TIME_COLUMN = "time_s"
SPEED_COLUMN = "speed_rpm"
AMBIENT_COLUMN = "ambient_C"
AMBIENT_SENSORS = ("ambient_C", "ambient")  # machine sensor names that feed AMBIENT_COLUMN
DEFAULT_TARGET = "error_um"
HEADER_LINE = 1


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

    @property
    def n_samples(self) -> int:
        return int(self.time_s.shape[0])

    @property
    def run_ids(self) -> tuple[str, ...]:
        """Run identifiers in order of first appearance."""
        _, first = np.unique(self.run, return_index=True)
        return tuple(str(self.run[i]) for i in sorted(first))

    @property
    def run_index(self) -> np.ndarray:
        """(n,) run number 0, 1, … of each row, in order of first appearance."""
        order = {run_id: i for i, run_id in enumerate(self.run_ids)}
        return np.array([order[r] for r in self.run], dtype=int)

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
        return MeasuredRuns(
            source=self.source,
            run=self.run[rows],
            time_s=self.time_s[rows],
            speed_rpm=self.speed_rpm[rows],
            sensors=self.sensors,
            target=self.target,
            numeric={k: v[rows] for k, v in self.numeric.items()},
            labels={k: v[rows] for k, v in self.labels.items()},
            lines=self.lines[rows],
            skipped=self.skipped,
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
    """The header row's column names; refuses an empty file or duplicate names."""
    try:
        with path.open(newline="", encoding="utf-8") as handle:
            header = next(csv.reader(handle), None)
    except FileNotFoundError:
        raise DataError(path, None, None, "file not found") from None
    except UnicodeDecodeError as exc:
        raise DataError(path, None, None, f"not UTF-8 text ({exc.reason})") from None
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


def load_runs(
    path: str | Path,
    target: str = DEFAULT_TARGET,
    sensors: Sequence[str] | None = None,
) -> MeasuredRuns:
    """Read and check a measured-run CSV.

    Args:
        path: the file.
        target: the measured thermal-error column, µm (``--target``).
        sensors: the temperature columns the command needs (default: every
            ``T<n>`` column); an unknown name is refused.
    """
    path = Path(path)
    names = read_header(path)
    sensor_names = [n for n in names if SENSOR_PATTERN.match(n)]
    _require_columns(path, names, target, sensor_names, sensors)
    chosen_sensors = tuple(sensors) if sensors is not None else tuple(sensor_names)

    table = _read_table(path, len(names))
    table.columns = names
    if table.empty:
        raise DataError(path, HEADER_LINE + 1, None, "no data rows after the header")
    lines = np.arange(HEADER_LINE + 1, HEADER_LINE + 1 + len(table))

    required_numeric = [TIME_COLUMN, SPEED_COLUMN, *chosen_sensors, target]
    if AMBIENT_COLUMN in names:
        required_numeric.append(AMBIENT_COLUMN)
    needed = [RUN_COLUMN, *required_numeric]

    empty = table[needed].isna().any(axis=1).to_numpy()
    skipped: tuple[SkippedRows, ...] = ()
    if empty.any():
        skipped = (
            SkippedRows(
                count=int(empty.sum()),
                reason=f"an empty cell in a needed column ({', '.join(needed)})",
                first_lines=tuple(int(x) for x in lines[empty][:5]),
            ),
        )
        table = table.loc[~empty].reset_index(drop=True)
        lines = lines[~empty]
        if table.empty:
            raise DataError(path, None, None, "every data row has an empty needed cell")

    numeric: dict[str, np.ndarray] = {}
    labels: dict[str, np.ndarray] = {}
    for name in names:
        if name == RUN_COLUMN:
            continue
        if name in required_numeric:
            numeric[name] = _to_numbers(path, table[name], name, lines)
        else:
            converted = pd.to_numeric(table[name], errors="coerce").to_numpy(dtype=float)
            if np.all(np.isfinite(converted)):
                numeric[name] = converted
            else:
                labels[name] = table[name].fillna("").astype(str).to_numpy(dtype=object)

    run = table[RUN_COLUMN].str.strip().to_numpy(dtype=object)
    _check_runs(path, run, numeric[TIME_COLUMN], lines)
    return MeasuredRuns(
        source=str(path),
        run=run,
        time_s=numeric[TIME_COLUMN],
        speed_rpm=numeric[SPEED_COLUMN],
        sensors=chosen_sensors,
        target=target,
        numeric={k: v for k, v in numeric.items() if k not in (TIME_COLUMN, SPEED_COLUMN)},
        labels=labels,
        lines=lines,
        skipped=skipped,
    )


def _read_table(path: Path, n_columns: int) -> pd.DataFrame:
    """The cells, numbers parsed natively where a whole column is numeric.

    Only an empty cell counts as missing (NaN); text such as "nan" or "hot" keeps
    its column as text, so the check that follows can name the exact cell. A row
    with the wrong number of fields is refused by line.
    """
    try:
        return pd.read_csv(
            path,
            dtype={RUN_COLUMN: str},
            keep_default_na=False,
            na_values=[""],
            skip_blank_lines=False,
            skipinitialspace=True,
            encoding="utf-8",
        )
    except pd.errors.ParserError as exc:
        found = re.search(r"Expected (\d+) fields in line (\d+), saw (\d+)", str(exc))
        if found is None:
            raise DataError(path, None, None, f"not a readable CSV file ({exc})") from None
        raise DataError(
            path,
            int(found.group(2)),
            None,
            f"expected {n_columns} fields as in the header, found {found.group(3)}",
        ) from None


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
                path, HEADER_LINE, required, f"missing required column (header has: {header})"
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


def _to_numbers(path: Path, cells: pd.Series, name: str, lines: np.ndarray) -> np.ndarray:
    """Convert a required column, naming the first bad cell exactly."""
    values = pd.to_numeric(cells, errors="coerce").to_numpy(dtype=float)
    bad = ~np.isfinite(values)
    if bad.any():
        row = int(np.flatnonzero(bad)[0])
        raise DataError(
            path,
            int(lines[row]),
            name,
            f"expected a finite number, found '{cells.iloc[row]}'",
        )
    return values


def group_bounds(labels: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """First row and end row (exclusive) of each contiguous block of equal labels."""
    starts = np.flatnonzero(np.r_[True, labels[1:] != labels[:-1]])
    return starts, np.r_[starts[1:], labels.size]


def _check_runs(path: Path, run: np.ndarray, time_s: np.ndarray, lines: np.ndarray) -> None:
    """Runs must be contiguous blocks with strictly increasing time."""
    starts, _ = group_bounds(run)
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
    same_run = run[1:] == run[:-1]
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
