"""The ``fit`` command's work: prepare the runs, fit, validate, save, report (§3).

The command (:mod:`gateway.cli.main`) parses the options and loads the file; this
module imports the fitting stack (scipy, scikit-learn), so the command imports it
only once the file is known good.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

from gateway import __version__
from gateway.offline.tables import accuracy_table, sigma_matrix_table
from gateway.offline.targets import combined, each_target, say_heading
from models.data.dataset import MeasuredRuns
from models.data.features import Prepared, prepare
from models.fit.forward import Forward
from models.fit.ranking import format_report
from models.fit.workflow import FitOutcome, fit_and_store
from models.store import ModelStore


@dataclass(frozen=True)
class FitRequest:
    """What the ``fit`` command was asked (its options, parsed)."""

    data_csv: Path
    method: str
    target: str
    sensors: list[str] | None
    reference: str
    progress: bool
    store_dir: Path
    per_run: bool
    regime_column: str | None
    sensor_accuracy_C: float
    max_bias_error_um: float
    collinearity: str = "short"  # "full": every input's VIF and bias sensitivity


def run_fit(
    data: MeasuredRuns,
    request: FitRequest,
    say: Callable[[str], None],
    warn: Callable[[str], None],
    prepared: Prepared | None = None,
) -> dict[str, Any]:
    """Fit ``request.method`` on ``data``, save it to the store, print the validation;
    return the command's JSON. ``prepared``: ``data`` already prepared (several targets)."""
    if prepared is None:
        prepared = prepare(data, request.sensors, request.reference).without_sensor_readings()
    _say_inputs(prepared, request, say)
    outcome = fit_and_store(
        prepared,
        request.method,
        ModelStore(request.store_dir),
        sensors=request.sensors,
        per_run=request.per_run,
        regime_column=request.regime_column,
        progress=request.progress,
        software_version=__version__,
        sensor_accuracy_C=request.sensor_accuracy_C,
        data_with_readings=data,
    )
    _say_outcome(outcome, request, say, warn)
    return {
        "method": request.method,
        "target": request.target,
        "reference": prepared.plan.describe(),
        "validations": {g: v.as_dict() for g, v in outcome.validations.items()},
        "sigma": [row.__dict__ for row in outcome.sigma_rows],
        "ranking": outcome.ranking.as_json() if outcome.ranking else None,
        "saved": {k: str(v) for k, v in outcome.saved.items()},
        "conditioning": {k: c.as_dict() for k, c in outcome.conditioning.items()},
        "forward": {
            g: {**f.as_dict(), "against_loro": outcome.agreement[g].as_dict()}
            for g, f in outcome.forward.items()
        },
    }


def run_fit_targets(
    data: MeasuredRuns,
    targets: list[str],
    request: FitRequest,
    say: Callable[[str], None],
    warn: Callable[[str], None],
) -> dict[str, Any]:
    """:func:`run_fit` for each target of ``data`` (read once, prepared once), one section
    each; the command's JSON (:func:`gateway.offline.targets.combined`)."""
    results: dict[str, dict[str, Any]] = {}
    runs = each_target(data, targets, request.sensors, request.reference, request.progress)
    for one in runs:
        say_heading(one, data, targets, say, warn)
        asked = replace(request, target=one.target)
        results[one.target] = run_fit(one.data, asked, say, warn, one.prepared)
    return combined(results, {"method": request.method})


def _say_inputs(prepared: Prepared, request: FitRequest, say: Callable[[str], None]) -> None:
    """The rows, runs and sensors fitted, and where the rises are taken from."""
    data = prepared.data  # the readings of the sensors are let go: their rises are kept
    recordings = prepared.plan.recording_runs
    say(
        f"{request.data_csv.name}: {data.n_samples} rows, {len(data.run_ids)} runs, "
        f"target {request.target} (µm), sensors {','.join(prepared.inputs.sensors)} (°C)"
    )
    say(
        f"references ({request.reference}): {len(recordings)} recording(s); rises are taken "
        "from the leading at-rest samples of each recording: "
        + " | ".join(" ".join(r) for r in recordings)
    )
    say(prepared.plan.error_line())


def _say_outcome(
    outcome: FitOutcome,
    request: FitRequest,
    say: Callable[[str], None],
    warn: Callable[[str], None],
) -> None:
    """Validation tables, the ranking, each model's summary and conditioning, what was saved."""
    for group, validation in outcome.validations.items():
        say(f"\n{request.method} [{group}] — {validation.scheme}")
        say(accuracy_table(validation))
        forward = outcome.forward.get(group)
        if forward is not None:
            say(f"\n{request.method} [{group}] — {forward_label(forward)}")
            say(accuracy_table(forward))
            agreement = outcome.agreement[group]
            (warn if agreement.disagree else say)(
                ("warning: " if agreement.disagree else "") + agreement.sentence()
            )
    if outcome.sigma_rows:
        say("\nσ (µm) of each run's model (rows) on each run (columns):")
        say(sigma_matrix_table(outcome.sigma_rows))
    if outcome.ranking is not None:
        say("\n" + format_report(outcome.ranking))
    for model_id, text in outcome.summaries.items():
        say(f"\n{model_id}: {text}")
    for model_id, conditioning in outcome.conditioning.items():
        say(f"\n{model_id} {conditioning.table(request.collinearity == 'full')}")
        if conditioning.worst_single_um > request.max_bias_error_um:
            warn(
                f"warning: {model_id}: a bias of ±{request.sensor_accuracy_C:g} °C on "
                f"{conditioning.worst_sensor} moves the compensation by "
                f"{conditioning.worst_single_um:.1f} µm (limit {request.max_bias_error_um:g} µm): "
                "the inputs are collinear; try --method ridge or pls, or fewer --sensors"
            )
    for model_id, path in outcome.saved.items():
        say(f"saved {model_id} → {path}")


def forward_label(forward: Forward) -> str:
    """The forward scheme in a few words, for the table's heading."""
    return (
        f"forward: each later {forward.unit} predicted by a model fitted on the earlier ones "
        "only, started as a new recording"
    )
