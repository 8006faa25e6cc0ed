"""Where temperature rises and errors are measured from.

Every model works on *rises*: ΔT = T − T_ref and Δe = e − e_ref (paper 002 §4:
"ΔT1 is the change of T1 relative to its initial temperature"). The question is
which sample is the reference.

- A run that starts cold (its own experiment, the machine at rest and at room
  temperature) is its own reference: its first samples (see below).
- A run that is one part of a continuous recording (the heating–cooling cycles of
  ``fl_thermal.csv``) does *not* start cold: the machine is still warm from the
  cycle before, and the displacement probe was not re-zeroed. Taking that run's
  first samples as reference would claim zero error in a warm machine. Its
  reference is the start of the recording it belongs to, so the rises
  carry across cycles exactly as the machine carried its heat.

Policies (``--reference``):

- ``run-start``: every run is its own recording.
- ``recording-start``: all runs of the file form one recording.
- ``auto`` (default): a run continues the recording of the run before it in the
  file when its first ``time_s`` follows that run's last ``time_s`` by more than
  0 and at most ``CONTINUITY_FACTOR`` (3) × that run's median sample interval —
  i.e. the clock ran on without a break. Otherwise (time restarts, or a gap) it
  starts a new recording and is taken to start cold.

The reference of a recording is the mean of its leading samples taken *at rest*
(``speed_rpm`` = 0) within its first ``REFERENCE_WINDOW_S`` (600 s): a thermal
test zeroes its probes on the cold machine before the spindle starts (ISO 230-3;
``fl_thermal.csv`` opens with 7.5 min at rest). One probe reading carries the
probe's noise into every later rise of its run as a constant offset; the mean of
several at-rest readings does not. A recording whose first sample is already at
speed has its first sample as reference. The speed's own reference is then 0
whenever the recording starts at rest, the convention the runtime uses too.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from models.catalogue import POLICIES as POLICIES
from models.dataset import MeasuredRuns, group_bounds

CONTINUITY_FACTOR = 3.0
REFERENCE_WINDOW_S = 600.0


@dataclass(frozen=True)
class ReferencePlan:
    """Which recording each row belongs to and where that recording starts."""

    policy: str
    recording: np.ndarray  # (n,) recording number of each row
    recording_runs: tuple[tuple[str, ...], ...]  # run ids of each recording
    reference_rows: np.ndarray  # (n,) bool: the rows each recording's reference is the mean of

    def rises(self, values: np.ndarray) -> np.ndarray:
        """``values`` above each recording's reference (see :func:`rises`)."""
        return rises(values, self.recording, self.reference_rows)

    def describe(self) -> dict[str, object]:
        """The plan as stored with a model (how references are taken)."""
        return {
            "policy": self.policy,
            "reference_sample": (
                "mean of the recording's leading samples at rest (speed_rpm 0) within its first "
                f"{REFERENCE_WINDOW_S:g} s; its first sample if the spindle is already turning"
            ),
            "continuity_rule": (
                f"a run continues the previous run's recording when its first time_s follows "
                f"the previous last time_s by >0 and <= {CONTINUITY_FACTOR:g} x the median "
                "sample interval"
            ),
            "recordings": [list(runs) for runs in self.recording_runs],
        }


def plan_references(data: MeasuredRuns, policy: str = "auto") -> ReferencePlan:
    if policy not in POLICIES:
        raise ValueError(f"unknown reference policy '{policy}'; expected one of {POLICIES}")
    slices = data.run_slices()
    recording_of_run: list[int] = []
    for i, (_, rows) in enumerate(slices):
        if i == 0:
            recording_of_run.append(0)
            continue
        if policy == "run-start":
            continues = False
        elif policy == "recording-start":
            continues = True
        else:
            continues = _follows_on(data.time_s, slices[i - 1][1], rows)
        recording_of_run.append(recording_of_run[-1] + (0 if continues else 1))

    recording = np.empty(data.n_samples, dtype=np.int32)  # a few recordings, many rows
    groups: dict[int, list[str]] = {}
    for (run_id, rows), number in zip(slices, recording_of_run, strict=True):
        recording[rows] = number
        groups.setdefault(number, []).append(run_id)
    return ReferencePlan(
        policy=policy,
        recording=recording,
        recording_runs=tuple(tuple(groups[k]) for k in sorted(groups)),
        reference_rows=reference_rows(recording, data.time_s, data.speed_rpm),
    )


def reference_rows(recording: np.ndarray, time_s: np.ndarray, speed_rpm: np.ndarray) -> np.ndarray:
    """Each recording's first sample, and the at-rest samples that follow it without a break
    within ``REFERENCE_WINDOW_S``."""
    chosen = np.zeros(recording.size, dtype=bool)
    for start, end in zip(*group_bounds(recording), strict=True):
        chosen[start] = True
        if speed_rpm[start] != 0:
            continue
        window = np.searchsorted(time_s[start:end], time_s[start] + REFERENCE_WINDOW_S, "right")
        moving = np.flatnonzero(speed_rpm[start : start + window] != 0)
        chosen[start : start + (moving[0] if moving.size else window)] = True
    return chosen


def _follows_on(time_s: np.ndarray, previous: slice, current: slice) -> bool:
    before = time_s[previous]
    gap = time_s[current][0] - before[-1]
    interval = float(np.median(np.diff(before))) if before.size > 1 else np.inf
    return bool(0 < gap <= CONTINUITY_FACTOR * interval)


def first_rows(group: np.ndarray) -> np.ndarray:
    """(n,) index of the first row of each row's contiguous group (recording or run)."""
    starts, _ = group_bounds(group)
    return starts[np.searchsorted(starts, np.arange(group.size), side="right") - 1]


def rises(values: np.ndarray, recording: np.ndarray, reference: np.ndarray) -> np.ndarray:
    """values − their mean over the ``reference`` rows of each row's recording.

    Works for (n,) and (n, k). Recordings are numbered 0, 1, … as
    :func:`plan_references` numbers them.
    """
    values = np.asarray(values, dtype=float)
    labels = recording[reference]
    counts = np.bincount(labels, minlength=int(recording.max()) + 1).astype(float)
    sums = np.zeros((counts.size, *values.shape[1:]))
    np.add.at(sums, labels, values[reference])
    means = sums / counts.reshape(-1, *([1] * (values.ndim - 1)))
    return values - means[recording]
