"""What a recording must show before a model is fitted on it, and what deserves a remark.

The loader (:mod:`models.data.dataset`) checks every cell; these checks look at whole
columns, where a fault of the recording rather than of one row shows:

- an error column that never changes within a run has no thermal error in it: a
  model fitted on it predicts a constant, 0 µm once the reference is taken, and would
  be saved as if it compensated something. ``fit`` refuses it (``analyze`` refuses it
  too, in :mod:`models.analysis.search`).
- sensor columns that read the same on every row are one reading exported to several
  columns (a mapping or export fault): the fit is still defined — the estimators
  share the weight among the copies, as for one sensor — so it is a located warning.
- a speed that is 0 on every row is a machine at rest: warming from the room alone
  is a legitimate recording, but the model learns nothing of the spindle's own heat,
  so it is a located warning too.
"""

from __future__ import annotations

import numpy as np

from models.data.dataset import HEADER_LINE, DataError, MeasuredRuns


def refuse_constant_target(data: MeasuredRuns) -> None:
    """Refuse a target column that does not change within any run (a model of nothing)."""
    values = data.error_um
    for _, rows in data.run_slices():
        known = values[rows][np.isfinite(values[rows])]
        if known.size > 1 and np.ptp(known) > 0:
            return
    finite = values[np.isfinite(values)]
    held = f" ({finite[0]:g} µm on every row)" if finite.size and np.ptp(finite) == 0 else ""
    raise DataError(
        data.source,
        HEADER_LINE,
        data.target,
        f"does not change within any run{held}: there is no thermal error to fit; the "
        "measured displacement in µm, varying as the machine warms, was expected "
        "(see --target)",
    )


def recording_remarks(data: MeasuredRuns) -> list[str]:
    """Located warnings on the whole recording: copied sensor columns, a spindle at rest."""
    if data.n_samples == 0:
        return []
    span = f"lines {int(data.lines[0])}–{int(data.lines[-1])}" if data.lines.size else "every row"
    remarks = []
    for group in _identical_columns(data):
        names = ", ".join(f"'{name}'" for name in group)
        every = "every sensor column" if len(group) == len(data.sensors) else "columns"
        remarks.append(
            f"{data.source}:{HEADER_LINE}: {every} {names} read the same on every row "
            f"({span}): one reading exported to several columns? Sensors at different "
            "places were expected; the model sees them as one sensor"
        )
    speed = data.speed_rpm
    if speed.size and np.all(speed == 0):
        remarks.append(
            f"{data.source}:{HEADER_LINE}: column 'speed_rpm' is 0 r/min on every row "
            f"({span}): the spindle never turned, so the model learns nothing of its heat; "
            "a recording with the spindle running was expected"
        )
    return remarks


def _identical_columns(data: MeasuredRuns) -> list[list[str]]:
    """Groups of two or more sensor columns equal on every row (NaN equal to NaN)."""
    groups: list[list[str]] = []
    for name in data.sensors:
        values = data.numeric.get(name)
        if values is None:
            continue
        for group in groups:
            if np.array_equal(data.numeric[group[0]], values, equal_nan=True):
                group.append(name)
                break
        else:
            groups.append([name])
    return [group for group in groups if len(group) > 1]
