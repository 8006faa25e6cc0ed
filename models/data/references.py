"""Where temperature rises and errors are measured from.

Every model works on *rises*: ΔT = T − T_ref (paper 002 §4: "ΔT1 is the change
of T1 relative to its initial temperature") and on the error as the probe measured
it. The questions are which samples are the temperatures' reference, and what the
error's reference is.

Recordings
----------
- A run that starts cold (its own experiment, the machine at rest and at room
  temperature) is its own recording.
- A run that is one part of a continuous recording (the heating–cooling cycles of
  ``fl_thermal.csv``) does *not* start cold: the machine is still warm from the
  cycle before, and the displacement probe was not re-zeroed. Its references are
  those of the recording it belongs to, so the rises carry across cycles exactly
  as the machine carried its heat.

Policies (``--reference``):

- ``run-start``: every run is its own recording.
- ``recording-start``: all runs of the file form one recording.
- ``auto`` (default): a run continues the recording of the run before it in the
  file when its first ``time_s`` follows that run's last ``time_s`` by more than
  0 and at most ``CONTINUITY_FACTOR`` (3) × that run's median sample interval —
  i.e. the clock ran on without a break. Otherwise (time restarts, clock-of-day
  stamps of another day, or a gap) it starts a new recording and is taken to
  start cold.

Temperatures (and ``ambient_C`` and other candidate signals)
------------------------------------------------------------
The reference of a recording is the mean of its leading samples taken *at rest*
(``speed_rpm`` = 0) within its first ``REFERENCE_WINDOW_S`` (600 s): a thermal
test zeroes its probes on the cold machine before the spindle starts (ISO 230-3;
``fl_thermal.csv`` opens with 7.5 min at rest). A recording whose first sample
is already at speed has its first sample as reference (a temperature sensor's
noise, a few hundredths of a °C, is negligible next to the rises). The speed's
own reference is 0 r/min: the cold reference is the machine at rest.

The error: a model parameter, not one reading
----------------------------------------------
The error is **never** rebased on a reading of the recording it belongs to by
default. One probe reading carries the probe's noise (and, when the spindle is
already turning, the direct speed growth at that speed) into every later sample
of the recording as a constant offset that no model can predict. The error's
reference is instead the model's intercept, fitted with the model on every
training recording together: one common zero, the probe's zero on the cold
machine at rest, as a gauge is zeroed before a test. A gateway works the same
way: it never rebases its error mid-recording; it compensates the model's
prediction, intercept included, from its cold temperature reference
(``gateway/live/reference.py``).

Only when the data say that a recording's probe reads from an origin of its own
is that recording's error taken from a reference of its own. The test
(``own_origin``): the recording opens *at rest* (its first sample has
``speed_rpm`` = 0) and the mean of its at-rest lead-in (the same rows as the
temperatures' reference) lies more than ``ZERO_TOLERANCE_UM`` (1 µm) from zero.
A cold machine at rest has no thermal error, so a probe that reads far from zero
there was not zeroed on this machine state (an absolute gauge, or one zeroed for
another test); the lead-in mean is then that recording's origin and is
subtracted. A recording that opens at speed never has an origin of its own (its
first readings already hold the speed's growth); one that opens at rest reading
zero within the tolerance keeps the error as measured (subtracting its lead-in
mean would only add the mean's noise). 1 µm is several times a probe's noise
(0.1–0.5 µm) and well below any growth worth compensating.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from models.catalogue import POLICIES as POLICIES
from models.data.dataset import MeasuredRuns, group_bounds

CONTINUITY_FACTOR = 3.0
REFERENCE_WINDOW_S = 600.0
ZERO_TOLERANCE_UM = 1.0


@dataclass(frozen=True)
class ReferencePlan:
    """Which recording each row belongs to and where that recording starts."""

    policy: str
    recording: np.ndarray  # (n,) recording number of each row
    recording_runs: tuple[tuple[str, ...], ...]  # run ids of each recording
    reference_rows: np.ndarray  # (n,) bool: the rows each recording's reference is the mean of
    #: (recordings,) origin of each recording's error, µm: 0 where the error is kept as
    #: measured (the model's intercept is its reference), else the at-rest lead-in mean
    error_origin_um: np.ndarray

    def rises(self, values: np.ndarray) -> np.ndarray:
        """``values`` above each recording's reference (see :func:`rises`)."""
        return rises(values, self.recording, self.reference_rows)

    @property
    def own_origin(self) -> np.ndarray:
        """(recordings,) bool: whose error is taken from an origin of its own."""
        return self.error_origin_um != 0.0

    def error(self, error_um: np.ndarray) -> np.ndarray:
        """The error a model is fitted on: as measured, less an own origin where the data
        show one (module docstring); never a subtraction of one reading."""
        error_um = np.asarray(error_um, dtype=float)
        if not self.own_origin.any():
            return error_um
        return error_um - self.error_origin_um[self.recording]

    def error_line(self) -> str:
        """One line for people: where the error is taken from."""
        own = [
            f"{'+'.join(runs)} {origin:+.2f} µm"
            for runs, origin in zip(self.recording_runs, self.error_origin_um, strict=True)
            if origin != 0.0
        ]
        text = "error as measured, its reference the model's intercept"
        return text + (f"; own origin subtracted: {', '.join(own)}" if own else "")

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
            "error_reference": {
                "rule": (
                    "the error as measured, its reference the model's intercept fitted on "
                    "every training recording; a recording that opens at rest with an at-rest "
                    f"lead-in mean more than {ZERO_TOLERANCE_UM:g} um from zero reads from an "
                    "origin of its own, and that mean is subtracted"
                ),
                "zero_tolerance_um": ZERO_TOLERANCE_UM,
                "origin_um": [float(v) for v in self.error_origin_um],
            },
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
    chosen = reference_rows(recording, data.time_s, data.speed_rpm)
    return ReferencePlan(
        policy=policy,
        recording=recording,
        recording_runs=tuple(tuple(groups[k]) for k in sorted(groups)),
        reference_rows=chosen,
        error_origin_um=error_origins(data.error_um, recording, chosen, data.speed_rpm),
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


def error_origins(
    error_um: np.ndarray, recording: np.ndarray, reference: np.ndarray, speed_rpm: np.ndarray
) -> np.ndarray:
    """(recordings,) origin of each recording's error, µm (the test of the module docstring).

    0 for a recording that opens at speed or whose at-rest lead-in (the ``reference``
    rows) reads zero within ``ZERO_TOLERANCE_UM``; else the lead-in mean.
    """
    starts, ends = group_bounds(recording)
    origins = np.zeros(starts.size)
    for k, (start, end) in enumerate(zip(starts, ends, strict=True)):
        if speed_rpm[start] != 0:
            continue
        lead_in = np.asarray(error_um[start:end], dtype=float)[reference[start:end]]
        mean = float(lead_in.mean())
        if abs(mean) > ZERO_TOLERANCE_UM:
            origins[k] = mean
    return origins


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
