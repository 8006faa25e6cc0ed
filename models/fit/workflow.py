"""The ``fit`` workflow: validate a method on held-out runs, fit it, store it.

Three ways to group the data:

- all runs together → one model (regime ``all``);
- ``per_run`` → one model per run, as paper 002 fits Y1…Y6 on K1…K6, plus the
  cross-evaluation σ matrix of every model on every run;
- ``regime_column`` → one model per regime label (e.g. ``spectrum``/``constant``
  or a speed band), each validated leave-one-run-out inside its regime; the
  per-run cross-evaluation is ranked as paper 002 ranks it, to say which run is
  the best to model each regime from.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from models.base import ModelInputs
from models.data.dataset import MeasuredRuns
from models.data.features import Prepared
from models.estimators.registry import make_model
from models.estimators.sensor_relations import fit_relations
from models.fit.conditioning import DEFAULT_SENSOR_ACCURACY_C, Conditioning, assess
from models.fit.crossval import Validation, cross_evaluate, cross_validate, fold_labels
from models.fit.forward import Disagreement, Forward, disagreement, forward_validate
from models.fit.forward_progress import counted
from models.fit.interval import calibrate, forward_scaled_residuals
from models.fit.ranking import RegimeReport, SigmaRow, rank_regimes
from models.store import ModelStore, build_document


@dataclass
class FitOutcome:
    """What one ``fit`` produced: validations, stored files, cross-evaluation."""

    method: str
    validations: dict[str, Validation] = field(default_factory=dict)  # by regime / run
    saved: dict[str, Path] = field(default_factory=dict)  # model id → file
    sigma_rows: list[SigmaRow] = field(default_factory=list)
    ranking: RegimeReport | None = None
    summaries: dict[str, str] = field(default_factory=dict)
    conditioning: dict[str, Conditioning] = field(default_factory=dict)  # model id → figures
    #: by regime: each later recording (or run) predicted from the earlier ones only
    forward: dict[str, Forward] = field(default_factory=dict)
    agreement: dict[str, Disagreement] = field(default_factory=dict)  # forward vs LORO


def model_id_for(method: str, target: str, group: str) -> str:
    return f"{method}-{target}-{group}"


def fit_and_store(
    prepared: Prepared,
    method: str,
    store: ModelStore | None,
    sensors: Sequence[str] | None = None,
    per_run: bool = False,
    regime_column: str | None = None,
    progress: bool = False,
    software_version: str = "unknown",
    sensor_accuracy_C: float = DEFAULT_SENSOR_ACCURACY_C,
    data_with_readings: MeasuredRuns | None = None,
) -> FitOutcome:
    """Validate, fit and store ``method`` per group. With ``data_with_readings`` (the file
    as loaded, the sensors' readings kept) the model of all runs is validated forward
    too (:mod:`models.fit.forward`)."""

    def factory():
        return make_model(method, sensors)

    outcome = FitOutcome(method=method)
    data = prepared.data
    if per_run:
        regime_of_run = {run: f"run:{run}" for run in data.run_ids}
        groups = {run: data.run == run for run in data.run_ids}
    elif regime_column:
        regime_of_run = data.label_per_run(regime_column)
        groups = {
            regime: np.isin(data.run, [r for r, g in regime_of_run.items() if g == regime])
            for regime in dict.fromkeys(regime_of_run.values())
        }
    else:
        regime_of_run = {run: "all" for run in data.run_ids}
        groups = {"all": np.ones(data.n_samples, dtype=bool)}

    if per_run or regime_column:
        _, outcome.sigma_rows = cross_evaluate(factory, prepared, regime_of_run, progress)
        if regime_column:
            outcome.ranking = rank_regimes(outcome.sigma_rows)

    for group, rows in groups.items():
        part = prepared if rows.all() else prepared.take(rows)  # no copy of the whole data set
        validation = None if per_run else cross_validate(factory, part, progress)
        model = factory().fit(part.inputs, part.error_um)
        label = f"run-{group}" if per_run else group
        model_id = model_id_for(method, data.target, label)
        if validation is not None:
            outcome.validations[group] = validation
            _validate_forward(outcome, group, factory, part, data_with_readings, sensors, progress)
        summary = getattr(model, "summary", None)
        if callable(summary):
            outcome.summaries[model_id] = summary()
        conditioning = assess(model, part.inputs, sensor_accuracy_C)
        outcome.conditioning[model_id] = conditioning
        if store is None:
            continue
        document = build_document(
            model,
            model_id=model_id,
            inputs=part.inputs,
            error_um=part.error_um,
            target=data.target,
            source_file=data.source,
            runs=list(part.data.run_ids),
            reference=prepared.plan.describe(),
            regime=regime_of_run[group] if per_run else group,
            validation=_validation_record(validation, outcome.sigma_rows, group, per_run),
            software_version=software_version,
            conditioning=conditioning.as_dict(),
            sensor_relations=relations_document(part.inputs),
            interval=interval_record(validation, part, outcome.forward.get(group)),
        )
        outcome.saved[document["model_id"]] = store.save(document)
    return outcome


def _validate_forward(
    outcome: FitOutcome,
    group: str,
    factory,
    prepared: Prepared,
    data: MeasuredRuns | None,
    sensors: Sequence[str] | None,
    progress: bool = False,
) -> None:
    """The forward figure of ``group`` (every run; none without the readings) and how it
    compares with leave-one-run-out; ``progress``: a bar over its folds."""
    if data is None or prepared.data.n_samples != data.n_samples:
        return
    with counted(factory, prepared, progress) as made:
        forward = forward_validate(made, prepared, data, sensors)
    if forward is None:
        return
    validation = outcome.validations[group]
    outcome.forward[group] = forward
    outcome.agreement[group] = disagreement(
        forward, validation.predicted_um, prepared.error_um, prepared.data.run
    )


def _validation_record(
    validation: Validation | None, sigma_rows: list[SigmaRow], group: str, per_run: bool
) -> dict[str, object]:
    if validation is not None:
        return validation.as_dict()
    # A per-run model is validated by how it predicts every other run (paper 002 Table 3).
    others = {r.data: r.sigma_um for r in sigma_rows if r.model == group and r.data != group}
    return {"scheme": "cross-evaluation on the other runs", "sigma_um_by_run": others}


def fit_sensor_fallbacks(
    prepared: Prepared,
    method: str,
    store: ModelStore,
    sensors: Sequence[str] | None = None,
    software_version: str = "unknown",
) -> dict[str, Path]:
    """For each declared sensor, a model fitted without it (regime ``all``).

    The runtime switches to one of these when a sensor its model needs goes bad
    (open circuit, stuck, out of range), instead of losing compensation.
    """
    declared = list(sensors) if sensors is not None else list(prepared.inputs.sensors)
    saved: dict[str, Path] = {}
    for left_out in declared:
        remaining = [s for s in declared if s != left_out]
        if not remaining:
            continue

        def factory(remaining=remaining):
            return make_model(method, remaining)

        validation = cross_validate(factory, prepared)
        model = factory().fit(prepared.inputs, prepared.error_um)
        document = build_document(
            model,
            model_id=model_id_for(method, prepared.data.target, f"all-without-{left_out}"),
            inputs=prepared.inputs,
            error_um=prepared.error_um,
            target=prepared.data.target,
            source_file=prepared.data.source,
            runs=list(prepared.data.run_ids),
            reference=prepared.plan.describe(),
            regime="all",
            validation=validation.as_dict(),
            software_version=software_version,
            conditioning=assess(model, prepared.inputs).as_dict(),
            sensor_relations=relations_document(prepared.inputs),
            interval=interval_record(validation, prepared),
        )
        saved[document["model_id"]] = store.save(document)
    return saved


def relations_document(inputs: ModelInputs) -> dict[str, object] | None:
    """The training sensors' relations (:mod:`models.estimators.sensor_relations`) to store.

    Fitted on every sensor of the training inputs, not only the model's own, so a
    fallback model carries the relation of the sensor it does without. None when
    the data cannot support one (fewer than two sensors, or too few rows).
    """
    if len(inputs.sensors) < 2:
        return None
    try:
        return fit_relations(inputs.rise_C, inputs.sensors, inputs.run_index).as_document()
    except ValueError:
        return None


def interval_record(
    validation: Validation | None, prepared: Prepared, forward: Forward | None = None
) -> dict[str, object] | None:
    """The calibrated interval (:mod:`models.fit.interval`) from the held-out predictions,
    each row labelled by the run (or block) it was held out with, and from the forward
    figure's where there is one; None without held-out predictions."""
    if validation is None:
        return None
    labels = fold_labels(prepared)[1]
    forward_res = forward_labels = None
    if forward is not None:
        run = prepared.data.run
        units = [
            (
                np.flatnonzero(np.isin(run, forward.runs[unit])),
                np.flatnonzero(np.isin(run, forward.trained_on[unit])),
            )
            for unit in forward.folds
        ]
        forward_res = forward_scaled_residuals(
            forward.measured_um, forward.predicted_um, prepared.inputs, units
        )
        forward_labels = np.concatenate([run[rows] for rows, _ in units]) if units else None
    return calibrate(
        prepared.error_um,
        validation.predicted_um,
        labels,
        prepared.inputs,
        forward_abs_residuals_um=forward_res,
        forward_run_labels=forward_labels,
    )
