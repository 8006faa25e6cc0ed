"""Formatting an analysis result: one set of cells, laid out as text or as HTML.

Every figure the terminal and the report show goes through the formatters here
(:func:`um_text`, :func:`change_text`, :func:`p_text`, :func:`params_text`),
and every table is built once as rows of cells (:func:`candidate_rows`,
:func:`accuracy_rows`, :func:`run_rows`) that :func:`text_report` pads into
columns and the Jinja2 template (``templates/analysis_report.html.j2``,
autoescaped) puts into ``<td>``: the two cannot show different numbers.

Conventions for people: µm to 0.01, percentages to 0.1, a change of the RMSE
signed (−25.5 % is less error), time constants in minutes, p-values to three
significant digits and never 0 (below ``P_FLOOR`` they read "< 1e-16").
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import TYPE_CHECKING, Any

from models.analysis.format import (
    Row,
    change_text,
    columns,
    effect_name,
    p_text,
    params_text,
    pct_text,
    um_text,
    value_text,
)

if TYPE_CHECKING:
    from models.analysis.result import AnalysisResult, CandidateResult, StepResult

TEMPLATE = "analysis_report.html.j2"

CANDIDATE_HEADER = (
    "",
    "effect",
    "parameters",
    "held-out RMSE (µm)",
    "RMSE change (%)",
    "shape change (%)",
    "folds better",
    "p-value",
    "believed",
    "reason",
)
NUMERIC_CANDIDATE_COLUMNS = frozenset({3, 4, 5, 6, 7})
ACCURACY_HEADER = ("", "RMSE (µm)", "σ (µm)", "max |e| (µm)", "samples")
RUN_HEADER = ("run", "samples", "RMSE before (µm)", "RMSE after (µm)", "share of error after (%)")


# --------------------------------------------------------------------------- formatters


def step_text(step: StepResult) -> str:
    """What one round did, in one sentence."""
    if step.effect == "none":
        return (
            f"No candidate passed every rule, so the analysis stopped here; the held-out RMSE "
            f"stays at {um_text(step.before.rmse_um)} µm. The reason column says which rule "
            "each candidate failed."
        )
    return (
        f"Added {effect_name(step.effect, step.params)}: held-out RMSE "
        f"{um_text(step.before.rmse_um)} µm → {um_text(step.after.rmse_um)} µm "
        f"({change_text(step.rmse_gain_pct)} %)."
    )


def step_heading(step: StepResult) -> str:
    if step.effect == "none":
        return f"Step {step.number}: nothing added"
    return f"Step {step.number}: added {effect_name(step.effect, step.params)}"


# --------------------------------------------------------------------------- table rows


def candidate_cells(cand: CandidateResult, chosen: bool) -> tuple[str, ...]:
    return (
        "*" if chosen else "",
        cand.effect,
        params_text(cand.params) or "—",
        um_text(cand.rmse_um),
        change_text(cand.rmse_gain_pct),
        change_text(cand.shape_gain_pct),
        f"{cand.folds_improved}/{cand.folds}",
        p_text(cand.p_value),
        "yes" if cand.believed else "no",
        cand.reason,
    )


def candidate_rows(step: StepResult, order: str = "tried") -> list[Row]:
    """The round's candidates, in the order tried or (``order="rmse"``) best first."""
    chosen = step.chosen_index
    indexed = list(enumerate(step.candidates))
    if order == "rmse":
        indexed.sort(key=lambda item: item[1].rmse_um)
    return [Row(candidate_cells(c, i == chosen), i == chosen) for i, c in indexed]


def accuracy_rows(result: AnalysisResult) -> list[Row]:
    rows = []
    for label, acc in ((before_label(result), result.before), (after_label(result), result.after)):
        cells = (label, um_text(acc.rmse_um), um_text(acc.sigma_um), um_text(acc.max_abs_um))
        rows.append(Row((*cells, str(acc.n_samples))))
    return rows


def run_rows(result: AnalysisResult) -> list[Row]:
    return [
        Row(
            (
                r.run,
                str(r.n_samples),
                um_text(r.rmse_before_um),
                um_text(r.rmse_after_um),
                pct_text(100.0 * r.share_after),
            )
        )
        for r in result.per_run
    ]


def before_label(result: AnalysisResult) -> str:
    return f"before: {result.model}"


def after_label(result: AnalysisResult) -> str:
    effects = result.effects
    return "after: + " + " + ".join(effects) if effects else "after: nothing added"


def facts(result: AnalysisResult) -> list[tuple[str, Any]]:
    """How the figures were obtained (label, value): plain strings or mappings."""
    groups = [(r.run, r.n_samples) for r in result.per_run]
    runs = f"{len(groups)}: " + ", ".join(f"{name} ({n} rows)" for name, n in groups)
    rows: list[tuple[str, Any]] = [
        ("Model", result.model),
        ("Target", result.target),
        ("Sensors", ", ".join(result.sensors) or "—"),
        ("Runs", runs),
        ("Validation", result.validation),
        ("Tolerance", f"held-out RMSE ≤ {um_text(result.tolerance_um)} µm"),
        ("Reference", dict(result.reference)),
        ("Rules", dict(result.rules)),
        ("Source file", result.source or "—"),
        ("Data fingerprint", result.data_fingerprint or "—"),
    ]
    if result.skipped_rows:
        rows.append(("Skipped rows", result.skipped_rows))
    if result.stored_model:
        rows.append(("Stored model", dict(result.stored_model)))
    return rows


# --------------------------------------------------------------------------- layouts


def text_report(result: AnalysisResult) -> str:
    """The terminal layout: rounds with their candidates (best first), then the figures."""
    lines = [
        f"validation: {result.validation}; tolerance: held-out RMSE ≤ "
        f"{um_text(result.tolerance_um)} µm"
    ]
    for step in result.steps:
        before = um_text(step.before.rmse_um)
        lines += ["", f"round {step.number}: held-out RMSE before {before} µm"]
        table = columns(CANDIDATE_HEADER, candidate_rows(step, "rmse"), NUMERIC_CANDIDATE_COLUMNS)
        lines += ["  " + line for line in table]
        lines.append(f"  → {step_text(step)}")
    lines += ["", result.headline, ""]
    numbers = frozenset({1, 2, 3, 4})
    lines += columns(ACCURACY_HEADER, accuracy_rows(result), numbers)
    lines += ["", "per run (held-out):"]
    lines += ["  " + line for line in columns(RUN_HEADER, run_rows(result), numbers)]
    lines += ["", f"next: {result.next_step_text}"]
    if result.added_steps:
        lines.append(
            "note: an effect's entry was judged with every held-out run, the scored ones "
            "included; analyze --nested gives a figure no choice saw"
        )
    if result.base_choice is not None:
        lines.append(f"base: {base_choice_text(result.base_choice)}")
    if result.nested is not None:
        lines += ["", result.nested.to_text(result.tolerance_um)]
    return "\n".join(lines)


def base_choice_text(choice: dict[str, Any]) -> str:
    scores = ", ".join(f"{m} {um_text(v)}" for m, v in choice["heldout_rmse_um"].items())
    return (
        f"every base analysed, held-out RMSE {scores} µm; kept {choice['kept']}, "
        "its figures optimistic by this choice"
    )


def html_report(result: AnalysisResult, plots: Sequence[Any]) -> str:
    """The HTML layout, rendered from the package's Jinja2 template with autoescape on."""
    from jinja2 import Environment, PackageLoader, StrictUndefined

    env = Environment(
        loader=PackageLoader("models.analysis", "templates"),
        autoescape=True,
        undefined=StrictUndefined,
        keep_trailing_newline=True,
    )
    env.filters["value"] = value_text
    title = f"Thermal-error analysis: {result.model} → {result.target}"
    steps = [
        {
            "heading": step_heading(step),
            "text": step_text(step),
            "rows": candidate_rows(step),
        }
        for step in result.steps
    ]
    return env.get_template(TEMPLATE).render(
        title=title,
        headline=result.headline,
        next_step=result.next_step_text,
        accuracy_header=ACCURACY_HEADER,
        accuracy_rows=accuracy_rows(result),
        run_header=RUN_HEADER,
        run_rows=run_rows(result),
        facts=facts(result),
        candidate_header=CANDIDATE_HEADER,
        numeric=NUMERIC_CANDIDATE_COLUMNS,
        steps=steps,
        plots=list(plots),
        base_choice=None if result.base_choice is None else base_choice_text(result.base_choice),
        nested=None if result.nested is None else result.nested.tables(result.tolerance_um),
    )
