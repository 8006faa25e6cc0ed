"""Several error columns of one file, read once: a machine compensates X, Y and Z.

``fit``, ``analyze``, ``score`` and ``replay`` take ``--target`` several times, or
``--target all``: every error column of the file. An error column is a numeric
column whose name ends in ``_um`` (a displacement in µm, docs/data-format.md); the
file is read in one pass with every target (:func:`load_targets`), and each
target's :func:`view` holds exactly the rows a read of that target alone would
keep, so its figures are those of a single-target run.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import replace
from pathlib import Path

import numpy as np

from models.data.dataset import (
    AMBIENT_COLUMN,
    HEADER_LINE,
    RUN_COLUMN,
    SPEED_COLUMN,
    TIME_COLUMN,
    DataError,
    MeasuredRuns,
    SkippedRows,
    load_runs,
    read_header,
)

ALL = "all"
ERROR_SUFFIX = "_um"


def error_columns(names: Sequence[str]) -> list[str]:
    """The error columns of a header, in file order."""
    return [name for name in names if name.endswith(ERROR_SUFFIX)]


def chosen_targets(path: str | Path, given: Sequence[str]) -> list[str]:
    """``--target`` as given (repeatable), ``all`` replaced by every error column of the
    file; each target once, in the order given."""
    if ALL not in given:
        return list(dict.fromkeys(given))
    names = read_header(Path(path))
    every = error_columns(names)
    if not every:
        raise DataError(
            path,
            HEADER_LINE,
            None,
            f"--target all: no error column (a name ending in '{ERROR_SUFFIX}', µm) in the "
            f"header ({', '.join(names)})",
        )
    expanded = [name for item in given for name in (every if item == ALL else [item])]
    return list(dict.fromkeys(expanded))


def load_targets(
    path: str | Path,
    targets: Sequence[str],
    sensors: Sequence[str] | None = None,
    sparse_target: bool = False,
) -> MeasuredRuns:
    """The file read once with every target; one target: exactly today's single read."""
    if len(targets) == 1:
        return load_runs(path, target=targets[0], sensors=sensors, sparse_target=sparse_target)
    return load_runs(
        path,
        target=targets[0],
        sensors=sensors,
        sparse_target=sparse_target,
        also_targets=targets[1:],
    )


def view(
    data: MeasuredRuns,
    target: str,
    sensors: Sequence[str] | None = None,
    sparse_target: bool = False,
) -> MeasuredRuns:
    """``data`` (read by :func:`load_targets`) as a read of ``target`` with ``sensors``
    alone would give it: the rows with an empty cell in one of its needed columns left
    out (and counted as skipped), the target and sensors set."""
    chosen = tuple(sensors) if sensors is not None else data.sensors
    needed = [*chosen, *([] if sparse_target else [target])]
    if AMBIENT_COLUMN in data.numeric:
        needed.append(AMBIENT_COLUMN)  # the single read's order: sensors, target, ambient
    keep = np.ones(data.n_samples, dtype=bool)
    for name in needed:
        keep &= np.isfinite(data.column(name))
    if keep.all():
        return replace(data, target=target, sensors=chosen)
    if not keep.any():
        raise DataError(
            data.source,
            int(data.lines[0]),
            target,
            "every data row has an empty needed cell",
        )
    dropped = [int(line) for line in data.lines[~keep]]
    before = data.skipped[0] if data.skipped else SkippedRows(0, "", ())
    columns = ", ".join([RUN_COLUMN, TIME_COLUMN, SPEED_COLUMN, *needed])
    skipped = SkippedRows(  # as a read of this target alone words it: one count, every cause
        count=before.count + len(dropped),
        reason=f"an empty cell in a needed column ({columns})",
        first_lines=tuple(sorted({*before.first_lines, *dropped[:5]})[:5]),
    )
    narrowed = replace(data.take(keep), skipped=(skipped,))
    return replace(narrowed, target=target, sensors=chosen)
