"""The ``analyze`` command's work: trace the held-out residual to the effect the model
lacks, add it, compare; store the augmented model and write the report when asked (§5).

The command (:mod:`gateway.cli.main`) parses the options and loads the file; this
module imports the analysis stack (scipy, scikit-learn), so the command imports it
only once the file is known good.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

import numpy as np

from gateway import __version__
from gateway.offline.targets import combined, each_target, say_heading
from models.analysis import augmented
from models.analysis.nested import AUTO_BASES, analyse_bases, nested_analysis
from models.analysis.render import text_report
from models.analysis.result import AnalysisResult
from models.analysis.search import Accepted, ResidualAnalysis
from models.analysis.search import analyze as run_analysis
from models.data.dataset import MeasuredRuns
from models.data.features import Prepared, prepare
from models.store import data_fingerprint


class TooFewProbeRowsError(ValueError):
    """``--probe-rows`` on a file with fewer than 10 rows that have the target."""


@dataclass(frozen=True)
class AnalyzeRequest:
    """What the ``analyze`` command was asked (its options, parsed)."""

    data_csv: Path
    method: str  # a method name, or "auto"
    target: str
    sensors: list[str] | None
    reference: str
    progress: bool
    store_dir: Path | None
    report_dir: Path | None
    tolerance_um: float
    probe_rows: bool
    nested: bool


def run_analyze_targets(
    data: MeasuredRuns,
    targets: list[str],
    request: AnalyzeRequest,
    say: Callable[[str], None],
    note: Callable[[str], None],
) -> dict[str, Any]:
    """:func:`run_analyze` for each target of ``data`` (read once, prepared once), one section
    each, each target's report in a folder of its own under ``--report``; the command's
    JSON (:func:`gateway.offline.targets.combined`)."""
    results: dict[str, dict[str, Any]] = {}
    runs = each_target(
        data, targets, request.sensors, request.reference, request.progress, request.probe_rows
    )
    for one in runs:
        say_heading(one, data, targets, say, note)
        asked = replace(request, target=one.target)
        if len(targets) > 1 and request.report_dir is not None:
            asked = replace(asked, report_dir=request.report_dir / one.target)
        results[one.target] = run_analyze(one.data, asked, say, one.prepared).as_dict()
    return combined(results)


def run_analyze(
    data: MeasuredRuns,
    request: AnalyzeRequest,
    say: Callable[[str], None],
    prepared: Prepared | None = None,
) -> AnalysisResult:
    """Analyse ``data`` as ``request`` says, print the report; the result (its JSON).
    ``prepared``: ``data`` already prepared (several targets)."""
    prepared, fit_rows = _prepared(data, request, prepared)
    data_with_readings = None if fit_rows is not None else data
    data = prepared.data  # the readings of the sensors are let go: their rises are kept
    known = "" if fit_rows is None else f" ({int(fit_rows.sum())} with {request.target})"
    say(
        f"{request.data_csv.name}: {data.n_samples} rows{known}, {len(data.run_ids)} runs, "
        f"{len(prepared.plan.recording_runs)} recording(s), target {request.target} (µm), "
        f"model {request.method} on {','.join(prepared.inputs.sensors)} (°C)"
    )
    method, result, accepted, analysis = _analyse(prepared, request, fit_rows)
    methods = AUTO_BASES if request.method == "auto" else (request.method,)
    outer = (
        nested_analysis(prepared, methods, request.sensors, fit_rows, request.progress)
        if request.nested
        else None
    )
    result = replace(
        result,
        data_fingerprint=data_fingerprint(prepared.inputs, prepared.error_um),
        skipped_rows="; ".join(s.describe() for s in data.skipped) or None,
        tolerance_um=request.tolerance_um,
        nested=outer,
    )
    forward = _forward(method, prepared, data_with_readings, request, result)
    result = replace(result, forward=forward)
    say(text_report(result))
    if result.forward is not None:
        say(_forward_text(result.forward))
    if request.store_dir is not None and result.effects and not accepted:
        # Found by refitting lag-ridge with the effect as an input (models.analysis.inside):
        # the stored form (a base's prediction plus effect terms) cannot hold that model.
        say(
            f"not saved: {', '.join(result.effects)} was found inside the lag-ridge base, "
            "which the augmented-model store cannot hold yet; analyze --model mlr stores one"
        )
    elif request.store_dir is not None:
        model_id = f"{method}-{request.target}-" + ("-".join(result.effects) or "none")
        document = augmented.build_augmented_document(
            analysis, accepted, result, model_id, __version__
        )
        path = augmented.save(document, request.store_dir)
        result = replace(result, stored_model={"model_id": document["model_id"], "path": str(path)})
        say(f"saved {document['model_id']} → {path}")
    if request.report_dir is not None:
        from gateway.offline.report import write_report

        say(f"wrote {write_report(result, request.report_dir)}")
    return result


def _prepared(
    data: MeasuredRuns, request: AnalyzeRequest, prepared: Prepared | None = None
) -> tuple[Prepared, np.ndarray | None]:
    """The prepared runs, and with ``--probe-rows`` the rows that have the target."""
    if prepared is None:
        prepared = prepare(data, request.sensors, request.reference).without_sensor_readings()
    if not request.probe_rows:
        return prepared, None
    # A probe measures the error itself: the target is used as measured.
    prepared = replace(prepared, error_um=np.asarray(data.error_um, dtype=float))
    fit_rows = np.isfinite(prepared.error_um)
    if int(fit_rows.sum()) < 10:
        raise TooFewProbeRowsError(
            f"{request.data_csv}: --probe-rows: {int(fit_rows.sum())} rows with a "
            f"{request.target} value; expected at least 10"
        )
    return prepared, fit_rows


def _analyse(
    prepared: Prepared, request: AnalyzeRequest, fit_rows: np.ndarray | None
) -> tuple[str, AnalysisResult, list[Accepted], ResidualAnalysis]:
    """The declared model's analysis, or with ``auto`` the best of every base's (the
    choice recorded in the result): (method, result, accepted effects, analysis)."""
    if request.method != "auto":
        result, accepted, analysis = run_analysis(
            prepared, request.method, request.sensors, request.progress, fit_rows=fit_rows
        )
        return request.method, replace(result, base_choice=None), accepted, analysis
    method, analyses = analyse_bases(prepared, AUTO_BASES, request.sensors, fit_rows)
    kept = analyses[method]
    base_choice = {
        "models": list(AUTO_BASES),
        "heldout_rmse_um": {m: round(a.heldout_rmse_um, 4) for m, a in analyses.items()},
        "kept": method,
        "note": "the kept model's figures are optimistic by this choice",
    }
    result = replace(kept.result, base_choice=base_choice)
    return method, result, kept.accepted, kept.analysis


def _forward(
    method: str,
    prepared: Prepared,
    data: MeasuredRuns | None,
    request: AnalyzeRequest,
    result: AnalysisResult,
) -> dict[str, object] | None:
    """The base model's forward figure and how it compares with its leave-one-run-out
    figure (``result``'s before) (None with ``--probe-rows`` or too few runs)."""
    from models.estimators.registry import make_model
    from models.fit.forward import disagreement, forward_validate
    from models.fit.forward_progress import counted

    if data is None:
        return None

    def factory():
        return make_model(method, request.sensors)

    with counted(factory, prepared, request.progress) as made:
        forward = forward_validate(made, prepared, data, request.sensors)
    if forward is None:
        return None
    agreement = disagreement(forward, result.predicted_before_um, result.measured_um, result.run)
    return {
        **forward.as_dict(),
        "model": method,
        "of": "the base model, fitted as fit fits it (no effect added)",
        "against_loro": agreement.as_dict(),
        "note": agreement.sentence(),
    }


def _forward_text(forward: dict) -> str:
    """Two lines: the base's forward figure per unit, and how it compares with LORO."""
    units = ", ".join(f"{k} {v['rmse_um']:.2f}" for k, v in forward["per_fold"].items())
    pooled = forward["pooled"]["rmse_um"]
    prefix = "warning: " if forward["against_loro"]["disagree"] else ""
    return (
        f"forward ({forward['model']} base, each later {forward['unit']} predicted by a model "
        f"fitted on the earlier ones, started as a new recording): {pooled:.2f} µm "
        f"(RMSE µm: {units})\n{prefix}{forward['note']}"
    )
