"""Forward validation: each later recording predicted by a model fitted on the earlier ones.

A plant fits a model on last month's runs and runs it on next month's. Leave-one-run-out
(:mod:`models.fit.crossval`) predicts a run from the runs either side of it, and inside one
continuous recording it hands the held-out run the lag states the recording carried into
it. Neither holds on the next recording: the gateway takes its temperature reference
there afresh (cold reference) and starts every history term from that sample, as
``score`` does. A term that relies on history the runtime will not have (a 24 h lag
learned inside one 30 h recording) scores well leave-one-run-out and fails there.

The forward scheme predicts, in time order, each *unit* from a model fitted on the units
before it only:

- with two or more recordings, a unit is a recording;
- with one recording, a unit is a run; each is predicted as a new recording would be,
  prepared on its own (its own cold reference, its error taken by the same rules,
  every lag started at its first sample), exactly as ``score`` treats a later file.

The first unit predicted is the one after at least half of the units (and at least
:data:`MIN_TRAINING_RUNS` runs): a model fitted on one cycle says little about the method.
Nothing is chosen on a predicted unit; each model's own choices (penalties, structure)
are made inside its training units, as at ``fit``.

:func:`disagreement` says when the forward and leave-one-run-out figures differ by more
than their spread (the standard deviation of the per-unit RMSEs of both schemes on the
units predicted forward): then leave-one-run-out cannot be trusted for a later recording.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass

import numpy as np

from models.base import ThermalModel
from models.data.dataset import MeasuredRuns
from models.data.features import Prepared, prepare
from models.fit.metrics import Accuracy, accuracy

#: The fewest runs a forward fold is fitted on.
MIN_TRAINING_RUNS = 2
SCHEME = (
    "forward: each later unit (recording, or run in time order) predicted by a model "
    "fitted on the earlier units only, started as a new recording (cold reference, "
    "history terms from its first sample)"
)


@dataclass(frozen=True)
class Forward:
    """Forward predictions and their accuracy, per predicted unit and pooled."""

    unit: str  # "recording" or "run"
    folds: tuple[str, ...]  # the predicted units, in time order
    runs: dict[str, tuple[str, ...]]  # unit -> its runs
    trained_on: dict[str, tuple[str, ...]]  # unit -> the runs its model was fitted on
    per_fold: dict[str, Accuracy]
    pooled: Accuracy
    measured_um: np.ndarray  # the predicted rows' error, as each unit was prepared
    predicted_um: np.ndarray

    def as_dict(self) -> dict[str, object]:
        return {
            "scheme": SCHEME,
            "unit": self.unit,
            "pooled": self.pooled.as_dict(),
            "per_fold": {name: acc.as_dict() for name, acc in self.per_fold.items()},
            "runs": {name: list(runs) for name, runs in self.runs.items()},
            "trained_on": {name: list(runs) for name, runs in self.trained_on.items()},
        }


def forward_units(prepared: Prepared) -> tuple[str, list[tuple[str, tuple[str, ...]]]]:
    """("recording" | "run", [(unit name, its runs)]) in time order."""
    recordings = prepared.plan.recording_runs
    if len(recordings) >= 2:
        return "recording", [("+".join(runs), tuple(runs)) for runs in recordings]
    return "run", [(run, (run,)) for run in prepared.data.run_ids]


def first_predicted(units: Sequence[tuple[str, tuple[str, ...]]]) -> int | None:
    """Index of the first unit predicted forward (None: too few units)."""
    runs_before = np.cumsum([0] + [len(runs) for _, runs in units])
    for k in range(1, len(units)):
        if 2 * k >= len(units) and runs_before[k] >= MIN_TRAINING_RUNS:
            return k
    return None


def forward_validate(
    factory: Callable[[], ThermalModel],
    prepared: Prepared,
    data: MeasuredRuns,
    sensors: Sequence[str] | None = None,
) -> Forward | None:
    """Forward figure of the model ``factory`` makes (None: fewer than two units to use).

    ``prepared`` is the whole file as ``fit`` prepared it; ``data`` the file as loaded,
    with the sensors' readings (a predicted unit takes its own reference from them).
    """
    unit, units = forward_units(prepared)
    start = first_predicted(units)
    if start is None:
        return None
    per_fold: dict[str, Accuracy] = {}
    trained_on: dict[str, tuple[str, ...]] = {}
    unit_runs: dict[str, tuple[str, ...]] = {}
    measured, predicted = [], []
    for k in range(start, len(units)):
        name, runs = units[k]
        earlier = tuple(r for _, rs in units[:k] for r in rs)
        train = prepared.take(np.isin(prepared.data.run, earlier))
        model = factory().fit(train.inputs, train.error_um)
        test = prepare(data.take(np.isin(data.run, runs)), sensors, prepared.plan.policy)
        values = model.predict(test.inputs)
        per_fold[name] = accuracy(test.error_um, values)
        trained_on[name] = earlier
        unit_runs[name] = runs
        measured.append(test.error_um)
        predicted.append(values)
    measured_um, predicted_um = np.concatenate(measured), np.concatenate(predicted)
    return Forward(
        unit=unit,
        folds=tuple(per_fold),
        runs=unit_runs,
        trained_on=trained_on,
        per_fold=per_fold,
        pooled=accuracy(measured_um, predicted_um),
        measured_um=measured_um,
        predicted_um=predicted_um,
    )


@dataclass(frozen=True)
class Disagreement:
    """Forward against leave-one-run-out on the units predicted forward."""

    forward_rmse_um: float
    loro_rmse_um: float  # leave-one-run-out, pooled over the same rows
    spread_um: float
    disagree: bool

    def as_dict(self) -> dict[str, object]:
        return {
            "forward_rmse_um": self.forward_rmse_um,
            "loro_rmse_um_same_runs": self.loro_rmse_um,
            "spread_um": self.spread_um,
            "disagree": self.disagree,
        }

    def sentence(self) -> str:
        if not self.disagree:
            return (
                f"forward {self.forward_rmse_um:.2f} µm and leave-one-run-out "
                f"{self.loro_rmse_um:.2f} µm on the same runs agree within their spread "
                f"({self.spread_um:.2f} µm)"
            )
        worse = "worse" if self.forward_rmse_um > self.loro_rmse_um else "better"
        return (
            f"forward and leave-one-run-out disagree: on a later recording this model scores "
            f"{self.forward_rmse_um:.2f} µm, {worse} than the {self.loro_rmse_um:.2f} µm "
            f"leave-one-run-out gives on the same runs, by more than their spread "
            f"({self.spread_um:.2f} µm); trust the forward figure for a later recording"
        )


def disagreement(
    forward: Forward, loro_predicted_um: np.ndarray, loro_measured_um: np.ndarray, run: np.ndarray
) -> Disagreement:
    """Forward against leave-one-run-out (row-aligned with ``run``) on the forward units.

    The spread is the standard deviation of the per-unit RMSEs of both schemes together
    (ddof 1); the two disagree when their pooled RMSEs differ by more than it.
    """
    loro_rmse, forward_rmse = [], []
    rows = []
    for name, acc in forward.per_fold.items():
        mask = np.isin(run, forward.runs[name])
        rows.append(mask)
        e = loro_measured_um[mask] - loro_predicted_um[mask]
        loro_rmse.append(float(np.sqrt(np.mean(e**2))))
        forward_rmse.append(acc.rmse_um)
    every = np.logical_or.reduce(rows)
    e = loro_measured_um[every] - loro_predicted_um[every]
    loro = float(np.sqrt(np.mean(e**2)))
    values = np.array(loro_rmse + forward_rmse)
    spread = float(np.std(values, ddof=1)) if values.size > 1 else 0.0
    fwd = forward.pooled.rmse_um
    return Disagreement(fwd, loro, spread, bool(abs(fwd - loro) > spread) and math.isfinite(fwd))
